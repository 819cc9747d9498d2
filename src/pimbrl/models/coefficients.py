"""Physics priors that can be wrong, and physical coefficients learned from the data (the inverse problem).

A physics-informed model is only as good as the equation it is held to. When the system's coefficients are
known only roughly (a viscosity known to +-30 %, an actuator width never measured, a damping term nobody
wrote down), the residual can be built from a *prior* whose coefficients differ from the system's, and some
of those coefficients can be *learned*:

* a learned coefficient is a trainable scalar of the residual, initialised at the prior's value, free or
  confined to a range ``[low, high]`` (by projection after every step);
* it is fitted to the labelled transitions by the coarse scheme of the residual itself: the loss is the
  next-state error of ``N`` exponential steps of the equation (PDEs), or of the solver's own step (ODEs,
  :meth:`pimbrl.physics.Physics.with_coefficient_tensors`), with the current coefficients from each
  labelled state and action. Only labelled transitions carry information about the coefficients: on a
  label-free state the model could follow the equation with any coefficients, so the physics loss uses the
  current values but does not move them;
* a term the prior lacks is a coefficient the prior sets to zero (``damping``: prior 0, learned).

Specifications are strings, as on the command line: the prior ``"nu=0.007,damping=0"`` (coefficients that
differ from the environment's own), the learned ``"nu,damping:0:1"`` (``name`` free, ``name:low:high`` in a
range).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import cast

import numpy as np
import torch

from ..config import parse_learned, parse_prior
from ..physics import Physics, Stencil
from ..physics.pde import SemilinearPDE

__all__ = ["CORRECTION", "CORRECTION_NAMES", "CORRECTION_OF", "LearnedCoefficients", "parse_learned", "parse_prior"]

#: the name that adds the learned linear correction to the learned coefficients
CORRECTION = "correction"
#: second-order central differences of orders 0..4 (raw: divide by dx^j), the correction's basis
CORRECTION_STENCILS = (
    Stencil((0,), (1.0,), "I"),
    Stencil.centered((-0.5, 0.0, 0.5), "D1"),
    Stencil.centered((1.0, -2.0, 1.0), "D2"),
    Stencil.centered((-0.5, 1.0, 0.0, -1.0, 0.5), "D3"),
    Stencil.centered((1.0, -4.0, 6.0, -4.0, 1.0), "D4"),
)
#: how the correction's coefficients are reported: c_j of d^j u / dx^j
CORRECTION_NAMES = ("correction_u", "correction_u_x", "correction_u_xx", "correction_u_xxx", "correction_u_xxxx")
#: a PDE coefficient whose term the correction can stand for: (the correction's coefficient, its value per unit
#: of the coefficient) -- a drift ``-c u_x`` is ``correction_u_x = -c``, a damping ``-mu u`` is ``correction_u = -mu``
CORRECTION_OF = {"drift": ("correction_u_x", -1.0), "damping": ("correction_u", -1.0)}


def _refusal(physics: Physics, name: str, value: float) -> str | None:
    """Why ``physics`` refuses ``name = value`` (its one-line error), or ``None`` where it takes it.

    The model side judges imagined steps with the prior at the learned values
    (:meth:`~pimbrl.models.residual.PhysicsResidual.current_physics`), so every value a learned coefficient
    can take must make a valid system.
    """
    try:
        physics.with_coefficients(**{name: value})
    except ValueError as error:
        return str(error)
    return None


def _check_range_is_admissible(physics: Physics, name: str, low: float, high: float) -> None:
    """Refuse a range whose ends the physics itself refuses (a negative viscosity, a width of zero)."""
    for end in (low, high):
        error = _refusal(physics, name, end)
        if error is not None:
            raise ValueError(f"learned coefficient {name}: its range [{low}, {high}] admits a bad value ({error})")


def _check_free_from_zero(physics: Physics, name: str) -> None:
    """Refuse a free coefficient starting at 0 that the physics cannot take below 0 (a damping, a friction).

    A free coefficient at 0 steps to either side, so one the system refuses below 0 must be learned within a range.
    """
    if _refusal(physics, name, -1e-12) is not None:
        raise ValueError(
            f"learned coefficient {name}: its prior is 0 and {physics.name} refuses negative values, so it cannot be "
            f"learned free from 0; give it a range, e.g. {name}:0:1"
        )


class LearnedCoefficients(torch.nn.Module):
    """Trainable physical coefficients of a residual (a PDE's or an ODE system's), initialised at the prior's values.

    A free coefficient is ``prior + scale * theta`` with ``scale = |prior|`` (1 where the prior is 0), so that
    Adam's steps are relative changes whatever the coefficient's units, kept by projection at or above 1 % of
    a positive prior (a viscosity, a width cannot cross zero, where the equation's step would overflow); a
    ranged one is
    ``low + (high - low) * theta`` with ``theta`` projected back into ``[0, 1]`` after every step
    (:meth:`project`), so that its steps are fractions of the range and a prior on the range's edge (a missing
    damping term: prior 0, range ``0:1``) can start there. (A sigmoid would need hundreds of Adam steps to
    leave an edge: its logit starts far out.)

    The name :data:`CORRECTION` adds a learned linear correction ``sum_j c_j d^j u / dx^j`` (``j = 0..4``,
    second-order central differences) to the right-hand side, for what no named coefficient expresses (a
    drift, a dispersion, a damping nobody named). It is part of the exactly-integrated linear operator
    (complex eigenvalues for the odd orders), starts at zero, and its size is penalised
    (``penalty * sum_j theta_j^2``, APHYNITY-style: the smallest correction that explains the data). Each
    ``c_j = theta_j / (T max_k |sigma_j(k)|)`` with ``T`` the control step and ``sigma_j`` the stencil's
    symbol: ``theta_j = 1`` changes the finest resolved mode by one e-fold (or one radian) per control step.

    Args:
        physics: the prior (its values are the starting point).
        learned: name -> ``None`` (free) or ``(low, high)``, as returned by :func:`parse_learned`; the name
            ``"correction"`` (no range) adds the linear correction.
        penalty: weight of the correction's size in :meth:`penalty` (see above).
    """

    def __init__(self, physics: Physics, learned: Mapping[str, tuple[float, float] | None], penalty: float = 1e-6) -> None:
        super().__init__()
        if not physics.is_field and not physics.tensor_coefficients:
            raise ValueError(f"{physics.name}: its coefficients cannot be learned (its equation takes no tensor coefficients)")
        if not learned:
            raise ValueError("no coefficient to learn: name at least one (e.g. nu)")
        if CORRECTION in learned and not physics.is_field:
            raise ValueError(
                f"the {CORRECTION} is a linear operator on a PDE's grid; {physics.name} is an ODE system: "
                "name the coefficients to learn (e.g. a missing friction, prior 0)"
            )
        prior = physics.coefficient_values()
        self.ranges = {k: v for k, v in learned.items() if k != CORRECTION}
        if CORRECTION in learned and learned[CORRECTION] is not None:
            raise ValueError(f"the {CORRECTION} takes no range: give it as '{CORRECTION}'")
        self.prior = {}
        self.penalty_weight = float(penalty)
        raw = []
        for name in self.ranges:
            if name not in prior:
                physics.with_coefficients(**{name: 0.0})  # raises the one-line error naming the known ones
            value = prior[name]
            bounds = self.ranges[name]
            if bounds is None:
                if value == 0.0:
                    _check_free_from_zero(physics, name)
                raw.append(0.0)
            else:
                low, high = bounds
                if not low <= value <= high:
                    raise ValueError(
                        f"learned coefficient {name}: the prior's value {value} lies outside its range [{low}, {high}]; "
                        f"give the prior a value inside (e.g. --dyna.physics-prior {name}=...)"
                    )
                _check_range_is_admissible(physics, name, low, high)
                raw.append((value - low) / (high - low))
            self.prior[name] = value
        self.theta = torch.nn.Parameter(torch.tensor(raw, dtype=torch.float64))
        #: the linear correction's coefficients (``None``: no correction)
        self.correction: torch.nn.Parameter | None = None
        if CORRECTION in learned:
            field = cast(SemilinearPDE, physics)  # refused above for a system that is not a field
            n, dx, modes = field.n, field.dx, field.n // 2 + 1
            symbols = np.stack([s.symbol(n)[:modes] / dx**j for j, s in enumerate(CORRECTION_STENCILS)])
            scale = 1.0 / (physics.control_dt * np.abs(symbols).max(axis=1))
            self._basis: torch.Tensor
            self.register_buffer("_basis", torch.as_tensor(symbols * scale[:, None], dtype=torch.complex128))
            self._scale = scale
            self.correction = torch.nn.Parameter(torch.zeros(len(CORRECTION_STENCILS), dtype=torch.float64))
        #: every learned quantity reported by :meth:`current`: the named coefficients, then the correction's
        self.names = (*self.ranges, *(CORRECTION_NAMES if self.correction is not None else ()))

    def values(self, grad: bool = True) -> dict[str, torch.Tensor]:
        """The coefficients' current values (float64 tensors, differentiable in :attr:`theta` unless ``grad=False``)."""
        out = {}
        for i, name in enumerate(self.ranges):
            bounds = self.ranges[name]
            if bounds is None:
                prior = self.prior[name]
                out[name] = prior + (abs(prior) or 1.0) * self.theta[i]
            else:
                low, high = bounds
                out[name] = low + (high - low) * self.theta[i]
        return out if grad else {name: v.detach() for name, v in out.items()}

    @torch.no_grad()
    def project(self) -> None:
        """Put every ranged coefficient back into its range, and keep positive ones positive (after a step)."""
        for i, name in enumerate(self.ranges):
            if self.ranges[name] is not None:
                self.theta[i].clamp_(0.0, 1.0)
            elif self.prior[name] > 0:  # prior + prior * theta >= prior / 100
                self.theta[i].clamp_(min=-0.99)

    def correction_symbol(self, grad: bool = True) -> torch.Tensor | None:
        """The linear correction's eigenvalues on the rfft modes (complex128; differentiable unless ``grad=False``), or None."""
        if self.correction is None:
            return None
        symbol = (self.correction.to(torch.complex128)[:, None] * self._basis).sum(0)
        return symbol if grad else symbol.detach()

    def penalty(self) -> torch.Tensor:
        """``penalty * sum_j theta_j^2`` of the correction (zero without one)."""
        if self.correction is None:
            return torch.zeros((), dtype=torch.float64)
        return self.penalty_weight * self.correction.pow(2).sum()

    def named_values(self) -> dict[str, float]:
        """The named coefficients' current values as floats (the correction, not a coefficient of the physics, left out)."""
        with torch.no_grad():
            return {name: float(v) for name, v in self.values().items()}

    def current(self) -> dict[str, float]:
        """The coefficients' current values as floats, and the correction's ``c_j`` in physical units."""
        with torch.no_grad():
            out = self.named_values()
            if self.correction is not None:
                out.update({n: float(t) * s for n, t, s in zip(CORRECTION_NAMES, self.correction, self._scale, strict=True)})
            return out
