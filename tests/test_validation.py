"""Configuration values that used to pass validation and then crash or hang: non-finite and huge numbers."""

from __future__ import annotations

import dataclasses
import math
import typing

import pytest

from pimbrl.agents import DDPGConfig, SACConfig, TD3Config
from pimbrl.buffers import ReplayBuffer
from pimbrl.cli import main
from pimbrl.config import ConfigError, validate
from pimbrl.experiments.model_eval import ModelEvalConfig
from pimbrl.training import TrainConfig
from pimbrl.training.config import Experimental, config_from_dict, resolve_config
from pimbrl.training.methods import METHOD_TYPES, SECTIONS

#: numeric fields that are finite but deliberately unbounded: returns and a model-error threshold, which
#: are only compared with measured values (a huge one is harmless: it is simply always or never reached)
UNBOUNDED = {"TrainConfig.threshold", "AccuracyCheck.threshold", "Finetune.at_return"}
#: every configuration type: the run, the agents, the methods and their sections, the experimental knobs, model-eval
CONFIG_TYPES = (
    TrainConfig,
    TD3Config,
    DDPGConfig,
    SACConfig,
    Experimental,
    *METHOD_TYPES.values(),
    *SECTIONS.values(),
    ModelEvalConfig,
)


def _numeric_fields() -> list[tuple[type, str, type]]:
    out = []
    for cls in CONFIG_TYPES:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            args = [a for a in typing.get_args(hints[f.name]) if a is not type(None)] or [hints[f.name]]
            base = args[0]
            if base in (int, float) and hints[f.name] is not bool:
                out.append((cls, f.name, base))
    return out


NUMERIC = _numeric_fields()
FLOATS = [(cls, name) for cls, name, base in NUMERIC if base is float]


def _ids(params: list) -> list[str]:
    return [f"{p[0].__name__}.{p[1]}" for p in params]


@pytest.mark.parametrize(("cls", "name"), FLOATS, ids=_ids(FLOATS))
@pytest.mark.parametrize("bad", [math.inf, -math.inf, math.nan], ids=["inf", "-inf", "nan"])
def test_every_float_field_rejects_non_finite_values(cls: type, name: str, bad: float) -> None:
    cfg = dataclasses.replace(cls(), **{name: bad})
    with pytest.raises(ConfigError, match=rf"^{name} must be finite, got {bad!r}$"):
        validate(cfg)


@pytest.mark.parametrize(("cls", "name", "base"), NUMERIC, ids=_ids(NUMERIC))
def test_every_numeric_field_has_an_upper_bound(cls: type, name: str, base: type) -> None:
    huge = 10**30 if base is int else 1e300
    cfg = dataclasses.replace(cls(), **{name: huge})
    if f"{cls.__name__}.{name}" in UNBOUNDED:
        validate(cfg)
        return
    with pytest.raises(ConfigError, match=rf"^{name} must be "):
        validate(cfg)


def test_bounds_are_stated_in_the_help_texts() -> None:
    for cls in CONFIG_TYPES:
        for f in dataclasses.fields(cls):
            if f"{cls.__name__}.{f.name}" in UNBOUNDED or f.metadata.get("check") is None:
                continue
            assert "must be" in f.metadata["help"], f"{cls.__name__}.{f.name}: the help does not state the bound"
    buffer_size = next(f for f in dataclasses.fields(TrainConfig) if f.name == "buffer_size")
    assert "must be <= 100,000,000" in buffer_size.metadata["help"]


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"utd": math.inf}, "utd must be finite, got inf"),
        ({"utd": 1e300}, "utd must be <= 1,000, got 1e+300"),
        ({"agent.actor_lr": math.inf}, "agent.actor_lr must be finite, got inf"),
        ({"agent.critic_lr": math.nan}, "agent.critic_lr must be finite, got nan"),
        ({"agent": "sac", "agent.init_alpha": math.inf}, "agent.init_alpha must be finite, got inf"),
        ({"agent": "sac", "agent.alpha_lr": math.inf}, "agent.alpha_lr must be finite, got inf"),
        ({"agent": "sac", "agent.target_entropy": -math.inf}, "agent.target_entropy must be finite, got -inf"),
        ({"method": "pimbrl", "physics.weight": math.inf}, "physics.weight must be finite, got inf"),
        ({"threshold": math.nan}, "threshold must be finite, got nan"),
        ({"buffer_size": 10**12}, "buffer_size must be <= 100,000,000"),
        ({"agent.hidden": (100_000_000, 1)}, "agent.hidden must be"),
        ({"method": "mbrl", "imagine.buffer_size": 10**12}, "imagine.buffer_size must be <= 100,000,000"),
        ({"eval_episodes": 10**9}, "eval_episodes must be <= "),
        ({"method": "mbrl", "imagine.rollouts": 10**12}, "imagine.rollouts must be <= "),
        ({"agent.batch_size": 10**12}, "agent.batch_size must be <= "),
        ({"method": "mbrl", "fit.batch_size": 10**12}, "fit.batch_size must be <= "),
        ({"total_steps": 10**30}, "total_steps must be <= "),
        ({"seed": 10**30}, "seed must be <= "),
    ],
)
def test_resolve_config_rejects_non_finite_and_oversized_values(overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        resolve_config("pimbrl/Pendulum-v0", overrides)
    assert message in str(exc.value)
    assert "\n" not in str(exc.value)


def test_a_config_file_with_infinity_or_a_huge_integer_is_rejected() -> None:
    with pytest.raises(ConfigError, match="utd must be finite, got inf"):
        config_from_dict({"utd": math.inf})
    with pytest.raises(ConfigError, match="utd must be finite"):
        config_from_dict({"utd": 10**400})  # an int too large for a float: no OverflowError


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--utd", "inf"], "utd must be finite, got inf"),
        (["--utd", "1e300"], "utd must be <= 1,000, got 1e+300"),
        (["--buffer-size", "1e12"], "buffer_size must be <= 100,000,000, got 1000000000000"),
        (["--agent.hidden", "100000000,1"], "agent.hidden must be"),
        (["--agent.actor-lr", "inf"], "agent.actor_lr must be finite, got inf"),
        (["--eval-episodes", "1e9"], "eval_episodes must be <= "),
    ],
)
def test_cli_rejects_non_finite_and_oversized_values(args: list[str], message: str, tmp_path, capsys) -> None:
    run_dir = tmp_path / "r"
    assert main(["train", "pendulum", "--run-dir", str(run_dir), *args, "--quiet"]) == 2
    assert message in capsys.readouterr().err
    assert not run_dir.exists()


def test_replay_buffer_larger_than_available_memory_is_refused(monkeypatch) -> None:
    import pimbrl.buffers as buffers

    monkeypatch.setattr(buffers, "available_memory", lambda: 10**6)
    with pytest.raises(ValueError, match=r"replay buffer of 1,000,000 transitions needs about [0-9.]+ GB.*lower") as exc:
        ReplayBuffer(1_000_000, 64, 4)
    assert "\n" not in str(exc.value)
    ReplayBuffer(100, 64, 4)  # about 53 kB: fits


def test_model_eval_config_rejects_infinite_learning_rate() -> None:
    with pytest.raises(ConfigError, match="lr must be finite, got inf"):
        validate(ModelEvalConfig(lr=math.inf))
