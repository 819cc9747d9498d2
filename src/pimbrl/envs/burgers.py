"""Viscous Burgers reference tracking with two actuators."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from ..physics import Burgers
from .base import PhysicsEnv, PhysicsVectorEnv
from .render import BLUE, RED, field_frame
from .task import Task, check_finite_number

__all__ = ["BurgersEnv", "BurgersTask", "BurgersVectorEnv"]


class BurgersTask(Task):
    """Burgers task: observation ``u - ref_k``, 2 actuators in ``[-0.025, 0.075]``, 60 control steps.

    Args:
        divergence_penalty: reward of a step that blows up, a finite number (default -100; any whole episode returns
            more than about -60).
        **coefficients: physical coefficients of :class:`pimbrl.physics.Burgers` that differ from the paper's
            (``nu``, ``convection``, ``damping``, ``actuator_width``, ``drift``), e.g. ``nu=0.013``: a system whose
            physics a prior may get wrong (docs/partial-physics.md).
    """

    max_episode_steps = 60
    render_fps = 2  # a control step is 0.5 time units
    physics: Burgers
    action_space: spaces.Box

    def __init__(self, divergence_penalty: float = -100.0, **coefficients: float) -> None:
        self.physics = Burgers(episode_steps=self.max_episode_steps).with_coefficients(**coefficients)
        self.physics.check_stability()  # a one-line error now rather than at the first step
        self.divergence_penalty = check_finite_number(divergence_penalty, "divergence_penalty")
        bound = np.float32(self.physics.divergence_bound + 1.0)
        self.observation_space = spaces.Box(-bound, bound, shape=(self.physics.n,), dtype=np.float32)
        self.action_space = spaces.Box(
            self.physics.action_low.astype(np.float32), self.physics.action_high.astype(np.float32), dtype=np.float32
        )

    def initial_state(self, c: np.ndarray) -> np.ndarray:
        """``u0 = 0.2 c exp(-25 (xi - 0.5)^2) + 0.2 (1 - c) sin(4 pi xi) + 0.2`` for each ``c`` in ``[0, 1)``."""
        x = self.physics.x[None, :]
        c = np.asarray(c, dtype=np.float64)[:, None]
        return 0.2 * c * np.exp(-25.0 * (x - 0.5) ** 2) + 0.2 * (1.0 - c) * np.sin(4 * np.pi * x) + 0.2

    def sample_initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Initial fields of :meth:`initial_state` with ``c ~ U[0, 1)``."""
        return self.initial_state(rng.uniform(0.0, 1.0, size=n))

    def observe(self, u: np.ndarray, k: np.ndarray) -> np.ndarray:
        """``u - ref_k`` as float32."""
        return self.physics.observe(u, k).astype(np.float32)

    def physical_action(self, actions: Any, batch: int) -> np.ndarray:
        """Check the actions' shape and finiteness and clip them to the actuator bounds."""
        return self._box_action(actions, batch, self.action_space, self.physics.action_low, self.physics.action_high)

    def render(self, u: np.ndarray, k: int) -> np.ndarray:
        """The field ``u`` (blue) and the reference ``ref_k`` (red) over the grid; axis ``[-1, 1]``."""
        ref = np.full(len(u), self.physics.reference(k))
        return field_frame([(ref, RED), (u, BLUE)], self.render_scale)


_DOC = """Viscous Burgers reference tracking with two actuators (Liu & Wang 2021, section 3.2).

    ## Description
    A periodic 1-D velocity field on the unit interval is driven by two Gaussian actuators so that it
    tracks a spatially uniform reference that oscillates once per episode.

    ## Governing equation
    ``u_t + (u^2/2)_xi = nu u_xixi + a1 f1(xi) + a2 f2(xi)``, ``nu = 0.01``,
    ``f1 = exp(-225 (xi - 0.25)^2)``, ``f2 = exp(-225 (xi - 0.75)^2)``.

    ## Discretisation
    150 points on ``[0, 1)``; 4th-order central diffusion, 2nd-order backward (upwind for ``u > 0``)
    convection of ``u^2/2``; explicit Euler with ``dt = 0.001``, 500 steps per control step
    (0.5 time units), forcing frozen. (The paper's ``dt = 0.01`` blows up in the first control step.)
    Compiled float64 kernel generated from the stencil tables of :class:`pimbrl.physics.Burgers`.

    ## Action Space
    ``Box(-0.025, 0.075, (2,), float32)``: actuator amplitudes; values outside are clipped.

    ## Observation Space
    ``Box(-11, 11, (150,), float32)``: ``u - ref_k`` at the current control step ``k`` (no phase
    information, as in the paper).

    ## Rewards
    ``-10 mean((u_{k+1} - ref_{k+1})^2)`` on the post-step state, ``ref_k = 0.5 + 0.05 sin(2 pi k/60)``.
    (The paper's "return of 0.1" matches no coded reward; this is the code's scale.)

    ## Starting State
    ``u0 = 0.2 c exp(-25 (xi - 0.5)^2) + 0.2 (1 - c) sin(4 pi xi) + 0.2`` with ``c ~ U[0, 1)``;
    ``reset(options={"initial_state": u})`` starts from a given field (shape ``(150,)``).

    ## Episode End
    Truncation after 60 control steps (one period of the reference). Termination only on blow-up
    (non-finite or ``|u| > 10``), with reward ``divergence_penalty`` (-100) and ``info["diverged"]``.

    ## Rendering
    ``render_mode="rgb_array"``: the field (blue) and the reference (red) over the grid, 2 frames per
    second (one per control step).

    ## Arguments
    ``divergence_penalty`` (a finite number); the physical coefficients ``nu`` (0.01), ``convection`` (1),
    ``damping`` (0: a term ``-mu u`` added to the right-hand side), ``actuator_width`` (1/15) and ``drift`` (0: a
    term ``-c u_xi``), e.g.
    ``gym.make("pimbrl/Burgers-v0", nu=0.013)``.

    ## Version History
    * v0: initial version, numerics of the authors' code (docs/environments.md, section
      "Viscous Burgers", lists them in full).
    """


class BurgersEnv(PhysicsEnv):  # noqa: D101 - docstring set below, __doc__ = _DOC
    __doc__ = _DOC
    task_class = BurgersTask
    metadata = {"render_modes": ["rgb_array"], "render_fps": BurgersTask.render_fps}  # noqa: RUF012


class BurgersVectorEnv(PhysicsVectorEnv):  # noqa: D101 - docstring set below, __doc__ = _DOC
    __doc__ = _DOC + "\n    Native vector version: all sub-environments advance in one compiled call.\n"
    task_class = BurgersTask
