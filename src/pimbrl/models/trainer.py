"""Fitting a transition model with the data loss, the physics loss, or both.

``L_D`` is the mean squared error of the predicted next state (in physical units, compared with the
physics' state difference); ``L_E`` is the physics loss of :class:`~pimbrl.models.residual.PhysicsResidual`
on state-action pairs that need no label. One gradient step minimises ``w_D L_D + w_E L_E`` over
whatever batches it is given, so the phases of the paper (data first; physics on imagined states once
enough exist) and mixed training are the same call with different inputs.

The accuracy measure is :meth:`ModelTrainer.validation_mse`: ``L_D`` on held-out real transitions that
the model never trains on (the authors used the last training loss).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from .networks import TransitionModel
from .residual import PhysicsResidual

__all__ = ["ACTUATOR_WIDTH", "ModelTrainer", "TransitionData", "TransitionSource"]

#: the coefficient that sets the actuator shapes, which a model may take as input (the PDE systems)
ACTUATOR_WIDTH = "actuator_width"


@dataclass(frozen=True)
class TransitionData:
    """Physical transitions as float32 tensors: ``state (M, n)``, ``action (M, m)``, ``next_state (M, n)``."""

    state: torch.Tensor
    action: torch.Tensor
    next_state: torch.Tensor | None = None

    def __len__(self) -> int:
        return self.state.shape[0]

    def take(self, idx: torch.Tensor) -> TransitionData:
        """The transitions at indices ``idx`` (a 1-D index tensor), in that order."""
        nxt = None if self.next_state is None else self.next_state.index_select(0, idx)
        return TransitionData(self.state.index_select(0, idx), self.action.index_select(0, idx), nxt)

    def sample(self, batch: int, rng: np.random.Generator) -> TransitionData:
        """``batch`` transitions drawn uniformly with replacement."""
        return self.take(torch.from_numpy(rng.integers(0, len(self), size=batch)))


class TransitionSource(Protocol):
    """Anything that draws random batches of transitions."""

    def __len__(self) -> int: ...

    def sample(self, batch: int, rng: np.random.Generator) -> TransitionData:
        """``batch`` transitions drawn at random with ``rng``."""


class ModelTrainer:
    """Optimises a :class:`TransitionModel` (Adam) with weighted data and physics losses.

    Args:
        model: the transition model.
        residual: the physics residual (``None``: data loss only).
        lr: Adam learning rate.
        weight_data, weight_physics: ``w_D`` and ``w_E``.
        grad_clip: maximal gradient norm (``None``: no clipping).
        coefficient_lr: Adam learning rate of the residual's learned coefficients, if it has any (they are
            fitted to every labelled batch by :meth:`PhysicsResidual.coefficient_loss`).
    """

    def __init__(
        self,
        model: TransitionModel,
        residual: PhysicsResidual | None = None,
        lr: float = 1e-3,
        weight_data: float = 1.0,
        weight_physics: float = 1.0,
        grad_clip: float | None = 10.0,
        coefficient_lr: float = 1e-2,
    ) -> None:
        self.model = model
        self.residual = residual
        self.weight_data = float(weight_data)
        self.weight_physics = float(weight_physics)
        self.grad_clip = grad_clip
        params = list(model.parameters())
        # a model with nothing to train (the physics-only model) has no optimiser: its loss is only measured
        self.optimizer = torch.optim.Adam(params, lr=lr, fused=True) if params else None
        self.coefficients = residual.coefficients if residual is not None else None
        self.coefficient_optimizer = (
            torch.optim.Adam(self.coefficients.parameters(), lr=coefficient_lr) if self.coefficients is not None else None
        )
        self.steps = 0

    def ensure_normalization(self, data: TransitionData) -> None:
        """Fit the model's normalisation once, from the first data it sees (labelled if possible)."""
        if bool(self.model.fitted):
            return
        if data.next_state is not None:
            self.model.fit_normalization(data.state, data.next_state)
        else:
            self.model.fit_state_normalization(data.state)

    def step(self, labelled: TransitionData | None = None, unlabelled: TransitionData | None = None) -> dict[str, float]:
        """One gradient step on ``w_D L_D(labelled) + w_E L_E(unlabelled)`` (either may be ``None``)."""
        if labelled is None and unlabelled is None:
            raise ValueError("a model step needs labelled and/or unlabelled data")
        if unlabelled is not None and self.residual is None:
            raise ValueError("physics-loss steps need a PhysicsResidual")
        metrics: dict[str, float] = {}
        loss = torch.zeros(())
        if labelled is not None:
            assert labelled.next_state is not None
            pred = self.model.predict_next(labelled.state, labelled.action)
            data_loss = self.model.physics.state_difference(pred, labelled.next_state).pow(2).mean()
            loss = loss + self.weight_data * data_loss
            metrics["model/data_loss"] = float(data_loss.detach())
        if unlabelled is not None:
            assert self.residual is not None
            path = self.model(unlabelled.state, unlabelled.action)
            physics_loss = self.residual.loss(unlabelled.state, path, unlabelled.action)
            loss = loss + self.weight_physics * physics_loss
            metrics["model/physics_loss"] = float(physics_loss.detach())
        if not torch.isfinite(loss):
            raise FloatingPointError(f"the model loss became {float(loss)}; lower the model learning rate")
        if self.optimizer is not None:
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if self.grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.grad_clip)
            self.optimizer.step()
        if labelled is not None and self.coefficient_optimizer is not None:
            metrics["model/coefficient_loss"] = self._fit_coefficients(labelled)
        self.steps += 1
        return metrics

    def _fit_coefficients(self, labelled: TransitionData) -> float:
        """One Adam step of the learned coefficients on a labelled batch (the inverse problem)."""
        assert self.residual is not None
        assert self.coefficient_optimizer is not None
        assert self.coefficients is not None
        assert labelled.next_state is not None
        loss = self.residual.coefficient_loss(labelled.state, labelled.action, labelled.next_state)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"the coefficient loss became {float(loss)}; lower --dyna.coefficient-lr")
        self.coefficient_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.coefficient_optimizer.step()
        self.coefficients.project()
        self.follow_coefficients()
        return float(loss.detach())

    def follow_coefficients(self) -> None:
        """Give the model's forcing input the actuator shapes of the current learned width (if it is learned).

        Detached: the width is identified by the coefficient loss through the equation alone, never by the
        network's data loss. Called after every coefficient step; nothing to do where the width is not learned.
        """
        if self.residual is None or self.coefficients is None or ACTUATOR_WIDTH not in self.coefficients.ranges:
            return
        self.model.set_actuator_shapes(self.residual.actuator_shapes())

    def fit(
        self,
        steps: int,
        batch_size: int,
        rng: np.random.Generator,
        labelled: TransitionSource | None = None,
        unlabelled: TransitionSource | None = None,
        unlabelled_rng: np.random.Generator | None = None,
    ) -> dict[str, float]:
        """``steps`` gradient steps on random batches; returns the metrics averaged over the steps.

        ``labelled`` and ``unlabelled`` are anything with ``sample(batch, rng) -> TransitionData``
        (a :class:`TransitionData`, or a view of a replay buffer). Labelled batches draw from ``rng``,
        unlabelled ones from ``unlabelled_rng`` (default: ``rng`` too).
        """
        physics_rng = rng if unlabelled_rng is None else unlabelled_rng
        first = labelled if labelled is not None else unlabelled
        if isinstance(first, TransitionData):
            self.ensure_normalization(first)
        if self.optimizer is None:  # a model with no parameter (the physics-only model): its physics loss trains
            # nothing, so only learned coefficients are fitted, on labels; without them (or labels) no batch is drawn
            unlabelled = None
            if self.coefficient_optimizer is None or labelled is None:
                return {}
        totals: dict[str, float] = {}
        for _ in range(steps):
            m = self.step(
                None if labelled is None else labelled.sample(batch_size, rng),
                None if unlabelled is None else unlabelled.sample(batch_size, physics_rng),
            )
            for k, v in m.items():
                totals[k] = totals.get(k, 0.0) + v
        return {k: v / max(steps, 1) for k, v in totals.items()}

    @torch.no_grad()
    def per_transition_mse(self, data: TransitionData, batch_size: int = 1024) -> np.ndarray:
        """Mean squared next-state error of every transition ``(M,)`` (physical units)."""
        assert data.next_state is not None
        out = []
        for i in range(0, len(data), batch_size):
            idx = torch.arange(i, min(i + batch_size, len(data)))
            chunk = data.take(idx)
            pred = self.model.predict_next(chunk.state, chunk.action)
            assert chunk.next_state is not None  # take() keeps the labels that data has
            out.append(self.model.physics.state_difference(pred, chunk.next_state).pow(2).mean(dim=-1))
        return torch.cat(out).numpy() if out else np.zeros(0)

    def validation_mse(self, data: TransitionData) -> float:
        """``L_D`` on held-out transitions: the model-accuracy measure compared with the threshold lambda."""
        return float(self.per_transition_mse(data).mean()) if len(data) else float("inf")

    def state_dict(self) -> dict:
        """Model and optimiser state, learned coefficients (if any) and the step count, for checkpoints."""
        optimizer = self.optimizer.state_dict() if self.optimizer is not None else None
        state = {"model": self.model.state_dict(), "optimizer": optimizer, "steps": self.steps}
        if self.coefficients is not None and self.coefficient_optimizer is not None:
            state["coefficients"] = self.coefficients.state_dict()
            state["coefficient_optimizer"] = self.coefficient_optimizer.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` saved."""
        self.model.load_state_dict(state["model"])
        if self.optimizer is not None:
            self.optimizer.load_state_dict(state["optimizer"])
        if self.coefficients is not None and self.coefficient_optimizer is not None:
            self.coefficients.load_state_dict(state["coefficients"])
            self.coefficient_optimizer.load_state_dict(state["coefficient_optimizer"])
        self.steps = int(state["steps"])
