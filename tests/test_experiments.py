"""Sweeps (in-process and on Ray), and every figure command on tiny run directories."""

from __future__ import annotations

import csv
import json

import pytest

from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.experiments.sweep import load_sweep, run_sweep
from pimbrl.training.config import get_setting

from .test_dyna import DYNA_SMOKE, SMALL_MODEL
from .test_training import SMOKE, TINY

TRIAL_ARGS = ["--steps", "200", "--warmup-steps", "100", "--update-after", "100", "--eval-every", "100", "--eval-episodes", "2",
              "--agent.hidden", "16,16", "--agent.batch-size", "16"]  # fmt: skip


def _sweep_file(tmp_path, name: str = "tiny") -> str:
    path = tmp_path / f"{name}.json"
    spec = {
        "name": name,
        "envs": ["pendulum"],
        "methods": ["mfrl"],
        "seeds": [0],
        "grid": {"agent.gamma": [0.9, 0.99]},
        "train_args": TRIAL_ARGS,
    }
    path.write_text(json.dumps(spec))
    return str(path)


def _results(path) -> list[dict[str, str]]:
    with open(path / "results.csv") as fh:
        return [{k: v for k, v in r.items() if k != "wall_s"} for r in csv.DictReader(fh)]


@pytest.mark.slow
def test_sweep_in_process_and_on_ray_give_the_same_table(tmp_path, capsys) -> None:
    pytest.importorskip("ray")
    spec = _sweep_file(tmp_path)
    assert main(["sweep", spec, "--run-dir", str(tmp_path / "local"), "--no-ray"]) == 0
    assert main(["sweep", spec, "--run-dir", str(tmp_path / "ray"), "--cpus", "2"]) == 0
    local, ray = _results(tmp_path / "local"), _results(tmp_path / "ray")
    assert len(local) == 2 and local == ray
    assert {r["setting"] for r in local} == {"agent.gamma=0.9", "agent.gamma=0.99"}
    assert (tmp_path / "ray" / "curves.png").stat().st_size > 10_000
    # a finished sweep does no work on a second run
    capsys.readouterr()
    assert main(["sweep", spec, "--run-dir", str(tmp_path / "ray")]) == 0
    out = capsys.readouterr().out
    assert "2 runs, 2 finished, 0 to run" in out and "0 run now" in out
    assert _results(tmp_path / "ray") == ray


@pytest.mark.slow
def test_an_unreadable_trial_stops_the_sweep_before_it_starts(tmp_path) -> None:
    spec = load_sweep(_sweep_file(tmp_path))
    root = tmp_path / "sweep"
    broken = root / "Pendulum-v0" / "mfrl" / "agent.gamma=0.9" / "seed0"
    broken.mkdir(parents=True)
    (broken / "config.json").write_text("{ not json")
    # a sweep is a study: a run directory it cannot read stops it before any run starts, naming the run
    with pytest.raises(
        ConfigError,
        match=r"agent\.gamma=0\.9/seed0 holds a run made with another configuration: the recorded configuration \(unreadable\)",
    ):
        run_sweep(spec, root, use_ray=False, log=lambda m: None)
    assert not (root / "Pendulum-v0" / "mfrl" / "agent.gamma=0.99").exists()
    (broken / "config.json").unlink()  # the damaged run removed, the sweep runs every trial
    result = run_sweep(spec, root, use_ray=False, log=lambda m: None)
    assert len(result["rows"]) == 2 and not result["failed"]


def test_bad_sweep_files_get_clear_errors(tmp_path, capsys) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "gird": {}}))
    assert main(["sweep", str(bad), "--run-dir", str(tmp_path / "x"), "--no-ray"]) == 2
    assert "unknown key(s) gird" in capsys.readouterr().err
    bad.write_text(json.dumps({"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "grid": {"agent.gamma": [2.0]}}))
    assert main(["sweep", str(bad), "--run-dir", str(tmp_path / "x"), "--no-ray"]) == 2
    assert "agent.gamma must be in (0.0, 1.0], got 2.0" in capsys.readouterr().err


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    runs = {
        "ks": ["train", "ks", *SMOKE["ks"], *TINY],
        "ks-pimbrl": ["train", "ks", "--method", "pimbrl", *DYNA_SMOKE["ks"], *TINY, *SMALL_MODEL],
        "burgers": ["train", "burgers", *SMOKE["burgers"], *TINY],
        "model-eval": [
            "model-eval",
            "pendulum",
            "--transitions",
            "200",
            "--test-transitions",
            "30",
            "--steps",
            "20",
            "--refresh-every",
            "10",
        ],
    }
    for name, args in runs.items():
        assert main([*args, "--run-dir", str(root / name)]) == 0, name
    return root


@pytest.mark.parametrize(
    ("kind", "run"),
    [("ks-contours", "ks"), ("burgers", "burgers"), ("model-errors", "model-eval"), ("rollouts", "ks-pimbrl"), ("curves", "ks")],
)
def test_each_figure_command_writes_a_png(kind: str, run: str, tiny_runs, tmp_path) -> None:
    out = tmp_path / f"{kind}.png"
    args = ["figure", kind, str(tiny_runs / run), "--out", str(out)]
    if kind == "rollouts":
        args += ["--lengths", "1,3,10"]
    assert main(args) == 0
    assert out.stat().st_size > 10_000 and out.read_bytes()[:4] == b"\x89PNG"


def test_rollout_figure_needs_a_model(tiny_runs, tmp_path, capsys) -> None:
    assert main(["figure", "rollouts", str(tiny_runs / "ks"), "--out", str(tmp_path / "r.png")]) == 2
    assert "needs a run with a model" in capsys.readouterr().err


def test_shipped_sweep_files_plan_valid_trials(tmp_path) -> None:
    from pathlib import Path

    from pimbrl.experiments.sweep import plan_trials

    configs = sorted((Path(__file__).parent.parent / "configs").glob("*.json"))
    assert configs
    for path in configs:
        trials = plan_trials(load_sweep(path), tmp_path)
        assert trials
        for trial in trials:
            cfg = trial.config
            assert cfg.method.name == trial.method and cfg.seed == trial.seed
            for key, value in trial.params:
                assert get_setting(cfg, key) == value
