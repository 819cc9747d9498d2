"""Training configuration: one typed dataclass, per-environment presets from the paper, overrides.

``resolve_config(env, overrides)`` starts from the defaults, applies the environment's preset (SPEC
section 3 and the paper's tables), then the user's overrides, and validates every field.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from ..agents import AGENTS, AgentConfig
from ..config import ConfigError, from_dict, in_range, non_negative, one_of, param, positive, validate

__all__ = ["TrainConfig", "PRESETS", "resolve_config", "METHODS"]

METHODS = ("mfrl", "mbrl", "pimbrl")


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (saved as ``config.json`` in the run directory)."""

    env: str = param("pimbrl/Pendulum-v0", "environment id (pimbrl/... or any Gymnasium id)")
    method: str = param("mfrl", "mfrl (model-free), mbrl (data-only model), pimbrl (physics-informed model)", one_of(*METHODS))
    agent: str = param("td3", "off-policy agent", one_of(*AGENTS))
    seed: int = param(0, "seeds networks, exploration, replay sampling and the environment", non_negative())
    total_steps: int = param(15_000, "real environment steps", positive())
    warmup_steps: int = param(1_000, "initial steps with uniformly random actions", non_negative())
    update_after: int = param(1_000, "real steps collected before the first agent update", non_negative())
    update_every: int = param(50, "real steps between update phases (the paper's update_every)", positive())
    utd: float = param(1.0, "agent updates per real step (update-to-data ratio); the paper: 50 per 50 steps", positive())
    buffer_size: int = param(1_000_000, "capacity of the real replay buffer", positive())
    eval_every: int = param(1_000, "real steps between evaluations", positive())
    eval_episodes: int = param(100, "test episodes per evaluation (the paper: 100; 200 for KS)", positive())
    eval_seed: int = param(2021, "seed of the held-out test initial states (KS uses its test pool)", non_negative())
    threshold: float | None = param(None, "evaluation return that counts as solved (steps-to-threshold)")
    checkpoint_every: int = param(5_000, "real steps between checkpoints (taken at the next episode end)", positive())
    log_every: int = param(1_000, "real steps between rows of metrics.csv", positive())
    threads: int = param(1, "torch threads for this run", in_range(1, 256))
    tensorboard: bool = param(False, "also write TensorBoard events (needs the tensorboard package)")
    env_kwargs: dict = param({}, "keyword arguments for gymnasium.make")
    agent_config: AgentConfig = dataclasses.field(
        default_factory=AgentConfig, metadata={"help": "agent hyperparameters (flags --agent.<name>)", "prefix": "agent"}
    )


#: Per-environment presets (paper: TD3 gamma 0.99, 0.977 for KS; 50 updates every 50 steps; Adam 1e-3;
#: 2x256 networks; episode lengths 200 / 200 / 60 / 400; 100 test episodes, 200 for KS).
PRESETS: dict[str, dict[str, Any]] = {
    "pimbrl/CartPole-v0": {
        "total_steps": 15_000,
        "warmup_steps": 1_000,
        "update_after": 1_000,
        "eval_every": 250,
        "threshold": 200.0,
    },
    "pimbrl/Pendulum-v0": {
        "total_steps": 15_000,
        "warmup_steps": 1_000,
        "update_after": 1_000,
        "eval_every": 500,
        "threshold": -200.0,
    },
    "Pendulum-v1": {"total_steps": 15_000, "warmup_steps": 1_000, "update_after": 1_000, "eval_every": 500, "threshold": -200.0},
    "pimbrl/Burgers-v0": {
        "total_steps": 3_000,
        "warmup_steps": 120,
        "update_after": 120,
        "update_every": 60,
        "eval_every": 120,
        "checkpoint_every": 600,
        "log_every": 120,
    },
    "pimbrl/KuramotoSivashinsky-v0": {
        "total_steps": 200_000,
        "warmup_steps": 4_000,
        "update_after": 4_000,
        "eval_every": 5_000,
        "eval_episodes": 200,
        "threshold": -55.0,
        "checkpoint_every": 10_000,
        "agent_config": {"gamma": 0.977},
    },
}


def resolve_config(
    env: str, overrides: dict[str, Any] | None = None, agent_overrides: dict[str, Any] | None = None
) -> TrainConfig:
    """Defaults, then the preset of ``env``, then ``overrides`` / ``agent_overrides``; validated."""
    preset = dict(PRESETS.get(env, {}))
    agent_fields = dict(preset.pop("agent_config", {}))
    agent_fields.update(agent_overrides or {})
    fields = {**preset, **(overrides or {}), "env": env}
    try:
        agent_cfg = from_dict(AgentConfig, agent_fields)
        cfg = from_dict(TrainConfig, {k: v for k, v in fields.items() if k != "agent_config"})
    except TypeError as exc:
        raise ConfigError(str(exc)) from None
    cfg = dataclasses.replace(cfg, agent_config=agent_cfg)
    validate(cfg)
    return cfg
