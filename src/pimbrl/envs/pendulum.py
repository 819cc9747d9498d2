"""Pendulum swing-up (Gymnasium's Pendulum dynamics)."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from gymnasium import spaces

from ..physics import Pendulum, wrap_angle
from .base import PhysicsEnv, PhysicsVectorEnv
from .render import BLACK, RED, Canvas
from .task import Task

__all__ = ["PendulumEnv", "PendulumTask", "PendulumVectorEnv"]


class PendulumTask(Task):
    """Pendulum task: torque in ``[-2, 2]``, 200 control steps.

    Args:
        observation: ``"cos_sin"`` (default, Gymnasium's ``(cos theta, sin theta, theta_dot)``) or ``"theta"``
            (the paper's ``(theta, theta_dot)`` with ``theta`` wrapped into ``[-pi, pi)``). The wrapped angle
            jumps from ``pi`` to ``-pi`` where the pendulum hangs down, so a smooth policy cannot pump energy
            through the bottom: TD3 then swings up from only part of the initial states (measured: mean
            test return stuck near -970, bimodal -1522 / -0.1, over 15,000 steps), like the paper's MFRL
            curve (below -800).
        **coefficients: physical coefficients of :class:`pimbrl.physics.Pendulum` that differ from Gymnasium's
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
