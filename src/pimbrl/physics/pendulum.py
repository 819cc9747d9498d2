"""Pendulum: Gymnasium's inverted-pendulum swing-up dynamics.

    theta_ddot = 3 g / (2 l) sin(theta) + 3 / (m l^2) T,

integrated with semi-implicit Euler (``dt = 0.05``) and the angular speed clipped to ``[-8, 8]``, in the
operation order of Gymnasium's ``PendulumEnv`` so that trajectories match it bit for bit. ``theta = 0``
is upright. (The paper writes ``-3g/(2l) sin(theta + pi)``, the same thing.)
"""

from __future__ import annotations

import numpy as np

from .base import Array, Physics, xp_of

__all__ = ["Pendulum", "wrap_angle"]


def wrap_angle(theta: Array) -> Array:
    """Map angles into ``[-pi, pi)``."""
    return ((theta + np.pi) % (2 * np.pi)) - np.pi


class Pendulum(Physics):
    """Pendulum with state ``(theta, theta_dot)`` and a torque ``T`` in ``[-max_torque, max_torque]``.

    The clipping of ``theta_dot`` is part of the discrete dynamics, so the residual of a true step is
    exactly zero even when the speed limit is active.
    """

    name = "pendulum"

    def __init__(
        self,
        g: float = 10.0,
        m: float = 1.0,
        l: float = 1.0,  # noqa: E741 - the standard symbol
        dt: float = 0.05,
        max_speed: float = 8.0,
        max_torque: float = 2.0,
    ) -> None:
        self.g = float(g)
        self.m = float(m)
        self.l = float(l)
        self.dt = float(dt)
        self.substeps = 1
        self.max_speed = float(max_speed)
        self.max_torque = float(max_torque)
        self.state_dim = 2
        self.action_dim = 1
        self.action_low = np.array([-self.max_torque])
        self.action_high = np.array([self.max_torque])
        self._gravity_coef = 3 * self.g / (2 * self.l)
        self._torque_coef = 3.0 / (self.m * self.l**2)

    def rhs(self, u: Array, a: Array) -> Array:
        """``(theta_dot, 3 g / (2 l) sin(theta) + 3 / (m l^2) T)``, as in Gymnasium's pendulum."""
        xp = xp_of(u)
        theta, theta_dot = u[..., 0], u[..., 1]
        return xp.stack([theta_dot, self._gravity_coef * xp.sin(theta) + self._torque_coef * a[..., 0]], -1)

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
