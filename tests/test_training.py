"""Training harness: CLI smoke runs per environment, kill -9 and resume, atomic checkpoints, config errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pimbrl.cli import main
from pimbrl.training import RunDirectory
from pimbrl.training import rundir as rundir_module

from .settings import POOL_KWARGS, SMOKE_SETTINGS, TINY_SETTINGS, flags

TINY = [*flags(TINY_SETTINGS), "--quiet"]
POOL = json.dumps(POOL_KWARGS)
#: the smoke runs' `pimbrl train` flags (this module tests the command line)
SMOKE = {env: flags(settings) for env, settings in SMOKE_SETTINGS.items()}


@pytest.mark.parametrize("env", list(SMOKE))
def test_cli_train_eval_plot_smoke(env: str, tmp_path, capsys, monkeypatch) -> None:
    from pimbrl.systems import KSTask

    run = tmp_path / "run"
    assert main(["train", env, "--run-dir", str(run), *SMOKE[env], *TINY]) == 0
    payload = json.loads((run / "config.json").read_text())
    assert payload["status"] == "finished" and payload["versions"]["torch"].startswith("2.13")
    rows = RunDirectory(run).evaluations.read()
    assert rows and {"step", "return_mean", "return_min", "return_max", "wall_s"} <= set(rows[0])
    assert float(rows[-1]["return_min"]) <= float(rows[-1]["return_mean"]) <= float(rows[-1]["return_max"])
    assert (run / "checkpoints" / "latest.pt").exists() and (run / "metrics.csv").exists()
    capsys.readouterr()
    assert main(["eval", str(run)]) == 0
    assert "return mean" in capsys.readouterr().out
    if env != "ks":
        assert main(["eval", str(run), "--protocol", "authors"]) == 2
        assert "protocol 'authors' is not defined" in capsys.readouterr().err
    else:  # the paper's rows need the full training pool; this run's small one holds 24 states
        monkeypatch.setattr(KSTask, "AUTHORS_EVAL_ROWS", (0, 7, 23))
        assert main(["eval", str(run), "--protocol", "authors", "--json"]) == 0
        out = capsys.readouterr().out
        assert "3 authors-protocol episodes" in out
        payload = json.loads(out.strip().splitlines()[-1])
        assert payload["protocol"] == "authors" and len(payload["returns"]) == 3
        assert payload["return_q25"] <= payload["return_median"] <= payload["return_q75"]
    assert main(["plot", str(run), "--out", str(tmp_path / "c.png")]) == 0
    assert (tmp_path / "c.png").stat().st_size > 5_000
    # resuming a finished run does nothing
    assert main(["resume", str(run), "--quiet"]) == 0
    assert "already finished" in capsys.readouterr().out
    assert len(RunDirectory(run).evaluations.read()) == len(rows)


RESUME_ARGS = [
    "pendulum",
    "--steps", "1600",
    "--warmup-steps", "200",
    "--update-after", "200",
    "--eval-every", "200",
    "--eval-episodes", "4",
    "--checkpoint-every", "200",
    "--log-every", "100",
    *TINY,
]  # fmt: skip


def _table(path: Path, name: str, drop: tuple[str, ...] = ("wall_s", "steps_per_s")) -> list[dict[str, str]]:
    """Rows of a CSV log without the columns that measure time (``drop`` and every ``time/...`` column)."""
    import csv

    with open(path / name) as fh:
        return [{k: v for k, v in row.items() if k not in drop and not k.startswith("time/")} for row in csv.DictReader(fh)]


def kill_when(args: list[str], run: Path, ready) -> None:
    """Start `pimbrl train <args> --run-dir <run>` in a process and SIGKILL it once ``ready(run)`` holds."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "pimbrl.cli", "train", *args, "--run-dir", str(run)], env={**os.environ, "PYTHONUNBUFFERED": "1"}
    )
    deadline = time.time() + 300
    try:
        while time.time() < deadline:
            if ready(run):
                break
            if proc.poll() is not None:
                pytest.fail("the training process ended before it could be killed")
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert json.loads((run / "config.json").read_text())["status"] == "running", "the run finished before the kill"


@pytest.mark.slow
def test_kill_minus_nine_and_resume_equals_uninterrupted(tmp_path) -> None:
    ref, killed = tmp_path / "ref", tmp_path / "killed"
    assert main(["train", *RESUME_ARGS, "--run-dir", str(ref)]) == 0

    def ready(run: Path) -> bool:
        rows = RunDirectory(run).evaluations.read() if (run / "evaluations.csv").exists() else []
        return (run / "checkpoints" / "latest.pt").exists() and len(rows) >= 4

    kill_when(RESUME_ARGS, killed, ready)
    assert main(["resume", str(killed), "--quiet"]) == 0
    for name in ("evaluations.csv", "episodes.csv", "metrics.csv"):
        assert _table(ref, name) == _table(killed, name), name


def test_resume_without_checkpoint_restarts_cleanly(tmp_path) -> None:
    run = tmp_path / "run"
    args = [
        "pendulum",
        "--steps",
        "400",
        "--warmup-steps",
        "100",
        "--update-after",
        "100",
        "--eval-every",
        "200",
        "--eval-episodes",
        "2",
        *TINY,
    ]
    assert main(["train", *args, "--run-dir", str(run)]) == 0
    reference = _table(run, "evaluations.csv")
    # simulate a run killed before its first checkpoint: config written, a torn CSV line, no checkpoint
    (run / "checkpoints" / "latest.pt").unlink()
    with open(run / "evaluations.csv", "a") as fh:
        fh.write("200,-1234.5,-13")
    payload = json.loads((run / "config.json").read_text())
    payload["status"] = "running"
    (run / "config.json").write_text(json.dumps(payload))
    assert main(["resume", str(run), "--quiet"]) == 0
    assert _table(run, "evaluations.csv") == reference


def test_checkpoint_write_is_atomic(tmp_path, monkeypatch) -> None:
    run = RunDirectory(tmp_path)
    run.save_checkpoint({"value": 1})

    def broken_fsync(fd: int) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(rundir_module.os, "fsync", broken_fsync)
    with pytest.raises(OSError, match="disk full"):
        run.save_checkpoint({"value": 2})
    monkeypatch.undo()
    assert run.load_checkpoint()["value"] == 1
    assert [p.name for p in (tmp_path / "checkpoints").iterdir()] == ["latest.pt"]  # no temporary left behind


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--agent.gamma", "1.5"], "agent.gamma must be in (0.0, 1.0], got 1.5"),
        (["--eval-every", "0"], "eval_every must be > 0, got 0"),
        (
            ["--method", "magic"],
            "method must be one of mfrl, mbrl, pimbrl, known-scheme, identified-scheme, hybrid, pihybrid, feedback, mpc, dpc, got 'magic'",
        ),
        (["--agent.exploration-noise", "-0.1"], "agent.exploration_noise must be in [0.0, 1.0], got -0.1"),
        (["--env-kwargs", "{bad json"], "--env-kwargs must be a JSON object"),
    ],
)
def test_bad_config_values_get_clear_errors(args: list[str], message: str, tmp_path, capsys) -> None:
    assert main(["train", "pendulum", "--run-dir", str(tmp_path / "r"), *args, "--quiet"]) == 2
    assert message in capsys.readouterr().err


def test_existing_run_dir_and_unknown_env(tmp_path, capsys) -> None:
    run = tmp_path / "r"
    run.mkdir()
    (run / "config.json").write_text("{}")
    assert main(["train", "pendulum", "--run-dir", str(run), "--quiet"]) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert main(["train", "Nope-v9", "--run-dir", str(tmp_path / "x")]) == 2
    assert "unknown environment" in capsys.readouterr().err
    assert main(["resume", str(tmp_path / "missing")]) == 2
    assert "not a pimbrl run directory" in capsys.readouterr().err


def test_none_on_the_command_line_clears_a_preset_value() -> None:
    from pimbrl.training.cli_args import config_from_argv as build_train_config

    cfg = build_train_config(["ks", "--method", "pimbrl", "--finetune.at-return", "none", "--threshold", "none"])
    assert cfg.method.finetune.at_return is None and cfg.threshold is None
    preset = build_train_config(["ks", "--method", "pimbrl"])
    assert preset.method.finetune.at_return == -55.0 and preset.threshold == -55.0


def test_a_run_that_cannot_start_leaves_no_directory(tmp_path, capsys) -> None:
    run = tmp_path / "r"
    assert main(["train", "Pendulum-v1", "--method", "pimbrl", "--run-dir", str(run), "--quiet"]) == 2
    assert "pimbrl needs the system's equation, and Pendulum-v1 declares none" in capsys.readouterr().err
    assert not (run / "config.json").exists()
    assert main(["train", "Pendulum-v1", "--run-dir", str(run), *SMOKE["Pendulum-v1"], *TINY]) == 0


def test_print_config_shows_the_resolved_preset_and_trains_nothing(tmp_path, capsys) -> None:
    run = tmp_path / "never"
    assert main(["train", "ks", "--method", "pimbrl", "--utd", "3", "--print-config", "--run-dir", str(run)]) == 0
    cfg = json.loads(capsys.readouterr().out)
    assert cfg["env"] == "pimbrl/KuramotoSivashinsky-v0" and cfg["utd"] == 3.0
    assert cfg["agent"]["gamma"] == 0.977 and cfg["method"]["imagine"]["rollout_length"] == 3
    assert not run.exists()
