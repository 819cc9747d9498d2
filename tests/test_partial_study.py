"""benchmarks/run_partial_physics.py: a study extended with the runs of an earlier record (``--include``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "run_partial_physics.py"
STUDY = ["ks", "--true", "convection=0.7", "--prior", "convection=1", "--learn", "convection", "--steps", "12000"]


def _row(variant: str, seed: int, to: int | None, returns: dict[int, float]) -> dict:
    return {
        "variant": variant,
        "seed": seed,
        "steps": 12000,
        "finished": True,
        "steps_to_-900": to,
        "final_return": list(returns.values())[-1],
        "best_return": max(returns.values()),
        "model_val_mse": {str(k): 1e-5 for k in returns},
        "returns_after_warmup": {str(k): v for k, v in returns.items()},
        "mean_return_after_warmup": sum(returns.values()) / len(returns),
        "model_val_mse_after_warmup": {str(k): 1e-5 for k in returns},
    }


def _record(path: Path, rows: list[dict], **changes) -> Path:
    record = {
        "env": "ks",
        "true": "convection=0.7",
        "prior": "convection=1",
        "learn": "convection",
        "steps": 12000,
        "thresholds": [-900.0],
        "extra_flags": [],
        "pimbrl_flags": [],
        "runs": rows,
        **changes,
    }
    path.write_text(json.dumps(record))
    return path


def _script(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True)


def _module():
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import run_partial_physics
    finally:
        sys.path.remove(str(SCRIPT.parent))
    return run_partial_physics


def test_included_runs_join_the_summary_with_censored_medians(tmp_path) -> None:
    rows = [
        _row("mbrl", 0, 3000, {2000: -950.0, 3000: -880.0}),
        _row("mbrl", 1, None, {2000: -990.0, 3000: -960.0}),
        _row("mbrl", 2, 5000, {2000: -999.0, 3000: -970.0}),
        _row("physics-true", 0, 2000, {2000: -890.0, 3000: -850.0}),
    ]
    first = _record(tmp_path / "first.json", rows[:2])
    second = _record(tmp_path / "second.json", rows[2:])
    out = _script(*STUDY, "--thresholds=-900", "--variants", "mbrl,physics-true", "--seeds", "0,1,2",
                  "--out-dir", str(tmp_path / "runs"), "--no-run", "--include", f"{first},{second}")  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "mbrl  seeds [0, 1, 2]  to -900: [3000, None, 5000]" in out.stdout
    assert "physics-true  seeds [0]  to -900: [2000]" in out.stdout
    assert "        mbrl  to -900: 5,000" in out.stdout  # the median line: the middle seed reached -900 at 5,000
    summary = _module().summarise(
        _module().merge_runs([], {"r": [_as_loaded(r) for r in rows]}, ["mbrl", "physics-true"])[0],
        ["mbrl", "physics-true"],
        [-900.0],
    )
    # one seed of three did not reach -900 within 12,000: no mean, but the median is the middle reached seed
    assert summary["mbrl"]["mean_steps_to_-900"] is None
    assert summary["mbrl"]["median_steps_to_-900"] == 5000
    assert summary["physics-true"]["median_steps_to_-900"] == 2000


def _as_loaded(row: dict) -> dict:  # as load_included returns a recorded run: integer step keys
    return {**row, "returns_after_warmup": {int(k): v for k, v in row["returns_after_warmup"].items()}}


def test_a_run_both_recorded_and_run_here_is_compared_and_the_fresh_one_kept() -> None:
    module = _module()
    old = [_as_loaded(_row("mbrl", s, 3000, {2000: -950.0, 3000: -880.0})) for s in (0, 1)]
    same = {**old[0]}
    other = {**old[1], "returns_after_warmup": {2000: -950.0, 3000: -879.5}, "steps_to_-900": 2000}
    merged, checks = module.merge_runs([same, other], {"first.json": old}, ["mbrl"])
    assert len(merged) == 2 and merged[1]["steps_to_-900"] == 2000
    assert checks[0] == "mbrl seed 0: equal to first.json's at all 2 evaluations; the run of this invocation is kept"
    assert checks[1].startswith("mbrl seed 1: differs from first.json's (largest return difference 0.5 over 2")
    # the run directory the record was made from agrees with it by construction: said so
    mine = {**same, "run_dir": "/runs/mbrl/seed0"}
    _, checks = module.merge_runs([mine], {"first.json": [{**old[0], "run_dir": "/runs/mbrl/seed0"}]}, ["mbrl"])
    assert checks[0].endswith("(the same run directory: not a reproduction check); the run of this invocation is kept")


def test_a_run_still_under_way_never_replaces_a_longer_recorded_one() -> None:
    module = _module()
    recorded = _as_loaded(_row("mbrl", 0, 6000, {2000: -950.0, 3000: -880.0}))
    cut = {**recorded, "steps": 3000, "finished": False, "steps_to_-900": None}
    merged, checks = module.merge_runs([cut], {"first.json": [recorded]}, ["mbrl"])
    assert merged == [recorded]
    assert checks == ["mbrl seed 0: the run here has 3,000 steps, first.json has 12,000: the recorded run is kept"]
    # a run in two records is kept once, from the first; another variant's runs are left out
    again = {**recorded, "returns_after_warmup": {2000: -951.0}}
    other = _as_loaded(_row("pimbrl-true", 0, 3000, {2000: -900.0}))
    merged, checks = module.merge_runs([], {"a.json": [recorded], "b.json": [again, other]}, ["mbrl"])
    assert merged == [recorded]
    assert checks == [
        "mbrl seed 0: differs from b.json's (largest return difference 1 over 1 evaluations); the run of a.json is kept"
    ]


def test_a_wrong_record_is_refused_before_any_run(tmp_path, monkeypatch, capsys) -> None:
    module = _module()

    def no_training(*args, **kwargs):
        raise AssertionError("a run started before the record was checked")

    monkeypatch.setattr(module, "run_all", no_training)
    monkeypatch.setattr(module, "check_reuse", no_training)
    record = _record(tmp_path / "other.json", [], steps=6000)
    argv = [*STUDY, "--thresholds=-900", "--out-dir", str(tmp_path / "runs"), "--include", str(record)]
    monkeypatch.setattr(sys, "argv", ["run_partial_physics.py", *argv])
    with pytest.raises(SystemExit, match="a record of another study \\(steps 6000 there, 12000 here\\)"):
        module.main()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"prior": "convection=1.3"}, "a record of another study (prior 'convection=1.3' there, 'convection=1' here)"),
        ({"extra_flags": ["--eval-every", "500"]}, "a record of another study (extra_flags"),
        ({"thresholds": [-1000.0]}, "the record has no steps to -900; ask only for its thresholds (-1000)"),
    ],
)
def test_a_record_of_another_study_is_refused(tmp_path, change: dict, message: str) -> None:
    record = _record(tmp_path / "other.json", [_row("mbrl", 0, 3000, {2000: -950.0})], **change)
    out = _script(*STUDY, "--thresholds=-900", "--out-dir", str(tmp_path / "runs"), "--no-run", "--include", str(record))
    assert out.returncode != 0 and message in out.stderr


def test_an_unreadable_record_is_refused(tmp_path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    out = _script(*STUDY, "--thresholds=-900", "--out-dir", str(tmp_path / "runs"), "--no-run", "--include", str(bad))
    assert out.returncode != 0 and "cannot read it as a JSON record" in out.stderr
