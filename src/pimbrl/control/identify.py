"""Under partial physics: the coefficients of the prior fitted to real transitions before control starts.

The real transitions come from the real environment with uniformly random actions, from its training
resets (seeded by the run), so they are counted as the real steps of the method. The fit is the inverse
problem the identified-scheme Dyna method solves (:meth:`PhysicsResidual.coefficient_loss`, Adam), here
once, on all the transitions at hand.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from ..models.hybrid import PhysicsModel
from ..models.residual import PhysicsResidual
from ..models.trainer import ModelTrainer, TransitionData
from ..physics import Physics

__all__ = ["collect_random", "identify_coefficients"]


def collect_random(env_id: str, env_kwargs: dict[str, Any], steps: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``steps`` real transitions ``(u, a, u')`` with uniformly random actions (physical), episodes from resets."""
    env = gym.make(env_id, **env_kwargs)
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(7,)))
    env.action_space.seed(int(rng.integers(2**31)))
    us, acts, nexts = [], [], []
    _, info = env.reset(seed=int(rng.integers(2**31)))
    for _ in range(steps):
        u = np.asarray(info["state"], dtype=np.float64)
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        if not info["diverged"]:
            us.append(u)
            acts.append(np.asarray(info["physical_action"], dtype=np.float64))
            nexts.append(np.asarray(info["state"], dtype=np.float64))
        if terminated or truncated:
            _, info = env.reset()
    env.close()
    return np.array(us), np.array(acts), np.array(nexts)


def identify_coefficients(
    prior: Physics,
    learned: Mapping[str, tuple[float, float] | None],
    transitions: tuple[np.ndarray, np.ndarray, np.ndarray],
    n_intermediate: int,
    iterations: int,
    batch_size: int,
    lr: float,
    seed: int,
) -> dict[str, float]:
    """The coefficients ``learned`` fitted to ``transitions`` from the prior's values: ``{name: value}``."""
    states = PhysicsResidual.states_per_step(prior, n_intermediate)
    residual = PhysicsResidual(prior, states, learned=learned)
    trainer = ModelTrainer(PhysicsModel(residual), residual=residual, coefficient_lr=lr)
    u, a, u1 = (torch.as_tensor(x, dtype=torch.float32) for x in transitions)
    data = TransitionData(u, a, u1)
    trainer.fit(iterations, batch_size, np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(8,))), labelled=data)
    assert residual.coefficients is not None
    return residual.coefficients.named_values()
