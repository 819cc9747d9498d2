"""A study's finished runs kept in the repository, so that a study can outlive the machine it started on.

A run directory holds a checkpoint of megabytes; what a study's record and report read from a finished
run is a few kilobytes of JSON and CSV (:data:`ARCHIVED`). ``pimbrl study archive SPEC`` copies those
files of every finished run, and the study's registration (``study.json``), into the study's archive
(default: ``archive/<study name>`` beside the spec), laid out as the run directory is. Committed, the
archive survives the session; on a fresh machine ``pimbrl study run SPEC`` copies each archived run back
into its run directory before it looks at what is missing, so only the unfinished runs train again.

Nothing is trusted that the archive cannot show: a run comes back only where the archive holds a
finished run of exactly the spec's configuration, and only into a directory that does not exist yet (a
run on this machine is never replaced). Every file is read without following a link and within its size
bound, JSON is parsed strictly, no checkpoint is kept or read, and each run is assembled beside its target
and renamed into place, so an interrupted copy leaves no half-made run. A restored run has no
checkpoint: it can be reported, not resumed or evaluated again.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..config import ConfigError
from ..fileio import MAX_CSV_BYTES, MAX_JSON_BYTES, atomic_write_bytes, check_below, fsync_directory, read_below, strict_json
from ..training.rundir import RunDirectory
from .registration import REGISTRATION_FILE
from .runner import config_differences

if TYPE_CHECKING:
    from .engine import StudyRun
    from .spec import StudySpec

__all__ = ["ARCHIVED", "ArchiveResult", "archive_study", "archived_runs", "copy_run_files", "default_archive", "restore_study"]

#: a finished run's files that the archive keeps (the record and report read no others); no checkpoint
ARCHIVED = (
    "config.json",
    "config.request.json",
    "evaluations.csv",
    "episodes.csv",
    "metrics.csv",
    "selection.csv",
    "coefficients.json",
    "control.json",
    "holdout.json",
)


def _bound(name: str) -> int:
    return MAX_JSON_BYTES if name.endswith(".json") else MAX_CSV_BYTES


def default_archive(spec: StudySpec) -> Path:
    """``archive/<study name>`` in the spec's folder (``archive/<study name>`` here for a spec without a file)."""
    folder = spec.path.parent if spec.path is not None else Path()
    return folder / "archive" / spec.name


def copy_run_files(
    source: Path,
    target: Path,
    names: Sequence[str] = ARCHIVED,
    edit: Callable[[str, bytes], bytes] | None = None,
) -> list[str]:
    """Copy the regular files ``names`` of the run directory ``source`` to the new directory ``target``.

    ``config.json`` must be there; the others are copied where they exist. ``edit(name, data)`` may change
    a file's bytes on the way. Each file is read without following a link and within its size bound; the
    copy is assembled in a hidden folder beside ``target`` and renamed into place (a crash leaves no
    half-made run). Raises ``FileExistsError`` where ``target`` exists, ``FileNotFoundError`` without a
    ``config.json``, :class:`~pimbrl.fileio.UnsafeFileError` for a link or an oversized file. Returns the
    names copied.
    """
    if os.path.lexists(target):
        raise FileExistsError(f"{target} exists")
    parent = target.parent
    parent.mkdir(parents=True, exist_ok=True)
    staging = parent / f".{target.name}.copying"
    if os.path.lexists(staging):
        shutil.rmtree(staging)
    staging.mkdir()
    copied = []
    try:
        for name in names:
            try:
                data = read_below(source, name, _bound(name))
            except FileNotFoundError:
                if name == "config.json":
                    raise
                continue
            atomic_write_bytes(staging / name, edit(name, data) if edit is not None else data)
            copied.append(name)
        os.replace(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    fsync_directory(parent)
    return copied


@dataclass
class ArchiveResult:
    """What :func:`archive_study` or :func:`restore_study` did, run by run (paths relative to the study)."""

    copied: list[str] = field(default_factory=list)  # runs copied now
    kept: list[str] = field(default_factory=list)  # runs already there, the same files
    passed: list[str] = field(default_factory=list)  # runs left out, each with the reason

    def line(self, verb: str, where: Path) -> str:
        """One line for the user: ``verb`` is ``"archived"`` or ``"restored"``, ``where`` the archive."""
        text = f"{verb} {len(self.copied)} finished run(s) {'to' if verb == 'archived' else 'from'} {where}"
        if self.kept:
            text += f"; {len(self.kept)} already there"
        if self.passed:
            text += f"; {len(self.passed)} left out ({self.passed[0]}" + (", ..." if len(self.passed) > 1 else "") + ")"
        return text


def _read_config(directory: Path) -> dict[str, Any] | None:
    """A run directory's ``config.json`` as a mapping, ``None`` where it has none."""
    try:
        payload = strict_json(read_below(directory, "config.json", MAX_JSON_BYTES), directory / "config.json")
    except FileNotFoundError:
        return None
    if not isinstance(payload, dict) or not isinstance(payload.get("config"), dict):
        raise ValueError(f"{directory / 'config.json'} is not a run's configuration")
    return payload


def _same_files(a: Path, b: Path) -> bool:
    """Whether two run directories hold the same :data:`ARCHIVED` files, byte for byte."""
    for name in ARCHIVED:
        try:
            left = read_below(a, name, _bound(name))
        except FileNotFoundError:
            left = None
        try:
            right = read_below(b, name, _bound(name))
        except FileNotFoundError:
            right = None
        if left != right:
            return False
    return True


def archive_study(spec: StudySpec, root: str | Path, archive: str | Path, runs: Sequence[StudyRun]) -> ArchiveResult:
    """Copy every finished run of ``runs`` (``spec``'s, planned in ``root``), and its registration, into ``archive``.

    Safe while the study runs: a run counts only when finished and held by no process. A run already in
    the archive with the same files is kept; one with other files is a :class:`ConfigError` (an archived run
    is never overwritten: remove it from the archive first, if the new one is meant to replace it).
    """
    root, archive = Path(root), Path(archive)
    if not root.is_dir():
        raise ConfigError(f"study {spec.name}: no run directory {root} (give --run-dir, or run the study first)")
    result = ArchiveResult()
    for run in runs:
        rel = str(run.path.relative_to(root))
        rd = RunDirectory(run.path)
        if rd.status != "finished" or rd.holder() is not None:
            continue
        payload = _read_config(run.path)
        diffs = config_differences(payload.get("config") if payload else None, run.config)
        if diffs:
            result.passed.append(f"{rel}: another configuration")
            continue
        target = archive / rel
        check_below(archive, rel, "directory")  # no link on the way into the archive
        if target.exists():
            if not _same_files(run.path, target):
                raise ConfigError(
                    f"{target} holds other files than the finished run {run.path}; an archived run is never overwritten "
                    "(remove it from the archive first if the new run replaces it)"
                )
            result.kept.append(rel)
            continue
        copy_run_files(run.path, target)
        result.copied.append(rel)
    if (root / REGISTRATION_FILE).exists():
        data = read_below(root, REGISTRATION_FILE, MAX_JSON_BYTES)
        here = strict_json(data, root / REGISTRATION_FILE)
        kept = _registration(archive, spec)
        first = here.get("first_run_started_unix") if isinstance(here, dict) else None
        if kept is not None and kept.get("first_run_started_unix") != first:
            raise ConfigError(
                f"{archive / REGISTRATION_FILE} records another first start of study {spec.name} than {root / REGISTRATION_FILE} "
                "(the study was started here without its archive); archive into a new --archive, or restore the archive "
                "into a new --run-dir"
            )
        archive.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(archive / REGISTRATION_FILE, data)
    return result


def _registration(archive: Path, spec: StudySpec) -> dict[str, Any] | None:
    """The registration the archive holds (``None`` without one); another study's is a :class:`ConfigError`."""
    try:
        value = strict_json(read_below(archive, REGISTRATION_FILE, MAX_JSON_BYTES), archive / REGISTRATION_FILE)
    except FileNotFoundError:
        return None
    if not isinstance(value, dict) or value.get("study") != spec.name:
        raise ConfigError(f"{archive / REGISTRATION_FILE} is not the registration of study {spec.name}; check --archive")
    return value


def archived_runs(root: str | Path, archive: str | Path, runs: Sequence[StudyRun]) -> list[str]:
    """The runs of ``runs`` (planned in ``root``) that ``archive`` holds finished, of their configuration (paths below it)."""
    root, archive = Path(root), Path(archive)
    if not archive.is_dir():
        return []
    out = []
    for run in runs:
        rel = str(run.path.relative_to(root))
        try:
            check_below(archive, rel, "directory")
            payload = _read_config(archive / rel)
        except (OSError, ValueError):
            continue
        if payload is not None and payload.get("status") == "finished" and not config_differences(payload["config"], run.config):
            out.append(rel)
    return out


def restore_study(spec: StudySpec, root: str | Path, archive: str | Path, runs: Sequence[StudyRun]) -> ArchiveResult:
    """Copy each archived finished run of ``spec`` whose directory in ``root`` does not exist back into ``root``.

    The archive's registration comes first, where ``root`` has none (a confirmatory study's start is then
    the archived one, not a new registration). A run the archive holds with another configuration, or not
    finished, stays out (named in :attr:`ArchiveResult.passed`); a run that exists here is never touched.
    """
    root, archive = Path(root), Path(archive)
    result = ArchiveResult()
    if not archive.is_dir():
        return result
    registration = _registration(archive, spec)
    root.mkdir(parents=True, exist_ok=True)
    if registration is not None and not (root / REGISTRATION_FILE).exists():
        atomic_write_bytes(root / REGISTRATION_FILE, read_below(archive, REGISTRATION_FILE, MAX_JSON_BYTES))
    elif registration is not None:
        here = strict_json(read_below(root, REGISTRATION_FILE, MAX_JSON_BYTES), root / REGISTRATION_FILE)
        if not isinstance(here, dict) or here.get("first_run_started_unix") != registration.get("first_run_started_unix"):
            raise ConfigError(
                f"{root} holds another start of study {spec.name} than its archive {archive}: its archived runs are not "
                "restored there; give the study a new --run-dir (the archive's runs come back into it), or --no-archive"
            )
    for run in runs:
        rel = str(run.path.relative_to(root))
        check_below(archive, rel, "directory")
        payload = _read_config(archive / rel) if (archive / rel).is_dir() else None
        if payload is None or os.path.lexists(run.path):
            continue
        if payload.get("status") != "finished":
            result.passed.append(f"{rel}: not finished there")
            continue
        if config_differences(payload["config"], run.config):
            result.passed.append(f"{rel}: another configuration")
            continue
        copy_run_files(archive / rel, run.path)
        result.copied.append(rel)
    return result
