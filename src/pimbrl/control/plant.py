"""The prior's coarse scheme and the task's reward as one differentiable control step (torch).

The same scheme object the known-scheme and identified-scheme Dyna methods use as their model
(:class:`~pimbrl.models.residual.PhysicsResidual`): for a PDE ``N`` ETDRK4 steps per control step, for an
ODE its solver step. The reward is the system's own, evaluated on the scheme's states (for KS it integrates
over the intermediate states, as imagined rewards do). MPC optimises actions through it; DPC trains a policy
through it.
"""

from __future__ import annotations

import numpy as np
import torch

from ..models.residual import PhysicsResidual
from ..physics import Physics

__all__ = ["SchemePlant", "make_plant"]


class SchemePlant:
    """``step(u, a, k) -> (u_next, reward)`` through a coarse scheme; differentiable in ``u`` and ``a``.

    Args:
        scheme: the coarse scheme (its physics holds the coefficients the controller believes).
        dtype: the dtype of the computation (float64 by default: KS is chaotic, float32 drifts within a
            long horizon).
    """

    def __init__(self, scheme: PhysicsResidual, dtype: torch.dtype = torch.float64) -> None:
        self.scheme = scheme
        self.physics: Physics = scheme.current_physics()
        self.dtype = dtype
        self.low = torch.as_tensor(self.physics.action_low, dtype=dtype)
        self.high = torch.as_tensor(self.physics.action_high, dtype=dtype)
        self.state_dim = self.physics.state_dim
        self.action_dim = self.physics.action_dim

    def physical(self, z: torch.Tensor) -> torch.Tensor:
        """Physical actions of normalised ones in ``[-1, 1]`` (clamped first)."""
        return self.low + (z.clamp(-1.0, 1.0) + 1.0) * 0.5 * (self.high - self.low)

    def normalised(self, a: np.ndarray | torch.Tensor) -> torch.Tensor:
        """Normalised actions in ``[-1, 1]`` of physical ones."""
        a_t = torch.as_tensor(a, dtype=self.dtype)
        return (2.0 * (a_t - self.low) / (self.high - self.low) - 1.0).clamp(-1.0, 1.0)

    def step(self, u: torch.Tensor, a: torch.Tensor, k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The next state ``(B, n)`` and the step's reward ``(B,)`` for states ``u``, physical actions ``a``."""
        path = self.scheme.rollout(u, a)
        u_next = path[:, -1]
        starts = torch.cat([u[:, None, :], path[:, :-1]], dim=1) if path.shape[1] > 1 else None
        reward = self.physics.reward(u, a, u_next, k, starts)
        return self.physics.constrain(u_next), reward + torch.zeros(len(u), dtype=u.dtype)


def make_plant(physics: Physics, n_intermediate: int = 5, scheme: str = "etd") -> SchemePlant:
    """The plant of ``physics`` (its coefficients as given: the truth, a wrong prior or identified values)."""
    states = PhysicsResidual.states_per_step(physics, n_intermediate)
    return SchemePlant(PhysicsResidual(physics, states, scheme="solver" if not physics.is_field else scheme))  # type: ignore[arg-type]
