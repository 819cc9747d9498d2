"""An interrupted run carried in its study's archive, checkpoint included, resumes on a fresh machine exactly."""

from __future__ import annotations

import json
import os
import shutil
import signal
import threading
from pathlib import Path

import pytest

from pimbrl.cli import main
from pimbrl.experiments import carry
from pimbrl.experiments.archive import archive_study, plan_restore, restore_study
from pimbrl.experiments.carry import CHECKPOINT, INTERRUPTED
from pimbrl.experiments.engine import collect_record, plan_study, run_study
from pimbrl.experiments.registration import start_study
from pimbrl.experiments.report import study_report
from pimbrl.experiments.spec import load_spec
from pimbrl.training import RunDirectory, RunStopped, create_run, open_run, train

from .test_stopping import SETTINGS, _tables

pytestmark = pytest.mark.skipif(
    threading.current_thread() is not threading.main_thread(), reason="signal handlers are set on the main thread only"
)

RUN = "mfrl/seed0"


def _spec(folder: Path, **overrides):
    body = {"name": "carry", "systems": ["burgers"], "methods": ["mfrl"], "seeds": [0]}
    body["overrides"] = {**{k: v for k, v in SETTINGS.items() if k != "method"}, **overrides}  # episodes of 60 steps
    path = folder / "s.yaml"
    path.write_text(json.dumps(body))
    return load_spec(path)


def _stopped_at(spec, root: Path, kill_at: int, resume: bool = False) -> Path:
    """The study's one run in ``root`` (``resume``: the one there), stopped by a SIGTERM at step ``kill_at``.

    It stops at the next episode end, with a checkpoint.
    """
    runs = plan_study(spec, root)
    if not (root / "study.json").exists():
        start_study(spec, root, runs)  # the registration, as `pimbrl study run` writes it

    def kill(name: str, run) -> None:
        if name == "act" and run.t == kill_at:
            os.kill(os.getpid(), signal.SIGTERM)

    run = open_run(runs[0].path, progress=False) if resume else create_run(runs[0].config, runs[0].path, progress=False)
    with pytest.raises(RunStopped):
        train(run, on_event=kill, stop_on_signal=True)
    assert RunDirectory(runs[0].path).status == "running"
    return runs[0].path


def _manifest(archive: Path) -> dict:
    return json.loads((archive / INTERRUPTED / RUN / "carried.json").read_text())


@pytest.mark.slow  # three short Burgers runs
def test_an_interrupted_run_carried_in_the_archive_resumes_elsewhere_as_if_never_stopped(tmp_path, capsys) -> None:
    spec = _spec(tmp_path, total_steps=240)
    whole = run_study(spec, tmp_path / "whole", status=False, log=lambda m: None)
    root, archive = tmp_path / "first", tmp_path / "archive"
    _stopped_at(spec, root, kill_at=70)  # stops at 120
    runs = plan_study(spec, root)
    assert archive_study(spec, root, archive, runs).carried == []  # without --checkpoints: finished runs only
    assert not (archive / INTERRUPTED).exists()
    result = archive_study(spec, root, archive, runs, checkpoints=True)
    assert result.carried == [RUN] and "1 interrupted run(s) with their checkpoints" in result.line("archived", archive)
    carried = archive / INTERRUPTED / RUN
    assert {p.name for p in carried.iterdir()} >= {"config.json", "evaluations.csv", CHECKPOINT, "carried.json"}
    assert not (carried / "checkpoints").exists() and not (carried / "run.lock").exists()
    assert _manifest(archive)["step"] == 120
    packed = (carried / CHECKPOINT).read_bytes()
    assert len(packed) < (root / RUN / "checkpoints" / "latest.pt").stat().st_size
    assert archive_study(spec, root, archive, runs, checkpoints=True).carried == []  # the same copy: kept

    # the same run started again from nothing elsewhere never overwrites the copy that came further
    behind = tmp_path / "behind"
    behind.mkdir()
    shutil.copy(root / "study.json", behind / "study.json")
    _stopped_at(spec, behind, kill_at=10)  # stops at 60
    assert archive_study(spec, behind, archive, plan_study(spec, behind), checkpoints=True).carried == []
    assert (carried / CHECKPOINT).read_bytes() == packed
    # a copy that came further replaces it
    _stopped_at(spec, root, kill_at=130, resume=True)  # from 120 on, stops at 180
    assert archive_study(spec, root, archive, runs, checkpoints=True).carried == [RUN]
    assert _manifest(archive)["step"] == 180 and (carried / CHECKPOINT).read_bytes() != packed

    # a fresh machine: the run comes back with its checkpoint and finishes exactly as the uninterrupted run
    fresh = tmp_path / "fresh"
    assert [r.seed for r in plan_restore(spec, fresh, archive, plan_study(spec, fresh)).carried] == [0]
    assert main(["study", "status", str(tmp_path / "s.yaml"), "--run-dir", str(fresh), "--archive", str(archive)]) == 0
    assert "1 interrupted run(s) with their checkpoints, to resume" in capsys.readouterr().out
    logs: list[str] = []
    again = run_study(spec, fresh, archive=archive, status=False, log=logs.append)
    assert "1 interrupted run(s) with their checkpoints, to resume where they stopped" in logs[0]
    assert _tables(fresh / RUN) == _tables(tmp_path / "whole" / RUN)
    assert [r["final_return"] for r in again["runs"]] == [r["final_return"] for r in whole["runs"]]
    # archived finished, the run's interrupted copy goes, and the stale interrupted run is not carried again
    assert archive_study(spec, fresh, archive, plan_study(spec, fresh)).copied == [RUN]
    assert not (archive / INTERRUPTED).exists() and (archive / RUN / "config.json").exists()
    assert archive_study(spec, root, archive, runs, checkpoints=True).carried == []
    assert not (archive / INTERRUPTED).exists()


@pytest.mark.slow  # one short Burgers run
def test_a_damaged_carried_checkpoint_is_refused_in_one_line_and_nothing_is_made(tmp_path, capsys, monkeypatch) -> None:
    spec = _spec(tmp_path)
    root, archive = tmp_path / "first", tmp_path / "archive"
    _stopped_at(spec, root, kill_at=70)
    with monkeypatch.context() as m:  # a checkpoint too large for a repository is named, not carried
        m.setattr(carry, "MAX_CARRIED_BYTES", 1000)
        result = archive_study(spec, root, tmp_path / "small", plan_study(spec, root), checkpoints=True)
    assert not result.carried and result.passed[0].startswith(f"{RUN}: its checkpoint is too large (")
    assert not (tmp_path / "small" / INTERRUPTED / RUN).exists()
    archive_study(spec, root, archive, plan_study(spec, root), checkpoints=True)
    packed = archive / INTERRUPTED / RUN / CHECKPOINT
    packed.write_bytes(packed.read_bytes()[: len(packed.read_bytes()) // 2])
    fresh = tmp_path / "fresh"
    capsys.readouterr()  # the stop's own line
    code = main(["study", "run", str(tmp_path / "s.yaml"), "--run-dir", str(fresh), "--archive", str(archive)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and f"{CHECKPOINT} is truncated" in err[0] and "remove the folder" in err[0]
    # checked before anything is written: no registration, no half-made run (only the driver's lock file)
    assert [p.name for p in fresh.iterdir()] == ["compare.lock"]


@pytest.mark.slow  # one short Burgers run
def test_a_run_resumed_on_another_cpu_or_commit_says_so_and_the_report_lists_both(tmp_path) -> None:
    spec = _spec(tmp_path)
    root = tmp_path / "first"
    path = _stopped_at(spec, root, kill_at=70)
    rd = RunDirectory(path)
    rd.update_status(provenance={**rd.read_config()["provenance"], "cpu": "Another CPU"})  # as if it began elsewhere
    open_run(path, progress=False).run_dir.close()
    resumed = rd.read_config()["resumed_on"]
    assert len(resumed) == 1 and resumed[0]["cpu"] != "Another CPU" and "commit" in resumed[0]
    train(open_run(path, progress=False))  # resumed again where it last ran: no second entry
    assert rd.read_config()["resumed_on"] == resumed and rd.status == "finished"
    record = collect_record(spec, plan_study(spec, root), root)
    assert record["runs"][0]["resumed_on"] == resumed
    provenance_line = next(line for line in study_report(spec, record).markdown.splitlines() if "CPU" in line)
    assert "Another CPU" in provenance_line and resumed[0]["cpu"] in provenance_line


def test_checkpoints_is_a_flag_of_study_archive_alone(tmp_path, capsys) -> None:
    _spec(tmp_path)
    assert main(["study", "status", str(tmp_path / "s.yaml"), "--checkpoints"]) == 2
    assert capsys.readouterr().err.strip() == "pimbrl study: error: --checkpoints applies to study archive, not status"


def _control_study(tmp_path: Path, method: str, overrides: dict) -> tuple:
    """A one-run Pendulum study of ``method``: its spec, its uninterrupted record, and its first run directory
    planned and registered (``root``) beside an archive path; returns ``(spec, whole, root, archive, runs)``."""
    body = {"name": f"carry-{method}", "systems": ["pendulum"], "methods": {method: {"method": method}}, "seeds": [0]}
    (tmp_path / "s.yaml").write_text(json.dumps({**body, "overrides": overrides}))
    spec = load_spec(tmp_path / "s.yaml")
    whole = run_study(spec, tmp_path / "whole", status=False, log=lambda m: None)
    root, archive = tmp_path / "first", tmp_path / "archive"
    runs = plan_study(spec, root)
    start_study(spec, root, runs)
    return spec, whole, root, archive, runs


def _killed_in_call(monkeypatch, owner, name: str, at: int, run) -> None:
    """Train ``run`` with ``owner.name`` raising KeyboardInterrupt at its ``at``-th call (a kill there); then unpatch."""
    real, calls = getattr(owner, name), {"n": 0}

    def dying(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == at:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(owner, name, dying)
    with pytest.raises(KeyboardInterrupt):
        train(run)
    monkeypatch.setattr(owner, name, real)


@pytest.mark.slow  # two short MPC runs on Pendulum
def test_an_interrupted_controller_is_carried_with_its_saved_chunks_and_finishes_as_if_never_stopped(
    tmp_path, monkeypatch
) -> None:
    import pimbrl.training.control_run as control_run

    mpc = {"eval_episodes": 6, "model.horizon": 5, "model.iterations": 2, "model.first_iterations": 3, "model.batch": 2}
    spec, whole, root, archive, runs = _control_study(tmp_path, "mpc", mpc)
    # killed in its second chunk of two test episodes
    _killed_in_call(monkeypatch, control_run, "play", 2, create_run(runs[0].config, runs[0].path, progress=False))
    rel = str(runs[0].path.relative_to(root))
    assert archive_study(spec, root, archive, runs, checkpoints=True).carried == [rel]
    carried = archive / INTERRUPTED / rel
    assert not (carried / CHECKPOINT).exists() and json.loads((carried / "control.json").read_text())["test"]["chunks"]
    assert json.loads((carried / "carried.json").read_text())["sha256"] is None
    logs: list[str] = []
    again = run_study(spec, tmp_path / "fresh", archive=archive, status=False, log=logs.append)
    assert "1 interrupted run(s) with their checkpoints, to resume where they stopped" in logs[0]
    assert again["runs"][0]["final_return"] == pytest.approx(whole["runs"][0]["final_return"], abs=1e-9)


@pytest.mark.slow  # two short DPC runs on Pendulum
def test_an_interrupted_dpc_run_is_carried_with_its_checkpoint_and_finishes_as_if_never_stopped(tmp_path, monkeypatch) -> None:
    from pimbrl.control.dpc import DPCTrainer

    dpc = {
        "eval_episodes": 2,
        "model.iterations": 6,
        "model.validate_every": 2,
        "model.horizon": 4,
        "model.batch_size": 4,
        "model.hidden": [8],
        "model.validation_episodes": 2,
    }
    spec, whole, root, archive, runs = _control_study(tmp_path, "dpc", dpc)
    # killed in its fifth gradient step: the checkpoint of step 4 is the last one saved
    _killed_in_call(monkeypatch, DPCTrainer, "step", 5, create_run(runs[0].config, runs[0].path, progress=False))
    rel = str(runs[0].path.relative_to(root))
    assert archive_study(spec, root, archive, runs, checkpoints=True).carried == [rel]
    manifest = json.loads((archive / INTERRUPTED / rel / "carried.json").read_text())
    assert manifest["step"] == 4 and manifest["sha256"] is not None and (archive / INTERRUPTED / rel / CHECKPOINT).is_file()
    fresh = tmp_path / "fresh"
    restored = restore_study(spec, fresh, archive, plan_study(spec, fresh))
    assert restored.carried == [rel]
    assert RunDirectory(fresh / rel).load_checkpoint()["dpc"]["steps"] == 4  # it goes on from step 4
    logs: list[str] = []
    again = run_study(spec, fresh, archive=archive, status=False, log=logs.append)
    assert any(line.startswith("start dpc seed 0: resume ") for line in logs), logs
    assert json.loads((tmp_path / "fresh" / rel / "control.json").read_text())["dpc"]["steps"] == 6
    assert again["runs"][0]["final_return"] == pytest.approx(whole["runs"][0]["final_return"], abs=1e-9)


@pytest.mark.slow  # one short Burgers run
def test_a_carried_copy_of_a_run_the_spec_no_longer_plans_is_removed_and_said(tmp_path) -> None:
    spec = _spec(tmp_path, total_steps=240)
    root, archive = tmp_path / "first", tmp_path / "archive"
    _stopped_at(spec, root, kill_at=70)
    runs = plan_study(spec, root)
    assert archive_study(spec, root, archive, runs, checkpoints=True).carried == [RUN]
    top = archive / INTERRUPTED
    stale = top / "mfrl" / "seed7"  # as a spec planning seed 7 once carried it
    shutil.copytree(top / RUN, stale)
    # what is no copy of an unplanned run: manifests on the way to the planned run, a killed carry's staging,
    # a linked folder, a copy nested deeper than the plan's runs
    manifest = (top / RUN / "carried.json").read_bytes()
    (top / "carried.json").write_bytes(manifest)
    (top / "mfrl" / "carried.json").write_bytes(manifest)
    shutil.copytree(top / RUN, top / "mfrl" / ".seed8.carrying")
    (top / "mfrl" / "seed9").symlink_to(top / RUN, target_is_directory=True)
    shutil.copytree(top / RUN, top / RUN / "deeper")
    assert archive_study(spec, root, archive, runs, checkpoints=True).dropped == []  # only with drop_unplanned
    assert stale.is_dir()
    result = archive_study(spec, root, archive, runs, checkpoints=True, drop_unplanned=True)
    assert result.dropped == ["mfrl/seed7"] and not stale.exists()
    assert "1 carried run(s) the spec no longer plans removed (mfrl/seed7)" in result.line("archived", archive)
    assert (top / RUN / CHECKPOINT).is_file() and (top / RUN / "deeper").is_dir()  # the planned run's copy stays
    assert (top / "mfrl" / "seed9").is_symlink() and (top / "mfrl" / "carried.json").is_file()
    # the command line removes them (its plan is the spec's whole plan)
    shutil.copytree(top / RUN, stale)
    assert (
        main(["study", "archive", str(tmp_path / "s.yaml"), "--run-dir", str(root), "--archive", str(archive), "--checkpoints"])
        == 0
    )
    assert not stale.exists() and (top / RUN / CHECKPOINT).is_file()


@pytest.mark.slow  # one short Burgers run
def test_a_run_resumed_after_its_last_evaluation_still_reports_its_inference_cost(tmp_path) -> None:
    spec = _spec(tmp_path, total_steps=120)
    root = tmp_path / "runs"
    runs = plan_study(spec, root)
    train(create_run(runs[0].config, runs[0].path, progress=False))
    cost = RunDirectory(runs[0].path).load_checkpoint()["inference_s_per_step"]
    assert isinstance(cost, float) and cost > 0
    again = open_run(runs[0].path, progress=False)  # a fresh process, as a resume after the last evaluation is
    assert again.inference_s_per_step == cost
