"""Off-policy actor-critic agents: TD3 (the paper's), DDPG and SAC. They see batches, not environments.

The hyperparameters (:class:`AgentConfig`, in :mod:`.config`) import without torch; the agents
themselves are imported on first use, so that building the command line stays fast.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .config import AGENT_NAMES, AgentConfig

if TYPE_CHECKING:
    from .base import Agent
    from .sac import SAC
    from .td3 import DDPG, TD3

__all__ = ["AGENTS", "AGENT_NAMES", "DDPG", "SAC", "TD3", "Agent", "AgentConfig", "make_agent"]

#: names imported on first access (they import torch)
_LAZY = {"Agent": "base", "SAC": "sac", "TD3": "td3", "DDPG": "td3"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from importlib import import_module

        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    if name == "AGENTS":
        return _agents()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _agents() -> dict[str, type[Agent]]:
    """``{"td3": TD3, "ddpg": DDPG, "sac": SAC}`` (the classes of :data:`AGENT_NAMES`)."""
    from .sac import SAC
    from .td3 import DDPG, TD3

    return {"td3": TD3, "ddpg": DDPG, "sac": SAC}


def make_agent(name: str, obs_dim: int, act_dim: int, config: AgentConfig, seed: int) -> Agent:
    """Construct the agent ``name`` (``td3``, ``ddpg`` or ``sac``)."""
    try:
        cls = _agents()[name]
    except KeyError:
        raise ValueError(f"unknown agent {name!r}: choose one of {', '.join(AGENT_NAMES)}") from None
    return cls(obs_dim, act_dim, config, seed)
