"""The :class:`Physics` interface: one object per controlled system that owns its governing equation.

Every consumer of an equation calls the same object:

* the Gymnasium environments call :meth:`Physics.advance` (fast, batched, float64, compiled for PDEs);
* the physics-informed model loss calls :meth:`Physics.residual` (torch, differentiable);
* imagined environments call :meth:`Physics.reward` and :meth:`Physics.terminated` on predicted states;
* plots and tests call :meth:`Physics.step` (the plain reference integrator, NumPy or torch).

The reference methods (``rhs``, ``substep``, ``step``, ``residual``, ``reward``) accept NumPy arrays or
torch tensors of any floating dtype, batched over leading dimensions; the state is the last axis.
"""

from __future__ import annotations

import copy
import difflib
import functools
import inspect
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

import numpy as np
import torch

Array = TypeVar("Array", np.ndarray, torch.Tensor)

__all__ = ["Array", "Physics", "active", "check_coefficient", "records_arguments", "superpose", "xp_of"]

PhysicsT = TypeVar("PhysicsT", bound="Physics")
InitT = TypeVar("InitT", bound=Callable[..., None])


def records_arguments(init: InitT) -> InitT:
    """Decorate a :class:`Physics` constructor so that the object remembers the arguments it was built with.

    :meth:`Physics.with_coefficients` rebuilds the system from them with some coefficients changed.
    """
    signature = inspect.signature(init)

    @functools.wraps(init)
    def wrapper(self: Physics, *args: Any, **kwargs: Any) -> None:
        bound = signature.bind(self, *args, **kwargs)
        bound.apply_defaults()
        init(self, *args, **kwargs)
        self._arguments = {k: v for k, v in bound.arguments.items() if k != "self"}

    return wrapper  # type: ignore[return-value]


def check_coefficient(
    system: str,
    name: str,
    value: float,
    *,
    positive: bool = False,
    nonnegative: bool = False,
    low: float = -math.inf,
    high: float = math.inf,
) -> float:
    """``value`` as a float if it is a finite number within the system's physical bounds.

    That is ``> 0`` where ``positive``, ``>= 0`` where ``nonnegative``, and within ``[low, high]``.

    Raises:
        ValueError: a one-line message naming ``system``, the argument ``name`` and what it must be.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{system}: {name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or (positive and not v > 0) or (nonnegative and not v >= 0) or not low <= v <= high:
        if math.isfinite(high) or math.isfinite(low):
            left = "(0" if positive else "[0" if nonnegative else f"[{low:g}"
            need = f" in {left}, {high:g}]"
        else:
            need = " > 0" if positive else " >= 0" if nonnegative else ""
        raise ValueError(f"{system}: {name} must be a finite number{need}, got {value!r}")
    return v


def active(coefficient: float | torch.Tensor) -> bool:
    """Whether a term with this coefficient must be computed: a nonzero number, or any tensor.

    Terms a system lacks by default (a friction, a damping) are skipped at 0 so that the default dynamics
    stay bit for bit those of the reference implementation; a tensor coefficient (being learned, see
    :meth:`Physics.with_coefficient_tensors`) always keeps its term, so that its gradient exists even at 0.
    """
    return isinstance(coefficient, torch.Tensor) or coefficient != 0.0


def xp_of(x: Any) -> Any:
    """The array namespace of ``x``: the ``torch`` module for tensors, else ``numpy``."""
    return torch if isinstance(x, torch.Tensor) else np


def superpose(a: Array, shapes: np.ndarray | torch.Tensor) -> Array:
    """Forcing field ``sum_i a[..., i] * shapes[i]`` of actuator amplitudes ``a`` and shape functions.

    Written as an explicit sum rather than a matmul so that its rounding does not depend on the batch
    shape: a batched step then equals the stacked single steps bit for bit.
    """
    g: np.ndarray | torch.Tensor = shapes
    if isinstance(a, torch.Tensor):
        g = torch.as_tensor(shapes, dtype=a.dtype, device=a.device)
    f = a[..., 0:1] * g[0]
    for i in range(1, g.shape[0]):
        f = f + a[..., i : i + 1] * g[i]
    return f


class Physics(ABC):
    """A controlled dynamical system ``du/dt = F(u, a)`` with its discretisation, reward and limits.

    Attributes:
        name: short identifier.
        state_dim: length of the physical state vector ``u``.
        action_dim: number of physical control inputs ``a``.
        action_low, action_high: bounds of the physical control inputs.
        dt: the solver's time step.
        substeps: solver steps per control step (the action is frozen over a control step).
        divergence_bound: a state with ``|u| > divergence_bound`` anywhere (or any non-finite value)
            counts as blown up.
    """

    name: str = "physics"
    state_dim: int
    action_dim: int
    action_low: np.ndarray
    action_high: np.ndarray
    dt: float
    substeps: int
    divergence_bound: float = np.inf
    #: names of the physical coefficients (constructor arguments and attributes of the same name) that an
    #: environment can be given and that a physics prior can get wrong: see :meth:`with_coefficients`
    coefficients: tuple[str, ...] = ()
    _arguments: dict[str, Any]

    def coefficient_values(self) -> dict[str, float]:
        """The physical coefficients of this system, by name (see :attr:`coefficients`)."""
        return {name: float(getattr(self, name)) for name in self.coefficients}

    def with_coefficients(self: PhysicsT, **values: float) -> PhysicsT:
        """The same system with some physical coefficients changed; every other setting is kept.

        With no values, this object itself.

        Raises:
            ValueError: for a name that is not one of :attr:`coefficients`, or a value that is not a finite
                number.
        """
        self._check_coefficient_names(values)
        for name, value in values.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"{self.name}: coefficient {name} must be a finite number, got {value!r}")
        if not values:
            return self
        if not hasattr(self, "_arguments"):
            raise TypeError(f"{type(self).__name__}.__init__ is not decorated with @records_arguments")
        return type(self)(**{**self._arguments, **{k: float(v) for k, v in values.items()}})

    #: whether :meth:`with_coefficient_tensors` works (the ODE systems: their equations are written once for
    #: floats and tensors alike); the PDEs expose their differentiable parts through ``operators`` instead
    tensor_coefficients: bool = False

    def with_coefficient_tensors(self: PhysicsT, values: Mapping[str, torch.Tensor]) -> PhysicsT:
        """A copy whose coefficients ``values`` are tensors, so that its steps are differentiable in them.

        For fitting coefficients to data (the inverse problem): ``copy.step(u, a)`` on torch tensors carries
        the gradient to ``values``. Terms skipped at a zero float coefficient are computed for a tensor one
        (:func:`active`). The copy is for torch computations only.

        Raises:
            ValueError: for a system without this ability (see :attr:`tensor_coefficients`) or an unknown name.
        """
        if not self.tensor_coefficients:
            raise ValueError(f"{self.name}: coefficients cannot be given as tensors (only the ODE systems take them)")
        self._check_coefficient_names(values)
        out = copy.copy(self)
        for name, value in values.items():
            setattr(out, name, value)
        out._derive_coefficients()
        return out

    def _check_coefficient_names(self, names: Iterable[str]) -> None:
        """A one-line ``ValueError`` for a name that is not one of :attr:`coefficients` (with a did-you-mean hint)."""
        for name in names:
            if name not in self.coefficients:
                known = ", ".join(self.coefficients) or "none"
                close = difflib.get_close_matches(name, self.coefficients, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise ValueError(f"{self.name} has no coefficient {name!r}{hint}; its coefficients are: {known}")

    def _derive_coefficients(self) -> None:  # noqa: B027 - optional hook, empty by default
        """Recompute the attributes derived from the coefficients (none by default; see subclasses)."""

    @property
    def control_dt(self) -> float:
        """Physical time covered by one control step."""
        return self.dt * self.substeps

    # ------------------------------------------------------------------ the equation
    @abstractmethod
    def rhs(self, u: Array, a: Array) -> Array:
        """Right-hand side ``du/dt`` of the (semi-)discrete equation, batched over leading dimensions."""

    @abstractmethod
    def substep(self, u: Array, a: Array) -> Array:
        """One solver step of length :attr:`dt` with the action held fixed (reference implementation)."""

    def step(self, u: Array, a: Array, substeps: int | None = None) -> Array:
        """``substeps`` solver steps (default: one control step) with the reference integrator."""
        for _ in range(self.substeps if substeps is None else substeps):
            u = self.substep(u, a)
        return u

    def path(self, u: Array, a: Array, substeps: int | None = None) -> Array:
        """States at the start of each of ``substeps`` solver steps, stacked on axis ``-2`` (``u`` first)."""
        xp = xp_of(u)
        states = []
        for _ in range(self.substeps if substeps is None else substeps):
            states.append(u)
            u = self.substep(u, a)
        return xp.stack(states, -2)

    def canonical(self, u: Array) -> Array:
        """The canonical representative of a state (systems with angles override this to wrap them)."""
        return u

    def state_difference(self, u1: Array, u0: Array) -> Array:
        """``u1 - u0`` in the state's own geometry (systems with angles override this to wrap them)."""
        return u1 - u0

    def constrain(self, u: Array) -> Array:
        """Project a (predicted) state onto the hard constraints of the dynamics (default: none).

        A learned model applies it to its predictions, so that it cannot leave a set the true dynamics never
        leave (e.g. the pendulum's speed limit).
        """
        return u

    def admissible_box(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Bounds ``(low, high)`` of the states the task can visit, for label-free physics-loss states.

        ``None`` where no such box is declared (the PDEs: their label-free states come from symmetries and
        perturbations of observed fields instead).
        """
        return None

    #: the state is a field on a periodic 1-D grid with a linear part and actuator shapes (the PDE systems,
    #: :class:`~pimbrl.physics.pde.SemilinearPDE`): what the convolutional models, the ETDRK4 coarse step and
    #: the field sources of the physics loss need. Models choose their path by this, not by a class.
    is_field: bool = False
    #: the reward varies smoothly with states and actions, so that a controller can optimise it by gradient
    #: (MPC, DPC); Cart-Pole's (+1 per step until the pole falls) does not
    differentiable_reward: bool = True
    #: the equation is invariant under circular shifts of a periodic grid (PDEs on a periodic domain)
    shift_symmetric: bool = False
    #: the equation is invariant under the reflection ``u(x) -> -u(-x)`` (odd-symmetric PDEs: Burgers, KS)
    reflection_symmetric: bool = False

    def residual(self, u0: Array, u1: Array, a: Array, substeps: int = 1) -> Array:
        """Residual of the discrete equation between two states ``substeps`` solver steps apart.

        ``(u1 - step(u0, a, substeps)) / (substeps * dt)``: in units of ``du/dt``, and zero up to
        round-off when ``u1`` is the solver's own output. Differentiable in ``u0``, ``u1`` and ``a``.
        """
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        return self.state_difference(u1, self.step(u0, a, substeps)) / (substeps * self.dt)

    # ------------------------------------------------------------------ the task
    @abstractmethod
    def reward(self, u: Array, a: Array, u_next: Array, k: Array | int, path: Array | None = None) -> Array:
        """Reward of the control step ``u --a--> u_next`` taken at control-step index ``k``.

        ``path`` holds the states at the start of the solver steps of this control step (axis ``-2``),
        for rewards that integrate over the step; where it is ``None`` the start state alone is used.
        """

    def terminated(self, u: Array) -> Array:
        """True where a state ends the episode by the task's own rule (not by blow-up)."""
        if isinstance(u, torch.Tensor):
            return torch.zeros(u.shape[:-1], dtype=torch.bool, device=u.device)
        return np.zeros(u.shape[:-1], dtype=bool)

    def diverged(self, u: Array) -> Array:
        """True where a state is non-finite or beyond :attr:`divergence_bound`."""
        xp = xp_of(u)
        bad = ~xp.isfinite(u) | (xp.abs(u) > self.divergence_bound)
        return bad.any(-1)

    def clip_action(self, a: np.ndarray) -> np.ndarray:
        """Clip physical actions into ``[action_low, action_high]``."""
        return np.clip(a, self.action_low, self.action_high)

    # ------------------------------------------------------------------ the fast simulator
    @abstractmethod
    def advance(self, u: np.ndarray, a: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step for a batch of states, with its rewards.

        ``u`` has shape ``(B, state_dim)`` and ``a`` shape ``(B, action_dim)``, both float64; ``k`` holds
        the control-step indices ``(B,)``. Returns ``(u_next, reward)``; computes in float64 and equals
        :meth:`step` / :meth:`reward` to round-off. Does not check for blow-up (the environments do).
        """

    def __repr__(self) -> str:
        name = type(self).__name__
        return f"{name}(state_dim={self.state_dim}, action_dim={self.action_dim}, dt={self.dt}, substeps={self.substeps})"
