"""Off-policy actor-critic agents: TD3 (the paper's), DDPG and SAC. They see batches, not environments."""

from __future__ import annotations

from .base import Agent, AgentConfig
from .sac import SAC
from .td3 import DDPG, TD3

__all__ = ["AGENTS", "DDPG", "SAC", "TD3", "Agent", "AgentConfig", "make_agent"]

AGENTS: dict[str, type[Agent]] = {"td3": TD3, "ddpg": DDPG, "sac": SAC}


def make_agent(name: str, obs_dim: int, act_dim: int, config: AgentConfig, seed: int) -> Agent:
    """Construct the agent ``name`` (``td3``, ``ddpg`` or ``sac``)."""
    try:
        cls = AGENTS[name]
    except KeyError:
        raise ValueError(f"unknown agent {name!r}: choose one of {', '.join(AGENTS)}") from None
    return cls(obs_dim, act_dim, config, seed)
