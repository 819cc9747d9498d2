"""Cart-Pole: Gymnasium's classic cart-pole dynamics (Barto, Sutton & Anderson 1983), optionally with friction.

The equations are written once here in array-agnostic form (NumPy or torch, batched), with the
operation order of Gymnasium's ``CartPoleEnv`` so that trajectories match it bit for bit. The paper's
equation (3.1) has typos; this is the form Gymnasium (and the authors' environment) integrate.

With friction (``mu_c = cart_friction``, ``mu_p = pole_friction``; both 0 by default, as Gymnasium) these
are Barto, Sutton & Anderson's (1983, appendix) frictional equations, in Gymnasium's sign convention
(``theta = 0`` upright, ``g > 0``; ``m = masspole``, ``M = masscart + masspole``, ``l`` the half-length)::

    temp      = (F + m l theta_dot^2 sin(theta) - mu_c sgn(x_dot)) / M
    theta_acc = (g sin(theta) - cos(theta) temp - mu_p theta_dot / (m l)) / (l (4/3 - m cos^2(theta) / M))
    x_acc     = temp - m l theta_acc cos(theta) / M

``mu_c sgn(x_dot)`` is a Coulomb friction force of constant magnitude ``mu_c`` (newtons) on the cart,
``mu_p theta_dot`` a viscous friction torque at the pivot. They follow from the Lagrangian of a uniform
pole (moment of inertia ``m l^2 / 3`` about its centre) on a cart with these two generalised friction
forces. Florian (2007, "Correct equations for the dynamics of the cart-pole system") points out that
physical Coulomb friction scales with the cart's normal force, which varies with the pole's motion; that
refinement is not modelled: ``mu_c`` is Barto et al.'s constant friction force. At ``x_dot = 0`` the
cart friction is 0 (no static friction). A friction term that is 0 is not computed at all, so the
defaults stay Gymnasium's bit for bit.
"""

from __future__ import annotations

import math

import numpy as np

from .base import Array, Physics, active, check_coefficient, records_arguments, xp_of

__all__ = ["CartPole"]


class CartPole(Physics):
    """Cart-pole with state ``(x, x_dot, theta, theta_dot)`` and a horizontal force on the cart.

    The physical action is the force (``[-force_mag, force_mag]``); the Gymnasium environment applies
    ``+force_mag`` for action 1 and ``-force_mag`` for action 0. Explicit Euler with ``tau = 0.02``.

    Args:
        gravity: gravitational acceleration (9.8), a finite number.
        masscart: mass of the cart (1.0), > 0.
        masspole: mass of the pole (0.1), > 0.
        length: half the pole's length (0.5), > 0.
        force_mag: magnitude of the force on the cart (10).
        tau: explicit Euler step (0.02).
        x_threshold: the episode ends beyond ``|x| > x_threshold`` (2.4).
        theta_threshold_radians: the episode ends beyond ``|theta| >`` this (12 degrees).
        cart_friction: magnitude ``mu_c`` of a Coulomb friction force ``-mu_c sgn(x_dot)`` on the cart
            (0: none, as Gymnasium), >= 0.
        pole_friction: coefficient ``mu_p`` of a viscous friction torque ``-mu_p theta_dot`` at the pivot
            (0: none, as Gymnasium), >= 0.

    The physical coefficients (:attr:`coefficients`) are ``gravity``, ``masscart``, ``masspole``,
    ``length``, ``cart_friction`` and ``pole_friction``. See the module docstring for the equations.

    Raises:
        ValueError: for a mass or length ``<= 0``, a friction ``< 0`` or a coefficient that is not finite.
    """

    name = "cartpole"
    coefficients = ("gravity", "masscart", "masspole", "length", "cart_friction", "pole_friction")
    tensor_coefficients = True

    @records_arguments
    def __init__(
        self,
        gravity: float = 9.8,
        masscart: float = 1.0,
        masspole: float = 0.1,
        length: float = 0.5,
        force_mag: float = 10.0,
        tau: float = 0.02,
        x_threshold: float = 2.4,
        theta_threshold_radians: float = 12 * 2 * math.pi / 360,
        cart_friction: float = 0.0,
        pole_friction: float = 0.0,
    ) -> None:
        self.gravity = check_coefficient("CartPole", "gravity", gravity)
        self.masscart = check_coefficient("CartPole", "masscart", masscart, positive=True)
        self.masspole = check_coefficient("CartPole", "masspole", masspole, positive=True)
        self.length = check_coefficient("CartPole", "length", length, positive=True)  # half the pole's length
        self.cart_friction = check_coefficient("CartPole", "cart_friction", cart_friction, nonnegative=True)
        self.pole_friction = check_coefficient("CartPole", "pole_friction", pole_friction, nonnegative=True)
        self._derive_coefficients()
        self.force_mag = float(force_mag)
        self.dt = float(tau)
        self.substeps = 1
        self.x_threshold = float(x_threshold)
        self.theta_threshold_radians = float(theta_threshold_radians)
        self.state_dim = 4
        self.action_dim = 1
        self.action_low = np.array([-self.force_mag])
        self.action_high = np.array([self.force_mag])

    def _derive_coefficients(self) -> None:
        """The total mass and the pole's mass times half-length, as Gymnasium computes them."""
        self.total_mass = self.masspole + self.masscart
        self.polemass_length = self.masspole * self.length

    def rhs(self, u: Array, a: Array) -> Array:
        """Gymnasium's cart-pole equations of motion, with Barto et al.'s friction terms where nonzero.

        Returns ``(x_dot, x_acc, theta_dot, theta_acc)``.
        """
        xp = xp_of(u)
        x_dot, theta, theta_dot = u[..., 1], u[..., 2], u[..., 3]
        force = a[..., 0]
        costheta = xp.cos(theta)
        sintheta = xp.sin(theta)
        numerator = force + self.polemass_length * (theta_dot * theta_dot) * sintheta
        if active(self.cart_friction):  # each friction term is skipped at 0: the defaults stay Gymnasium's
            numerator = numerator - self.cart_friction * xp.sign(x_dot)
        temp = numerator / self.total_mass
        angular = self.gravity * sintheta - costheta * temp
        if active(self.pole_friction):
            angular = angular - self.pole_friction * theta_dot / self.polemass_length
        thetaacc = angular / (self.length * (4.0 / 3.0 - self.masspole * (costheta * costheta) / self.total_mass))
        xacc = temp - self.polemass_length * thetaacc * costheta / self.total_mass
        return xp.stack([x_dot, xacc, theta_dot, thetaacc], -1)

    def substep(self, u: Array, a: Array) -> Array:
        """One explicit Euler step of length :attr:`dt` (Gymnasium's ``euler`` integrator)."""
        return u + self.dt * self.rhs(u, a)

    def reward(self, u: Array, a: Array, u_next: Array, k: Array | int, path: Array | None = None) -> Array:
        """+1 for every step, the terminating one included (Gymnasium's reward)."""
        return 0.0 * u_next[..., 0] + 1.0

    #: speed bounds of :meth:`admissible_box` (cart m/s, pole rad/s): beyond what a balancing episode reaches
    speed_box = (3.0, 3.5)

    def admissible_box(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The termination box in position and angle; :attr:`speed_box` in the speeds."""
        high = np.array([self.x_threshold, self.speed_box[0], self.theta_threshold_radians, self.speed_box[1]])
        return -high, high

    def terminated(self, u: Array) -> Array:
        """The cart leaves ``|x| <= 2.4`` or the pole tilts beyond 12 degrees."""
        x, theta = u[..., 0], u[..., 2]
        return (
            (x < -self.x_threshold)
            | (x > self.x_threshold)
            | (theta < -self.theta_threshold_radians)
            | (theta > self.theta_threshold_radians)
        )

    def advance(self, u: np.ndarray, a: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One Euler step and the constant reward for a batch of states."""
        u = np.asarray(u, dtype=np.float64)
        a = np.asarray(a, dtype=np.float64)
        u_next = self.substep(u, a)
        return u_next, self.reward(u, a, u_next, k)
