"""A run directory's small files, copied between a run directory and a study's archive.

What a study's record and report read from a run is a few kilobytes of JSON and CSV (:data:`ARCHIVED`);
:func:`copy_run_files` copies them safely (no link followed, each file within its bound, the copy assembled
beside its place and renamed into it). The archive (:mod:`.archive`) and its carried interrupted runs
(:mod:`.carry`) both copy through it.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ..fileio import MAX_CSV_BYTES, MAX_JSON_BYTES, atomic_write_bytes, check_below, fsync_directory, read_below
from ..training.rundir import RunDirectory
from .runner import config_differences

__all__ = ["ARCHIVED", "STAGING", "copy_run_files", "open_run_files", "same_files"]

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
#: the suffix of a run being assembled beside its target
STAGING = ".copying"


def open_run_files(directory: Path, config: Any) -> tuple[RunDirectory, dict[str, Any]] | str:
    """The run in ``directory`` and its ``config.json``, where it is a run of ``config``; else why not.

    Why not: ``"no config.json"``, ``"unreadable (...)"`` or ``"another configuration"``. A link or another
    special file among :data:`ARCHIVED` is an :class:`~pimbrl.fileio.UnsafeFileError` (never followed).
    What the run's status must be is the caller's to check (the archive wants it finished, a carry not).
    """
    for name in ARCHIVED:
        check_below(directory, name)
    rd = RunDirectory(directory)
    try:
        payload = rd.read_config()
    except FileNotFoundError:
        return "no config.json"
    except ValueError as exc:
        return f"unreadable ({str(exc).splitlines()[0]})"
    if config_differences(payload.get("config"), config):
        return "another configuration"
    return rd, payload


def _bound(name: str) -> int:
    return MAX_JSON_BYTES if name.endswith(".json") else MAX_CSV_BYTES


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
    staging = parent / f".{target.name}{STAGING}"
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


def same_files(a: Path, b: Path) -> bool:
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
