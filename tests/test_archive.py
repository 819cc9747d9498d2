"""A study's archive: finished runs kept in the repository come back on a fresh machine, and only they."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.experiments.archive import ARCHIVED, archive_study, archived_runs, default_archive, restore_study
from pimbrl.experiments.engine import plan_study, run_study
from pimbrl.experiments.spec import load_spec
from pimbrl.fileio import UnsafeFileError

TINY_MFRL = {
    "total_steps": 80,
    "warmup_steps": 20,
    "update_after": 20,
    "eval_every": 40,
    "eval_episodes": 1,
    "agent.hidden": [32, 32],
    "agent.batch_size": 32,
}


def _spec(tmp_path: Path, name: str = "s.yaml", **data) -> Path:
    body = {"name": "arch", "systems": ["pendulum"], "methods": ["mfrl"], "seeds": 2, "overrides": TINY_MFRL, **data}
    path = tmp_path / name
    path.write_text(json.dumps(body))
    return path


def _finals(record: dict) -> dict[int, float]:
    return {r["seed"]: r["final_return"] for r in record["runs"]}


def test_the_default_archive_lies_beside_the_spec(tmp_path) -> None:
    spec = load_spec(_spec(tmp_path))
    assert default_archive(spec) == tmp_path / "archive" / "arch"


@pytest.mark.slow
def test_archived_runs_come_back_on_a_fresh_machine_and_only_the_rest_train(tmp_path, capsys) -> None:
    path = _spec(tmp_path)
    spec = load_spec(path)
    root, archive = tmp_path / "runs", tmp_path / "kept"
    first = run_study(spec, root, status=False, log=lambda m: None)
    assert len(first["runs"]) == 2 and all(r["finished"] for r in first["runs"])

    runs = plan_study(spec, root)
    result = archive_study(spec, root, archive, runs)
    assert sorted(result.copied) == ["mfrl/seed0", "mfrl/seed1"] and not result.kept
    held = {p.name for p in (archive / "mfrl" / "seed0").iterdir()}
    assert "config.json" in held and "evaluations.csv" in held and held <= set(ARCHIVED)  # no checkpoint, lock or log
    assert (archive / "study.json").is_file()
    assert archive_study(spec, root, archive, runs).kept == result.copied  # a second archive copies nothing
    assert sorted(archived_runs(root, archive, runs)) == ["mfrl/seed0", "mfrl/seed1"]

    # a fresh machine: nothing trains, the record is the same
    fresh = tmp_path / "fresh"
    logs: list[str] = []
    again = run_study(spec, fresh, archive=archive, status=False, log=logs.append)
    assert logs[0].startswith("restored 2 finished run(s) from") and "2 finished, 0 to run" in logs[1]
    assert _finals(again) == _finals(first) and all(r["finished"] for r in again["runs"])
    assert not (fresh / "mfrl" / "seed0" / "checkpoints").exists()
    assert (
        json.loads((fresh / "study.json").read_text())["first_run_started_unix"]
        == json.loads((root / "study.json").read_text())["first_run_started_unix"]
    )  # the archived start, not a new one

    # one archived run missing, another of other settings: the first trains, the second is left out and trains
    partial = tmp_path / "partial"
    shutil.copytree(archive, partial)
    shutil.rmtree(partial / "mfrl" / "seed1")
    config = json.loads((partial / "mfrl" / "seed0" / "config.json").read_text())
    config["config"]["total_steps"] = 40
    (partial / "mfrl" / "seed0" / "config.json").write_text(json.dumps(config))
    logs.clear()
    third = run_study(spec, tmp_path / "third", archive=partial, status=False, log=logs.append)
    assert "restored 0 finished run(s)" in logs[0] and "1 left out (mfrl/seed0: another configuration)" in logs[0]
    assert "0 finished, 2 to run" in logs[1] and _finals(third) == _finals(first)

    # an archived run is never overwritten by other files
    (root / "mfrl" / "seed1" / "episodes.csv").write_text("step,episode,return,length\n")
    with pytest.raises(ConfigError, match="never overwritten"):
        archive_study(spec, root, archive, runs)

    # the command line: archive, then status names what waits there
    assert main(["study", "archive", str(path), "--run-dir", str(tmp_path / "third"), "--archive", str(tmp_path / "cli")]) == 0
    assert "archived 2 finished run(s) to" in capsys.readouterr().out
    assert main(["study", "status", str(path), "--run-dir", str(tmp_path / "none"), "--archive", str(tmp_path / "cli")]) == 0
    assert "2 finished run(s) wait in the archive" in capsys.readouterr().out


def test_a_restore_refuses_links_another_studys_archive_and_another_start(tmp_path) -> None:
    spec = load_spec(_spec(tmp_path))
    root, archive = tmp_path / "runs", tmp_path / "kept"
    runs = plan_study(spec, root)
    seed0 = archive / "mfrl" / "seed0"
    seed0.mkdir(parents=True)
    (tmp_path / "elsewhere.json").write_text("{}")
    (seed0 / "config.json").symlink_to(tmp_path / "elsewhere.json")
    with pytest.raises(UnsafeFileError, match="link"):
        restore_study(spec, root, archive, runs)
    assert not (root / "mfrl").exists()  # nothing half-made

    (seed0 / "config.json").unlink()
    (archive / "study.json").write_text(json.dumps({"study": "another", "first_run_started_unix": 1.0}))
    with pytest.raises(ConfigError, match="not the registration of study arch"):
        restore_study(spec, root, archive, runs)

    (archive / "study.json").write_text(json.dumps({"study": "arch", "first_run_started_unix": 1.0}))
    (root / "study.json").write_text(json.dumps({"study": "arch", "first_run_started_unix": 2.0}))
    with pytest.raises(ConfigError, match="another start of study arch"):
        restore_study(spec, root, archive, runs)
    with pytest.raises(ConfigError, match="another first start"):
        archive_study(spec, root, archive, runs)
