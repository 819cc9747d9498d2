"""Off-policy actor-critic agents: TD3 (the paper's), DDPG, SAC, CrossQ and REDQ. They see batches, not environments.

The hyperparameters (:class:`AgentConfig`, in :mod:`.config`) import without torch; the agents
themselves are imported on first use, so that building the command line stays fast.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .config import (
    AGENT_NAMES,
    AGENT_TYPES,
    AgentConfig,
    CrossQConfig,
    DDPGConfig,
    REDQConfig,
    SACConfig,
    TD3Config,
)

if TYPE_CHECKING:
    from .base import Agent
    from .crossq import CrossQ
    from .redq import REDQ
    from .sac import SAC
    from .td3 import DDPG, TD3

__all__ = [
    "AGENTS",
    "AGENT_NAMES",
    "AGENT_TYPES",
    "DDPG",
    "REDQ",
    "SAC",
    "TD3",
    "Agent",
    "AgentConfig",
    "CrossQ",
    "CrossQConfig",
    "DDPGConfig",
    "REDQConfig",
    "SACConfig",
    "TD3Config",
    "make_agent",
]

#: names imported on first access (they import torch)
_LAZY = {"Agent": "base", "SAC": "sac", "TD3": "td3", "DDPG": "td3", "CrossQ": "crossq", "REDQ": "redq"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from importlib import import_module

        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    if name == "AGENTS":
        return _agents()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _agents() -> dict[str, type[Agent]]:
    """``{"td3": TD3, "ddpg": DDPG, "sac": SAC, "crossq": CrossQ, "redq": REDQ}`` (the classes of :data:`AGENT_NAMES`)."""
    from .crossq import CrossQ
    from .redq import REDQ
    from .sac import SAC
    from .td3 import DDPG, TD3

    return {"td3": TD3, "ddpg": DDPG, "sac": SAC, "crossq": CrossQ, "redq": REDQ}


def make_agent(
    config: AgentConfig, obs_dim: int, act_dim: int, seed: int, critic_layer_norm: bool = False, device: str = "cpu"
) -> Agent:
    """Construct the agent that ``config`` configures (:class:`TD3Config` -> TD3, ...).

    ``critic_layer_norm`` is the experimental layer normalisation of the critics' hidden layers; ``device``
    where its networks run (``cpu`` or ``cuda``).
    """
    name = getattr(config, "name", None)
    if name not in AGENT_TYPES or type(config) is not AGENT_TYPES[name]:
        raise ValueError(f"make_agent needs one of {', '.join(t.__name__ for t in AGENT_TYPES.values())}, got {config!r}")
    return _agents()[name](obs_dim, act_dim, config, seed, critic_layer_norm=critic_layer_norm, device=device)
