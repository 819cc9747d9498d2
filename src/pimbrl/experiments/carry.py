"""An interrupted run carried to the next machine in its study's archive, checkpoint included.

The archive (:mod:`.archive`) keeps finished runs only, a few kilobytes each. A run stopped at a checkpoint
(``--time-limit``, SIGTERM) lives in its run directory alone, so a study whose machine does not outlive a
working session loses every unfinished run's progress, and a run longer than a session never finishes.
``pimbrl study archive SPEC --checkpoints`` therefore also copies every *interrupted* run of the spec's
configuration (started, not finished, held by no process, with a checkpoint or a control run's saved
stages) into ``<archive>/.interrupted/<run>/``: its files of :data:`~.runfiles.ARCHIVED`, its checkpoint
xz-compressed (:data:`CHECKPOINT`) and a small manifest (:data:`MANIFEST`: the checkpoint's step, size and
SHA-256). ``pimbrl study run`` puts such a run back where the run directory lacks it and the archive holds
no finished copy of it (:func:`~.archive.plan_restore`); it then resumes from that checkpoint as a run
stopped on this machine would, and the run records the CPU and commit it resumed on where they differ
(``resumed_on`` in its ``config.json``, listed by the report beside the first start's).

The rules: a checkpoint is carried only after its checksum is verified, and comes back only after it is
decompressed (within the size its manifest states) and verified again; a copy is replaced by a later one of
the same run only where the later one has come at least as far (its checkpoint's step; a control run's
saved wall-clock), so a run that started again from nothing on a machine without the archive never
overwrites progress; a finished run archived removes its interrupted copy, and none is made where the
archive holds the finished one. A compressed checkpoint over :data:`MAX_CARRIED_BYTES` is not carried
(the line says so, and an earlier copy under the bound stays): a repository is no place for it.
"""

from __future__ import annotations

import json
import lzma
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..fileio import (
    MAX_CHECKPOINT_BYTES,
    MAX_JSON_BYTES,
    atomic_write_bytes,
    check_below,
    ensure_directory_below,
    fsync_directory,
    read_below,
    strict_json,
)
from ..training.rundir import CheckpointError, RunDirectory, load_checkpoint_bytes, unpack_checkpoint
from .runfiles import ARCHIVED, copy_run_files, open_run_files, same_files

if TYPE_CHECKING:
    from .engine import StudyRun

__all__ = [
    "CHECKPOINT",
    "INTERRUPTED",
    "MANIFEST",
    "MAX_CARRIED_BYTES",
    "carried_copy_why_not",
    "carry_run",
    "drop_carried",
    "interrupted_why_not",
    "load_carried",
    "recover_carried",
    "restore_carried",
    "unplanned_carried",
]

#: the folder of an archive that holds interrupted runs (hidden: it is no arm of the study)
INTERRUPTED = ".interrupted"
#: a carried run's checkpoint, xz-compressed ``checkpoints/latest.pt``
CHECKPOINT = "checkpoint.pt.xz"
#: a carried run's manifest: ``{"step", "wall_s", "bytes", "sha256"}`` of what it carries
MANIFEST = "carried.json"
#: the largest compressed checkpoint carried (a file of more is refused by common git hosts)
MAX_CARRIED_BYTES = 90 << 20
#: xz's preset 9: a 64 MiB window, which finds a replay buffer's rows stored twice (observation and state)
_PRESET = 9
#: the suffixes of a carried run being assembled beside its place, and of the copy it replaces meanwhile
_STAGING, _OLD = ".carrying", ".old"


@dataclass(frozen=True)
class _Progress:
    """How far a run has come, as its checkpoint and saved stages say (not its logs, which may run ahead)."""

    step: int  # the checkpoint's real steps, or a DPC run's gradient steps (0 without one)
    wall_s: float  # a control run's saved wall-clock (control.json), else 0
    sha256: str | None  # the checkpoint's checksum (its header), None without one

    def behind(self, other: _Progress) -> bool:
        return (self.step, self.wall_s) < (other.step, other.wall_s)


def interrupted_why_not(directory: Path, run: StudyRun) -> str | None:
    """``None`` where ``directory`` holds an interrupted run of ``run``'s configuration worth carrying; else why not.

    Worth carrying: a checkpoint (an RL or DPC run) or a control run's saved stages (``control.json``);
    a run stopped before either starts from nothing wherever it goes.
    """
    opened = open_run_files(directory, run.config)
    if isinstance(opened, str):
        return opened
    rd, payload = opened
    if payload.get("status") == "finished":
        return "finished"
    if rd.holder() is not None:
        return "running"
    has_checkpoint = check_below(directory, "checkpoints/latest.pt") is not None
    if not has_checkpoint and check_below(directory, "control.json") is None:
        return "no checkpoint yet"
    return None


def _control_wall(directory: Path) -> float:
    from ..training.control_run import read_stages

    stages = read_stages(RunDirectory(directory)) or {}
    wall = stages.get("wall_s", 0.0)
    return float(wall) if isinstance(wall, (int, float)) and not isinstance(wall, bool) else 0.0


def _source(directory: Path) -> tuple[_Progress, bytes | None]:
    """The interrupted run in ``directory``: its progress and its checkpoint's bytes (checksum verified)."""
    try:
        data = read_below(directory, "checkpoints/latest.pt", MAX_CHECKPOINT_BYTES)
    except FileNotFoundError:
        return _Progress(0, _control_wall(directory), None), None
    state = load_checkpoint_bytes(data, directory / "checkpoints" / "latest.pt")
    dpc = state.get("dpc")  # a DPC run's checkpoint counts its gradient steps; an RL run's, its real steps
    step = int(dpc.get("steps", 0) if isinstance(dpc, dict) else state.get("t", 0))
    sha = data[: data.find(b"\n")].split(b" ")[-1].decode()
    return _Progress(step, _control_wall(directory), sha), data


def _manifest(where: Path) -> dict[str, Any]:
    """A carried copy's manifest (a ValueError where it is missing, damaged or of the wrong types)."""
    try:
        value = strict_json(read_below(where, MANIFEST, MAX_JSON_BYTES), where / MANIFEST)
    except FileNotFoundError:
        raise ValueError(f"{where} has no {MANIFEST}") from None
    ok = isinstance(value, dict) and isinstance(value.get("step"), int) and isinstance(value.get("wall_s"), (int, float))
    sized = isinstance(value, dict) and (value.get("sha256") is None or isinstance(value.get("bytes"), int))
    if not (ok and sized):
        raise ValueError(f"{where / MANIFEST} is not a manifest pimbrl wrote")
    return value


def carried_copy_why_not(archive: Path, rel: str, run: StudyRun) -> str | None:
    """``None`` where ``archive`` carries an interrupted copy of ``run`` (at ``rel``) that can come back; else why not.

    ``"none"`` where it carries none. The checkpoint itself is verified when it comes back (:func:`load_carried`).
    """
    where = Path(INTERRUPTED) / rel
    if check_below(archive, where, "directory") is None:
        return "none"
    why = interrupted_why_not(archive / where, run)
    if why not in (None, "no checkpoint yet"):  # the archive keeps the checkpoint compressed, not in checkpoints/
        return why
    try:
        manifest = _manifest(archive / where)
    except ValueError as exc:
        return f"unreadable ({str(exc).splitlines()[0]})"
    if manifest.get("sha256") is not None and check_below(archive / where, CHECKPOINT) is None:
        return "no checkpoint"
    if manifest.get("sha256") is None and (not run.config.control or check_below(archive / where, "control.json") is None):
        return "no checkpoint"  # an RL run without its checkpoint would start again from nothing
    return None


def _carried_progress(archive: Path, rel: str, run: StudyRun) -> _Progress | None:
    """The progress of the carried copy of ``run`` (``None``: none there, or one that cannot come back)."""
    if carried_copy_why_not(archive, rel, run) is not None:
        return None
    manifest = _manifest(archive / INTERRUPTED / rel)
    return _Progress(int(manifest["step"]), float(manifest["wall_s"]), manifest.get("sha256"))


def _recover(target: Path) -> None:
    """Undo what a copy killed half-way left beside ``target``: its staging goes, a replaced copy comes back."""
    staging, old = (target.parent / f".{target.name}{suffix}" for suffix in (_STAGING, _OLD))
    for leftover in (staging, target.parent / f".{staging.name}.copying"):
        if os.path.lexists(leftover):
            shutil.rmtree(leftover)
    if os.path.lexists(old):
        if os.path.lexists(target):
            shutil.rmtree(old)
        else:  # killed between the two renames: the old copy is the only one
            os.replace(old, target)


def recover_carried(archive: Path, rel: str) -> None:
    """Undo what a carry of the run at ``rel`` killed half-way left in ``archive`` (nothing where there is none)."""
    where = Path(INTERRUPTED) / rel
    if check_below(archive, INTERRUPTED, "directory") is not None and check_below(archive, where.parent, "directory"):
        _recover(archive / where)


def carry_run(source: Path, archive: Path, rel: str, run: StudyRun) -> str:
    """Copy the interrupted run in ``source`` to ``archive/.interrupted/rel``; returns what was done.

    ``"copied"``, ``"kept"`` (the archive's copy is this one or has come further) or ``"too large (...)"``.
    The copy is assembled beside its place and renamed into it (an earlier copy is replaced only then). A
    damaged checkpoint in ``source`` is a :class:`~pimbrl.training.rundir.CheckpointError`.
    """
    target_rel = Path(INTERRUPTED) / rel
    ensure_directory_below(archive, INTERRUPTED)
    check_below(archive, target_rel, "directory")  # no link on the way
    target = archive / target_rel
    if target.parent.is_dir():
        _recover(target)
    here, checkpoint = _source(source)
    kept = _carried_progress(archive, rel, run) if target.is_dir() else None
    if kept is not None and here.behind(kept):
        return "kept"
    if kept is not None and kept.sha256 == here.sha256 and kept == here and same_files(source, target):
        return "kept"
    packed = lzma.compress(checkpoint, preset=_PRESET) if checkpoint is not None else None
    if packed is not None and len(packed) > MAX_CARRIED_BYTES:
        return f"too large ({len(packed) / 2**20:,.0f} MiB compressed, over {MAX_CARRIED_BYTES >> 20} MiB)"
    manifest = {
        "step": here.step,
        "wall_s": here.wall_s,
        "bytes": len(checkpoint) if checkpoint is not None else None,
        "sha256": here.sha256,
    }
    target.parent.mkdir(parents=True, exist_ok=True)
    staging, old = (target.parent / f".{target.name}{suffix}" for suffix in (_STAGING, _OLD))
    copy_run_files(source, staging, ARCHIVED)
    try:
        if packed is not None:
            atomic_write_bytes(staging / CHECKPOINT, packed)
        atomic_write_bytes(staging / MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode())
        if target.is_dir():
            os.replace(target, old)
        os.replace(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)
    fsync_directory(target.parent)
    return "copied"


def load_carried(archive: Path, rel: str) -> bytes | None:
    """The checkpoint of the carried copy at ``rel``, decompressed and verified (``None``: a control run's, without one).

    Decompressed within the size its manifest states (never more than the checkpoint bound); a damaged,
    truncated or mismatching one is a one-line :class:`~pimbrl.training.rundir.CheckpointError` naming the
    folder to remove.
    """
    where = archive / INTERRUPTED / rel
    manifest = _manifest(where)
    if manifest.get("sha256") is None:
        return None
    size = int(manifest["bytes"])
    fix = f"remove the folder {where} to train the run again from its start"
    if not 0 < size <= MAX_CHECKPOINT_BYTES:
        raise CheckpointError(f"{where / MANIFEST} states an impossible checkpoint size ({size} bytes); {fix}")
    packed = read_below(where, CHECKPOINT, MAX_CARRIED_BYTES)
    decompressor = lzma.LZMADecompressor(format=lzma.FORMAT_XZ)
    try:
        data = decompressor.decompress(packed, max_length=size + 1)
    except lzma.LZMAError as exc:
        raise CheckpointError(f"{where / CHECKPOINT} is damaged ({exc}); {fix}") from None
    if len(data) != size or not decompressor.eof or decompressor.unused_data:
        raise CheckpointError(f"{where / CHECKPOINT} is truncated or not the checkpoint its manifest states; {fix}")
    try:
        unpack_checkpoint(data, where / CHECKPOINT)
    except CheckpointError as exc:
        raise CheckpointError(f"{str(exc).splitlines()[0]} ({fix})") from None
    return data


def drop_carried(archive: Path, rel: str) -> bool:
    """Remove the interrupted copy of the run at ``rel`` (its finished copy is archived); whether there was one."""
    where = Path(INTERRUPTED) / rel
    if check_below(archive, INTERRUPTED, "directory") is None or check_below(archive, where, "directory") is None:
        return False
    shutil.rmtree(archive / where)
    for parent in (archive / where).parents:  # the folders it leaves empty, up to and with .interrupted itself
        if parent == archive or not parent.is_relative_to(archive / INTERRUPTED) or any(parent.iterdir()):
            break
        parent.rmdir()
    return True


def restore_carried(archive: Path, rel: str, target: Path, checkpoint: bytes | None) -> None:
    """Copy the interrupted copy at ``archive/.interrupted/rel`` into the new run directory ``target``.

    ``checkpoint``: its checkpoint as :func:`load_carried` gave it (verified before anything is written).
    The run is assembled beside ``target`` and renamed into place.
    """
    source = archive / INTERRUPTED / rel
    staging = target.parent / f".{target.name}{_STAGING}"
    _recover(target)
    copy_run_files(source, staging, ARCHIVED)
    try:
        if checkpoint is not None:
            ensure_directory_below(staging, "checkpoints")
            atomic_write_bytes(staging / "checkpoints" / "latest.pt", checkpoint)
        if os.path.lexists(target):
            raise FileExistsError(f"{target} exists")
        os.replace(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    fsync_directory(target.parent)


def unplanned_carried(archive: Path, planned: set[str]) -> list[str]:
    """The carried copies in ``archive`` (paths relative to the study) of runs not in ``planned``, sorted.

    A copy is a folder below :data:`INTERRUPTED`, as deep as the planned runs' paths, that holds a regular
    :data:`MANIFEST`. Not followed or counted: links, hidden folders (a killed carry's staging, which
    :func:`recover_carried` tidies), :data:`INTERRUPTED` itself and any folder on the way to a planned run.
    Such a copy is left by a run its spec no longer plans (a pending spec edited between two sessions):
    nothing would ever restore it.
    """
    if not planned or check_below(archive, INTERRUPTED, "directory") is None:
        return []
    depths = {len(Path(rel).parts) for rel in planned}
    on_the_way = {Path(*Path(rel).parts[:n]).as_posix() for rel in planned for n in range(1, len(Path(rel).parts))}
    top = archive / INTERRUPTED
    found = []
    for folder, dirs, _files in os.walk(top):  # os.walk follows no link to a directory
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        rel = Path(folder).relative_to(top)
        if len(rel.parts) not in depths or rel.as_posix() in planned or rel.as_posix() in on_the_way:
            continue
        dirs.clear()
        try:
            manifest = check_below(top, rel / MANIFEST)
        except ValueError:  # a link or a special file there: no copy pimbrl wrote
            continue
        if manifest is not None:
            found.append(rel.as_posix())
    return sorted(found)
