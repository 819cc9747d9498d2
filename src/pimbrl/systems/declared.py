"""Declare a system of your own: an ODE or a 1-D periodic PDE, its task and its bounds, in one class.

Subclass :class:`ODESystem` or :class:`PeriodicPDESystem`, set the class attributes and write the equation
(array-agnostic: the same code serves NumPy in the simulator and torch in the physics loss), the reward
and the initial-state distribution; then :func:`declare` builds the Gymnasium environments (single and
native vector) and registers the system. From the one class the library derives:

* the simulator (a batched float64 reference integrator: RK4 or explicit Euler, ``substeps`` per control
  step with the action held);
* the environments, with disjoint train / validation / test initial draws (separate seed streams: training
  resets from the env's seed, validation from :data:`pimbrl.envs.VALIDATION_SEED`, evaluation from
  the evaluation seed);
* the physics residual of PiMBRL, the scheme-as-model and hybrid models, learned coefficients (ODEs), and
  for a PDE the convolutional models and the ETDRK4 coarse step of its linear part;
* the validation of coefficients from their declared bounds (:class:`Coefficient`).

See docs/systems.md for a walk-through and examples/duffing.py, examples/allen_cahn.py for two systems.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, cast

import numpy as np
import torch
from gymnasium import spaces

from ..envs.base import PhysicsEnv, PhysicsVectorEnv
from ..envs.task import Task, check_finite_number
from ..physics.base import Array, Physics, xp_of
from ..physics.kernels import PDEKernelSpec
from ..physics.pde import SemilinearPDE
from ..physics.stencil import Stencil
from .registry import System, SystemSpecError, register

__all__ = [
    "Coefficient",
    "DeclaredTask",
    "FourierOperator",
    "ODESystem",
    "PeriodicPDESystem",
    "declare",
    "gaussian_actuators",
    "xp_of",
]


@dataclass(frozen=True)
class Coefficient:
    """A physical coefficient: its default value and the interval of physical values ``[low, high]``.

    Values outside the interval (or not finite) are refused when the system is built, with a one-line error
    that names the coefficient and its bounds.
    """

    default: float
    low: float = -math.inf
    high: float = math.inf
    doc: str = ""

    def __post_init__(self) -> None:
        if not (self.low <= self.default <= self.high) or not math.isfinite(self.default):
            raise SystemSpecError(f"a Coefficient's default {self.default!r} must be finite and in [{self.low}, {self.high}]")

    def check(self, system: str, name: str, value: Any) -> float:
        """``value`` as a float if it is a finite number within the bounds, else a one-line ``ValueError``."""
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise ValueError(f"{system}: coefficient {name} must be a number, got {value!r}")
        v = float(value)
        if not (math.isfinite(v) and self.low <= v <= self.high):
            raise ValueError(
                f"{system}: coefficient {name} must be a finite number in [{self.low:g}, {self.high:g}], got {value!r}"
            )
        return v


def _declared(cls: type, attr: str) -> Any:
    if not hasattr(cls, attr):
        raise SystemSpecError(f"{cls.__name__} must set the class attribute {attr}")
    return getattr(cls, attr)


#: names a coefficient may not take: the settings of a declared system (a coefficient would overwrite them)
_RESERVED = frozenset(
    {"n", "length", "dx", "x", "dt", "substeps", "method", "integrator", "name", "state_dim", "action_dim",
     "action_low", "action_high", "episode_steps", "divergence_bound", "linear", "actuator_shapes", "bounds",
     "coefficients", "nonlinear_coef", "reflection_symmetric", "shift_symmetric"}
)  # fmt: skip


def _check_settings(system: Any) -> None:
    """One-line :class:`SystemSpecError` for a declared system's settings that cannot work (each its own message)."""
    name = system.name
    if not (math.isfinite(system.dt) and system.dt > 0):
        raise SystemSpecError(f"{name}: dt must be a finite number > 0, got {system.dt!r}")
    if system.substeps < 1:
        raise SystemSpecError(f"{name}: substeps must be >= 1, got {system.substeps!r}")
    low, high = system.action_low, system.action_high
    if low.shape != high.shape or low.size == 0:
        raise SystemSpecError(
            f"{name}: action_low and action_high need one bound per action, got {low.tolist()} and {high.tolist()}"
        )
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(low < high)):
        raise SystemSpecError(f"{name}: each action needs finite bounds with action_low < action_high")


class _Declared:
    """What both kinds of declared system share: named, bounded coefficients and the task's parts."""

    #: the coefficients by name (replaced by their names in :attr:`Physics.coefficients`; kept in :attr:`bounds`)
    bounds: ClassVar[dict[str, Coefficient]] = {}
    coefficients: tuple[str, ...] = ()
    episode_steps: ClassVar[int] = 200
    name: str = "system"

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        declared = cls.__dict__.get("coefficients")
        if declared is None:
            return
        if not isinstance(declared, Mapping):
            raise SystemSpecError(
                f"{cls.__name__}.coefficients must be a dict of name -> Coefficient(default, low, high), got {declared!r}"
            )
        for key, c in declared.items():
            if not isinstance(c, Coefficient):
                raise SystemSpecError(f"{cls.__name__}.coefficients[{key!r}] must be a Coefficient(default, low, high)")
            if not isinstance(key, str) or not key.isidentifier() or key in _RESERVED or hasattr(Physics, key):
                raise SystemSpecError(
                    f"{cls.__name__}: {key!r} cannot name a coefficient (a setting or method of every system has that name)"
                )
        cls.bounds = dict(declared)
        cls.coefficients = tuple(declared)

    def _set_settings(self) -> None:
        """The solver step, the steps per control step and the action bounds from the class, checked."""
        cls = type(self)
        physics = cast(Physics, self)
        physics.action_low = np.atleast_1d(np.asarray(_declared(cls, "action_low"), dtype=np.float64))
        physics.action_high = np.atleast_1d(np.asarray(_declared(cls, "action_high"), dtype=np.float64))
        physics.action_dim = len(physics.action_low)
        physics.dt = float(_declared(cls, "dt"))
        physics.substeps = int(_declared(cls, "substeps"))
        _check_settings(self)

    def _set_coefficients(self, values: Mapping[str, Any]) -> None:
        unknown = [k for k in values if k not in self.bounds]
        if unknown:
            known = ", ".join(self.bounds) or "none"
            raise ValueError(f"{self.name} has no coefficient {unknown[0]!r}; its coefficients are: {known}")
        for key, c in self.bounds.items():
            setattr(self, key, c.check(self.name, key, values.get(key, c.default)))

    def with_coefficients(self, **values: float) -> Any:
        """The same system with some coefficients changed (checked against their bounds)."""
        if not values:
            return self
        return type(self)(**{**self.coefficient_values(), **values})  # type: ignore[attr-defined]

    # ------------------------------------------------------------------ the task (override these)
    def initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``(n, state_dim)`` initial states drawn with ``rng`` (every system must define it)."""
        raise NotImplementedError(f"{type(self).__name__} must define initial_states(self, rng, n)")

    def observe(self, u: Array, k: Array | int) -> Array:
        """The observation of state ``u`` at control step ``k`` (default: the state itself)."""
        return u

    # ------------------------------------------------------------------ the simulator (derived)
    def advance(self, u: np.ndarray, a: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step of the reference integrator in float64 for a batch, and its rewards."""
        u = np.asarray(u, dtype=np.float64)
        a = np.asarray(a, dtype=np.float64)
        physics = cast(Physics, self)  # (a mixin of Physics subclasses)
        with np.errstate(over="ignore", invalid="ignore"):  # a blow-up is the environment's to report
            u_next = physics.step(u, a)
            return u_next, physics.reward(u, a, u_next, k)


class ODESystem(_Declared, Physics):
    """Base class of a user ODE system ``du/dt = rhs(u, a)``.

    Set, as class attributes: ``name``, ``state_dim``, ``action_low`` and ``action_high`` (one bound per
    action), ``dt`` (the solver step), ``substeps`` (solver steps per control step, default 1),
    ``integrator`` (``"rk4"``, default, or ``"euler"``), ``episode_steps``, ``divergence_bound`` and
    ``coefficients`` (name -> :class:`Coefficient`); define :meth:`rhs` (reading the coefficients as
    ``self.<name>``), :meth:`reward` and :meth:`initial_states`. The coefficients are keyword arguments of
    the constructor and of the environment (``gym.make(id, delta=0.3)``).
    """

    substeps = 1
    integrator: ClassVar[str] = "rk4"
    tensor_coefficients = True

    def __init__(self, **values: float) -> None:
        self._set_coefficients(values)
        _declared(type(self), "state_dim")
        if self.integrator not in ("rk4", "euler"):
            raise SystemSpecError(f"{self.name}: integrator must be 'rk4' or 'euler', got {self.integrator!r}")
        self._set_settings()

    def substep(self, u: Array, a: Array) -> Array:
        """One solver step: classic RK4 (default) or explicit Euler, with the action held."""
        dt = self.dt
        k1 = self.rhs(u, a)
        if self.integrator == "euler":
            return u + dt * k1
        k2 = self.rhs(u + 0.5 * dt * k1, a)
        k3 = self.rhs(u + 0.5 * dt * k2, a)
        k4 = self.rhs(u + dt * k3, a)
        return u + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


class FourierOperator:
    """A linear periodic operator given by its Fourier symbol: ``L u = ifft(symbol * fft(u))``.

    Args:
        symbol: the eigenvalues on the ``n`` FFT modes (``numpy.fft.fftfreq`` order), real for a symmetric
            operator (diffusion, hyper-diffusion).

    It offers what :class:`~pimbrl.physics.stencil.Stencil` offers the PDE machinery: :meth:`apply` (NumPy or
    torch) and :meth:`symbol`.
    """

    def __init__(self, symbol: np.ndarray) -> None:
        self._symbol = np.asarray(symbol, dtype=np.complex128)
        if self._symbol.ndim != 1 or not np.all(np.isfinite(self._symbol)):
            raise SystemSpecError("a Fourier symbol must be a finite 1-D array, one eigenvalue per grid point")
        self.real = bool(np.allclose(self._symbol.imag, 0.0))
        self.name = "fourier"

    def symbol(self, n: int) -> np.ndarray:
        """The eigenvalues on the ``n`` FFT modes."""
        if n != len(self._symbol):
            raise ValueError(f"this Fourier symbol has {len(self._symbol)} modes, not {n}")
        return self._symbol.copy()

    def apply(self, u: Array) -> Array:
        """``L u`` along the last axis."""
        n = len(self._symbol)
        if isinstance(u, torch.Tensor):
            if self.real:
                s = torch.as_tensor(self._symbol.real[: n // 2 + 1], dtype=u.dtype, device=u.device)
                return torch.fft.irfft(s * torch.fft.rfft(u), n=n)
            s = torch.as_tensor(self._symbol, device=u.device)
            return torch.fft.ifft(s * torch.fft.fft(u)).real.to(u.dtype)
        if self.real:
            return np.fft.irfft(self._symbol.real[: n // 2 + 1] * np.fft.rfft(u), n=n)
        return np.fft.ifft(self._symbol * np.fft.fft(u)).real


def gaussian_actuators(x: np.ndarray, centres: Any, width: float, length: float) -> np.ndarray:
    """``(len(centres), n)`` periodic Gaussian actuator shapes ``exp(-(d / width)^2)``, ``d`` the periodic distance."""
    d = x[None, :] - np.asarray(centres, dtype=np.float64)[:, None]
    d = (d + length / 2) % length - length / 2
    return np.exp(-((d / width) ** 2))


class PeriodicPDESystem(_Declared, SemilinearPDE):
    """Base class of a user PDE ``u_t = L u + N(u) + sum_i a_i g_i(x)`` on a periodic 1-D grid.

    Set, as class attributes: ``name``, ``n`` (grid points), ``length`` (of the domain), ``dt``, ``substeps``,
    ``method`` (``"rk4"``, default, or ``"euler"``), ``action_low``, ``action_high`` (one bound per
    actuator), ``episode_steps``, ``divergence_bound``, ``coefficients`` (name -> :class:`Coefficient`),
    ``reflection_symmetric`` (whether ``u(x) -> -u(-x)`` maps solutions to solutions); define
    :meth:`linear_operator` (a :class:`~pimbrl.physics.Stencil` scaled by the grid spacing, or a
    :class:`FourierOperator`), :meth:`nonlinearity` (array-agnostic), :meth:`actuators`, :meth:`reward`
    and :meth:`initial_states`. ``self.x`` (the grid) and ``self.dx`` are set before those are called.

    Learned coefficients and the learned correction are not offered for a declared PDE yet (docs/systems.md).
    """

    method = "rk4"
    reflection_symmetric = False

    def __init__(self, **values: float) -> None:
        self._set_coefficients(values)
        self.n = int(_declared(type(self), "n"))
        self.length = float(_declared(type(self), "length"))
        self.dx = self.length / self.n
        self.x = np.arange(self.n) * self.dx
        self.state_dim = self.n
        if self.method not in ("rk4", "euler"):
            raise SystemSpecError(f"{self.name}: method must be 'rk4' or 'euler', got {self.method!r}")
        if self.n < 5 or self.n != _declared(type(self), "n") or not (math.isfinite(self.length) and self.length > 0):
            raise SystemSpecError(f"{self.name}: need a whole number n >= 5 of grid points and a finite length > 0")
        self._set_settings()
        # a FourierOperator offers what the PDE machinery calls on a Stencil here: apply and symbol
        self.linear = self.linear_operator()  # type: ignore[assignment]
        self.actuator_shapes = np.asarray(self.actuators(), dtype=np.float64)
        if self.actuator_shapes.shape != (self.action_dim, self.n):
            raise SystemSpecError(
                f"{self.name}: actuators() must return shape ({self.action_dim}, {self.n}), got {self.actuator_shapes.shape}"
            )
        self.nonlinear_coef = 0.0
        self.check_stability()

    # ------------------------------------------------------------------ what a user defines
    def linear_operator(self) -> Stencil | FourierOperator:
        """The linear part ``L`` (a stencil already divided by its power of ``dx``, or a Fourier symbol)."""
        raise NotImplementedError(f"{type(self).__name__} must define linear_operator(self)")

    def nonlinearity(self, u: Array) -> Array:
        """The nonlinear part ``N(u)``, array-agnostic (NumPy and torch), batched over leading axes."""
        raise NotImplementedError(f"{type(self).__name__} must define nonlinearity(self, u)")

    def actuators(self) -> np.ndarray:
        """The ``(action_dim, n)`` actuator shapes ``g_i(x)``."""
        raise NotImplementedError(f"{type(self).__name__} must define actuators(self)")

    # ------------------------------------------------------------------ derived
    def nonlinear(self, u: Array, f: Array) -> Array:
        """``N(u) + f``: everything but the linear part."""
        return self.nonlinearity(u) + f

    def upwind(self, u: Array) -> Array:
        """Not used: a declared PDE's nonlinearity is :meth:`nonlinearity`."""
        raise NotImplementedError("a declared PDE has no upwind term; see nonlinearity()")

    def operators(self, values: Mapping[str, Any]) -> tuple[Any, Any, Any]:
        """Not offered yet: learned coefficients of a declared PDE (docs/systems.md)."""
        raise ValueError(f"{self.name}: learning the coefficients of a declared PDE is not supported yet")

    def kernel_spec(self) -> PDEKernelSpec:
        """Not used: a declared PDE runs on the batched NumPy reference integrator."""
        raise NotImplementedError("a declared PDE has no compiled kernel")


class DeclaredTask(Task):
    """The task of a declared system: its observation, Box actions, episode and initial draws.

    Args:
        divergence_penalty: reward of a step that blows up (default -100), a finite number.
        **coefficients: the system's coefficients that differ from their defaults (checked against their bounds).
    """

    physics_class: ClassVar[type[Any]]
    physics: Any  # an ODESystem or a PeriodicPDESystem: a Physics with the declared task's parts
    action_space: spaces.Box

    def __init__(self, divergence_penalty: float = -100.0, **coefficients: float) -> None:
        self.physics = self.physics_class(**coefficients)
        self.max_episode_steps = int(self.physics.episode_steps)
        self.divergence_penalty = check_finite_number(divergence_penalty, "divergence_penalty")
        probe = self.sample_initial_states(np.random.default_rng(0), 1)
        obs = np.asarray(self.physics.observe(probe, np.zeros(1, dtype=np.int64)))
        bound = np.float32(self.physics.divergence_bound + 1.0) if math.isfinite(self.physics.divergence_bound) else np.inf
        self.observation_space = spaces.Box(-bound, bound, shape=obs.shape[1:], dtype=np.float32)
        self.action_space = spaces.Box(
            self.physics.action_low.astype(np.float32), self.physics.action_high.astype(np.float32), dtype=np.float32
        )

    def sample_initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """The system's :meth:`initial_states`, checked: ``(n, state_dim)``, finite."""
        u = np.asarray(self.physics.initial_states(rng, n), dtype=np.float64)
        if u.shape != (n, self.state_dim) or not np.all(np.isfinite(u)):
            raise ValueError(
                f"{self.physics.name}.initial_states(rng, {n}) must return {n} finite states of shape ({n}, {self.state_dim}), "
                f"got shape {u.shape}"
            )
        return u

    def observe(self, u: np.ndarray, k: np.ndarray) -> np.ndarray:
        """The system's :meth:`observe` as float32."""
        return np.asarray(self.physics.observe(u, k), dtype=np.float32)

    def physical_action(self, actions: Any, batch: int) -> np.ndarray:
        """Check the actions' shape and finiteness and clip them to the bounds."""
        return self._box_action(actions, batch, self.action_space, self.physics.action_low, self.physics.action_high)


def declare(
    physics_class: type[Any],
    id: str,
    *,
    aliases: tuple[str, ...] = (),
    preset: Mapping[str, Any] | str | Path | None = None,
    out_of_sample: Callable[[Task, np.random.Generator, int], np.ndarray] | None = None,
    model_eval: Mapping[str, Any] | None = None,
    feedback: str | None = None,
    feedback_gains: tuple[float, ...] = (),
    feedback_options: Mapping[str, Any] | None = None,
) -> System:
    """Build the environments of a declared system and register it; returns its :class:`System`.

    Args:
        physics_class: a subclass of :class:`ODESystem` or :class:`PeriodicPDESystem`.
        id: its Gymnasium id, ``namespace/Name-v0``.
        aliases: short names for the command line (``pimbrl train duffing``).
        preset: its training recipes: the path of a preset file (YAML, :mod:`pimbrl.systems.presets`) or the
            same structure as a mapping; without one, a run says so when it starts.
        out_of_sample: initial states outside the training distribution for ``pimbrl model-eval``.
        model_eval: settings of ``pimbrl model-eval``.
        feedback: its feedback floor (``pimbrl train --method feedback``): ``proportional``, ``lqr`` or
            ``energy-lqr``; ``None``: proportional for a PDE with actuator shapes, an LQR around the origin else.
        feedback_gains: the gains that floor tries on the validation draws (empty: its kind's default grid).
        feedback_options: the controller's further arguments (an LQR's target ``state``, ``action``, ``q``).
    """
    if not (isinstance(physics_class, type) and issubclass(physics_class, (ODESystem, PeriodicPDESystem))):
        raise SystemSpecError(f"declare() takes a subclass of ODESystem or PeriodicPDESystem, got {physics_class!r}")
    physics_class()  # build it once: a declaration error surfaces here, at import, in one line
    task = type(
        f"{physics_class.__name__}Task", (DeclaredTask,), {"physics_class": physics_class, "__module__": physics_class.__module__}
    )
    return register_task(
        task,
        id,
        aliases=aliases,
        preset=preset,
        out_of_sample=out_of_sample,
        model_eval=model_eval,
        feedback=feedback,
        feedback_gains=feedback_gains,
        feedback_options=feedback_options,
    )


def register_task(
    task: type[DeclaredTask],
    id: str,
    *,
    aliases: tuple[str, ...] = (),
    preset: Mapping[str, Any] | str | Path | None = None,
    out_of_sample: Callable[..., np.ndarray] | None = None,
    model_eval: Mapping[str, Any] | None = None,
    feedback: str | None = None,
    feedback_gains: tuple[float, ...] = (),
    feedback_options: Mapping[str, Any] | None = None,
) -> System:
    """Build the single and vector environments of a declared system's task and register the system.

    The classes are named after the system's class and documented by its docstring (:func:`declare`,
    :func:`pimbrl.systems.declare_external`).
    """
    physics_class = task.physics_class
    stem, module = physics_class.__name__, physics_class.__module__
    doc = physics_class.__doc__ or f"The declared system {id}."
    env = type(f"{stem}Env", (PhysicsEnv,), {"task_class": task, "__doc__": doc, "__module__": module})
    vector = type(f"{stem}VectorEnv", (PhysicsVectorEnv,), {"task_class": task, "__doc__": doc, "__module__": module})
    system = System(
        id=id,
        env=env,
        vector_env=vector,
        episode_steps=int(physics_class.episode_steps),
        aliases=tuple(aliases),
        preset=preset if isinstance(preset, (str, Path)) else dict(preset or {}),
        out_of_sample=out_of_sample,
        model_eval=dict(model_eval or {}),
        feedback=feedback,
        feedback_gains=tuple(feedback_gains),
        feedback_options=dict(feedback_options or {}),
    )
    try:
        system.recipes()  # a preset that cannot be read is an error here, at import, in one line
    except ValueError as exc:
        raise SystemSpecError(str(exc)) from None
    return register(system)
