"""Physics priors that can be wrong, and physical coefficients learned from the data (the inverse problem).

A physics-informed model is only as good as the equation it is held to. When the system's coefficients are
known only roughly (a viscosity known to +-30 %, an actuator width never measured, a damping term nobody
wrote down), the residual can be built from a *prior* whose coefficients differ from the system's, and some
of those coefficients can be *learned*:

* a learned coefficient is a trainable scalar of the residual, initialised at the prior's value, free or
  confined to a range ``[low, high]`` (through a sigmoid);
* it is fitted to the labelled transitions by the coarse scheme of the residual itself: the loss is the
  next-state error of ``N`` exponential steps of the equation with the current coefficients from each
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

import torch

from ..config import parse_learned, parse_prior
from ..physics import Physics
from ..physics.pde import SemilinearPDE

__all__ = ["LearnedCoefficients", "parse_learned", "parse_prior"]


class LearnedCoefficients(torch.nn.Module):
    """Trainable physical coefficients of a PDE's residual, initialised at the prior's values.

    A free coefficient is ``prior + scale * theta`` with ``scale = |prior|`` (1 where the prior is 0), so that
    Adam's steps are relative changes whatever the coefficient's units; a ranged one is
    ``low + (high - low) * theta`` with ``theta`` projected back into ``[0, 1]`` after every step
    (:meth:`project`), so that its steps are fractions of the range and a prior on the range's edge (a missing
    damping term: prior 0, range ``0:1``) can start there. (A sigmoid would need hundreds of Adam steps to
    leave an edge: its logit starts far out.)

    Args:
        physics: the prior (its values are the starting point).
        learned: name -> ``None`` (free) or ``(low, high)``, as returned by :func:`parse_learned`.
    """

    def __init__(self, physics: Physics, learned: Mapping[str, tuple[float, float] | None]) -> None:
        super().__init__()
        if not isinstance(physics, SemilinearPDE):
            raise ValueError(
                f"learned coefficients need a PDE system (Burgers, Kuramoto-Sivashinsky), not {physics.name}: "
                "an ODE system's residual is its own solver step, which is not differentiable in its coefficients"
            )
        if not learned:
            raise ValueError("no coefficient to learn: name at least one (e.g. nu)")
        prior = physics.coefficient_values()
        self.names = tuple(learned)
        self.ranges = dict(learned)
        self.prior = {}
        raw = []
        for name in self.names:
            if name not in prior:
                physics.with_coefficients(**{name: 0.0})  # raises the one-line error naming the known ones
            value = prior[name]
            bounds = self.ranges[name]
            if bounds is None:
                raw.append(0.0)
            else:
                low, high = bounds
                if not low <= value <= high:
                    raise ValueError(
                        f"learned coefficient {name}: the prior's value {value} lies outside its range [{low}, {high}]; "
                        f"give the prior a value inside (e.g. --dyna.physics-prior {name}=...)"
                    )
                raw.append((value - low) / (high - low))
            self.prior[name] = value
        self.theta = torch.nn.Parameter(torch.tensor(raw, dtype=torch.float64))

    def values(self) -> dict[str, torch.Tensor]:
        """The coefficients' current values (float64 tensors, differentiable in :attr:`theta`)."""
        out = {}
        for i, name in enumerate(self.names):
            bounds = self.ranges[name]
            if bounds is None:
                prior = self.prior[name]
                out[name] = prior + (abs(prior) or 1.0) * self.theta[i]
            else:
                low, high = bounds
                out[name] = low + (high - low) * self.theta[i]
        return out

    @torch.no_grad()
    def project(self) -> None:
        """Put every ranged coefficient back into its range (after an optimiser step)."""
        for i, name in enumerate(self.names):
            if self.ranges[name] is not None:
                self.theta[i].clamp_(0.0, 1.0)

    def current(self) -> dict[str, float]:
        """The coefficients' current values as floats."""
        with torch.no_grad():
            return {name: float(v) for name, v in self.values().items()}
