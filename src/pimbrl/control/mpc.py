"""Model-predictive control by gradient through the differentiable scheme.

At every control step, for all states of the batch at once: a plan of ``horizon`` normalised actions is
improved by ``iterations`` Adam steps on minus the sum of the rewards the scheme predicts over the horizon
(cut at the episode's end: nothing past it is simulated or counted); the plan's first action is applied. The next step starts
from the plan shifted by one (its last action repeated): the warm start. Each state's plan is its own
(the loss is a sum over the batch and Adam acts elementwise), so batching changes no decision.

Cost per control step and state: ``iterations x horizon`` scheme steps forward and backward (fewer in the
episode's last ``horizon`` steps).
"""

from __future__ import annotations

import numpy as np
import torch

from .base import Controller
from .plant import SchemePlant

__all__ = ["GradientMPC"]


class GradientMPC(Controller):
    """Receding-horizon control, the plan optimised by Adam through ``plant``.

    Args:
        plant: the differentiable scheme and reward.
        horizon: control steps planned ahead.
        iterations: Adam steps per control step.
        lr: Adam's learning rate, in normalised action units.
        first_iterations: Adam steps at an episode's first control step (the plan starts from zero actions).
        episode_steps: the episode's length; rewards planned beyond it are not counted.
    """

    def __init__(
        self,
        plant: SchemePlant,
        horizon: int,
        iterations: int,
        lr: float,
        first_iterations: int,
        episode_steps: int,
    ) -> None:
        self.plant = plant
        self.horizon = int(horizon)
        self.iterations = int(iterations)
        self.first_iterations = int(first_iterations)
        self.lr = float(lr)
        self.episode_steps = int(episode_steps)
        self.plan: torch.Tensor | None = None
        self.transitions = 0

    def reset(self, batch: int) -> None:
        """Zero plans for ``batch`` new episodes."""
        self.plan = torch.zeros(batch, self.horizon, self.plant.action_dim, dtype=self.plant.dtype)

    def __call__(self, states: np.ndarray, k: np.ndarray) -> np.ndarray:
        """The first action of each state's optimised plan (physical units)."""
        if self.plan is None or len(self.plan) != len(states):
            self.reset(len(states))
        assert self.plan is not None
        first = bool(np.all(k == 0))
        u0 = torch.as_tensor(states, dtype=self.plant.dtype)
        k0 = torch.as_tensor(k, dtype=torch.int64)
        if self.span(k0) == 0:  # every episode has ended: nothing to plan (the plan's first action, unchanged)
            return self.plant.physical(self.plan[:, 0]).numpy()
        plan = self.plan.clone().requires_grad_(True)
        optimizer = torch.optim.Adam([plan], lr=self.lr)
        steps = self.first_iterations if first else self.iterations
        hit = torch.zeros(len(states), dtype=torch.bool)  # the rows whose plan lost a step to a blow-up
        for _ in range(steps):
            before = plan.detach().clone()
            planned = self.planned_return(u0, k0, plan)
            # a row on which the scheme blew up gets no step: its gradient is zeroed, and after Adam's step
            # (which would still move it by its momentum) its plan is restored; the other rows are independent
            bad = ~torch.isfinite(planned)
            hit |= bad
            loss = -torch.where(bad, torch.zeros_like(planned), planned).sum()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            assert plan.grad is not None
            plan.grad.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
            optimizer.step()
            with torch.no_grad():
                plan.clamp_(-1.0, 1.0)
                if bad.any():
                    plan[bad] = before[bad]
        self.transitions += steps * self.span(k0) * len(states)
        self.blown_up += int(hit.sum())
        done = plan.detach()
        self.plan = torch.cat([done[:, 1:], done[:, -1:]], dim=1)  # the warm start of the next step
        return self.plant.physical(done[:, 0]).numpy()

    def span(self, k0: torch.Tensor) -> int:
        """Control steps simulated from steps ``k0``: the horizon, cut where every episode of the batch has ended."""
        return max(0, min(self.horizon, self.episode_steps - int(k0.min())))

    def planned_return(self, u0: torch.Tensor, k0: torch.Tensor, plan: torch.Tensor) -> torch.Tensor:
        """The scheme's return ``(B,)`` of ``plan`` from ``u0`` at steps ``k0`` (within the episode only)."""
        actions = self.plant.physical(plan)
        u = u0
        total = torch.zeros(len(u0), dtype=u0.dtype)
        for h in range(self.span(k0)):
            k = k0 + h
            u, r = self.plant.step(u, actions[:, h], k)
            total = total + torch.where(k < self.episode_steps, r, torch.zeros_like(r))
        return total
