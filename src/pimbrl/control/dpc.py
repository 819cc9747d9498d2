"""Differentiable predictive control: a policy network trained by back-propagating the return through the scheme.

No reinforcement learning and no critic: each gradient step rolls the policy out for ``horizon`` control steps
through the prior's differentiable coarse scheme (:class:`~.plant.SchemePlant`) from a batch of start states,
and ascends the sum of the predicted rewards. Start states are fresh draws of the task's training resets or,
for ``continue_fraction`` of the batch, states earlier rollouts reached (with their step indices), so that the
policy learns the whole episode, not only its first ``horizon`` steps. Every ``validate_every`` steps the policy
plays the validation draws on the real environment; the best policy so far is kept (the test states decide
nothing). Inference is one network call per control step.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from ..envs import Task
from .base import Controller
from .plant import SchemePlant

__all__ = ["DPCPolicy", "DPCTrainer", "policy_features"]

#: what to change when rollouts blow up in the scheme (both of DPC's errors say it)
_SCHEME_FIX = "raise --model.n-intermediate (the scheme's steps per control step) or lower --model.horizon"


def policy_features(plant: SchemePlant, u: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """What the policy sees: the system's observation where its physics defines one in torch, else the state.

    Burgers: ``u - ref_k``; a declared system: its ``observe``; the others: their canonical state (the
    pendulum's angle wrapped, as ``(cos, sin, speed)``).
    """
    physics = plant.physics
    observe = getattr(physics, "observe", None)
    if observe is not None:
        return observe(u, k)
    if physics.name == "pendulum":
        return torch.stack([torch.cos(u[:, 0]), torch.sin(u[:, 0]), u[:, 1]], -1)
    return physics.canonical(u)


class DPCPolicy(nn.Module, Controller):
    """A tanh-squashed MLP from :func:`policy_features` to normalised actions; acts in physical units."""

    def __init__(self, plant: SchemePlant, hidden: Sequence[int], seed: int) -> None:
        nn.Module.__init__(self)
        self.plant = plant
        probe = policy_features(plant, torch.zeros(1, plant.state_dim, dtype=plant.dtype), torch.zeros(1, dtype=torch.int64))
        sizes = [probe.shape[-1], *hidden, plant.action_dim]
        layers: list[nn.Module] = []
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(seed))
            for i in range(len(sizes) - 1):
                layers.append(nn.Linear(sizes[i], sizes[i + 1]))
                if i < len(sizes) - 2:
                    layers.append(nn.ReLU())
            last = layers[-1]
            assert isinstance(last, nn.Linear)
            with torch.no_grad():  # small first actions: the policy starts near zero control
                last.weight.mul_(0.01)
                last.bias.zero_()
        self.net = nn.Sequential(*layers).to(plant.dtype)
        self.transitions = 0

    def forward(self, u: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """Physical actions ``(B, m)`` of states ``u`` at steps ``k`` (differentiable)."""
        return self.plant.physical(torch.tanh(self.net(policy_features(self.plant, u, k))))

    @torch.no_grad()
    def __call__(self, states: np.ndarray, k: np.ndarray) -> np.ndarray:
        """One network call: physical actions for a batch of physical states."""
        u = torch.as_tensor(states, dtype=self.plant.dtype)
        return self.forward(u, torch.as_tensor(k, dtype=torch.int64)).numpy()


@dataclass
class DPCTrainer:
    """Trains :class:`DPCPolicy` through the plant; :meth:`run` does ``iterations`` steps with validation."""

    policy: DPCPolicy
    task: Task
    horizon: int
    batch_size: int
    lr: float
    continue_fraction: float
    seed: int
    steps: int = 0
    scheme_transitions: int = 0
    #: gradient steps skipped because a gradient was not finite
    skipped: int = 0
    #: real simulator steps of the validation episodes
    validation_transitions: int = 0
    best_return: float | None = None
    best_step: int | None = None
    best_state: dict[str, Any] | None = None
    history: list[dict[str, float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.optimizer = torch.optim.Adam(self.policy.parameters(), lr=self.lr)
        self.rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(9,)))
        self.episode_steps = int(self.task.max_episode_steps)
        self.pool_u = np.zeros((0, self.policy.plant.state_dim))
        self.pool_k = np.zeros(0, dtype=np.int64)

    def _starts(self) -> tuple[torch.Tensor, torch.Tensor]:
        n_cont = min(round(self.continue_fraction * self.batch_size), len(self.pool_u))
        fresh = self.task.sample_initial_states(self.rng, self.batch_size - n_cont)
        idx = self.rng.integers(len(self.pool_u), size=n_cont) if n_cont else np.zeros(0, dtype=np.int64)
        u = np.concatenate([fresh, self.pool_u[idx]])
        k = np.concatenate([np.zeros(len(fresh), dtype=np.int64), self.pool_k[idx]])
        return torch.as_tensor(u, dtype=self.policy.plant.dtype), torch.as_tensor(k, dtype=torch.int64)

    def step(self) -> float:
        """One gradient step; returns the batch's mean predicted return over the horizon."""
        plant = self.policy.plant
        u, k = self._starts()
        total = torch.zeros(len(u), dtype=plant.dtype)
        alive = torch.ones(len(u), dtype=torch.bool)
        for _ in range(self.horizon):
            a = self.policy.forward(u, k)
            u, r = plant.step(u, a, k)
            total = total + torch.where(alive, r, torch.zeros_like(r))
            k = k + 1
            alive = alive & (k < self.episode_steps)
        finite = torch.isfinite(total)
        if not bool(finite.any()):
            raise FloatingPointError(
                f"every DPC rollout blew up in the scheme; {_SCHEME_FIX}, or lower --model.lr, or check the prior"
            )
        loss = -total[finite].mean()  # a rollout that blew up is left out of the loss
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grads = [p.grad for p in self.policy.parameters() if p.grad is not None]
        if all(bool(torch.isfinite(g).all()) for g in grads):
            nn.utils.clip_grad_norm_(self.policy.parameters(), 10.0)
            self.optimizer.step()
        else:  # a blown-up row can still send NaN back through the batch: the step is skipped, never applied
            self.skipped += 1
        keep = (k < self.episode_steps).numpy() & np.isfinite(u.detach().numpy()).all(-1)
        self.pool_u = np.concatenate([self.pool_u, u.detach().numpy()[keep]])[-20 * self.batch_size :]
        self.pool_k = np.concatenate([self.pool_k, k.numpy()[keep]])[-20 * self.batch_size :]
        self.steps += 1
        self.scheme_transitions += len(total) * self.horizon
        return float(total[finite].mean().detach())

    def check_applied(self) -> None:
        """Raise :class:`FloatingPointError` when steps were taken and every one was skipped (its gradient not finite).

        The policy then never changed: its validation or test return would only be the untrained policy's. A
        run that applied some of its steps is not stopped; ``skipped`` (``skipped_steps`` in ``control.json``)
        counts the others.
        """
        if self.steps and self.skipped == self.steps:
            raise FloatingPointError(
                f"DPC: all {self.steps:,d} gradient steps so far were skipped (in every batch a rollout blew up in the "
                "scheme, so the gradient was not finite) and the policy never changed: the scheme is too coarse for "
                f"this system and horizon; {_SCHEME_FIX}"
            )

    def validate(self, score: Callable[[DPCPolicy], tuple[float, int]]) -> float:
        """Score the policy (``score``: its mean return on the validation draws and the steps played); keep the best.

        Raises :class:`FloatingPointError` where no gradient step was applied (:meth:`check_applied`).
        """
        self.check_applied()
        value, steps = score(self.policy)
        value = float(value)
        self.validation_transitions += int(steps)
        self.history.append({"step": float(self.steps), "validation_return": value})
        if self.best_return is None or value > self.best_return:
            self.best_return, self.best_step = value, self.steps
            self.best_state = copy.deepcopy(self.policy.state_dict())
        return value

    def state_dict(self) -> dict[str, Any]:
        """Everything a resumed training needs (the policy, the optimiser, the pool, the best policy)."""
        return {
            "policy": self.policy.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "rng": self.rng.bit_generator.state,
            "pool_u": torch.as_tensor(self.pool_u),
            "pool_k": torch.as_tensor(self.pool_k),
            "steps": self.steps,
            "scheme_transitions": self.scheme_transitions,
            "skipped": self.skipped,
            "validation_transitions": self.validation_transitions,
            "best_return": self.best_return,
            "best_step": self.best_step,
            "best_state": self.best_state,
            "history": self.history,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.policy.load_state_dict(state["policy"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.rng.bit_generator.state = state["rng"]
        self.pool_u = state["pool_u"].numpy()
        self.pool_k = state["pool_k"].numpy()
        self.steps = int(state["steps"])
        self.scheme_transitions = int(state["scheme_transitions"])
        self.skipped = int(state.get("skipped", 0))
        self.validation_transitions = int(state.get("validation_transitions", 0))
        self.best_return = state["best_return"]
        self.best_step = state["best_step"]
        self.best_state = state["best_state"]
        self.history = list(state["history"])
