"""A study's finished runs kept in the repository, so that a study can outlive the machine it started on.

A run directory holds a checkpoint of megabytes; what a study's record and report read from a finished
run is a few kilobytes of JSON and CSV (:data:`ARCHIVED`). ``pimbrl study archive SPEC`` copies those
files of every finished run, and the study's registration (``study.json``), into the study's archive
(default: ``archive/<study name>`` beside the spec), laid out as the run directory is. Committed, the
archive survives the session; on a fresh machine ``pimbrl study run SPEC`` copies each archived run back
into its run directory before it starts, so that only the unfinished runs train again.

Nothing is trusted that the archive cannot show. A run is archived, and comes back, only where it is a
finished run with evaluations, of exactly the spec's configuration, and only into a directory that does
not exist yet (a run on this machine is never replaced). An archived run is never overwritten by other
files. The registration keeps the study's one first start: the archive's and the run directory's are
merged (every start and every spec SHA-256 either has seen), and where they record different first starts,
or where a run directory holds runs but no registration, nothing is copied either way. Every file is read
without following a link and within its size bound, no checkpoint is kept or read (but a carried one, below), and each run is
assembled beside its target and renamed into place, so an interrupted copy leaves no half-made run. A
restored finished run has no checkpoint: it can be reported, not resumed or evaluated again.

With ``--checkpoints``, an interrupted run is carried too, checkpoint included, and comes back to resume
where it stopped (:mod:`.carry`); archiving a run's finished copy removes its interrupted one, and the
carried copies of runs the spec no longer plans are removed (the line names them).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..config import ConfigError
from ..fileio import MAX_JSON_BYTES, atomic_write_bytes, check_below, read_below, strict_json
from .carry import (
    INTERRUPTED,
    carried_copy_why_not,
    carry_run,
    drop_carried,
    interrupted_why_not,
    load_carried,
    recover_carried,
    restore_carried,
    unplanned_carried,
)
from .registration import REGISTRATION_FILE
from .runfiles import ARCHIVED, STAGING, copy_run_files, open_run_files, same_files

if TYPE_CHECKING:
    from .engine import StudyRun
    from .spec import StudySpec

__all__ = [
    "ARCHIVED",
    "ArchiveResult",
    "archive_study",
    "copy_run_files",
    "default_archive",
    "plan_restore",
    "restore_study",
]


def default_archive(spec: StudySpec) -> Path:
    """``archive/<study name>`` in the spec's folder (``archive/<study name>`` here for a spec without a file)."""
    folder = spec.path.parent if spec.path is not None else Path()
    return folder / "archive" / spec.name


@dataclass
class ArchiveResult:
    """What :func:`archive_study` or :func:`restore_study` did, run by run (paths relative to the study)."""

    copied: list[str] = field(default_factory=list)  # runs copied now
    kept: list[str] = field(default_factory=list)  # runs already there, the same files
    passed: list[str] = field(default_factory=list)  # runs left out, each with the reason
    carried: list[str] = field(default_factory=list)  # interrupted runs copied (archive) or put back (restore) now
    dropped: list[str] = field(default_factory=list)  # carried copies of runs the spec no longer plans, removed now

    def line(self, verb: str, where: Path) -> str:
        """One line for the user: ``verb`` is ``"archived"`` or ``"restored"``, ``where`` the archive."""
        text = f"{verb} {len(self.copied)} finished run(s) {'to' if verb == 'archived' else 'from'} {where}"
        if self.kept:
            text += f"; {len(self.kept)} already there"
        if self.carried:
            text += f"; {len(self.carried)} interrupted run(s) with their checkpoints" + (
                ", to resume where they stopped" if verb == "restored" else ""
            )
        if self.dropped:
            text += (
                f"; {len(self.dropped)} carried run(s) the spec no longer plans removed ({self.dropped[0]}"
                + (", ..." if len(self.dropped) > 1 else "")
                + ")"
            )
        if self.passed:
            text += f"; {len(self.passed)} left out ({self.passed[0]}" + (", ..." if len(self.passed) > 1 else "") + ")"
        return text


# ------------------------------------------------------------------ registration
def _registration(folder: Path, spec: StudySpec) -> dict[str, Any] | None:
    """The registration ``folder`` holds (``None`` without one); another study's is a :class:`ConfigError`."""
    path = folder / REGISTRATION_FILE
    try:
        value = strict_json(read_below(folder, REGISTRATION_FILE, MAX_JSON_BYTES), path)
    except FileNotFoundError:
        return None
    except ValueError as exc:  # a link, a FIFO, damaged JSON
        raise ConfigError(
            f"{str(exc).splitlines()[0]}; restore {path} (git checkout, if it is committed) or leave the archive out "
            "(--no-archive)"
        ) from None
    if not isinstance(value, dict) or value.get("study") != spec.name:
        raise ConfigError(f"{path} is not the registration of study {spec.name}: give the study its own --run-dir and --archive")
    if not isinstance(value.get("first_run_started_unix"), (int, float)):
        raise ConfigError(
            f"{path} records no first start of study {spec.name}: it is not a registration `pimbrl study run` wrote; "
            "restore it (git checkout) or leave the archive out (--no-archive)"
        )
    return value


def _unregistered(archive: Path, runs: Sequence[StudyRun], root: Path) -> str | None:
    """A run ``archive`` holds though it has no registration (its start unknown), else ``None``."""
    if os.path.lexists(archive / REGISTRATION_FILE):
        return None
    for run in runs:
        for where in (archive, archive / INTERRUPTED):
            if os.path.lexists(where / run.path.relative_to(root)):
                return str(where / run.path.relative_to(root))
    return None


def _merged(a: dict[str, Any], b: dict[str, Any], a_where: Path, b_where: Path) -> dict[str, Any]:
    """One registration holding every start and spec SHA-256 of two of the same first start; else a ConfigError."""
    if a.get("first_run_started_unix") != b.get("first_run_started_unix") or a.get("registered") != b.get("registered"):
        raise ConfigError(
            f"{a_where} and {b_where} record different first starts of study {a.get('study')} (it was started again "
            "without its archive): nothing is copied; restore the archive into a new --run-dir, or archive into a new "
            "--archive"
        )
    starts: dict[str, Any] = {}
    for start in [*a.get("starts", []), *b.get("starts", [])]:
        starts.setdefault(json.dumps(start, sort_keys=True), start)
    seen = list(dict.fromkeys([*a.get("spec_sha256_seen", []), *b.get("spec_sha256_seen", [])]))
    ordered = sorted(starts.values(), key=lambda s: s.get("unix", 0) if isinstance(s, dict) else 0)
    return {**b, **a, "starts": ordered, "spec_sha256_seen": seen}


def _write_registration(folder: Path, value: dict[str, Any]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(folder / REGISTRATION_FILE, (json.dumps(value, indent=1) + "\n").encode())


# ------------------------------------------------------------------ reading a run
def _finished_run(directory: Path, run: StudyRun) -> str | None:
    """``None`` where ``directory`` holds a finished run of ``run``'s configuration with evaluations; else why not.

    A link or another special file there is an :class:`~pimbrl.fileio.UnsafeFileError` (never followed); a
    damaged ``config.json`` is a reason ("unreadable"), as is another configuration, checked first
    (:func:`~.runfiles.open_run_files`); then "not finished", then a damaged or missing evaluation.
    """
    opened = open_run_files(directory, run.config)
    if isinstance(opened, str):
        return opened
    rd, payload = opened
    if payload.get("status") != "finished" or rd.holder() is not None:
        return "not finished"
    try:
        result = rd.result()
    except ValueError as exc:
        return f"unreadable ({str(exc).splitlines()[0]})"
    return "no evaluation" if result is None else None


def _lock(archive: Path) -> int:
    """An exclusive lock of the archive folder (the OS's, on the folder itself: no lock file to commit)."""
    import fcntl

    archive.mkdir(parents=True, exist_ok=True)
    fd = os.open(archive, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise ConfigError(f"another pimbrl process is writing the archive {archive}; wait for it to end") from None
    return fd


def _remove_staging(archive: Path, runs: Sequence[StudyRun], root: Path) -> None:
    """The folders a killed copy left half-made beside the planned runs' places in the archive (nothing else)."""
    for run in runs:
        rel = run.path.relative_to(root)
        staging = archive / rel.parent / f".{rel.name}{STAGING}"
        if check_below(archive, staging.relative_to(archive), "directory") is not None:
            shutil.rmtree(staging)
        recover_carried(archive, str(rel))


# ------------------------------------------------------------------ archive and restore
def archive_study(
    spec: StudySpec,
    root: str | Path,
    archive: str | Path,
    runs: Sequence[StudyRun],
    checkpoints: bool = False,
    drop_unplanned: bool = False,
) -> ArchiveResult:
    """Copy every finished run of ``runs`` (``spec``'s, planned in ``root``), and its registration, into ``archive``.

    ``checkpoints``: also carry every interrupted run with its checkpoint (:func:`~.carry.carry_run`). A
    finished run archived (now or before) loses its interrupted copy. ``drop_unplanned`` (``runs`` is then
    the spec's whole plan): remove the carried copies of runs not in ``runs``, which the spec no longer plans
    (:func:`~.carry.unplanned_carried`).

    Safe while the study runs: a run counts only when finished and held by no process. Everything is checked
    before anything is copied: the run directory's registration (it must be there, of this study, and of the
    archive's first start), and every run already in the archive (the same files, else a
    :class:`ConfigError`: an archived run is never overwritten; remove it from the archive first if the new run
    replaces it). The two registrations are then merged into the archive.
    """
    root, archive = Path(root), Path(archive)
    if not root.is_dir():
        raise ConfigError(f"study {spec.name}: no run directory {root} (give --run-dir, or run the study first)")
    here = _registration(root, spec)
    if here is None and not any(os.path.lexists(r.path) for r in runs):  # e.g. a queued study the queue has not reached
        raise ConfigError(f"study {spec.name}: not started in {root} yet (no registration, no run): nothing to archive")
    if here is None:
        raise ConfigError(
            f"{root} holds no registration of study {spec.name} (no {REGISTRATION_FILE}): only runs made by `pimbrl study "
            "run` are archived; run the study there with `pimbrl study run`, or give its own --run-dir"
        )

    def check() -> dict[str, Any]:  # the registration to write, or a ConfigError before anything is written
        stray = _unregistered(archive, runs, root)
        if stray is not None:
            raise ConfigError(
                f"{stray} is archived but {archive} holds no registration (its start is unknown): restore "
                f"{archive / REGISTRATION_FILE} (git checkout), or archive into a new --archive"
            )
        kept = _registration(archive, spec) if archive.is_dir() else None
        return here if kept is None else _merged(kept, here, archive / REGISTRATION_FILE, root / REGISTRATION_FILE)

    check()  # before the archive folder is made
    fd = _lock(archive)
    try:
        registration = check()  # again under the lock
        _remove_staging(archive, runs, root)
        result = ArchiveResult()
        todo, interrupted = [], []
        for run in runs:
            rel = str(run.path.relative_to(root))
            if not run.path.is_dir():
                continue
            if _finished_run(run.path, run) is not None:
                if checkpoints and interrupted_why_not(run.path, run) is None:
                    interrupted.append((run, rel))
                continue
            target = archive / rel
            check_below(archive, rel, "directory")  # no link on the way into the archive
            if not target.exists():
                todo.append((run, rel))
            elif same_files(run.path, target):
                result.kept.append(rel)
            else:
                raise ConfigError(
                    f"{target} holds other files than the finished run {run.path}; an archived run is never overwritten "
                    "and nothing was copied (remove it from the archive first if the new run replaces it)"
                )
        _write_registration(archive, registration)  # first: it covers every run copied after it
        for run, rel in todo:
            copy_run_files(run.path, archive / rel)
            result.copied.append(rel)
        for rel in [*result.copied, *result.kept]:  # finished: an interrupted copy is out of date
            drop_carried(archive, rel)
        for run, rel in interrupted:
            if _finished_run(archive / rel, run) is None:  # the archive holds it finished: nothing to carry
                drop_carried(archive, rel)
                continue
            try:
                done = carry_run(run.path, archive, rel, run)
            except (OSError, ValueError) as exc:  # one damaged run is named; the finished runs are archived all the same
                result.passed.append(f"{rel}: not carried ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})")
                continue
            if done == "copied":
                result.carried.append(rel)
            elif done != "kept":
                result.passed.append(f"{rel}: its checkpoint is {done}")
        if drop_unplanned:  # copies of runs the spec no longer plans: nothing would ever restore them
            planned = {r.path.relative_to(root).as_posix() for r in runs}
            for rel in unplanned_carried(archive, planned):
                drop_carried(archive, rel)
                result.dropped.append(rel)
    finally:
        os.close(fd)
    return result


@dataclass
class RestorePlan:
    """What :func:`restore_study` would do: the runs to copy back, those left out, and the registration to write."""

    runs: list[StudyRun] = field(default_factory=list)
    carried: list[StudyRun] = field(default_factory=list)  # interrupted runs to put back with their checkpoints
    passed: list[str] = field(default_factory=list)
    registration: dict[str, Any] | None = None  # to write into the run directory (``None``: leave it)
    refusal: str | None = None  # why nothing can be restored into this run directory


def plan_restore(spec: StudySpec, root: str | Path, archive: str | Path, runs: Sequence[StudyRun]) -> RestorePlan:
    """Which archived runs of ``runs`` would come back into ``root`` (nothing is written).

    A run that exists in ``root`` is not looked at. An archived run comes back where it is finished, has
    evaluations and is of the run's configuration; otherwise it is left out with the reason (and trains). A
    refusal (with nothing restored) where ``root`` holds another first start of the study, or runs but no
    registration (the archive's registration would then cover runs it never saw).
    """
    root, archive = Path(root), Path(archive)
    plan = RestorePlan()
    if not archive.is_dir():
        return plan
    kept = _registration(archive, spec)
    stray = _unregistered(archive, runs, root)
    if stray is not None:
        plan.refusal = (
            f"{stray} is archived but {archive} holds no registration (its start is unknown): restore "
            f"{archive / REGISTRATION_FILE} (git checkout), or leave the archive out (--no-archive)"
        )
        return plan
    for run in runs:
        if os.path.lexists(run.path):
            continue
        rel = str(run.path.relative_to(root))
        why = _finished_run(archive / rel, run) if check_below(archive, rel, "directory") is not None else "no config.json"
        if why is None:
            plan.runs.append(run)
            continue
        if why != "no config.json":
            plan.passed.append(f"{rel}: {why} there")
        carried = carried_copy_why_not(archive, rel, run)
        if carried is None:
            plan.carried.append(run)
        elif carried != "none":
            plan.passed.append(f"{INTERRUPTED}/{rel}: {carried} there")
    if kept is None:
        return plan
    here = _registration(root, spec) if root.is_dir() else None
    if here is None:
        made = [str(r.path) for r in runs if os.path.lexists(r.path / "config.json")]
        if made:
            plan.refusal = (
                f"{made[0]} holds a run but its run directory holds no registration of study {spec.name}: the archive's "
                "registration would cover runs it never saw; give a new --run-dir (the archive's runs come back into "
                "it), or --no-archive"
            )
        else:
            plan.registration = kept
        return plan
    try:
        merged = _merged(here, kept, root / REGISTRATION_FILE, archive / REGISTRATION_FILE)
    except ConfigError as exc:
        plan.refusal = str(exc)
        return plan
    plan.registration = merged if merged != here else None
    return plan


def restore_study(
    spec: StudySpec, root: str | Path, archive: str | Path, runs: Sequence[StudyRun], plan: RestorePlan | None = None
) -> ArchiveResult:
    """Copy each archived finished run of ``runs`` whose directory in ``root`` does not exist back into ``root``.

    The archive's registration comes first (merged with one ``root`` holds), so a confirmatory study keeps its
    archived first start. :func:`plan_restore` decides (``plan``: its answer, where nothing in ``root`` has
    changed since it was made); its refusal is a :class:`ConfigError`.
    """
    root, archive = Path(root), Path(archive)
    if plan is None:
        plan = plan_restore(spec, root, archive, runs)
    if plan.refusal is not None:
        raise ConfigError(plan.refusal)
    result = ArchiveResult(passed=list(plan.passed))
    # every carried checkpoint decompressed and verified first: a damaged one is an error before anything is written
    checkpoints = [load_carried(archive, str(run.path.relative_to(root))) for run in plan.carried]
    if plan.registration is not None:
        _write_registration(root, plan.registration)
    for run in plan.runs:
        copy_run_files(archive / run.path.relative_to(root), run.path)
        result.copied.append(str(run.path.relative_to(root)))
    for run, checkpoint in zip(plan.carried, checkpoints, strict=True):
        run.path.parent.mkdir(parents=True, exist_ok=True)
        restore_carried(archive, str(run.path.relative_to(root)), run.path, checkpoint)
        result.carried.append(str(run.path.relative_to(root)))
    return result
