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

from pathlib import Path
from typing import Any, Literal

import numpy as np
from gymnasium import spaces

from ..envs.base import PhysicsEnv, PhysicsVectorEnv
from ..envs.render import BLACK, RED, Canvas
from ..envs.task import Task
from ..physics.base import Array, Physics, active, check_coefficient, records_arguments, xp_of
from .registry import System

__all__ = ["SYSTEM", "Pendulum", "PendulumEnv", "PendulumTask", "PendulumVectorEnv", "wrap_angle"]


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
        self.g = check_coefficient("Pendulum", "g", g, low=-100.0, high=100.0)
        self.m = check_coefficient("Pendulum", "m", m, positive=True, high=1e3)
        self.l = check_coefficient("Pendulum", "l", l, positive=True, high=1e3)
        self.damping = check_coefficient("Pendulum", "damping", damping, nonnegative=True, high=1e3)
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


class PendulumTask(Task):
    """Pendulum task: torque in ``[-2, 2]``, 200 control steps.

    Args:
        observation: ``"cos_sin"`` (default, Gymnasium's ``(cos theta, sin theta, theta_dot)``) or ``"theta"``
            (the paper's ``(theta, theta_dot)`` with ``theta`` wrapped into ``[-pi, pi)``). The wrapped angle
            jumps from ``pi`` to ``-pi`` where the pendulum hangs down, so a smooth policy cannot pump energy
            through the bottom: TD3 then swings up from only part of the initial states (measured: mean
            test return stuck near -970, bimodal -1522 / -0.1, over 15,000 steps), like the paper's MFRL
            curve (below -800).
        **coefficients: physical coefficients of :class:`pimbrl.systems.Pendulum` that differ from Gymnasium's
            (``g`` = 10, ``m`` = 1, ``l`` = 1, ``damping`` = 0), e.g. ``m=1.3`` or ``damping=0.1``: a system
            whose physics a prior may get wrong.
    """

    max_episode_steps = 200
    render_fps = 20  # a control step is 0.05 time units
    physics: Pendulum
    action_space: spaces.Box

    def __init__(self, observation: Literal["theta", "cos_sin"] = "cos_sin", **coefficients: float) -> None:
        if observation not in ("theta", "cos_sin"):
            raise ValueError(f"observation must be 'theta' or 'cos_sin', got {observation!r}")
        self.physics = Pendulum().with_coefficients(**coefficients)
        self.observation_mode = observation
        s = np.float32(self.physics.max_speed)
        high = np.array([np.pi, s], dtype=np.float32) if observation == "theta" else np.array([1.0, 1.0, s], dtype=np.float32)
        self.observation_space = spaces.Box(-high, high, dtype=np.float32)
        self.action_space = spaces.Box(
            self.physics.action_low.astype(np.float32), self.physics.action_high.astype(np.float32), dtype=np.float32
        )

    def sample_initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``theta ~ U[-pi, pi]`` and ``theta_dot ~ U[-1, 1]``, as in Gymnasium."""
        high = np.array([np.pi, 1.0])
        return rng.uniform(low=-high, high=high, size=(n, 2))

    def observe(self, u: np.ndarray, k: np.ndarray) -> np.ndarray:
        """``(cos theta, sin theta, theta_dot)`` or ``(wrapped theta, theta_dot)``, as float32."""
        theta, theta_dot = u[:, 0], u[:, 1]
        if self.observation_mode == "theta":
            return np.stack([wrap_angle(theta), theta_dot], -1).astype(np.float32)
        return np.stack([np.cos(theta), np.sin(theta), theta_dot], -1).astype(np.float32)

    def physical_action(self, actions: Any, batch: int) -> np.ndarray:
        """Check the torques' shape and finiteness and clip them to ``[-2, 2]``."""
        return self._box_action(actions, batch, self.action_space, self.physics.action_low, self.physics.action_high)

    def render(self, u: np.ndarray, k: int) -> np.ndarray:
        """A 400 x 400 sketch: the rod (red) from the pivot at the angle ``theta`` (0 points up)."""
        size = 400
        canvas = Canvas(size, size)
        centre = size / 2
        length = 0.4 * size
        theta = float(u[0])
        tip = (centre + length * np.sin(theta), centre - length * np.cos(theta))
        canvas.segment((centre, centre), tip, RED, 0.08 * size)
        canvas.disc(tip, 0.04 * size, RED)
        canvas.disc((centre, centre), 0.015 * size, BLACK)
        return canvas.image


_DOC = """Pendulum swing-up (Gymnasium's Pendulum; the paper's section 3.1.2).

    ## Description
    A pendulum hinged at one end starts at a random angle; a bounded torque must swing it up and keep
    it upright with little effort.

    ## Governing equation
    ``theta_ddot = 3 g / (2 l) sin(theta) + 3 / (m l^2) (T - damping theta_dot)`` with ``g = 10``,
    ``m = l = 1`` and ``damping = 0`` (a uniform rod; ``damping`` is a viscous friction torque at the
    pivot); ``theta = 0`` is upright.

    ## Discretisation
    Semi-implicit Euler, ``dt = 0.05``, angular speed clipped to ``[-8, 8]``, in Gymnasium's
    operation order: with the default coefficients, trajectories equal Gymnasium's ``Pendulum-v1`` bit for
    bit.

    ## Action Space
    ``Box(-2, 2, (1,), float32)``: the torque; values outside are clipped.

    ## Observation Space
    ``observation="cos_sin"`` (default): ``(cos theta, sin theta, theta_dot)`` as Gymnasium;
    ``observation="theta"``: ``(theta, theta_dot)`` with ``theta`` wrapped into ``[-pi, pi)``, as the
    paper observes (see :class:`PendulumTask` for why it is not the default).

    ## Rewards
    ``-(wrap(theta)^2 + 0.1 theta_dot^2 + 0.001 T^2)`` on the pre-step state.

    ## Starting State
    ``theta ~ U(-pi, pi)``, ``theta_dot ~ U(-1, 1)``; ``reset(options={"initial_state": (theta, theta_dot)})``.

    ## Episode End
    Truncation after 200 steps; never terminates.

    ## Rendering
    ``render_mode="rgb_array"``: a 400 x 400 sketch of the rod, 20 frames per second.

    ## Arguments
    ``observation``: ``"cos_sin"`` (default) or ``"theta"``; the physical coefficients ``g`` (10), ``m`` (1),
    ``l`` (1) and ``damping`` (0: a friction torque ``-damping theta_dot`` at the pivot), e.g.
    ``gym.make("pimbrl/Pendulum-v0", m=1.3)``. Masses and lengths must be > 0, ``damping`` >= 0.

    ## Version History
    * v0: initial version.
    """


class PendulumEnv(PhysicsEnv):  # noqa: D101 - docstring set below, __doc__ = _DOC
    __doc__ = _DOC
    task_class = PendulumTask
    metadata = {"render_modes": ["rgb_array"], "render_fps": PendulumTask.render_fps}  # noqa: RUF012


class PendulumVectorEnv(PhysicsVectorEnv):  # noqa: D101 - docstring set below, __doc__ = _DOC
    __doc__ = _DOC + "\n    Native vector version: all sub-environments advance in one NumPy call.\n"
    task_class = PendulumTask


def fast_states(task: Task, rng: np.random.Generator, n: int) -> np.ndarray:
    """Out of sample: Pendulum states uniform over the whole state space, up to the speed limit."""
    max_speed = task.physics.max_speed  # type: ignore[attr-defined]  # Pendulum
    return np.stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-max_speed, max_speed, n)], axis=1)


#: the declaration: recipes in pendulum.yaml beside this file, out-of-sample set and model-study settings
SYSTEM = System(
    id="pimbrl/Pendulum-v0",
    env=PendulumEnv,
    vector_env=PendulumVectorEnv,
    episode_steps=200,
    aliases=("pendulum",),
    preset=Path(__file__).with_suffix(".yaml"),  # default, paper (and best where one is recorded)
    out_of_sample=fast_states,
    model_eval={"transitions": 2_000, "steps": 3_000},
    feedback="energy-lqr",  # energy pumping, then the LQR of the reward's weights near the top
)
