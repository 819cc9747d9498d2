"""The transition model of a run, by kind: a network (the paper's or the equivariant one) or the physics in it."""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

from ..config import MODEL_KINDS, PHYSICS_MODEL_KINDS
from ..physics import Physics
from ..physics.pde import SemilinearPDE
from .hybrid import HybridModel, PhysicsModel
from .networks import ConvLSTMModel, EquivariantConvModel, MLPModel, TransitionModel
from .residual import PhysicsResidual

__all__ = ["MODELS", "make_model"]

#: every kind of model (the names live in pimbrl.config, which the command line reads without torch)
MODELS = MODEL_KINDS


def make_model(
    physics: Physics,
    n_intermediate: int = 5,
    hidden: Sequence[int] = (256, 256),
    predict_increment: bool = True,
    kind: str = "convlstm",
    scheme: PhysicsResidual | None = None,
    correction_scale: float = 0.01,
) -> TransitionModel:
    """The transition model for ``physics``.

    Networks: for the PDE systems the paper's ConvLSTM (``kind="convlstm"``) or the translation-equivariant
    convolutional model (``kind="equivariant"``); an MLP for the ODE systems (whatever ``kind``
    names) that emits one state per solver step.
    With the physics inside (:mod:`pimbrl.models.hybrid`, any system): the prior's coarse scheme alone
    (``kind="physics"``) or with a correction network (``kind="hybrid"``, scaled by ``correction_scale``);
    ``scheme`` gives that scheme (a run passes its physics residual, so that the model follows the learned
    coefficients), by default the ETDRK4 scheme of ``physics`` with ``n_intermediate`` steps (PDEs) or its
    solver step (ODEs).
    """
    if kind not in MODELS:
        raise ValueError(f"model kind must be one of {', '.join(MODELS)}, got {kind!r}")
    if kind in PHYSICS_MODEL_KINDS:
        if scheme is None:
            scheme = PhysicsResidual(physics, PhysicsResidual.states_per_step(physics, n_intermediate))
        return PhysicsModel(scheme) if kind == "physics" else HybridModel(scheme, correction_scale, hidden=hidden)
    if not physics.is_field:  # one state per solver step: the equation's own intermediate states
        return MLPModel(physics, hidden=hidden, predict_increment=predict_increment, n_intermediate=physics.substeps)
    field = cast(SemilinearPDE, physics)
    if kind == "equivariant":
        return EquivariantConvModel(field, n_intermediate=n_intermediate)
    return ConvLSTMModel(field, n_intermediate=n_intermediate, predict_increment=predict_increment)
