"""Small run settings shared by the tests, as the Python API takes them (setting paths -> values).

Unit tests build runs with :func:`pimbrl.training.resolve_config` from these; command-line tests turn them
into `pimbrl train` flags with :func:`flags` (only they go through argv).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from pimbrl.training.config import flag_of, has_setting

from .conftest import SMALL_POOL

#: the short names of the tests and the environments they stand for
ENV_IDS = {
    "ks": "pimbrl/KuramotoSivashinsky-v0",
    "burgers": "pimbrl/Burgers-v0",
    "cartpole": "pimbrl/CartPole-v0",
    "pendulum": "pimbrl/Pendulum-v0",
    "Pendulum-v1": "Pendulum-v1",
}
#: a small KS initial-state pool (fast to generate)
POOL_KWARGS = {
    "pool_config": {
        "n_train": SMALL_POOL.n_train,
        "n_test": SMALL_POOL.n_test,
        "batch": SMALL_POOL.batch,
        "seed": SMALL_POOL.seed,
    }
}
#: small networks
TINY_SETTINGS: dict[str, Any] = {"agent.hidden": (32, 32), "agent.batch_size": 32}
#: model-free smoke runs per environment
SMOKE_SETTINGS: dict[str, dict[str, Any]] = {
    "ks": {"total_steps": 40, "warmup_steps": 20, "update_after": 20, "update_every": 20, "eval_every": 40,
           "eval_episodes": 2, "env_kwargs": POOL_KWARGS},
    "burgers": {"total_steps": 120, "warmup_steps": 60, "update_after": 60, "eval_every": 60, "eval_episodes": 4},
    "cartpole": {"total_steps": 200, "warmup_steps": 100, "update_after": 100, "eval_every": 100, "eval_episodes": 4},
    "pendulum": {"total_steps": 200, "warmup_steps": 100, "update_after": 100, "eval_every": 100, "eval_episodes": 3},
    "Pendulum-v1": {"total_steps": 200, "warmup_steps": 100, "update_after": 100, "eval_every": 100, "eval_episodes": 2},
}  # fmt: skip
#: model-based smoke runs per environment (the model in use from its first phase: lambda 1e3)
DYNA_SMOKE_SETTINGS: dict[str, dict[str, Any]] = {
    "ks": {"total_steps": 60, "warmup_steps": 20, "update_after": 20, "update_every": 20, "eval_every": 60,
           "eval_episodes": 2, "env_kwargs": POOL_KWARGS, "model.start_after": 20, "physics.start_after": 30,
           "fit.steps": 2, "check.threshold": 1e3},
    "burgers": {"total_steps": 180, "warmup_steps": 60, "update_after": 60, "eval_every": 60, "eval_episodes": 3,
                "model.start_after": 60, "physics.start_after": 60, "fit.steps": 3, "check.threshold": 1e3},
    "cartpole": {"total_steps": 300, "warmup_steps": 100, "update_after": 100, "eval_every": 150, "eval_episodes": 3,
                 "model.start_after": 100, "physics.start_after": 150, "fit.steps": 5, "check.threshold": 1e3,
                 "imagine.rollout_length": 20},
    "pendulum": {"total_steps": 300, "warmup_steps": 100, "update_after": 100, "eval_every": 150, "eval_episodes": 3,
                 "model.start_after": 100, "physics.start_after": 150, "fit.steps": 5, "check.threshold": 1e3,
                 "imagine.rollout_length": 20},
}  # fmt: skip
#: a small model phase
SMALL_MODEL_SETTINGS: dict[str, Any] = {"fit.batch_size": 32, "imagine.rollouts": 16, "check.validation_size": 64}


def for_method(settings: Mapping[str, Any], method: str, agent: str = "td3") -> dict[str, Any]:
    """``settings`` without those ``method`` (with ``agent``) does not have: mbrl has no physics loss, the
    known scheme no fit (given, they would be an error)."""
    return {k: v for k, v in settings.items() if has_setting(method, agent, k)}


def flags(settings: Mapping[str, Any]) -> list[str]:
    """The `pimbrl train` flags that give ``settings`` (``--steps 40 --agent.hidden 32,32 ...``)."""
    out: list[str] = []
    for path, value in settings.items():
        if path == "env_kwargs":
            out += ["--env-kwargs", json.dumps(value)]
            continue
        if isinstance(value, bool):
            text = "true" if value else "false"
        elif isinstance(value, (tuple, list)):
            text = ",".join(str(v) for v in value)
        elif value is None:
            text = "none"
        else:
            text = str(value)
        out += [flag_of(path), text]
    return out
