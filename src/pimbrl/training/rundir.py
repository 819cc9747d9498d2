"""Run directories: resolved config, CSV logs that survive a crash, atomic checkpoints.

Layout of a run directory::

    config.json          resolved configuration, package versions, command line, status
    run.lock             the lock of the process writing the run (its pid, host and command)
    evaluations.csv      one row per evaluation: step, return_mean, return_min, return_max, ..., wall_s
    metrics.csv          training metrics every ``log_every`` steps (losses, update-to-data ratio, speed)
    episodes.csv         one row per training episode
    checkpoints/latest.pt  the full training state (written atomically, with a checksum)
    selection.csv        model-based policy selection, one row per evaluation (``dyna.select_episodes``)
    tb/                  TensorBoard events (optional)

Every file is written so that a process killed at any moment (``kill -9``) leaves a consistent directory:
checkpoints and the config are written to a temporary file, fsynced and renamed; CSV rows are appended
and flushed, and on resume each CSV is cut back to the rows of the checkpointed step (a torn last line
is dropped). Temporary files left by a kill are removed when the run is next opened for writing
(:meth:`RunDirectory.remove_stale_temporaries`).

One process at a time writes a run: :meth:`RunDirectory.lock` takes an exclusive OS lock
(``fcntl.flock``) on ``run.lock``, held until :meth:`RunDirectory.close` or the end of the process (the
OS drops it also when the process is killed). Reading a run (evaluation, figures) needs no lock.

A run directory is read as untrusted input (it may be someone else's): every file is opened through
:func:`pimbrl.fileio.open_below` (no symbolic link below the directory followed, regular files only, a size
bound, no write to a file with other hard links), ``config.json`` is strict JSON with typed fields, and the
CSV logs' numbers must be finite (:meth:`CsvLog.read`). :meth:`RunDirectory.check_entries` refuses a
directory holding anything pimbrl does not make there before anything is read or changed.

A checkpoint file is a one-line header, ``pimbrl-checkpoint <format> sha256 <hex digest>``, then the
``torch.save`` bytes of the state. It is read only if the format is this version's and the digest
matches, and then with ``torch.load(weights_only=True)``: tensors and plain data, never code.
"""

from __future__ import annotations

import csv
import datetime
import hashlib
import io
import json
import math
import os
import pickle
import re
import socket
import stat
import sys
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from ..config import ConfigError, check_env_id
from ..fileio import (
    MAX_CHECKPOINT_BYTES,
    MAX_CSV_BYTES,
    MAX_JSON_BYTES,
    UnsafeFileError,
    append_below,
    atomic_write_bytes,
    check_below,
    ensure_directory_below,
    open_below,
    read_below,
    strict_json,
)
from ..physics.kernels import GENERATOR_VERSION

__all__ = [
    "CHECKPOINT_VERSION",
    "LOCK_FILE",
    "CheckpointError",
    "CsvLog",
    "RunDirectory",
    "RunLockedError",
    "atomic_write_bytes",
    "kernel_note",
    "load_checkpoint_bytes",
    "pack_checkpoint",
    "package_versions",
    "steps_to_threshold",
    "unpack_checkpoint",
]

#: Format of checkpoint files. 1: a bare ``torch.save`` pickle (earlier versions); 2: header with a SHA-256
#: checksum, then ``torch.save`` bytes of tensors and plain data only (read with ``weights_only=True``).
CHECKPOINT_VERSION = 2
_MAGIC = b"pimbrl-checkpoint"
#: The lock file of a run directory (holds the pid, host and command of the process writing the run).
LOCK_FILE = "run.lock"
#: ``.<name>.<random>.tmp``: a temporary file of :func:`atomic_write_bytes`.
_TEMPORARY = re.compile(r"^\..+\.[A-Za-z0-9_]+\.tmp$")


class CheckpointError(ValueError):
    """A checkpoint cannot be used (another format, corrupted, not plain data, inconsistent counters)."""


class RunLockedError(FileExistsError):
    """Another process holds the lock of a run directory; the message names it."""


def pack_checkpoint(payload: bytes) -> bytes:
    """A checkpoint file's bytes: the header (format, SHA-256 of ``payload``) and ``payload``."""
    digest = hashlib.sha256(payload).hexdigest().encode()
    return b"%s %d sha256 %s\n" % (_MAGIC, CHECKPOINT_VERSION, digest) + payload


def unpack_checkpoint(data: bytes, path: str | os.PathLike) -> bytes:
    """The payload of a checkpoint file's bytes, after checking its format and checksum.

    Raises :class:`CheckpointError` (named after ``path``) for another format or a checksum mismatch.
    """
    if data.startswith(b"PK\x03\x04"):  # a bare torch.save zip: format 1, which may hold pickled code
        raise CheckpointError(
            f"checkpoint {path} was written by another version of pimbrl (checkpoint format 1, without a checksum; "
            f"this version reads format {CHECKPOINT_VERSION}) and is not loaded: continue or evaluate the run with "
            "the pimbrl version that wrote it, or start a new run"
        )
    end = data.find(b"\n", 0, 256)
    fields = data[:end].split(b" ") if end > 0 else []
    if len(fields) != 4 or fields[0] != _MAGIC or fields[2] != b"sha256" or not fields[1].isdigit():
        raise CheckpointError(
            f"checkpoint {path} is corrupted or not a pimbrl checkpoint (no valid header); it is not used: "
            "delete it to restart the run from its beginning (`pimbrl resume`), or start a new run"
        )
    version = int(fields[1])
    if version != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"checkpoint {path} was written by another version of pimbrl (checkpoint format {version}; this "
            f"version reads format {CHECKPOINT_VERSION}) and is not loaded: continue or evaluate the run with the "
            "pimbrl version that wrote it, or start a new run"
        )
    payload = data[end + 1 :]
    if hashlib.sha256(payload).hexdigest().encode() != fields[3]:
        raise CheckpointError(
            f"checkpoint {path} is corrupted (checksum mismatch); it is not used: delete it to restart the run "
            "from its beginning (`pimbrl resume`), or start a new run"
        )
    return payload


_PLAIN = (torch.Tensor, int, float, bool, str, bytes, type(None), torch.dtype, torch.Size, torch.device)


def _plain(obj: Any, where: str) -> Any:
    """``obj`` as tensors and plain data (what ``weights_only`` loads): NumPy scalars become Python ones.

    Anything else is a ``TypeError`` naming where in the state it is (a bug, found when saving rather
    than when the checkpoint is read).
    """
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, _PLAIN):
        return obj
    if isinstance(obj, dict):
        items = {k: _plain(v, f"{where}/{k}") for k, v in obj.items()}
        if all(items[k] is v for k, v in obj.items()):
            return obj  # unchanged (keeps a module state dict's metadata)
        return OrderedDict(items) if isinstance(obj, OrderedDict) else items
    if isinstance(obj, (list, tuple)):
        seq = [_plain(v, f"{where}[{i}]") for i, v in enumerate(obj)]
        if all(a is b for a, b in zip(seq, obj)):
            return obj
        return type(obj)(seq) if type(obj) in (list, tuple) else seq
    raise TypeError(f"checkpoint state {where or '/'} is a {type(obj).__name__}; a checkpoint holds tensors and plain data only")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def steps_to_threshold(evaluations: list[dict[str, Any]], threshold: float | None) -> int | None:
    """First evaluation step whose mean return reaches ``threshold`` (``None`` if never)."""
    if threshold is None:
        return None
    for row in evaluations:
        if float(row["return_mean"]) >= threshold:
            return int(float(row["step"]))
    return None


def wall_s_to_threshold(evaluations: list[dict[str, Any]], threshold: float | None) -> float | None:
    """Training wall-clock (seconds) at the first evaluation whose mean return reaches ``threshold``."""
    if threshold is None:
        return None
    return next((float(r["wall_s"]) for r in evaluations if float(r["return_mean"]) >= threshold), None)


def _first_cpu_block() -> dict[str, str]:
    """The first processor's fields in ``/proc/cpuinfo`` (``{}`` where there is no such file)."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if not line.strip():
                    if fields:  # the first processor's block is enough
                        break
                    continue
                key, _, value = line.partition(":")
                fields.setdefault(key.strip(), value.strip())
    except OSError:
        return {}
    return fields


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``'s ``model name``; else the platform's processor or machine).

    Results are bit for bit on one CPU model only, so a record names the model, not just ``x86_64``.
    """
    import platform

    return _first_cpu_block().get("model name") or platform.processor() or platform.machine() or "unknown"


def cpu_identity() -> str | None:
    """The CPU beyond its model name: vendor, family, model and stepping, and a digest of its feature flags.

    A virtual machine may mask the model name (``Intel(R) Xeon(R) Processor``); the family, model, stepping
    and the instruction-set flags (which decide the vector kernels NumPy, torch and Numba run) tell such
    machines apart. ``None`` where ``/proc/cpuinfo`` is not there.
    """
    import hashlib

    fields = _first_cpu_block()
    if not any(k in fields for k in ("vendor_id", "cpu family", "model", "stepping", "flags")):
        return None
    flags = hashlib.sha256(" ".join(sorted(fields.get("flags", "").split())).encode()).hexdigest()[:8]
    return (
        f"{fields.get('vendor_id', '?')} family {fields.get('cpu family', '?')} model {fields.get('model', '?')} "
        f"stepping {fields.get('stepping', '?')}, flags {flags}"
    )


def source_commit() -> str | None:
    """The git commit of the source tree this pimbrl was loaded from (``None`` for an installed package).

    Only the checkout whose ``src/pimbrl`` this module is in counts (an install inside another project's
    virtual environment records nothing). Read from its ``.git`` without running git: a directory, or the
    file a worktree has (``gitdir: ...``, with ``commondir`` for shared refs); a branch ref, packed refs or a
    detached head.
    """
    package = Path(__file__).resolve().parent.parent
    repo = package.parent.parent
    if package.parent.name != "src" or not (repo / "pyproject.toml").is_file():
        return None
    try:
        git = repo / ".git"
        if git.is_file():  # a worktree: "gitdir: <path>"
            text = git.read_text().strip()
            if not text.startswith("gitdir:"):
                return None
            git = (repo / text.split(":", 1)[1].strip()).resolve()
        if not git.is_dir():
            return None
        common = git
        if (git / "commondir").is_file():
            common = (git / (git / "commondir").read_text().strip()).resolve()
        head = (git / "HEAD").read_text().strip()
        if not head.startswith("ref: "):
            return head or None
        ref = head[5:]
        for base in (git, common):
            if (base / ref).is_file():
                return (base / ref).read_text().strip()
        packed = common / "packed-refs"
        if packed.is_file():
            for line in packed.read_text().splitlines():
                if line.endswith(" " + ref):
                    return line.split()[0]
    except OSError:
        return None
    return None


def provenance() -> dict[str, Any]:
    """Where a run ran: the CPU model (and :func:`cpu_identity`), the cores this process may use, the commit of the code."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": cpu_model(), "cpu_id": cpu_identity(), "cores": cores, "commit": source_commit()}


def package_versions() -> dict[str, str]:
    """Versions of Python, pimbrl and its main dependencies, recorded in a run's configuration file."""
    import gymnasium
    import numba
    import numpy

    from .. import __version__

    return {
        "pimbrl": __version__,
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "numpy": numpy.__version__,
        "gymnasium": gymnasium.__version__,
        "numba": numba.__version__,
        "kernel": GENERATOR_VERSION,
    }


def kernel_note(versions: dict[str, str]) -> str | None:
    """A note where a run's recorded simulator kernel is not this pimbrl's (``None`` where it is).

    The PDE kernels of different versions agree to round-off only, so a chaotic system's trajectories, and
    the KS initial-state pools built from them (the training pool's composition), differ between them.
    """
    made = versions.get("kernel")
    if made == GENERATOR_VERSION:
        return None
    made_with = f"simulator kernel {made}" if made else "a simulator kernel before version 5 (not recorded)"
    return (
        f"this run was made with {made_with}, this pimbrl has kernel {GENERATOR_VERSION}: the PDE simulations agree "
        "to round-off only and the KS training pool differs (evaluate or resume it with the pimbrl it was made with "
        "for the same states)"
    )


class CsvLog:
    """An append-only CSV file with a fixed header; rows are flushed as they are written.

    The file is ``root/name``, opened without following links (:func:`~pimbrl.fileio.append_below`).
    ``numeric`` columns are checked when the log is read: finite numbers (``step`` a whole number >= 0), or
    empty where ``required`` does not list them.
    """

    def __init__(
        self,
        root: Path,
        name: str,
        columns: list[str],
        numeric: Sequence[str] = ("step",),
        required: Sequence[str] = ("step",),
    ) -> None:
        self.root = root
        self.name = name
        self.path = root / name
        self.columns = columns
        self.numeric = tuple(numeric)
        self.required = tuple(required)
        self._fh: io.TextIOWrapper | None = None

    def _open(self) -> io.TextIOWrapper:
        if self._fh is None:
            self._fh = append_below(self.root, self.name)
            if os.fstat(self._fh.fileno()).st_size == 0:
                self._fh.write(",".join(self.columns) + "\n")
                self._fh.flush()
        return self._fh

    def append(self, row: dict[str, Any]) -> None:
        """Write one row (its keys outside the header are ignored, missing ones left empty) and flush."""
        fh = self._open()
        writer = csv.DictWriter(fh, fieldnames=self.columns, extrasaction="ignore", lineterminator="\n")
        writer.writerow({k: _fmt(row.get(k)) for k in self.columns})
        fh.flush()

    def _lines(self) -> list[str] | None:
        """The file's complete lines (a torn last line, from a killed process, left out); ``None`` if missing."""
        try:
            data = read_below(self.root, self.name, MAX_CSV_BYTES)
        except FileNotFoundError:
            return None
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            raise UnsafeFileError(f"{self.path}: not a CSV log written by pimbrl (not UTF-8 text)") from None
        lines = text.split("\n")
        return lines[:-1]  # the part after the last newline: empty, or a row still being (or never fully) written

    def truncate_after(self, step: int) -> None:
        """Keep only the rows with ``step <= step`` (used when resuming from a checkpoint).

        A torn last line is dropped; any other malformed row is an :class:`~pimbrl.fileio.UnsafeFileError`
        naming its line (a damaged or edited log is reported, never silently cut).
        """
        self.close()
        lines = self._lines()
        if lines is None:
            return
        header = lines[0] if lines and lines[0] else ",".join(self.columns)
        kept = [header]
        for number, line, values in self._rows(lines):
            if _whole(values[0], self.path, number, "step") <= step:
                kept.append(line)
        atomic_write_bytes(self.path, ("\n".join(kept) + "\n").encode())

    def _rows(self, lines: list[str]) -> Iterator[tuple[int, str, list[str]]]:
        """(line number, line, values) of each data row, checked to have the header's number of fields."""
        width = len(lines[0].split(",")) if lines and lines[0] else len(self.columns)
        for number, line in enumerate(lines[1:], start=2):
            if not line:
                continue
            values = _fields(line, self.path, number)
            if len(values) != width:
                raise UnsafeFileError(
                    f"{self.path} line {number} has {len(values)} fields, its header {width}: the log was edited or "
                    "damaged; restore it, or delete that line"
                )
            yield number, line, values

    def read(self) -> list[dict[str, str]]:
        """All complete rows as dictionaries of strings (none if the file does not exist), checked.

        The header must hold the ``required`` columns, every row as many fields as the header, and each
        ``numeric`` value be a finite number (``step`` a whole number >= 0); otherwise
        :class:`~pimbrl.fileio.UnsafeFileError` names the file, the line and the value.
        """
        lines = self._lines()
        if not lines:
            return []
        header = _fields(lines[0], self.path, 1)
        missing = [c for c in self.required if c not in header]
        if missing:
            raise UnsafeFileError(
                f"{self.path} has no column {missing[0]!r} (its header: {lines[0][:200]!r}); it is not a log pimbrl wrote"
            )
        rows = []
        for number, _, values in self._rows(lines):
            row = dict(zip(header, values))
            for column in self.numeric:
                value = row.get(column, "")
                if value == "" and column not in self.required:
                    continue
                if column == "step":
                    _whole(value, self.path, number, column)
                else:
                    _finite(value, self.path, number, column)
            rows.append(row)
        return rows

    def close(self) -> None:
        """Close the file if it is open (a later append reopens it)."""
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def _fields(line: str, path: Path, number: int) -> list[str]:
    """The fields of one CSV line; :class:`UnsafeFileError` naming the line where it cannot be split."""
    try:
        return next(csv.reader([line]))
    except csv.Error as exc:
        raise UnsafeFileError(
            f"{path} line {number} is not a CSV row pimbrl wrote ({exc}); the log was edited or damaged: restore it, "
            "or delete that line"
        ) from None


#: the largest step count read from a log (far beyond any run; a larger one is a damaged file)
_MAX_STEP = 10**15


def _finite(text: str, path: Path, line: int, column: str) -> float:
    """``text`` as a finite float; :class:`UnsafeFileError` naming the file, line and column otherwise."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise UnsafeFileError(
            f"{path} line {line}: {column} {text[:40]!r} is not a finite number; the log was edited or damaged: "
            "restore it, or delete that line"
        )
    return value


def _whole(text: str, path: Path, line: int, column: str) -> int:
    """``text`` as a whole number in ``[0, 1e15]``; :class:`UnsafeFileError` otherwise."""
    value = _finite(text, path, line, column)
    if value != int(value) or not 0 <= value <= _MAX_STEP:
        raise UnsafeFileError(
            f"{path} line {line}: {column} {text[:40]!r} is not a step count (a whole number >= 0); the log was "
            "edited or damaged: restore it, or delete that line"
        )
    return int(value)


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, torch.Tensor):
        return repr(float(v))
    return str(v)


class RunDirectory:
    """A training run's directory (see the module docstring for its layout)."""

    EVAL_COLUMNS: ClassVar[list[str]] = [
        "step",
        "return_mean",
        "return_min",
        "return_max",
        "return_std",
        "length_mean",
        "episodes",
        "updates",
        "wall_s",
    ]
    #: the columns of ``evaluations.csv`` every reader relies on
    EVAL_REQUIRED: ClassVar[tuple[str, ...]] = ("step", "return_mean", "return_min", "return_max", "updates", "wall_s")
    EPISODE_COLUMNS: ClassVar[list[str]] = ["step", "episode", "return", "length"]
    #: every entry pimbrl makes in a run directory, and what it is (nothing else there is read or written)
    ENTRIES: ClassVar[dict[str, str]] = {
        "config.json": "regular file",
        LOCK_FILE: "regular file",
        "evaluations.csv": "regular file",
        "episodes.csv": "regular file",
        "metrics.csv": "regular file",
        "selection.csv": "regular file",
        "coefficients.json": "regular file",
        "control.json": "regular file",
        "holdout.json": "regular file",
        "checkpoints": "directory",
        "checkpoints/latest.pt": "regular file",
        "tb": "directory",
        "compare.log": "regular file",
        "config.request.json": "regular file",
    }
    #: the logs a run appends to: they must have no other hard links
    APPENDED: ClassVar[tuple[str, ...]] = ("evaluations.csv", "episodes.csv", "metrics.csv", "selection.csv", "compare.log")
    #: model-based policy selection (:mod:`pimbrl.training.selection`), one row per evaluation
    SELECTION_COLUMNS: ClassVar[list[str]] = [
        "step",
        "model_return_mean",
        "model_return_min",
        "blown_up",
        "return_mean",
        "selected_step",
        "selected_return_mean",
    ]

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.config_path = self.path / "config.json"
        self.checkpoint_path = self.path / "checkpoints" / "latest.pt"
        self.evaluations = CsvLog(
            self.path,
            "evaluations.csv",
            self.EVAL_COLUMNS,
            numeric=[c for c in self.EVAL_COLUMNS if c != "episodes"],
            required=self.EVAL_REQUIRED,
        )
        self.episodes = CsvLog(self.path, "episodes.csv", self.EPISODE_COLUMNS)
        self.selection = CsvLog(self.path, "selection.csv", self.SELECTION_COLUMNS)
        self._metrics: CsvLog | None = None
        self._lock_fd: int | None = None

    # ------------------------------------------------------------------ lock
    @property
    def lock_path(self) -> Path:
        """The lock file, ``run.lock``."""
        return self.path / LOCK_FILE

    @property
    def locked(self) -> bool:
        """Whether this object holds the run's lock."""
        return self._lock_fd is not None

    def lock(self, command: str | None = None) -> None:
        """Take the run's exclusive lock for this process (the directory must exist).

        The lock is an OS lock (``fcntl.flock``) on ``run.lock``, held until :meth:`close` or the end of
        the process, also a killed one. The file records the holder's pid, host and ``command`` (default:
        this process's command line). Raises :class:`RunLockedError`, naming the holder, if another
        process (or another open of the run in this process) holds it.
        """
        if self._lock_fd is not None:
            return
        try:
            import fcntl
        except ImportError:  # pragma: no cover - no advisory locks on this platform
            return
        # never through a link, never a file with another name elsewhere (it is truncated below)
        fd = open_below(self.path, LOCK_FILE, os.O_RDWR | os.O_CREAT, single_link=True)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            other = _describe_holder(fd)
            os.close(fd)
            raise RunLockedError(
                f"{self.path} is in use by another pimbrl process ({other}); wait for it to end or stop it, "
                "then try again (only one process may write a run; `pimbrl eval` and `figure` may read it meanwhile)"
            ) from None
        except BaseException:
            os.close(fd)
            raise
        holder = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "command": command if command is not None else " ".join(sys.argv),
            "since": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        }
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(holder) + "\n").encode(), 0)
        except OSError:
            pass  # the lock holds without the description
        self._lock_fd = fd

    def holder(self) -> str | None:
        """The process holding the run's lock, described (``None`` where no other holds it).

        This object's own lock does not count; a lock file that cannot be opened safely (a link, a FIFO)
        is an :class:`~pimbrl.fileio.UnsafeFileError`.
        """
        if self._lock_fd is not None:
            return None
        try:
            import fcntl
        except ImportError:  # pragma: no cover - no advisory locks on this platform
            return None
        try:
            fd = open_below(self.path, LOCK_FILE)
        except FileNotFoundError:
            return None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return _describe_holder(fd)
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        finally:
            os.close(fd)

    def check_entries(self, writing: bool = False) -> None:
        """Refuse a run directory whose entries are not what pimbrl makes there, before anything is read.

        Every entry of :attr:`ENTRIES` that exists must be what it should be (a regular file or a folder),
        never a symbolic link; with ``writing``, the logs appended to must have no other hard links.
        Raises :class:`~pimbrl.fileio.UnsafeFileError` naming the first that is not.
        """
        for name, want in self.ENTRIES.items():
            check_below(self.path, name, want, single_link=writing and name in self.APPENDED)

    def unlock(self) -> None:
        """Release the run's lock if this object holds it."""
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # closing the only descriptor of the open file releases the flock
            self._lock_fd = None

    def remove_stale_temporaries(self) -> list[Path]:
        """Delete the temporary files (``.<name>.<random>.tmp``) left by a process killed while writing.

        Call it only while holding the lock (a running process's temporary file is not stale); returns
        the files removed.
        """
        removed = []
        for directory in (self.path, self.checkpoint_path.parent):
            if directory != self.path and check_below(self.path, directory.name, "directory") is None:
                continue  # no checkpoints folder (a link there is refused, never entered)
            for entry in directory.iterdir():
                if _TEMPORARY.match(entry.name) and stat.S_ISREG(os.lstat(entry).st_mode):
                    try:
                        entry.unlink()
                        removed.append(entry)
                    except FileNotFoundError:
                        pass
        return removed

    # ------------------------------------------------------------------ config
    def write_config(self, payload: dict[str, Any]) -> None:
        """Write ``config.json`` atomically."""
        atomic_write_bytes(self.config_path, (json.dumps(payload, indent=2, sort_keys=False) + "\n").encode())

    def write_json(self, name: str, payload: dict[str, Any]) -> None:
        """Write ``name`` (a JSON file of the run, e.g. ``coefficients.json``) atomically."""
        atomic_write_bytes(self.path / name, (json.dumps(payload, indent=2) + "\n").encode())

    def read_config(self) -> dict[str, Any]:
        """The contents of ``config.json``, with the type of every top-level field pimbrl reads checked.

        ``FileNotFoundError`` if this is not a run directory; :class:`~pimbrl.fileio.UnsafeFileError` (a
        ``ValueError``) if the file is a link, a FIFO, too large, not strict JSON (``NaN``, ``Infinity`` and
        overflowing numbers are refused), not an object, or if ``status``, ``config``, ``versions``,
        ``summary`` or ``command`` has the wrong type.
        """
        try:
            data = read_below(self.path, "config.json", MAX_JSON_BYTES)
        except FileNotFoundError:
            raise FileNotFoundError(f"{self.path} is not a pimbrl run directory (no config.json)") from None
        payload = strict_json(data, self.config_path)
        if not isinstance(payload, dict):
            raise UnsafeFileError(f"{self.config_path}: must be a JSON object, got {type(payload).__name__}")
        for key, check, what in _TOP_LEVEL:
            if key in payload and not check(payload[key]):
                raise UnsafeFileError(
                    f"{self.config_path}: {key} must be {what}, got {_short(payload[key])}; the file was edited or damaged"
                )
        return payload

    def require_system(self, payload: dict[str, Any] | None = None) -> None:
        """A one-line :class:`~pimbrl.config.ConfigError` where the run's system is not registered in this process.

        The message names what declared it when the run was created (``system.origin`` in ``config.json``): the
        ``--import`` to pass, or the package whose entry point declares it. Nothing named in the file is
        imported.
        """
        import gymnasium as gym

        payload = self.read_config() if payload is None else payload
        env = (payload.get("config") or {}).get("env")
        if not isinstance(env, str) or env in gym.registry:
            return
        origin = (payload.get("system") or {}).get("origin", "")
        if not _ORIGIN.match(origin):  # text from an untrusted file: printed only in a known, one-line form
            origin = ""
        if origin.startswith("--import "):
            fix = (
                f"pass `{origin}` as its config.json records (check that file first: pimbrl imports nothing named "
                "in a run directory)"
            )
        elif origin.startswith("entry point "):
            fix = f"install the package whose {origin} (group pimbrl.systems) declares it"
        else:
            fix = "install or --import the module that registers it (pimbrl imports nothing named in a run directory)"
        raise ConfigError(f"{self.path}: the run's system {env} is not registered here; {fix}")

    def recorded_config(self, payload: dict[str, Any] | None = None) -> dict[str, Any]:
        """The ``config`` object of ``config.json``, with its ``env`` checked to be a registered-id string.

        For readers that use a few fields without building the run (plots, figures). The env id must not
        be Gymnasium's ``module:id`` form, which imports a module (a run names a registered id only);
        whether it is registered here is not checked (a plot needs no environment). Errors are
        :class:`~pimbrl.fileio.UnsafeFileError` naming the file. ``payload``: the file's contents where the
        caller has read them already (:meth:`read_config`).
        """
        config = (self.read_config() if payload is None else payload).get("config")
        if not isinstance(config, dict):
            raise UnsafeFileError(
                f"{self.config_path}: has no 'config' object; this is not a run written by pimbrl (or its config.json was edited)"
            )
        env = config.get("env")
        try:
            check_env_id(env)
        except ValueError as exc:
            raise UnsafeFileError(f"{self.config_path}: {exc}") from None
        threshold = config.get("threshold")
        if threshold is not None and not _is_number(threshold):
            raise UnsafeFileError(f"{self.config_path}: threshold must be a number or null, got {_short(threshold)}")
        return config

    @property
    def status(self) -> str | None:
        """``"running"``, ``"finished"``, or ``None`` where there is no readable run."""
        try:
            return self.read_config().get("status")
        except (FileNotFoundError, ValueError):  # ValueError: UnsafeFileError, a damaged or planted config.json
            return None

    def result(self, threshold: float | None = None) -> dict[str, Any] | None:
        """What a run has reached so far (``None`` without a config.json or evaluations).

        That is its steps, steps to ``threshold`` (default: the run's own) and the training wall-clock at which
        it was first reached, final and best mean test return, wall-clock, updates and its curves.
        """
        try:
            payload = self.read_config()  # a damaged config.json is an error here, not a run to leave out
        except FileNotFoundError:
            return None
        rows = self.evaluations.read()
        if not rows:
            return None
        if threshold is None:
            threshold = self.recorded_config(payload).get("threshold")
        steps = int(float(rows[-1]["step"]))
        updates = int(float(rows[-1]["updates"]))
        summary = payload.get("summary") or {}
        return {
            # a run whose lock another process holds is in use (resumed, extended), never counted as finished
            "finished": payload.get("status") == "finished" and self.holder() is None,
            "steps": steps,
            "steps_to_threshold": steps_to_threshold(rows, threshold),
            "wall_s_to_threshold": wall_s_to_threshold(rows, threshold),
            "final_return": float(rows[-1]["return_mean"]),
            "best_return": max(float(r["return_mean"]) for r in rows),
            "wall_s": float(summary.get("wall_s", rows[-1]["wall_s"])),
            "updates": updates,
            "update_to_data": updates / max(steps, 1),
            "curve": {
                **{k: [float(r[k]) for r in rows] for k in ("step", "return_mean", "return_min", "return_max", "wall_s")},
                **self._imagined_at([int(float(r["step"])) for r in rows]),
            },
        }

    def _imagined_at(self, steps: list[int]) -> dict[str, list[float | None]]:
        """``{"imagined_total": [...]}``: the imagined transitions made by each of ``steps`` (a run with a model).

        Read from the ``metrics.csv`` row logged at each step (runs log one at every evaluation; earlier runs
        only every ``log_every`` steps: ``None`` where no row was logged at that step). ``{}`` for a run that
        logs no imagined transitions (model-free runs, controllers), has no metrics, or whose metrics cannot
        be read (the outcome does not depend on them).
        """
        log = CsvLog(self.path, "metrics.csv", [], numeric=("step", "imagined_total"), required=("step",))
        try:
            rows = [r for r in log.read() if r.get("imagined_total") not in (None, "")]
        except ValueError:  # a damaged metrics.csv (UnsafeFileError): no count, the run's outcome stands
            return {}
        if not rows:
            return {}
        logged = {int(float(r["step"])): float(r["imagined_total"]) for r in rows}
        return {"imagined_total": [logged.get(step) for step in steps]}

    def note_resume(self) -> bool:
        """Add this process's :func:`provenance` to ``resumed_on`` where its CPU (model, identity) or commit differs.

        The last is the latest entry of ``resumed_on``, else the run's first ``provenance``. Returns whether an
        entry was added; a run resumed where it last ran is left as it was.
        """
        payload = self.read_config()
        resumed = list(payload.get("resumed_on") or [])
        last = resumed[-1] if resumed else payload.get("provenance") or {}
        here = provenance()
        fields = ("cpu", "cpu_id", "commit")  # cpu_id: a masked model name is told apart by its family, flags, ...
        if isinstance(last, dict) and all(last.get(k) == here[k] for k in fields):
            return False
        self.update_status(resumed_on=[*resumed, {**here, "unix": round(time.time(), 3)}])
        return True

    def update_status(self, **fields: Any) -> None:
        """Set top-level ``fields`` of ``config.json`` (e.g. ``status``), keeping the rest."""
        payload = self.read_config()
        payload.update(fields)
        self.write_config(payload)

    # ------------------------------------------------------------------ metrics
    def metrics(self, columns: list[str]) -> CsvLog:
        """The metrics log; its columns are fixed by the first call (or the existing file's header)."""
        if self._metrics is None:
            try:
                head = read_below(self.path, "metrics.csv", MAX_CSV_BYTES).split(b"\n", 1)[0]
            except FileNotFoundError:
                head = b""
            if head:
                columns = head.decode("utf-8", errors="replace").strip().split(",")
            self._metrics = CsvLog(self.path, "metrics.csv", columns)
        return self._metrics

    def truncate_logs(self, step: int) -> None:
        """Drop the rows of every log after ``step`` (used when resuming from a checkpoint)."""
        for log in (self.evaluations, self.episodes, self.selection):
            log.truncate_after(step)
        if check_below(self.path, "metrics.csv") is not None:
            self.metrics([]).truncate_after(step)

    def close(self) -> None:
        """Close the open log files and release the lock (if held)."""
        for log in (self.evaluations, self.episodes, self.selection, self._metrics):
            if log is not None:
                log.close()
        self.unlock()

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, state: dict[str, Any]) -> None:
        """Write ``state`` to ``checkpoints/latest.pt`` atomically, with the format version and a checksum.

        ``state`` must be tensors and plain data (NumPy scalars are converted); see :func:`pack_checkpoint`.
        """
        buf = io.BytesIO()
        torch.save(_plain({"version": CHECKPOINT_VERSION, **state}, ""), buf)
        ensure_directory_below(self.path, "checkpoints")  # never written through a link
        atomic_write_bytes(self.checkpoint_path, pack_checkpoint(buf.getvalue()))

    def load_checkpoint(self) -> dict[str, Any]:
        """The latest checkpoint, verified and loaded as tensors and plain data only.

        ``FileNotFoundError`` if there is none; :class:`CheckpointError` (one line) if it was written by
        another format version, is corrupted (checksum mismatch), holds anything but tensors and plain
        data (never unpickled as code) or cannot be read.
        """
        path = self.checkpoint_path
        try:
            data = read_below(self.path, "checkpoints/latest.pt", MAX_CHECKPOINT_BYTES)
        except FileNotFoundError:
            raise FileNotFoundError(f"no checkpoint in {self.path} (expected {path})") from None
        except UnsafeFileError:
            raise
        except OSError as exc:
            raise CheckpointError(f"checkpoint {path} could not be read ({_first_line(exc)})") from None
        return load_checkpoint_bytes(data, path)


def load_checkpoint_bytes(data: bytes, path: str | os.PathLike) -> dict[str, Any]:
    """A checkpoint file's bytes, verified (:func:`unpack_checkpoint`) and loaded as tensors and plain data only.

    Raises :class:`CheckpointError` (one line, named after ``path``) for another format, a checksum mismatch,
    anything but tensors and plain data (never unpickled as code) or a payload that cannot be read.
    """
    payload = unpack_checkpoint(data, path)
    try:
        state = torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r"GLOBAL ([\w.]+)", str(exc))
        what = f" (it references {found.group(1)})" if found else ""
        raise CheckpointError(
            f"checkpoint {path} holds more than tensors and plain data{what} and is not loaded: pimbrl never "
            "runs code from a checkpoint; delete it, or start a new run"
        ) from None
    except Exception as exc:
        raise CheckpointError(f"checkpoint {path} could not be read ({_first_line(exc)})") from None
    if not isinstance(state, dict) or state.get("version") != CHECKPOINT_VERSION:
        version = state.get("version") if isinstance(state, dict) else None
        raise CheckpointError(
            f"checkpoint {path} has schema version {version!r}, expected {CHECKPOINT_VERSION}: it was written by "
            "another version of pimbrl; continue the run with that version, or start a new run"
        )
    return state


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _string_map(value: Any) -> bool:
    return isinstance(value, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in value.items())


def _summary(value: Any) -> bool:
    return value is None or (isinstance(value, dict) and ("wall_s" not in value or _is_number(value["wall_s"])))


#: the top-level fields of config.json pimbrl reads: (name, check, what it must be)
#: the forms of ``system.origin`` a message may repeat: one line of printable characters, of a known kind
_ORIGIN = re.compile(r"(--import [^\x00-\x1f\x7f`]{1,300}|entry point [\w.-]{1,200}|module [\w.]{1,200}|pimbrl|gymnasium)\Z")

_TOP_LEVEL: tuple[tuple[str, Callable[[Any], bool], str], ...] = (
    ("status", lambda v: v in ("running", "finished"), '"running" or "finished"'),
    ("config", lambda v: isinstance(v, dict), "an object"),
    ("versions", _string_map, "an object of strings (package versions)"),
    ("summary", _summary, "an object (with a finite wall_s, if any), or null"),
    ("command", lambda v: isinstance(v, str), "a string"),
    ("system", _string_map, "an object of strings"),
    # a seed-free controller's copy (pimbrl.experiments.replicas): its source and the probe it was checked against
    ("replicate_of", lambda v: _string_map(v) and "source" in v, "an object of strings naming its source"),
    # where a resumed run went on, when that differs from where it last ran (a run carried to another machine)
    ("resumed_on", lambda v: isinstance(v, list) and all(isinstance(e, dict) for e in v), "a list of objects"),
)


def _describe_holder(fd: int) -> str:
    """The holder recorded in a lock file (``pid 12 on host, since ...: command``)."""
    try:
        holder = json.loads(os.pread(fd, 65536, 0).decode())
        command = " ".join(str(holder["command"]).split())
        return f"pid {holder['pid']} on {holder['host']}, since {holder['since']}: {command}"
    except (OSError, ValueError, KeyError, TypeError):
        return "holder not recorded yet"
