"""Gymnasium environments: registered as ``pimbrl/<Name>-v0`` when :mod:`pimbrl` is imported."""

from __future__ import annotations

import gymnasium as gym

from .base import PHYSICS_INFO_KEYS, PhysicsEnv, PhysicsVectorEnv
from .burgers import BurgersEnv, BurgersTask, BurgersVectorEnv
from .cartpole import CartPoleEnv, CartPoleTask, CartPoleVectorEnv
from .ks import KSTask, KuramotoSivashinskyEnv, KuramotoSivashinskyVectorEnv
from .ks_states import KSPool, KSPoolConfig, ks_initial_state_pool
from .pendulum import PendulumEnv, PendulumTask, PendulumVectorEnv
from .task import VALIDATION_SEED, StepOutcome, Task

__all__ = [
    "ENV_IDS",
    "PHYSICS_INFO_KEYS",
    "VALIDATION_SEED",
    "BurgersEnv",
    "BurgersTask",
    "BurgersVectorEnv",
    "CartPoleEnv",
    "CartPoleTask",
    "CartPoleVectorEnv",
    "KSPool",
    "KSPoolConfig",
    "KSTask",
    "KuramotoSivashinskyEnv",
    "KuramotoSivashinskyVectorEnv",
    "PendulumEnv",
    "PendulumTask",
    "PendulumVectorEnv",
    "PhysicsEnv",
    "PhysicsVectorEnv",
    "StepOutcome",
    "Task",
    "ks_initial_state_pool",
    "register_envs",
]

#: registered id -> (module path of the classes, single class, vector class, episode length)
_REGISTRY = {
    "pimbrl/KuramotoSivashinsky-v0": ("pimbrl.envs.ks", "KuramotoSivashinskyEnv", "KuramotoSivashinskyVectorEnv", 400),
    "pimbrl/Burgers-v0": ("pimbrl.envs.burgers", "BurgersEnv", "BurgersVectorEnv", 60),
    "pimbrl/CartPole-v0": ("pimbrl.envs.cartpole", "CartPoleEnv", "CartPoleVectorEnv", 200),
    "pimbrl/Pendulum-v0": ("pimbrl.envs.pendulum", "PendulumEnv", "PendulumVectorEnv", 200),
}
ENV_IDS = tuple(_REGISTRY)


def register_envs() -> None:
    """Register the four environments with Gymnasium (idempotent)."""
    for env_id, (module, single, vector, steps) in _REGISTRY.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point=f"{module}:{single}",
            vector_entry_point=f"{module}:{vector}",
            max_episode_steps=steps,
        )
