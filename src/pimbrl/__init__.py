"""pimbrl: physics-informed model-based reinforcement learning for dynamic control.

Importing the package registers the built-in systems' Gymnasium environments
``pimbrl/KuramotoSivashinsky-v0``, ``pimbrl/Burgers-v0``, ``pimbrl/CartPole-v0`` and
``pimbrl/Pendulum-v0`` (:mod:`pimbrl.systems`). Registration names their classes by entry point only: the
environments (and torch, numba) are imported when one is made, so that ``import pimbrl`` and the command
line start fast. A system of your own: :mod:`pimbrl.systems` and docs/systems.md.
"""

from __future__ import annotations

from .systems.registry import BUILTIN, register_builtin

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "__version__", "register_envs"]

#: the ids of the built-in systems
ENV_IDS = tuple(BUILTIN)


def register_envs() -> None:
    """Register the built-in systems with Gymnasium (idempotent)."""
    register_builtin()


register_builtin()
