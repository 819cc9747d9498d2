"""Sweeps (in-process and on Ray, with a study on the same Ray instance), and every figure command on tiny run directories."""

from __future__ import annotations

import csv
import json

import pytest

from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.experiments.engine import QueuedStudy, run_studies, run_study
from pimbrl.experiments.spec import load_spec
from pimbrl.experiments.sweep import load_sweep, run_sweep
from pimbrl.training.config import get_setting

from .test_dyna import DYNA_SMOKE, SMALL_MODEL
from .test_studies import TINY as STUDY_TINY
from .test_studies import _spec as _study_spec
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
def test_studies_and_sweeps_on_ray_give_what_local_processes_give(tmp_path, capsys) -> None:
    """A study's runs (a model-free and a model-based arm) and a sweep's table, on Ray and as local processes.

    Both share one Ray instance: its start and its workers' imports are most of this test's time (minutes on
    a loaded machine), and a second instance would double them.
    """
    ray = pytest.importorskip("ray")
    from pimbrl.experiments.watchdog import watch_descendants

    spec = load_spec(_study_spec(tmp_path, methods=["mfrl", "mbrl"], overrides=STUDY_TINY))
    local = run_study(spec, tmp_path / "local", status=False, log=lambda m: None)
    sweep = _sweep_file(tmp_path)
    assert main(["sweep", sweep, "--run-dir", str(tmp_path / "sweep-local"), "--no-ray"]) == 0
    watchdog = watch_descendants()  # Ray's helpers end with this process, also a killed one
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        # a queue of two on Ray (one study after the other): the study, then a one-run study of its own
        other = load_spec(_study_spec(tmp_path, name="other.yaml", seeds=[1]))
        queue = [QueuedStudy(spec, tmp_path / "ray"), QueuedStudy(other, tmp_path / "ray-other")]
        on_ray, other_record = run_studies(queue, backend="ray", jobs=2, status=False, log=lambda m: None)
        assert main(["sweep", sweep, "--run-dir", str(tmp_path / "sweep-ray"), "--cpus", "2"]) == 0
    finally:
        ray.shutdown()
        watchdog.stop()
    assert not local["failed"] and not on_ray["failed"] and len(local["runs"]) == len(on_ray["runs"]) == 2
    assert other_record["study"] == "other" and [r["seed"] for r in other_record["runs"]] == [1]
    for a, b in zip(local["runs"], on_ray["runs"]):
        assert (a["arm"], a["seed"]) == (b["arm"], b["seed"])
        assert a["curve"]["return_mean"] == b["curve"]["return_mean"] and a["updates"] == b["updates"]
    table, ray_table = _results(tmp_path / "sweep-local"), _results(tmp_path / "sweep-ray")
    assert len(table) == 2 and table == ray_table
    assert {r["setting"] for r in table} == {"agent.gamma=0.9", "agent.gamma=0.99"}
    assert (tmp_path / "sweep-ray" / "curves.png").stat().st_size > 10_000
    # a finished sweep does no work on a second run (and starts no Ray instance)
    capsys.readouterr()
    assert main(["sweep", sweep, "--run-dir", str(tmp_path / "sweep-ray")]) == 0
    out = capsys.readouterr().out
    assert "2 runs, 2 finished, 0 to run" in out and "0 run now" in out
    assert _results(tmp_path / "sweep-ray") == ray_table and not ray.is_initialized()


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
