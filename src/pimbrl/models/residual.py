"""The physics-informed loss: the residual of the known equation between a model's intermediate states.

For a model that emits ``N`` states ``v_1 .. v_N`` at ``t + i h`` (``h = T/N``, ``v_0 = u_t``), the defect of
step ``i`` is ``d_i = v_i - Phi_h(v_{i-1}, a)`` (compared with the physics' own state difference, so angles
wrap), where ``Phi_h`` is one step of a discretisation of the *same* semi-discrete equations the
simulator integrates. The residual in units of ``du/dt`` is ``d_i / h``.

Units of the loss (``units``):

* ``"substep"``: ``mean(d_i^2)``, each defect in the units of one sub-step's increment. A model whose
  increments are coherently 5 % too large has defects ``N`` times smaller than its next-state error, so
  this loss is about ``N^2`` times smaller than the data loss for the same relative error (measured on KS,
  N = 5: 5.1e-7 against 1.2e-5) and barely pulls;
* ``"step"``: ``N^2 mean(d_i^2)``, the defects in units of a whole control step's increment: comparable
  with the data loss for coherent errors. For the ODE systems (``N = 1``) the two are the same.

The loss needs no label, so it can be applied to any state-action pair, including states the model
itself generated (see :mod:`pimbrl.models.state_sources`).

With ``learned`` coefficients (:mod:`pimbrl.models.coefficients`) the coarse step is built from the
equation at the coefficients' current values (PDEs, ``"etd"``: its parts, :meth:`SemilinearPDE.operators`;
ODEs: the solver step of a copy with tensor coefficients, :meth:`Physics.with_coefficient_tensors`); the
physics loss uses them without moving them, :meth:`PhysicsResidual.coefficient_loss` fits them to labels.

Schemes for ``Phi_h``:

* ``"etd"`` (PDEs, default): one ETDRK4 step of size ``h`` with the linear stencil treated exactly through
  its Fourier symbol (:class:`pimbrl.physics.pde.ETDRK4`). Cost: one exponential step for all ``N``
  defects at once, whatever ``N``. Stable for every ``N``; its distance from the simulator's solver is
  measured in docs/models.md.
* ``"solver"``: the simulator's own integrator, composed ``S/N`` times (``S`` solver steps per control
  step; needs ``N`` to divide ``S``). Zero to round-off on the simulator's output for every such ``N``,
  at the cost of ``S`` solver steps per sample. For the ODE systems (``S = 1``, ``N = 1``) this is the
  only scheme, and it is exact and cheap.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import Literal, cast

import numpy as np
import torch

from ..physics import Physics
from ..physics.base import superpose
from ..physics.pde import ETDRK4, SemilinearPDE
from .coefficients import LearnedCoefficients

__all__ = ["UNITS", "PhysicsResidual", "Scheme", "as_scheme"]

Scheme = Literal["etd", "solver"]


def as_scheme(name: str) -> Scheme:
    """The residual scheme a setting names: ``solver`` (the simulator's), else ``etd`` (the exponential integrator)."""
    return "solver" if name == "solver" else "etd"


#: units of the physics loss (see the module docstring)
UNITS = ("substep", "step")


class PhysicsResidual:
    """Defects of ``N`` intermediate states against one coarse step of ``physics``.

    Args:
        physics: the system whose equation is enforced.
        n_intermediate: ``N``, the number of states the model emits per control step.
        scheme: ``"etd"`` or ``"solver"`` (see the module docstring).
        units: ``"substep"`` or ``"step"``: the units of the loss (see the module docstring).
        learned: coefficients of ``physics`` to learn (name -> ``None`` or ``(low, high)``; for a PDE with the
            ``"etd"`` scheme only); ``physics`` holds their starting values (the prior). ``"correction"`` adds
            a learned linear correction (PDEs; :class:`~pimbrl.models.coefficients.LearnedCoefficients`).
        correction_penalty: weight of the correction's size.
    """

    def __init__(
        self,
        physics: Physics,
        n_intermediate: int,
        scheme: Scheme = "etd",
        units: str = "substep",
        learned: Mapping[str, tuple[float, float] | None] | None = None,
        correction_penalty: float = 1e-6,
    ) -> None:
        if n_intermediate < 1:
            raise ValueError(f"n_intermediate must be >= 1, got {n_intermediate}")
        if units not in UNITS:
            raise ValueError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
        self.units = units
        self.physics = physics
        self.n = int(n_intermediate)
        self.h = physics.control_dt / self.n
        pde = cast(SemilinearPDE, physics) if physics.is_field else None
        if pde is None:
            if self.n != physics.substeps:
                raise ValueError(
                    f"{physics.name}: an ODE model emits one state per solver step; need n_intermediate={physics.substeps}"
                )
            scheme = "solver"
        if scheme not in ("etd", "solver"):
            raise ValueError(f"scheme must be 'etd' or 'solver', got {scheme!r}")
        if scheme == "solver" and physics.substeps % self.n:
            raise ValueError(
                f"scheme='solver' needs n_intermediate to divide the {physics.substeps} solver steps "
                f"per control step, got {self.n}"
            )
        self.scheme: Scheme = scheme
        if pde is not None and scheme == "solver":
            pde.check_stability()  # the solver's own step: it must be stable with the prior's coefficients
        # the PDE (typed as such) and its exponential integrator, for the "etd" scheme
        self._etd: tuple[SemilinearPDE, ETDRK4] | None = (
            (pde, pde.etdrk4(self.n)) if (pde is not None and scheme == "etd") else None
        )
        #: the trainable coefficients (``None``: the prior's values, fixed)
        self.coefficients: LearnedCoefficients | None = None
        if learned:
            if pde is not None and self._etd is None:
                raise ValueError("learned coefficients need the etd residual (--dyna.residual etd), not the solver's")
            self.coefficients = LearnedCoefficients(physics, learned, penalty=correction_penalty)

    def current_physics(self) -> Physics:
        """The prior with its learned coefficients at their current values (the prior itself without any).

        What the model side judges imagined steps with (rewards that depend on the actuator shapes, say); the
        learned correction is not a coefficient of the physics and is left out.
        """
        values = self.coefficients.named_values() if self.coefficients is not None else {}
        return self.physics.with_coefficients(**values) if values else self.physics

    def actuator_shapes(self) -> np.ndarray:
        """The actuator shapes ``(action_dim, n)`` at the current learned coefficients (float64, no gradient).

        The prior's own where no coefficient is learned. PDEs only (an ODE system has no actuator shapes).
        """
        if self._etd is None:
            raise ValueError(f"{self.physics.name} has no actuator shapes: only the PDE systems (etd residual) do")
        pde = self._etd[0]
        if self.coefficients is None:
            return pde.actuator_shapes
        return np.asarray(pde.operators(self.coefficients.named_values())[2], dtype=np.float64)

    @staticmethod
    def states_per_step(physics: Physics, n_intermediate: int) -> int:
        """The states a model emits per control step: ``n_intermediate`` for a PDE, one per solver step for an ODE."""
        return n_intermediate if physics.is_field else physics.substeps

    def coarse_step(self, u: torch.Tensor, a: torch.Tensor, fit: bool = False) -> torch.Tensor:
        """``Phi_h(u, a)`` for states ``(M, n)`` and physical actions ``(M, action_dim)``.

        With learned coefficients, ``fit=True`` keeps the gradient to them (for :meth:`coefficient_loss`).
        """
        if self._etd is not None and self.coefficients is not None:
            return self._learned_step(fit)(u, a)
        if self._etd is not None:
            pde, etd = self._etd
            f = pde.forcing(a)
            return etd.step(u, lambda v: pde.nonlinear(v, f))
        phys = self.physics
        if self.coefficients is not None:  # an ODE system stepped with its learned coefficients
            phys = phys.with_coefficient_tensors(self.coefficients.values(grad=fit))
        return phys.step(u, a, substeps=phys.substeps // self.n)

    def _learned_step(self, fit: bool) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """The ETDRK4 step of a PDE at the learned coefficients' current values, as ``step(u, a)``."""
        assert self._etd is not None
        assert self.coefficients is not None
        pde = self._etd[0]
        correction = self.coefficients.correction_symbol(grad=fit)
        lam, nonlinear_coef, shapes = pde.operators(self.coefficients.values(grad=fit))
        if correction is not None:
            lam = torch.as_tensor(lam).to(torch.complex128) + correction
        etd = ETDRK4(torch.as_tensor(lam), pde.n, self.h)

        def step(u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
            f = superpose(a, torch.as_tensor(shapes, dtype=u.dtype))  # keeps the gradient of a learned width
            coef = torch.as_tensor(nonlinear_coef, dtype=u.dtype)
            return etd.step(u, lambda v: coef * pde.upwind(v) + f)

        return step

    def defects(self, u0: torch.Tensor, path: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """``d_i = v_i - Phi_h(v_{i-1}, a)`` for ``path`` ``(B, N, state_dim)`` from ``u0`` ``(B, state_dim)``."""
        b, n, dim = path.shape
        if n != self.n:
            raise ValueError(f"the residual was built for {self.n} intermediate states, the path has {n}")
        prev = torch.cat([u0[:, None, :], path[:, :-1, :]], dim=1).reshape(b * n, dim)
        acts = a[:, None, :].expand(b, n, a.shape[-1]).reshape(b * n, -1)
        stepped = self.coarse_step(prev, acts).reshape(b, n, dim)
        return self.physics.state_difference(path, stepped)

    def loss(self, u0: torch.Tensor, path: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The physics loss: ``mean(d^2)``, times ``N^2`` in ``"step"`` units."""
        loss = self.defects(u0, path, a).pow(2).mean()
        return loss * self.n**2 if self.units == "step" else loss

    def rollout(self, u0: torch.Tensor, a: torch.Tensor, fit: bool = False) -> torch.Tensor:
        """The coarse scheme's own path ``(B, N, state_dim)`` from ``u0``: the states on which its defects vanish."""
        # without a gradient a learned PDE step is built once for the N steps (the same states as N builds)
        once = self._etd is not None and self.coefficients is not None and not fit
        step = self._learned_step(fit=False) if once else functools.partial(self.coarse_step, fit=fit)
        states: list[torch.Tensor] = []
        u = u0
        for _ in range(self.n):
            u = step(u, a)
            states.append(u)
        return torch.stack(states, dim=1)

    def coefficient_loss(self, u0: torch.Tensor, a: torch.Tensor, u1: torch.Tensor) -> torch.Tensor:
        """Relative next-state error of the equation with the learned coefficients on labelled transitions.

        ``mean((Phi_h^N(u0, a) - u1)^2) / mean((u1 - u0)^2)`` (float64; the denominator, the no-change error,
        makes it scale-free) plus the correction's penalty: differentiable in the coefficients only (the
        inverse problem).
        """
        if self.coefficients is None:
            raise ValueError("this residual learns no coefficient")
        pred = self.rollout(u0.double(), a.double(), fit=True)[:, -1]
        error = self.physics.state_difference(pred, u1.double()).pow(2).mean()
        scale = self.physics.state_difference(u1.double(), u0.double()).pow(2).mean().clamp_min(1e-30)
        return error / scale + self.coefficients.penalty()
