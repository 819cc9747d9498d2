"""Cart-Pole: Gymnasium's classic cart-pole dynamics (Barto, Sutton & Anderson 1983).

The equations are written once here in array-agnostic form (NumPy or torch, batched), with the
operation order of Gymnasium's ``CartPoleEnv`` so that trajectories match it bit for bit. The paper's
equation (3.1) has typos; this is the form Gymnasium (and the authors' environment) integrate.
"""

from __future__ import annotations

import math

import numpy as np

from .base import Array, Physics, xp_of

__all__ = ["CartPole"]


class CartPole(Physics):
    """Cart-pole with state ``(x, x_dot, theta, theta_dot)`` and a horizontal force on the cart.

    The physical action is the force (``[-force_mag, force_mag]``); the Gymnasium environment applies
    ``+force_mag`` for action 1 and ``-force_mag`` for action 0. Explicit Euler with ``tau = 0.02``.
    """

    name = "cartpole"

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
    ) -> None:
        self.gravity = float(gravity)
        self.masscart = float(masscart)
        self.masspole = float(masspole)
        self.total_mass = self.masspole + self.masscart
        self.length = float(length)  # half the pole's length
        self.polemass_length = self.masspole * self.length
        self.force_mag = float(force_mag)
        self.dt = float(tau)
        self.substeps = 1
        self.x_threshold = float(x_threshold)
        self.theta_threshold_radians = float(theta_threshold_radians)
        self.state_dim = 4
        self.action_dim = 1
        self.action_low = np.array([-self.force_mag])
        self.action_high = np.array([self.force_mag])

    def rhs(self, u: Array, a: Array) -> Array:
        """Gymnasium's cart-pole equations of motion: ``(x_dot, x_acc, theta_dot, theta_acc)``."""
        xp = xp_of(u)
        x_dot, theta, theta_dot = u[..., 1], u[..., 2], u[..., 3]
        force = a[..., 0]
        costheta = xp.cos(theta)
        sintheta = xp.sin(theta)
        temp = (force + self.polemass_length * (theta_dot * theta_dot) * sintheta) / self.total_mass
        thetaacc = (self.gravity * sintheta - costheta * temp) / (
            self.length * (4.0 / 3.0 - self.masspole * (costheta * costheta) / self.total_mass)
        )
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
