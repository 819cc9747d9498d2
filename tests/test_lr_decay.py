"""The learning-rate decay (``lr_decay_after``, ``lr_decay_to``): constant, then linear, kept by checkpoints."""

from __future__ import annotations

import pytest

from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.training import RunDirectory, create_run, resolve_config, train
from pimbrl.training.loop import lr_scale

from .test_training import RESUME_ARGS, _table, kill_when

PENDULUM = {"total_steps": 600, "warmup_steps": 100, "update_after": 100, "eval_every": 100, "eval_episodes": 3, "log_every": 100}
SMALL_AGENT = {"agent.hidden": (16, 16), "agent.batch_size": 16}


def test_the_scale_is_one_until_the_start_then_linear_to_the_final_fraction() -> None:
    assert [lr_scale(t, 300, 600, 0.25) for t in (0, 150, 300)] == [1.0, 1.0, 1.0]
    assert lr_scale(450, 300, 600, 0.25) == pytest.approx(0.625)
    assert lr_scale(600, 300, 600, 0.25) == pytest.approx(0.25)
    assert lr_scale(900, 300, 600, 0.25) == pytest.approx(0.25)  # past the end it stays at the final fraction
    assert lr_scale(600, 0, 600, 0.0) == 0.0


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"experimental.lr_decay_to": 0.5}, "give --experimental.lr-decay-after STEP too"),
        ({"experimental.lr_decay_after": 600}, "is not before --total-steps 600"),
        ({"experimental.lr_decay_after": 100, "experimental.lr_decay_to": 1.0}, "keeps the learning rates constant"),
        ({"experimental.lr_decay_after": 100, "experimental.lr_decay_to": 1.5}, r"lr_decay_to must be in \[0.0, 1.0\]"),
    ],
)
def test_a_decay_that_cannot_happen_as_asked_is_refused(fields: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        resolve_config("pimbrl/Pendulum-v0", {**PENDULUM, **fields, **SMALL_AGENT})


def _run(tmp_path, name: str, agent: str, **fields):
    cfg = resolve_config("pimbrl/Pendulum-v0", {**PENDULUM, "agent": agent, **fields, **SMALL_AGENT})
    run = create_run(cfg, tmp_path / name, progress=False)
    train(run)
    return run


@pytest.mark.slow  # a few seconds: the whole suite runs it, the fast tier does not
@pytest.mark.parametrize("agent", ["td3", "sac"])
def test_a_decaying_run_is_the_constant_run_until_the_decay_starts_and_ends_at_the_final_rates(tmp_path, agent) -> None:
    plain = _run(tmp_path, "plain", agent)
    decay = _run(tmp_path, "decay", agent, **{"experimental.lr_decay_after": 300, "experimental.lr_decay_to": 0.25})
    drop = ("wall_s", "steps_per_s", "lr_scale")
    evals_plain = _table(plain.run_dir.path, "evaluations.csv", drop)
    evals_decay = _table(decay.run_dir.path, "evaluations.csv", drop)
    # the phases up to step 300 run at scale 1: the same run, bit for bit; after, the rates are lower
    assert evals_plain[:3] == evals_decay[:3]
    assert evals_plain[3:] != evals_decay[3:]
    cfg = decay.cfg.agent
    assert decay.agent.actor_opt.param_groups[0]["lr"] == pytest.approx(0.25 * cfg.actor_lr)
    assert decay.agent.critic_opt.param_groups[0]["lr"] == pytest.approx(0.25 * cfg.critic_lr)
    assert plain.agent.actor_opt.param_groups[0]["lr"] == cfg.actor_lr
    if agent == "sac":  # the temperature keeps its own rate
        assert decay.agent.alpha_opt.param_groups[0]["lr"] == cfg.alpha_lr
    scales = [float(r["lr_scale"]) for r in _table(decay.run_dir.path, "metrics.csv", ())]
    assert scales[0] == 1.0 and scales[-1] == pytest.approx(0.25) and scales == sorted(scales, reverse=True)
    assert "lr_scale" not in _table(plain.run_dir.path, "metrics.csv", ())[0]


@pytest.mark.slow
def test_kill_and_resume_of_a_decaying_run_equals_the_uninterrupted_one(tmp_path) -> None:
    args = [*RESUME_ARGS, "--experimental.lr-decay-after", "600", "--experimental.lr-decay-to", "0.2"]
    ref, killed = tmp_path / "ref", tmp_path / "killed"
    assert main(["train", *args, "--run-dir", str(ref)]) == 0

    def ready(run) -> bool:
        rows = RunDirectory(run).evaluations.read() if (run / "evaluations.csv").exists() else []
        return (run / "checkpoints" / "latest.pt").exists() and len(rows) >= 5  # a checkpoint inside the decay

    kill_when(args, killed, ready)
    assert main(["resume", str(killed), "--quiet"]) == 0
    for name in ("evaluations.csv", "episodes.csv", "metrics.csv"):
        assert _table(ref, name) == _table(killed, name), name
