"""Viscous Burgers equation with two actuators, tracking a moving reference (Liu & Wang 2021, 3.2).

    u_t + (u^2/2)_xi = nu u_xixi + a1 f1(xi) + a2 f2(xi),   xi in [0, 1) periodic, nu = 0.01,

discretised as the authors' code computes it (docs/environments.md, section "Viscous Burgers"):
4th-order central diffusion, 2nd-order backward (upwind for u > 0) convection of ``s = u^2/2``,
explicit Euler with dt = 0.001 and 500 steps per control step (0.5 time units). The paper's dt = 0.01
blows up in the first control step.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, overload

import numpy as np
import torch
from gymnasium import spaces

from ..envs.base import PhysicsEnv, PhysicsVectorEnv
from ..envs.render import BLUE, RED, field_frame
from ..envs.task import Task, check_finite_number
from ..physics.base import Array, check_coefficient, records_arguments, xp_of
from ..physics.kernels import PDEKernel, PDEKernelSpec
from ..physics.pde import SemilinearPDE
from ..physics.stencil import Stencil
from .registry import System

__all__ = ["BURGERS_D1", "BURGERS_D2", "BURGERS_UPWIND", "SYSTEM", "Burgers", "BurgersEnv", "BurgersTask", "BurgersVectorEnv"]


#: 4th-order central second difference (raw: divide by dx^2).
BURGERS_D2 = Stencil.centered((-1 / 12, 4 / 3, -5 / 2, 4 / 3, -1 / 12), "D2")
#: 4th-order central first difference (raw: divide by dx), for the ``drift`` term.
BURGERS_D1 = Stencil.centered((1 / 12, -2 / 3, 0.0, 2 / 3, -1 / 12), "D1")
#: 2nd-order backward first difference (raw: divide by dx), applied to u^2.
BURGERS_UPWIND = Stencil((-2, -1, 0), (0.5, -2.0, 1.5), "Db")


_NO_WEIGHTS = np.zeros(4)  # the Burgers reward is evaluated on the final state, not accumulated


class Burgers(SemilinearPDE):
    """The controlled viscous Burgers system with a sinusoidal reference ``ref_k``.

    Args:
        n: grid points (150).
        nu: viscosity (0.01).
        dt: Euler step (0.001).
        substeps: Euler steps per control step (500).
        action_low, action_high: actuator amplitude bounds (-0.025, 0.075).
        episode_steps: control steps in one period of the reference (60).
        ref_mean, ref_amplitude: the reference is ``ref_mean + ref_amplitude * sin(2 pi k / episode_steps)``.
        divergence_bound: ``|u|`` beyond this counts as blown up (10).
        convection: factor of the convection term ``(u^2/2)_xi`` (1).
        damping: coefficient ``mu`` of a linear damping term ``-mu u`` on the right-hand side (0: none; a term
            a physics prior may miss).
        actuator_width: half-width ``w`` of the actuators ``exp(-((xi - c)/w)^2)`` (1/15, i.e. the paper's
            ``exp(-225 (xi - c)^2)``).
        drift: speed ``c`` of a linear advection term ``-c u_xi`` on the right-hand side (0: none; a term of a
            form a physics prior may lack altogether; 4th-order central difference).

    The physical coefficients (:attr:`coefficients`) are ``nu``, ``convection``, ``damping``,
    ``actuator_width`` and ``drift``.
    """

    name = "burgers"
    coefficients = ("nu", "convection", "damping", "actuator_width", "drift")

    @records_arguments
    def __init__(
        self,
        n: int = 150,
        nu: float = 0.01,
        dt: float = 0.001,
        substeps: int = 500,
        action_low: float = -0.025,
        action_high: float = 0.075,
        episode_steps: int = 60,
        ref_mean: float = 0.5,
        ref_amplitude: float = 0.05,
        divergence_bound: float = 10.0,
        convection: float = 1.0,
        damping: float = 0.0,
        actuator_width: float = 1 / 15,
        drift: float = 0.0,
    ) -> None:
        if n < 5:
            raise ValueError(f"Burgers needs at least 5 grid points, got n={n}")
        if dt <= 0 or substeps < 1:
            raise ValueError(f"need dt > 0, substeps >= 1; got dt={dt}, substeps={substeps}")
        nu = check_coefficient(self.name, "nu", nu, nonnegative=True, high=1.0)
        actuator_width = check_coefficient(self.name, "actuator_width", actuator_width, low=1e-3, high=1.0)
        for name, value in (("convection", convection), ("damping", damping), ("drift", drift)):
            check_coefficient(self.name, name, value, low=-1e3, high=1e3)
        self.n = int(n)
        self.dx = 1.0 / self.n
        self.nu = float(nu)
        self.dt = float(dt)
        self.substeps = int(substeps)
        self.state_dim = self.n
        self.action_dim = 2
        self.action_low = np.full(2, float(action_low))
        self.action_high = np.full(2, float(action_high))
        self.episode_steps = int(episode_steps)
        self.ref_mean = float(ref_mean)
        self.ref_amplitude = float(ref_amplitude)
        self.divergence_bound = float(divergence_bound)
        self.convection = float(convection)
        self.damping = float(damping)
        self.actuator_width = float(actuator_width)
        self.drift = float(drift)
        self.x = np.arange(self.n) * self.dx
        #: ``(2, n)`` actuator shapes, ``exp(-225 (xi - 0.25)^2)`` and ``exp(-225 (xi - 0.75)^2)`` by default
        self.actuator_shapes = self._shapes(self.actuator_width)
        #: the linear operator ``nu D2 / dx^2`` (``- mu`` with damping)
        self.linear = self._with_added_terms(BURGERS_D2.scaled(self.nu / self.dx**2, "nu*D2/dx^2"))
        #: coefficient of ``Db(u^2)``: ``-(u^2/2)_xi = -Db(u^2) / (2 dx)``
        self.nonlinear_coef = -self.convection / (2.0 * self.dx)
        self.method = "euler"
        self._kernel: PDEKernel | None = None

    def _shapes(self, width: Any) -> Any:
        xp = xp_of(width)
        d = xp.as_tensor(self.x[None, :] - self._centres[:, None]) if xp is torch else self.x[None, :] - self._centres[:, None]
        return xp.exp(-(1.0 / width**2) * d**2)

    _centres = np.array([0.25, 0.75])
    drift_stencil = BURGERS_D1

    def operators(self, values: Mapping[str, Any]) -> tuple[Any, Any, Any]:
        """``lam = nu D2/dx^2 - mu``, ``-convection / (2 dx)`` and the actuator shapes (see the base class)."""
        lam = self._added_eigenvalues(self._coefficient(values, "nu") * self._symbol(BURGERS_D2, 2, values), values)
        nonlinear = -self._coefficient(values, "convection") / (2.0 * self.dx)
        width = self._coefficient(values, "actuator_width")
        return lam, nonlinear, self._shapes(width)

    # ------------------------------------------------------------------ equation
    def upwind(self, u: Array) -> Array:
        """Raw backward difference ``Db(u^2)`` (upwind while ``u > 0``; divide by dx)."""
        return BURGERS_UPWIND.apply(u * u)

    # ------------------------------------------------------------------ task
    @overload
    def reference(self, k: int) -> float: ...
    @overload
    def reference(self, k: Array) -> Array: ...
    def reference(self, k: np.ndarray | torch.Tensor | int) -> np.ndarray | torch.Tensor | float:
        """Reference value at control step ``k``: ``0.5 + 0.05 sin(2 pi k / 60)``."""
        if isinstance(k, torch.Tensor):
            return self.ref_mean + self.ref_amplitude * torch.sin(2 * np.pi * (k / self.episode_steps))
        return self.ref_mean + self.ref_amplitude * np.sin(2 * np.pi * (k / self.episode_steps))

    def observe(self, u: Array, k: Array | int) -> Array:
        """Observation ``u - ref_k`` (``k`` broadcast over the state axis)."""
        ref = self.reference(k)
        if not isinstance(ref, float) and ref.ndim > 0:
            ref = ref[..., None]
        return u - ref

    def reward(self, u: Array, a: Array, u_next: Array, k: Array | int, path: Array | None = None) -> Array:
        """``-10 mean((u_next - ref_{k+1})^2)``: the tracking error after the step."""
        err = self.observe(u_next, k + 1)
        return -10.0 * (err * err).mean(-1)

    # ------------------------------------------------------------------ fast simulator
    def kernel_spec(self) -> PDEKernelSpec:
        """The compiled kernel's operators: exactly this object's stencils and explicit Euler."""
        return PDEKernelSpec(
            linear=self.linear,
            nonlinear_coef=self.nonlinear_coef,
            upwind_backward=BURGERS_UPWIND,
            upwind_forward=None,
            method="euler",
            n=self.n,
        )

    def advance(self, u: np.ndarray, a: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step of the compiled kernel, then the tracking reward of the reached state."""
        u = np.asarray(u, dtype=np.float64)
        a = np.asarray(a, dtype=np.float64)
        u_next, _, _ = self.run_kernel(u, a, False, _NO_WEIGHTS)
        return u_next, self.reward(u, a, u_next, np.asarray(k))


class BurgersTask(Task):
    """Burgers task: observation ``u - ref_k``, 2 actuators in ``[-0.025, 0.075]``, 60 control steps.

    Args:
        divergence_penalty: reward of a step that blows up, a finite number (default -100; any whole episode returns
            more than about -60).
        **coefficients: physical coefficients of :class:`pimbrl.systems.Burgers` that differ from the paper's
            (``nu``, ``convection``, ``damping``, ``actuator_width``, ``drift``), e.g. ``nu=0.013``: a system whose
            physics a prior may get wrong (docs/journal/2026-11-24-partial-physics-identification.md).
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
    Compiled float64 kernel generated from the stencil tables of :class:`pimbrl.systems.Burgers`.

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


def large_states(task: Task, rng: np.random.Generator, n: int) -> np.ndarray:
    """Out of sample: the task's Burgers initial shapes doubled (twice the amplitude and twice the offset)."""
    c = rng.uniform(0, 1, (n, 1))[:, 0]
    return 2.0 * task.initial_state(c)  # type: ignore[attr-defined]  # BurgersTask


#: the declaration: recipes in burgers.yaml beside this file, out-of-sample set and model-study settings
SYSTEM = System(
    id="pimbrl/Burgers-v0",
    env=BurgersEnv,
    vector_env=BurgersVectorEnv,
    episode_steps=60,
    aliases=("burgers",),
    preset=Path(__file__).with_suffix(".yaml"),  # default, paper (and best where one is recorded)
    out_of_sample=large_states,
    model_eval={"transitions": 1_200, "steps": 3_000},
    feedback="proportional",
)
