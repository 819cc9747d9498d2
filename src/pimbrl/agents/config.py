"""Agent hyperparameters, one type per agent: plain data, importable without torch (for flags and configs).

A setting an agent does not have is not a field of its type: ``SACConfig(policy_delay=2)`` is a ``TypeError``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..config import MAX_BATCH, MAX_LR, at_most, in_range, non_negative, param, positive

__all__ = [
    "AGENT_NAMES",
    "AGENT_TYPES",
    "MAX_LAYERS",
    "MAX_WIDTH",
    "ActorCritic",
    "AgentConfig",
    "DDPGConfig",
    "SACConfig",
    "TD3Config",
]

#: bounds of :attr:`AgentConfig.hidden`: hidden layers, and units per layer
MAX_LAYERS = 16
MAX_WIDTH = 4_096

#: the agents of :func:`pimbrl.agents.make_agent` (the keys of :data:`pimbrl.agents.AGENTS`)
AGENT_NAMES = ("td3", "ddpg", "sac")


@dataclass(frozen=True)
class ActorCritic:
    """What every off-policy actor-critic agent here takes (defaults: the paper's TD3 table)."""

    name: ClassVar[str] = "agent"
    hidden: tuple[int, ...] = param(
        (256, 256),
        "hidden layer sizes of actor and critics",
        (
            lambda v: 0 < len(v) <= MAX_LAYERS and all(0 < h <= MAX_WIDTH for h in v),
            f"must be 1 to {MAX_LAYERS} layer sizes, each in [1, {MAX_WIDTH:,}]",
        ),
    )
    actor_lr: float = param(1e-3, "actor learning rate (Adam)", [positive(), at_most(MAX_LR)])
    critic_lr: float = param(1e-3, "critic learning rate (Adam)", [positive(), at_most(MAX_LR)])
    gamma: float = param(0.99, "discount factor", in_range(0.0, 1.0, lo_open=True))
    polyak: float = param(
        0.995, "target networks: theta_targ <- polyak theta_targ + (1 - polyak) theta", in_range(0.0, 1.0, hi_open=True)
    )
    batch_size: int = param(128, "minibatch size of each update", [positive(), at_most(MAX_BATCH)])


@dataclass(frozen=True)
class DDPGConfig(ActorCritic):
    """DDPG: one critic, a deterministic actor with Gaussian exploration noise."""

    name: ClassVar[str] = "ddpg"
    exploration_noise: float = param(0.1, "Gaussian action noise, as a fraction of each action's half-range", in_range(0.0, 1.0))
    preactivation_penalty: float = param(
        0.0,
        "weight of mean(z^2), z the actor's pre-tanh output, in the actor loss: keeps the actor off tanh saturation, "
        "where its gradient vanishes (0: none, the paper's)",
        [non_negative(), at_most(1e3)],
    )


@dataclass(frozen=True)
class TD3Config(DDPGConfig):
    """TD3 (the paper's agent): twin critics, delayed actor updates, target-policy smoothing."""

    name: ClassVar[str] = "td3"
    policy_delay: int = param(2, "actor and target updates every this many critic updates", [positive(), at_most(1_000)])
    target_smoothing: bool = param(True, "target-policy smoothing (Fujimoto et al.); the paper's Algorithm A1 has none")
    target_noise: float = param(0.2, "std of the target-policy smoothing noise (normalised actions)", in_range(0.0, 1.0))
    noise_clip: float = param(0.5, "clip of the target-policy smoothing noise", in_range(0.0, 1.0))


@dataclass(frozen=True)
class SACConfig(ActorCritic):
    """SAC: a stochastic actor whose entropy temperature is tuned."""

    name: ClassVar[str] = "sac"
    init_alpha: float = param(0.2, "initial entropy temperature", [positive(), at_most(1_000)])
    autotune_alpha: bool = param(True, "tune the temperature to reach the target entropy")
    alpha_lr: float = param(3e-4, "temperature learning rate", [positive(), at_most(MAX_LR)])
    target_entropy: float | None = param(None, "target entropy (default: -action_dim)", in_range(-1_000.0, 1_000.0))


#: an agent's configuration
AgentConfig = TD3Config | DDPGConfig | SACConfig
#: every agent's configuration type by name (:func:`pimbrl.agents.make_agent`)
AGENT_TYPES: dict[str, type] = {"td3": TD3Config, "ddpg": DDPGConfig, "sac": SACConfig}
