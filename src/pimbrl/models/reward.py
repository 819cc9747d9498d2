"""A learned reward, for a system whose reward function is not known (data-only MBRL on any Gymnasium env).

A pimbrl system scores imagined transitions with its declared reward. An environment outside pimbrl (any
Gymnasium env with Box spaces, :mod:`pimbrl.systems.observed`) declares none: its reward is learned from the
real transitions, ``r = MLP(u, a, u')`` on standardised inputs, fitted by mean squared error alongside the
transition model.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from .networks import silu_mlp

__all__ = ["LearnedReward"]


class LearnedReward(nn.Module):
    """``r(u, a, u') = mean_r + std_r * MLP(standardised [u, a, u'])``.

    Args:
        state_dim, action_dim: sizes of the state and of the physical action.
        hidden: widths of the hidden layers.
        lr: Adam learning rate.
        seed: seeds the initialisation and the batches of :meth:`fit` (a generator of its own).
    """

    # buffers registered in __init__ (declared here for the type checker)
    mean: torch.Tensor
    std: torch.Tensor
    target: torch.Tensor
    fitted: torch.Tensor

    def __init__(
        self, state_dim: int, action_dim: int, hidden: Sequence[int] = (256, 256), lr: float = 1e-3, seed: int = 0
    ) -> None:
        super().__init__()
        self.generator = torch.Generator().manual_seed(int(seed))
        inputs = 2 * state_dim + action_dim
        with torch.random.fork_rng(devices=[]):  # the initialisation from ``seed``, the global generator untouched
            torch.manual_seed(int(seed))
            self.net = silu_mlp([inputs, *hidden, 1])
        self.register_buffer("mean", torch.zeros(inputs))
        self.register_buffer("std", torch.ones(inputs))
        self.register_buffer("target", torch.tensor([0.0, 1.0]))  # mean and std of the rewards
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=lr)

    def _inputs(self, u: Any, a: Any, u_next: Any) -> torch.Tensor:
        x = torch.cat([torch.as_tensor(v, dtype=torch.float32) for v in (u, a, u_next)], dim=-1)
        return (x - self.mean) / self.std

    def fit(self, u: torch.Tensor, a: torch.Tensor, u_next: torch.Tensor, r: torch.Tensor, steps: int, batch_size: int) -> float:
        """``steps`` Adam steps of mean squared error on batches of the given transitions; returns the last loss."""
        if len(r) == 0 or steps <= 0:
            return float("nan")
        if not bool(self.fitted):  # statistics of the first training data, kept afterwards
            x = torch.cat([torch.as_tensor(v, dtype=torch.float32) for v in (u, a, u_next)], dim=-1)
            self.mean.copy_(x.mean(0))
            self.std.copy_(x.std(0).nan_to_num(1.0).clamp_min(1e-6))
            r32 = torch.as_tensor(r, dtype=torch.float32)
            self.target.copy_(torch.stack([r32.mean(), r32.std().nan_to_num(1.0).clamp_min(1e-6)]))
            self.fitted.fill_(True)
        x = self._inputs(u, a, u_next)
        y = (torch.as_tensor(r, dtype=torch.float32).reshape(-1) - self.target[0]) / self.target[1]
        loss = torch.zeros(())
        for _ in range(steps):
            idx = torch.randint(len(y), (min(batch_size, len(y)),), generator=self.generator)
            loss = (self.net(x[idx])[:, 0] - y[idx]).pow(2).mean()
            self.optimizer.zero_grad()
            loss.backward()
            self.optimizer.step()
        return float(loss.detach()) * float(self.target[1]) ** 2

    @torch.no_grad()
    def predict(self, u: Any, a: Any, u_next: Any) -> np.ndarray:
        """Predicted rewards (float64 NumPy) of a batch of transitions."""
        out = self.net(self._inputs(u, a, u_next))[:, 0] * self.target[1] + self.target[0]
        return out.double().numpy()

    def state(self) -> dict[str, Any]:
        """Weights, optimiser and generator, for a checkpoint."""
        return {"module": self.state_dict(), "optimizer": self.optimizer.state_dict(), "generator": self.generator.get_state()}

    def load_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state`."""
        self.load_state_dict(state["module"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
