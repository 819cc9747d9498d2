"""A study's archive: finished runs kept in the repository come back on a fresh machine, and only they."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.experiments.archive import ARCHIVED, archive_study, default_archive, plan_restore, restore_study
from pimbrl.experiments.engine import plan_study, run_study
from pimbrl.experiments.spec import load_spec
from pimbrl.fileio import UnsafeFileError

from .test_studies import TINY_MFRL, _git


def _spec(folder: Path, name: str = "s.yaml", **data) -> Path:
    body = {"name": "arch", "systems": ["pendulum"], "methods": ["mfrl"], "seeds": 2, "overrides": TINY_MFRL, **data}
    path = folder / name
    path.write_text(json.dumps(body))
    return path


def _finals(record: dict) -> dict[int, float]:
    return {r["seed"]: r["final_return"] for r in record["runs"]}


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, dict]:
    """A finished two-seed study (its spec's folder; the record of its first run), made once for this module."""
    folder = tmp_path_factory.mktemp("trained")
    spec = load_spec(_spec(folder))
    record = run_study(spec, folder / "runs", status=False, log=lambda m: None)
    assert len(record["runs"]) == 2 and all(r["finished"] for r in record["runs"])
    return folder, record


@pytest.fixture
def study(trained, tmp_path) -> tuple:
    """A copy of the trained study in this test's folder: (spec, spec path, run directory, first record)."""
    folder, record = trained
    shutil.copytree(folder, tmp_path, dirs_exist_ok=True)
    path = tmp_path / "s.yaml"
    return load_spec(path), path, tmp_path / "runs", record


def test_the_default_archive_lies_beside_the_spec(tmp_path) -> None:
    spec = load_spec(_spec(tmp_path))
    assert default_archive(spec) == tmp_path / "archive" / "arch"


@pytest.mark.slow
def test_archived_runs_come_back_on_a_fresh_machine_and_nothing_trains(study, tmp_path) -> None:
    spec, _, root, first = study
    archive = tmp_path / "kept"
    runs = plan_study(spec, root)
    result = archive_study(spec, root, archive, runs)
    assert sorted(result.copied) == ["mfrl/seed0", "mfrl/seed1"] and not result.kept
    held = {p.name for p in (archive / "mfrl" / "seed0").iterdir()}
    assert "config.json" in held and "evaluations.csv" in held and held <= set(ARCHIVED)  # no checkpoint, lock or log
    assert json.loads((archive / "study.json").read_text()) == json.loads((root / "study.json").read_text())
    assert archive_study(spec, root, archive, runs).kept == result.copied  # a second archive copies nothing

    fresh = tmp_path / "fresh"
    assert [r.seed for r in plan_restore(spec, fresh, archive, plan_study(spec, fresh)).runs] == [0, 1]
    logs: list[str] = []
    again = run_study(spec, fresh, archive=archive, status=False, log=logs.append)
    assert logs[0].startswith("restored 2 finished run(s) from") and "2 finished, 0 to run" in logs[1]
    assert _finals(again) == _finals(first) and all(r["finished"] for r in again["runs"]) and not again["missing"]
    assert not (fresh / "mfrl" / "seed0" / "checkpoints").exists()
    registration = json.loads((fresh / "study.json").read_text())
    original = json.loads((root / "study.json").read_text())
    assert registration["first_run_started_unix"] == original["first_run_started_unix"]  # the archived start
    assert registration["starts"] == original["starts"]  # a start that trains nothing (all restored) adds none
    logs.clear()
    run_study(spec, fresh, archive=archive, status=False, log=logs.append)  # nothing to restore: no restore line
    assert "2 finished, 0 to run" in logs[0]


@pytest.mark.slow
def test_only_finished_runs_of_the_spec_s_settings_come_back_and_the_rest_train(study, tmp_path) -> None:
    spec, _, root, first = study
    archive = tmp_path / "kept"
    archive_study(spec, root, archive, plan_study(spec, root))
    config = json.loads((archive / "mfrl" / "seed0" / "config.json").read_text())
    config["config"]["total_steps"] = 40
    (archive / "mfrl" / "seed0" / "config.json").write_text(json.dumps(config))
    (archive / "mfrl" / "seed1" / "evaluations.csv").unlink()  # finished, says its config; no evaluation
    logs: list[str] = []
    third = run_study(spec, tmp_path / "third", archive=archive, status=False, log=logs.append)
    assert logs[0].startswith("restored 0 finished run(s)") and "2 left out (mfrl/seed0: another configuration there" in logs[0]
    assert "0 finished, 2 to run" in logs[1] and _finals(third) == _finals(first)
    plan = plan_restore(spec, tmp_path / "fourth", archive, plan_study(spec, tmp_path / "fourth"))
    assert plan.passed == ["mfrl/seed0: another configuration there", "mfrl/seed1: no evaluation there"]


@pytest.mark.slow
def test_nothing_is_archived_when_anything_conflicts(study, tmp_path) -> None:
    spec, _, root, _ = study
    archive = tmp_path / "kept"
    runs = plan_study(spec, root)
    archive_study(spec, root, archive, runs)
    shutil.rmtree(archive / "mfrl" / "seed0")
    (archive / "mfrl" / "seed1" / "episodes.csv").write_text("step,episode,return,length\n")  # other files
    before = _files(archive)
    with pytest.raises(ConfigError, match="never overwritten and nothing was copied"):
        archive_study(spec, root, archive, runs)
    assert _files(archive) == before  # seed0, listed first, was not copied either

    # the same study started again elsewhere without its archive: a different first start, nothing archived
    shutil.copytree(archive, tmp_path / "clean")
    shutil.rmtree(tmp_path / "clean" / "mfrl" / "seed1")
    other = tmp_path / "other"
    shutil.copytree(root, other)
    registration = json.loads((other / "study.json").read_text())
    registration["first_run_started_unix"] += 100
    (other / "study.json").write_text(json.dumps(registration))
    with pytest.raises(ConfigError, match="different first starts"):
        archive_study(spec, other, tmp_path / "clean", plan_study(spec, other))
    assert _files(tmp_path / "clean") == ["study.json"]
    (other / "study.json").unlink()
    with pytest.raises(ConfigError, match="holds no registration"):
        archive_study(spec, other, tmp_path / "clean", plan_study(spec, other))


@pytest.mark.slow
def test_the_registration_keeps_every_start_and_spec_either_side_has_seen(study, tmp_path) -> None:
    spec, _, root, _ = study
    archive = tmp_path / "kept"
    runs = plan_study(spec, root)
    archive_study(spec, root, archive, runs)
    later = tmp_path / "later"
    restore_study(spec, later, archive, plan_study(spec, later))
    registration = json.loads((later / "study.json").read_text())
    registration["starts"].append({"unix": registration["starts"][-1]["unix"] + 5, "spec_sha256": "f" * 64})
    registration["spec_sha256_seen"].append("f" * 64)  # an edited spec ran here
    (later / "study.json").write_text(json.dumps(registration))
    archive_study(spec, later, archive, plan_study(spec, later))
    archive_study(spec, root, archive, runs)  # the first machine archives again: the edit is not forgotten
    kept = json.loads((archive / "study.json").read_text())
    assert "f" * 64 in kept["spec_sha256_seen"] and len(kept["starts"]) == len(registration["starts"])
    restore_study(spec, root, archive, runs)  # and a restore brings the edit into a run directory without it
    assert "f" * 64 in json.loads((root / "study.json").read_text())["spec_sha256_seen"]


@pytest.mark.slow
def test_a_restore_never_adopts_runs_made_outside_the_registration_nor_touches_a_run_that_exists(study, tmp_path) -> None:
    spec, _, root, _ = study
    archive = tmp_path / "kept"
    archive_study(spec, root, archive, plan_study(spec, root))
    # a run directory holding seed1 but no registration: the archive's registration would cover it
    stray = tmp_path / "stray"
    shutil.copytree(root / "mfrl" / "seed1", stray / "mfrl" / "seed1")
    with pytest.raises(ConfigError, match="holds a run but its run directory holds no registration"):
        restore_study(spec, stray, archive, plan_study(spec, stray))
    assert not (stray / "mfrl" / "seed0").exists() and not (stray / "study.json").exists()
    # a damaged archived entry of a run that exists here is not even read
    (archive / "mfrl" / "seed1" / "config.json").write_text("{not json")
    partial = tmp_path / "partial"
    shutil.copytree(root, partial)
    shutil.rmtree(partial / "mfrl" / "seed0")
    result = restore_study(spec, partial, archive, plan_study(spec, partial))
    assert result.copied == ["mfrl/seed0"] and not result.passed
    # where it would be restored, it is left out as unreadable (and trains)
    plan = plan_restore(spec, tmp_path / "new", archive, plan_study(spec, tmp_path / "new"))
    assert [r.seed for r in plan.runs] == [0] and plan.passed[0].startswith("mfrl/seed1: unreadable")


def test_a_restore_refuses_links_another_study_s_archive_and_another_start(tmp_path) -> None:
    spec = load_spec(_spec(tmp_path))
    root, archive = tmp_path / "runs", tmp_path / "kept"
    runs = plan_study(spec, root)
    seed0 = archive / "mfrl" / "seed0"
    seed0.mkdir(parents=True)
    (archive / "study.json").write_text(json.dumps({"study": "arch", "first_run_started_unix": 1.0}))
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
    root.mkdir()
    (root / "study.json").write_text(json.dumps({"study": "arch", "first_run_started_unix": 2.0}))
    with pytest.raises(ConfigError, match="different first starts"):
        restore_study(spec, root, archive, runs)
    with pytest.raises(ConfigError, match="different first starts"):
        archive_study(spec, root, archive, runs)


@pytest.mark.slow
def test_the_command_line_archives_restores_and_refuses_what_it_cannot_use(study, tmp_path, capsys, monkeypatch) -> None:
    _, path, root, _ = study
    monkeypatch.chdir(tmp_path)
    assert main(["study", "archive", str(path), "--run-dir", str(root)]) == 0
    out = capsys.readouterr().out
    assert "archived 2 finished run(s) to archive/arch" in out and "git add archive/arch" in out  # beside the spec
    assert main(["study", "status", str(path), "--run-dir", "fresh"]) == 0
    assert "2 finished run(s) wait in the archive archive/arch" in capsys.readouterr().out
    assert main(["study", "run", str(path), "--run-dir", "fresh"]) == 0
    out = capsys.readouterr().out
    assert "restored 2 finished run(s) from archive/arch" in out and "2 finished, 0 to run" in out
    assert main(["study", "run", str(path), "--run-dir", "typo", "--archive", "nowhere"]) == 2
    assert "no archive nowhere: check --archive" in capsys.readouterr().err
    assert not (tmp_path / "typo").exists()
    assert main(["study", "archive", str(path), "--run-dir", str(root), "--no-archive"]) == 2
    assert "drop --no-archive" in capsys.readouterr().err
    assert main(["study", "plan", str(path), "--archive", "archive/arch"]) == 2
    assert "apply to study run, status and archive, not plan" in capsys.readouterr().err
    assert main(["study", "archive", str(path), "--run-dir", str(root), "--archive", str(root / "inside")]) == 2
    assert "lie one inside the other" in capsys.readouterr().err
    assert main(["study", "status", str(path), "--run-dir", "fresh", "--no-archive"]) == 0
    assert "archive" not in capsys.readouterr().out


def test_the_reproduce_page_trains_an_archived_study_again(tmp_path) -> None:
    from pimbrl.experiments.report import _run_command

    spec = load_spec(_spec(tmp_path))
    assert not _run_command(spec, tmp_path).endswith("--no-archive")
    default_archive(spec).mkdir(parents=True)
    assert _run_command(spec, tmp_path) == "pimbrl study run s.yaml --run-dir runs/arch --no-archive"


@pytest.mark.slow
def test_an_archive_with_runs_but_no_registration_is_neither_restored_nor_added_to(study, tmp_path, monkeypatch) -> None:
    from pimbrl.experiments import archive as archive_module

    spec, _, root, _ = study
    archive = tmp_path / "kept"
    runs = plan_study(spec, root)
    calls = []

    def dying_copy(source, target, *args):  # the process dies while it copies the second run
        calls.append(target)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return copy(source, target, *args)

    copy = archive_module.copy_run_files
    monkeypatch.setattr(archive_module, "copy_run_files", dying_copy)
    with pytest.raises(KeyboardInterrupt):
        archive_study(spec, root, archive, runs)
    monkeypatch.undo()
    assert (archive / "study.json").is_file() and _files(archive / "mfrl") == sorted(
        f"seed0/{p.name}" for p in (archive / "mfrl" / "seed0").iterdir()
    )  # the registration came first; the second run is not half there
    (archive / "study.json").unlink()  # an archive whose start is unknown
    fresh = tmp_path / "fresh"
    with pytest.raises(ConfigError, match="holds no registration \\(its start is unknown\\)"):
        run_study(spec, fresh, archive=archive, status=False, log=lambda m: None)
    assert not (fresh / "mfrl").exists()
    with pytest.raises(ConfigError, match="holds no registration \\(its start is unknown\\)"):
        archive_study(spec, root, archive, runs)


@pytest.mark.slow
def test_rerun_moves_nothing_when_the_archive_is_refused_and_gets_archived_copies_back(study, tmp_path) -> None:
    spec, _, root, _ = study
    archive = tmp_path / "kept"
    archive_study(spec, root, archive, plan_study(spec, root))
    stale = tmp_path / "stale"
    shutil.copytree(root, stale)
    config = json.loads((stale / "mfrl" / "seed0" / "config.json").read_text())
    config["config"]["total_steps"] = 40  # a run of other settings, which --rerun moves aside
    (stale / "mfrl" / "seed0" / "config.json").write_text(json.dumps(config))
    registration = json.loads((stale / "study.json").read_text())
    (stale / "study.json").write_text(json.dumps({**registration, "first_run_started_unix": 1.0}))
    with pytest.raises(ConfigError, match="different first starts"):
        run_study(spec, stale, archive=archive, rerun=True, status=False, log=lambda m: None)
    assert sorted(p.name for p in (stale / "mfrl").iterdir()) == ["seed0", "seed1"]  # nothing moved aside
    (stale / "study.json").write_text(json.dumps(registration))
    logs: list[str] = []
    run_study(spec, stale, archive=archive, rerun=True, status=False, log=logs.append)
    assert any(line.startswith("restored 1 finished run(s)") for line in logs) and "2 finished, 0 to run" in logs[-2]


def test_archiving_into_another_study_s_folder_removes_nothing_there(tmp_path) -> None:
    spec = load_spec(_spec(tmp_path))
    root, elsewhere = tmp_path / "runs", tmp_path / "elsewhere"
    root.mkdir()
    (root / "study.json").write_text(json.dumps({"study": "arch", "first_run_started_unix": 1.0}))
    (elsewhere / "mfrl" / ".seed0.copying").mkdir(parents=True)
    (elsewhere / "study.json").write_text(json.dumps({"study": "another", "first_run_started_unix": 1.0}))
    with pytest.raises(ConfigError, match="not the registration of study arch"):
        archive_study(spec, root, elsewhere, plan_study(spec, root))
    assert (elsewhere / "mfrl" / ".seed0.copying").is_dir()
    (root / "study.json").write_text(json.dumps({"study": "arch"}))
    with pytest.raises(ConfigError, match="records no first start"):
        archive_study(spec, root, tmp_path / "new", plan_study(spec, root))
    assert not (tmp_path / "new").exists()  # a refused first archive leaves no folder


@pytest.mark.slow
def test_keep_archive_copies_each_run_as_it_finishes(tmp_path, capsys, monkeypatch) -> None:
    path = _spec(tmp_path, seeds=[0])
    spec = load_spec(path)
    logs: list[str] = []
    record = run_study(spec, tmp_path / "runs", archive=tmp_path / "kept", keep_archive=True, status=False, log=logs.append)
    done = logs.index("done mfrl seed 0")
    assert logs[done + 1].startswith("archived 1 finished run(s) to")  # at once, not only at the end
    assert (tmp_path / "kept" / "study.json").is_file()
    assert _finals(record) == {0: json_final(tmp_path / "kept" / "mfrl" / "seed0")}
    monkeypatch.chdir(tmp_path)
    assert main(["study", "status", str(path), "--keep-archive"]) == 2
    assert "--keep-archive applies to study run, not status" in capsys.readouterr().err
    assert main(["study", "run", str(path), "--run-dir", "runs", "--keep-archive", "--archive", "runs/inside"]) == 2
    assert "lie one inside the other" in capsys.readouterr().err


def json_final(run: Path) -> float:
    """The last evaluation's mean return in an archived run's evaluations.csv."""
    lines = (run / "evaluations.csv").read_text().strip().splitlines()
    header = lines[0].split(",")
    return float(lines[-1].split(",")[header.index("return_mean")])


def test_status_of_a_study_whose_runs_are_gone_but_whose_record_is_kept_says_so(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    path = _spec(tmp_path, record={"path": "kept.json", "format": "study"})
    assert main(["study", "status", str(path)]) == 0
    assert "no run directory runs/arch yet (start it" in capsys.readouterr().out
    (tmp_path / "kept.json").write_text("{}")
    assert main(["study", "status", str(path)]) == 0
    assert "no run directory runs/arch here; its record kept.json is kept" in capsys.readouterr().out


@pytest.mark.slow
def test_a_confirmatory_study_restored_from_its_archive_starts_with_its_registration(tmp_path) -> None:
    """A fresh run directory of a confirmatory study gets its registration back from the archive; the start is
    checked against that, not as a first start (whose check of the registering commit would refuse here)."""
    import time

    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    path = _spec(repo, kind="confirmatory", seeds=1)
    _git(repo, "add", "s.yaml")
    _git(repo, "commit", "-q", "-m", "register")
    time.sleep(1.1)  # commit times are whole seconds: the first start comes after the commit
    first = run_study(
        load_spec(path), repo / "runs", archive=repo / "archive", keep_archive=True, status=False, log=lambda m: None
    )
    assert first["registration"]["registered"] and (repo / "archive" / "study.json").exists()
    shutil.rmtree(repo / ".git")  # the registering commit is no longer at hand
    with pytest.raises(ConfigError, match="is not registered"):  # a first start is refused now: the check is alive
        run_study(load_spec(path), repo / "elsewhere", status=False, log=lambda m: None)
    lines: list[str] = []
    again = run_study(load_spec(path), repo / "fresh", archive=repo / "archive", status=False, log=lines.append)
    assert any(line.startswith("restored 1 finished run(s)") for line in lines)
    assert again["registration"]["registered"] == first["registration"]["registered"] and _finals(again) == _finals(first)


def test_archiving_a_study_not_started_yet_says_so_and_one_without_registration_is_refused(tmp_path) -> None:
    spec = load_spec(_spec(tmp_path))
    root = tmp_path / "runs"
    root.mkdir()
    (root / "compare.lock").write_text("")  # a queued study's directory: locked by the queue, nothing in it yet
    with pytest.raises(
        ConfigError, match=r"study arch: not started in .*runs yet \(no registration, no run\): nothing to archive"
    ):
        archive_study(spec, root, tmp_path / "archive", plan_study(spec, root))
    (root / "mfrl" / "seed0").mkdir(parents=True)  # a run made some other way: refused as before
    with pytest.raises(ConfigError, match=r"holds no registration of study arch .*only runs made by `pimbrl study run`"):
        archive_study(spec, root, tmp_path / "archive", plan_study(spec, root))
    assert not (tmp_path / "archive").exists()
