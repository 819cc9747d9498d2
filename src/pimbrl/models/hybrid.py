"""Transition models built on the physics prior itself: the prior's coarse scheme, alone or corrected.

The paper's physics-informed model is a network that the physics loss *teaches*; these put the equation
*inside* the model:

* :class:`PhysicsModel` (``--dyna.model physics``): the prior's coarse scheme
  (:meth:`PhysicsResidual.rollout`: ``N`` ETDRK4 steps for a PDE, the solver step for an ODE) and nothing
  else, the "physics-only" model (with ``--dyna.residual solver``: the simulator's own solver, exact for
  the true system). With the exact equation it is as accurate as that scheme (KS, ``N = 5``: 1.5e-8
  next-state MSE against the simulator in float64, 2-3e-8 in the models' float32) before it has seen a
  label; with a wrong prior it is as wrong as the prior, unless coefficients are learned
  (``--dyna.learn-coefficients``, which fit them to the labels through the same scheme).
* :class:`HybridModel` (``--dyna.model hybrid``): that scheme plus a correction network (the
  translation-equivariant convolutional network for a PDE, an MLP for an ODE) whose output layer starts at
  zero, so the model starts as the physics and the data loss fits what the prior gets wrong (a missing
  term, an error no coefficient expresses). The correction is scaled by ``correction_scale`` times the
  increments' standard deviation: an Adam step moves a weight by about the learning rate whatever its
  gradient, so an unscaled correction would wander further from zero than a good prior is from the truth.
  Under PiMBRL the physics loss of a hybrid path is the correction's own defect, a penalty that keeps it
  minimal where the prior is right (the physical-model-plus-minimal-correction idea of APHYNITY,
  Yin et al. 2021).

Both follow the residual's learned coefficients at their current values (no gradient through the model:
the coefficients are fitted by :meth:`PhysicsResidual.coefficient_loss` alone).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import numpy as np
import torch
from torch import nn

from ..physics.pde import SemilinearPDE
from .networks import EquivariantConvModel, MLPModel, TransitionModel
from .residual import PhysicsResidual

__all__ = ["HybridModel", "PhysicsModel"]


class PhysicsModel(TransitionModel):
    """The prior's coarse scheme as the transition model (no trainable parameter).

    Args:
        scheme: the residual whose :meth:`~PhysicsResidual.rollout` gives the ``N`` intermediate states
            (its ``n`` sets ``n_intermediate``; its learned coefficients, if any, are followed).
    """

    def __init__(self, scheme: PhysicsResidual) -> None:
        super().__init__(scheme.physics, per_feature=not scheme.physics.is_field)
        self.n_intermediate = scheme.n
        self.scheme = scheme  # a plain object, not a submodule: its coefficients are saved by the trainer

    @torch.no_grad()
    def physics_path(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The scheme's ``N`` states ``(B, N, n)`` in the dtype of ``u`` (no gradient)."""
        path = self.scheme.rollout(u, a.to(u.dtype))
        return self.physics.canonical(path).to(u.dtype)

    def forward(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The scheme's intermediate states ``(B, N, n)``; the last is ``u_{t+1}``."""
        return self.physics_path(u, a)


class HybridModel(PhysicsModel):
    """The prior's coarse scheme plus a correction network that starts at zero.

    ``v_i = Phi^i(u, a) + correction_scale * delta_std * c_i(u, a)``, where ``c`` is the output of the
    equivariant convolutional network (PDEs, ``N`` channels) or an MLP (ODEs) with its last layer zeroed.

    Args:
        scheme: the residual that gives the scheme (see :class:`PhysicsModel`).
        correction_scale: the correction's scale relative to the increments' standard deviation.
        hidden: the hidden layers of an ODE system's correction MLP.
    """

    def __init__(self, scheme: PhysicsResidual, correction_scale: float = 0.01, hidden: Sequence[int] = (256, 256)) -> None:
        super().__init__(scheme)
        if not correction_scale > 0:
            raise ValueError(f"correction_scale must be > 0, got {correction_scale}")
        self.correction_scale = float(correction_scale)
        physics = scheme.physics
        self.net: EquivariantConvModel | MLPModel
        if physics.is_field:
            self.net = EquivariantConvModel(cast(SemilinearPDE, physics), n_intermediate=scheme.n)
            last: nn.Module = self.net.out.conv
        else:
            self.net = MLPModel(physics, hidden=hidden, n_intermediate=scheme.n)
            last = self.net.net[-1]
        assert isinstance(last, nn.Conv1d | nn.Linear)
        assert last.bias is not None
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    @torch.no_grad()
    def fit_normalization(self, u: torch.Tensor, u_next: torch.Tensor) -> None:
        """Set this model's statistics and its network's (see :meth:`TransitionModel.fit_normalization`)."""
        super().fit_normalization(u, u_next)
        self.net.fit_normalization(u, u_next)

    @torch.no_grad()
    def fit_state_normalization(self, u: torch.Tensor) -> None:
        """Set this model's state statistics and its network's."""
        super().fit_state_normalization(u)
        self.net.fit_state_normalization(u)

    def set_actuator_shapes(self, shapes: np.ndarray | torch.Tensor) -> None:
        """Give the correction network's forcing input the shapes of a learned actuator width."""
        self.net.set_actuator_shapes(shapes)

    def correction(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The correction ``(B, N, n)`` added to the scheme's states."""
        return self.net.increments(u, a) * self.correction_scale

    def forward(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The scheme's states plus the correction ``(B, N, n)``; the last is ``u_{t+1}``."""
        return self.physics.constrain(self.physics.canonical(self.physics_path(u, a) + self.correction(u, a)))
