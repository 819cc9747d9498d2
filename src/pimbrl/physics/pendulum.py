"""Pendulum: Gymnasium's inverted-pendulum swing-up dynamics, optionally with viscous friction at the pivot.

    theta_ddot = 3 g / (2 l) sin(theta) + 3 / (m l^2) (T - damping theta_dot),

integrated with semi-implicit Euler (``dt = 0.05``) and the angular speed clipped to ``[-8, 8]``, in the
operation order of Gymnasium's ``PendulumEnv`` so that trajectories match it bit for bit (with
``damping = 0``, the default, the friction term is not computed at all). ``theta = 0`` is upright. (The
paper writes ``-3g/(2l) sin(theta + pi)``, the same thing.) The rod is uniform, with moment of inertia
``m l^2 / 3`` about the pivot, so a torque ``tau`` gives ``theta_ddot = 3 tau / (m l^2)``; the friction
torque is ``-damping theta_dot``.
"""

from __future__ import annotations

import numpy as np

from .base import Array, Physics, active, check_coefficient, records_arguments, xp_of

__all__ = ["Pendulum", "wrap_angle"]


def wrap_angle(theta: Array) -> Array:
    """Map angles into ``[-pi, pi)``."""
    return ((theta + np.pi) % (2 * np.pi)) - np.pi


class Pendulum(Physics):
    """Pendulum with state ``(theta, theta_dot)`` and a torque ``T`` in ``[-max_torque, max_torque]``.

    The clipping of ``theta_dot`` is part of the discrete dynamics, so the residual of a true step is
    exactly zero even when the speed limit is active.

    Args:
        g: gravitational acceleration (10, Gymnasium's), a finite number.
        m: mass of the rod (1), > 0.
        l: length of the rod (1), > 0.
        dt: semi-implicit Euler step (0.05).
        max_speed: the angular speed is clipped to ``[-max_speed, max_speed]`` after every step (8).
        max_torque: torque bound (2).
        damping: coefficient of a viscous friction torque ``-damping theta_dot`` at the pivot (0: none, as
            Gymnasium; a term a physics prior may miss), >= 0.

    The physical coefficients (:attr:`coefficients`) are ``g``, ``m``, ``l`` and ``damping``.

    Raises:
        ValueError: for ``m <= 0``, ``l <= 0``, ``damping < 0`` or a coefficient that is not finite.
    """

    name = "pendulum"
    coefficients = ("g", "m", "l", "damping")
    tensor_coefficients = True

    @records_arguments
    def __init__(
        self,
        g: float = 10.0,
        m: float = 1.0,
        l: float = 1.0,  # noqa: E741 - the standard symbol
        dt: float = 0.05,
        max_speed: float = 8.0,
        max_torque: float = 2.0,
        damping: float = 0.0,
    ) -> None:
        self.g = check_coefficient("Pendulum", "g", g)
        self.m = check_coefficient("Pendulum", "m", m, positive=True)
        self.l = check_coefficient("Pendulum", "l", l, positive=True)
        self.damping = check_coefficient("Pendulum", "damping", damping, nonnegative=True)
        self.dt = float(dt)
        self.substeps = 1
        self.max_speed = float(max_speed)
        self.max_torque = float(max_torque)
        self.state_dim = 2
        self.action_dim = 1
        self.action_low = np.array([-self.max_torque])
        self.action_high = np.array([self.max_torque])
        self._derive_coefficients()

    def _derive_coefficients(self) -> None:
        """``3 g / (2 l)`` and ``3 / (m l^2)``, in Gymnasium's operation order."""
        self._gravity_coef = 3 * self.g / (2 * self.l)
        self._torque_coef = 3.0 / (self.m * self.l**2)

    def rhs(self, u: Array, a: Array) -> Array:
        """``(theta_dot, 3 g / (2 l) sin(theta) + 3 / (m l^2) (T - damping theta_dot))``.

        With ``damping = 0`` this is Gymnasium's expression, evaluated in its order.
        """
        xp = xp_of(u)
        theta, theta_dot = u[..., 0], u[..., 1]
        torque = a[..., 0]
        if active(self.damping):  # skipped at 0, so that the default stays Gymnasium's bit for bit
            torque = torque - self.damping * theta_dot
        return xp.stack([theta_dot, self._gravity_coef * xp.sin(theta) + self._torque_coef * torque], -1)

    def substep(self, u: Array, a: Array) -> Array:
        """Gymnasium's semi-implicit Euler step: clip the new angular speed, then move the angle with it."""
        xp = xp_of(u)
        theta, theta_dot = u[..., 0], u[..., 1]
        acc = self.rhs(u, a)[..., 1]
        new_theta_dot = xp.clip(theta_dot + acc * self.dt, -self.max_speed, self.max_speed)
        new_theta = theta + new_theta_dot * self.dt
        return xp.stack([new_theta, new_theta_dot], -1)

    def canonical(self, u: Array) -> Array:
        """The state with ``theta`` wrapped into ``[-pi, pi)`` (the dynamics are 2 pi-periodic in theta)."""
        xp = xp_of(u)
        return xp.stack([wrap_angle(u[..., 0]), u[..., 1]], -1)

    def constrain(self, u: Array) -> Array:
        """The speed clipped to ``[-max_speed, max_speed]``, as every solver step clips it."""
        xp = xp_of(u)
        return xp.stack([u[..., 0], xp.clip(u[..., 1], -self.max_speed, self.max_speed)], -1)

    def admissible_box(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Every angle and every speed the solver allows."""
        return np.array([-np.pi, -self.max_speed]), np.array([np.pi, self.max_speed])

    def state_difference(self, u1: Array, u0: Array) -> Array:
        """Difference with the angle wrapped into ``[-pi, pi)``."""
        xp = xp_of(u1)
        d = u1 - u0
        return xp.stack([wrap_angle(d[..., 0]), d[..., 1]], -1)

    def reward(self, u: Array, a: Array, u_next: Array, k: Array | int, path: Array | None = None) -> Array:
        """``-(wrap(theta)^2 + 0.1 theta_dot^2 + 0.001 T^2)`` on the pre-step state."""
        theta, theta_dot, torque = u[..., 0], u[..., 1], a[..., 0]
        return -(wrap_angle(theta) ** 2 + 0.1 * theta_dot**2 + 0.001 * (torque**2))

    def advance(self, u: np.ndarray, a: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One step and the reward of the pre-step state for a batch of states."""
        u = np.asarray(u, dtype=np.float64)
        a = np.asarray(a, dtype=np.float64)
        u_next = self.substep(u, a)
        return u_next, self.reward(u, a, u_next, k)
