"""pimbrl: physics-informed model-based reinforcement learning for dynamic control.

Importing the package registers the Gymnasium environments ``pimbrl/KuramotoSivashinsky-v0``,
``pimbrl/Burgers-v0``, ``pimbrl/CartPole-v0`` and ``pimbrl/Pendulum-v0``. Registration names their
classes by entry point only: the environments (and torch, numba) are imported when one is made, so that
``import pimbrl`` and the command line start fast.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "__version__", "register_envs"]

#: the registered ids, in the order of :data:`pimbrl.envs.ENV_IDS` (tested to be the same)
ENV_IDS = ("pimbrl/KuramotoSivashinsky-v0", "pimbrl/Burgers-v0", "pimbrl/CartPole-v0", "pimbrl/Pendulum-v0")


def register_envs() -> None:
    """Register the four environments with Gymnasium (idempotent); see :func:`pimbrl.envs.register_envs`."""
    from .envs import register_envs as register

    register()


def _register_lazily() -> None:
    """Register the environments by entry point, without importing :mod:`pimbrl.envs` (idempotent).

    The ids, entry points and episode lengths are those of :func:`pimbrl.envs.register_envs` (tested).
    """
    import gymnasium as gym

    classes = {
        "pimbrl/KuramotoSivashinsky-v0": ("ks", "KuramotoSivashinskyEnv", "KuramotoSivashinskyVectorEnv", 400),
        "pimbrl/Burgers-v0": ("burgers", "BurgersEnv", "BurgersVectorEnv", 60),
        "pimbrl/CartPole-v0": ("cartpole", "CartPoleEnv", "CartPoleVectorEnv", 200),
        "pimbrl/Pendulum-v0": ("pendulum", "PendulumEnv", "PendulumVectorEnv", 200),
    }
    for env_id, (module, single, vector, steps) in classes.items():
        if env_id not in gym.registry:
            kwargs: dict[str, Any] = {"max_episode_steps": steps}
            gym.register(
                id=env_id,
                entry_point=f"pimbrl.envs.{module}:{single}",
                vector_entry_point=f"pimbrl.envs.{module}:{vector}",
                **kwargs,
            )


_register_lazily()
