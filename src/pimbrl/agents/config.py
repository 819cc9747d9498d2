"""Agent hyperparameters, one type per agent: plain data, importable without torch (for flags and configs).

A setting an agent does not have is not a field of its type: ``SACConfig(policy_delay=2)`` is a ``TypeError``,
and CrossQ, which has no target networks, has no ``polyak``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..config import MAX_BATCH, MAX_LR, ConfigError, at_most, in_range, non_negative, one_of, param, positive

__all__ = [
    "AGENT_NAMES",
    "AGENT_TYPES",
    "MAX_CRITICS",
    "MAX_LAYERS",
    "MAX_WIDTH",
    "ActorCritic",
    "AgentConfig",
    "CrossQConfig",
    "DDPGConfig",
    "REDQConfig",
    "SACConfig",
    "TD3Config",
]

#: bounds of :attr:`AgentConfig.hidden`: hidden layers, and units per layer
MAX_LAYERS = 16
MAX_WIDTH = 4_096
#: bound of REDQ's ensemble (:attr:`REDQConfig.n_critics`)
MAX_CRITICS = 100

#: the agents of :func:`pimbrl.agents.make_agent` (the keys of :data:`pimbrl.agents.AGENTS`)
AGENT_NAMES = ("td3", "ddpg", "sac", "crossq", "redq")


def _layer_sizes(v: tuple[int, ...]) -> bool:
    return 0 < len(v) <= MAX_LAYERS and all(0 < h <= MAX_WIDTH for h in v)


_LAYERS_RULE = f"must be 1 to {MAX_LAYERS} layer sizes, each in [1, {MAX_WIDTH:,}]"


@dataclass(frozen=True)
class _Networks:
    """What every off-policy actor-critic agent here takes (defaults: the paper's TD3 table)."""

    name: ClassVar[str] = "agent"
    #: a SAC-family agent (squashed Gaussian actor, entropy temperature): it also logs agent/entropy and agent/alpha
    sac_family: ClassVar[bool] = False
    hidden: tuple[int, ...] = param(
        (256, 256),
        "hidden layer sizes of actor and critics",
        (_layer_sizes, _LAYERS_RULE),
    )
    actor_lr: float = param(1e-3, "actor learning rate (Adam)", [positive(), at_most(MAX_LR)])
    critic_lr: float = param(1e-3, "critic learning rate (Adam)", [positive(), at_most(MAX_LR)])
    gamma: float = param(0.99, "discount factor", in_range(0.0, 1.0, lo_open=True))


@dataclass(frozen=True)
class ActorCritic(_Networks):
    """An off-policy actor-critic agent with target networks (every agent here but CrossQ)."""

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
class _Temperature:
    """The entropy temperature of the SAC family (SAC, CrossQ, REDQ)."""

    sac_family: ClassVar[bool] = True
    init_alpha: float = param(0.2, "initial entropy temperature", [positive(), at_most(1_000)])
    autotune_alpha: bool = param(True, "tune the temperature to reach the target entropy")
    alpha_lr: float = param(3e-4, "temperature learning rate", [positive(), at_most(MAX_LR)])
    target_entropy: float | None = param(None, "target entropy (default: -action_dim)", in_range(-1_000.0, 1_000.0))


@dataclass(frozen=True)
class SACConfig(_Temperature, ActorCritic):
    """SAC: a stochastic actor whose entropy temperature is tuned."""

    name: ClassVar[str] = "sac"


@dataclass(frozen=True)
class CrossQConfig(_Temperature, _Networks):
    """CrossQ (Bhatt et al., ICLR 2024): SAC without target networks, batch-normalised critics.

    The defaults are the paper's: learning rates 1e-3, Adam with beta1 0.5, batch 256, actor 2x256,
    critics 2x2048, actor every 3rd critic update, batch renormalisation with momentum 0.99 and 100k warm-up
    updates; the temperature starts at 1 and learns at the actor's rate (the authors' code).
    """

    name: ClassVar[str] = "crossq"
    hidden: tuple[int, ...] = param(
        (256, 256), "hidden layer sizes of the actor (the critics': critic_hidden)", (_layer_sizes, _LAYERS_RULE)
    )
    init_alpha: float = param(1.0, "initial entropy temperature", [positive(), at_most(1_000)])
    alpha_lr: float = param(1e-3, "temperature learning rate", [positive(), at_most(MAX_LR)])
    critic_hidden: tuple[int, ...] = param(
        (2048, 2048),
        "hidden layer sizes of the critics (CrossQ: wide critics; the actor's: hidden)",
        (_layer_sizes, _LAYERS_RULE),
    )
    batch_size: int = param(
        256, "minibatch size of each update (the critic sees it twice: (s, a) and (s', a'))", [positive(), at_most(MAX_BATCH)]
    )
    policy_delay: int = param(3, "actor and temperature updates every this many critic updates", [positive(), at_most(1_000)])
    adam_beta1: float = param(
        0.5, "Adam beta1 of actor and critics (the temperature's Adam keeps 0.9)", in_range(0.0, 1.0, hi_open=True)
    )
    adam_beta2: float = param(0.999, "Adam beta2 of actor and critics", in_range(0.0, 1.0, hi_open=True))
    critic_norm: str = param(
        "renorm",
        "normalisation of the critics' input and hidden layers: renorm (batch renormalisation, the paper's) or batch "
        "(plain batch normalisation)",
        one_of("renorm", "batch"),
    )
    norm_momentum: float = param(
        0.99, "running statistics: stat <- momentum stat + (1 - momentum) batch stat", in_range(0.0, 1.0, hi_open=True)
    )
    renorm_warmup: int = param(
        100_000,
        "critic updates of plain batch normalisation before the renormalisation's corrections start",
        [non_negative(), at_most(10**9)],
    )


@dataclass(frozen=True)
class REDQConfig(SACConfig):
    """REDQ (Chen et al., ICLR 2021): SAC with an ensemble of critics; the target's minimum is over a random subset.

    The defaults are the paper's (learning rates 3e-4, batch 256, 10 critics, subsets of 2). The paper also
    takes 20 updates per real step and one policy update per 20 critic updates: ``--utd 20
    --agent.policy-delay 20``.
    """

    name: ClassVar[str] = "redq"
    actor_lr: float = param(3e-4, "actor learning rate (Adam)", [positive(), at_most(MAX_LR)])
    critic_lr: float = param(3e-4, "critic learning rate (Adam)", [positive(), at_most(MAX_LR)])
    batch_size: int = param(256, "minibatch size of each update", [positive(), at_most(MAX_BATCH)])
    n_critics: int = param(10, "critics in the ensemble (N; the actor ascends their mean)", [positive(), at_most(MAX_CRITICS)])
    target_subset: int = param(
        2, "target critics drawn at random each update whose minimum is the TD target (M)", [positive(), at_most(MAX_CRITICS)]
    )
    policy_delay: int = param(
        1,
        "actor and temperature updates every this many critic updates (the paper: 20, one per real step at --utd 20)",
        [positive(), at_most(1_000)],
    )

    def __post_init__(self) -> None:
        n, m = self.n_critics, self.target_subset
        valid = all(isinstance(v, int) and 0 < v <= MAX_CRITICS for v in (n, m))  # else the fields' own checks speak
        if valid and m > n:
            raise ConfigError(
                f"agent.target_subset {m} is more than agent.n_critics {n}: the target's subset is drawn from the critics"
            )


#: an agent's configuration
AgentConfig = TD3Config | DDPGConfig | SACConfig | CrossQConfig | REDQConfig
#: every agent's configuration type by name (:func:`pimbrl.agents.make_agent`)
AGENT_TYPES: dict[str, type] = {
    "td3": TD3Config,
    "ddpg": DDPGConfig,
    "sac": SACConfig,
    "crossq": CrossQConfig,
    "redq": REDQConfig,
}
