"""Files of run directories and caches: written atomically, read as the untrusted data they may be.

One module at the bottom of the package, used by the run directories, the caches, the experiment summaries
and the figures alike.

Writing: a process killed at any moment leaves either the old file or the new one
(:func:`atomic_write_bytes`). Written files get the mode a newly created file would get (``0o666`` less the
umask, e.g. 0644), not the 0600 of the temporary file they are written through.

Reading: a run directory may come from someone else (a colleague's results, a downloaded archive, a shared
disk), so every file of it is opened through :func:`open_below`: no symbolic link below the directory the
user named is followed, only regular files are read (a FIFO cannot hang a reader, a device cannot be read
without end), files are read up to a bound (:func:`read_below`), a file appended to must have no other hard
links (:func:`append_below`), and JSON is parsed with finite numbers only (:func:`strict_json`). Anything
else is an :class:`UnsafeFileError` whose one-line message names the file and the fix.
"""

from __future__ import annotations

import errno
import io
import json
import math
import os
import stat
import tempfile
import warnings
from pathlib import Path
from typing import Any

__all__ = [
    "MAX_CHECKPOINT_BYTES",
    "MAX_CSV_BYTES",
    "MAX_JSON_BYTES",
    "UnsafeFileError",
    "append_below",
    "atomic_write_bytes",
    "check_below",
    "ensure_directory_below",
    "fsync_directory",
    "new_file_mode",
    "open_below",
    "private_directory",
    "read_below",
    "strict_json",
]


def new_file_mode() -> int:
    """``0o666`` less the process's umask, read without changing it where the OS allows (Linux: /proc)."""
    mask: int | None = None
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    mask = int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        mask = None
    if mask is None:
        mask = os.umask(0o022)
        os.umask(mask)
    return 0o666 & ~mask


def _fsynced_temporary(path: Path, data: bytes) -> str:
    """A temporary file beside ``path`` holding ``data``, flushed to disk (removed again if writing fails)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        if hasattr(os, "fchmod"):
            os.fchmod(fd, new_file_mode())
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
    except BaseException:
        os.remove(tmp)
        raise
    return tmp


def atomic_write_bytes(path: str | os.PathLike, data: bytes | io.BytesIO) -> None:
    """Write ``data`` to ``path`` via a fsynced temporary file in the same directory and an atomic rename."""
    path = Path(path)
    tmp = _fsynced_temporary(path, data.getvalue() if isinstance(data, io.BytesIO) else data)
    try:
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    fsync_directory(path.parent)  # make the rename itself durable


def create_file(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path``, which must not exist: whole or not at all, never over another file.

    A fsynced temporary file in the same directory is hard-linked to ``path`` (which fails with
    :class:`FileExistsError` where something is there, even one made a moment before) and then removed.
    """
    path = Path(path)
    tmp = _fsynced_temporary(path, data)
    try:
        os.link(tmp, path)
    finally:
        os.remove(tmp)
    fsync_directory(path.parent)


def fsync_directory(path: str | os.PathLike) -> None:
    """Make the renames in directory ``path`` durable, where the platform allows it (errors are ignored)."""
    try:
        dir_fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError:
        pass


# ---------------------------------------------------------------------- reading and appending what others may have made
#: The largest JSON file of a run directory read (``config.json`` and friends are a few kB).
MAX_JSON_BYTES = 64 << 20
#: The largest CSV log read (a 10-million-step KS run's logs are a few hundred MB at most).
MAX_CSV_BYTES = 4 << 30
#: The largest checkpoint read (the real buffer of a long KS run is a few hundred MB).
MAX_CHECKPOINT_BYTES = 64 << 30

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
_DIRECTORY = getattr(os, "O_DIRECTORY", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)


class UnsafeFileError(ValueError):
    """A file of a run directory or cache is not one pimbrl would have made; the message names it and the fix.

    A symbolic link (never followed), something other than a regular file (a FIFO, a device, a directory), a
    file with other hard links (never written to), or a file larger than any pimbrl writes.
    """


def _kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISLNK, "a symbolic link"),
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    ):
        if test(mode):
            return name
    return "of an unknown kind"


def _refuse_link(path: Path) -> UnsafeFileError:
    return UnsafeFileError(
        f"{path} is a symbolic link; pimbrl follows no link inside a run directory or cache: replace it with the "
        "file or folder itself, or remove it"
    )


def _refuse_kind(path: Path, mode: int, want: str) -> UnsafeFileError:
    return UnsafeFileError(
        f"{path} is {_kind(mode)}, not a {want}; it is not something pimbrl wrote: remove it, or replace it with "
        f"the run's own {want}"
    )


def _check_file(path: Path, info: os.stat_result, single_link: bool, own: bool) -> None:
    """Refuse a file with other hard links (``single_link``) or of another user (``own``)."""
    if single_link and info.st_nlink != 1:
        raise UnsafeFileError(
            f"{path} has {info.st_nlink} hard links (other names elsewhere); pimbrl writes only files of its own: "
            "replace it with a copy (cp), or remove it"
        )
    if own and hasattr(os, "getuid") and info.st_uid != os.getuid():
        raise UnsafeFileError(f"{path} belongs to user id {info.st_uid}, not to this user ({os.getuid()})")


def check_below(
    root: str | os.PathLike,
    relative: str | os.PathLike,
    want: str = "regular file",
    *,
    single_link: bool = False,
    own: bool = False,
) -> os.stat_result | None:
    """The ``lstat`` of ``root/relative`` (``None`` if missing), refusing what pimbrl never makes there.

    Every component below ``root`` must be no symbolic link, the ones on the way directories and the last a ``want``
    (``"regular file"`` or ``"directory"``); otherwise :class:`UnsafeFileError` names it. ``root`` itself,
    the directory the user named, may be a link. ``single_link`` and ``own`` also refuse a last component with
    other hard links or of another user (see :func:`open_below`).
    """
    root = Path(root)
    parts = Path(relative).parts
    info = None
    for i in range(len(parts)):
        path = root.joinpath(*parts[: i + 1])
        try:
            info = os.lstat(path)
        except FileNotFoundError:
            return None
        last = i == len(parts) - 1
        if stat.S_ISLNK(info.st_mode):
            raise _refuse_link(path)
        kind = want if last else "directory"
        if (kind == "directory") != stat.S_ISDIR(info.st_mode) or (kind == "regular file" and not stat.S_ISREG(info.st_mode)):
            raise _refuse_kind(path, info.st_mode, kind)
    if info is not None:
        _check_file(root.joinpath(*parts), info, single_link, own)
    return info


def open_below(
    root: str | os.PathLike,
    relative: str | os.PathLike,
    flags: int = os.O_RDONLY,
    *,
    single_link: bool = False,
    own: bool = False,
) -> int:
    """A descriptor of the regular file ``root/relative``, opened without following any link below ``root``.

    The folders on the way are opened one by one with ``O_NOFOLLOW`` (relative to each other, so a folder
    swapped for a link meanwhile is not followed either), the file with ``O_NOFOLLOW | O_NONBLOCK`` (a
    FIFO cannot block the open) and then checked to be a regular file; ``single_link`` also refuses a file
    with other hard links (a file pimbrl writes to must be its own), ``own`` a file of another user (a cache
    entry). ``flags`` may hold ``O_CREAT`` (mode
    ``0o666`` less the umask). Raises :class:`UnsafeFileError`, or ``FileNotFoundError`` for a missing file.
    """
    root = Path(root)
    parts = Path(relative).parts
    path = root.joinpath(*parts)
    check_below(root, relative)  # a clear message for a link or a FIFO; the opens below close the race
    dir_fd = os.open(root, os.O_RDONLY | _DIRECTORY | _CLOEXEC)
    try:
        for i, part in enumerate(parts[:-1]):
            try:
                inner = os.open(part, os.O_RDONLY | _DIRECTORY | _NOFOLLOW | _CLOEXEC, dir_fd=dir_fd)
            except OSError as exc:
                if exc.errno in (errno.ELOOP, errno.ENOTDIR):
                    raise _refuse_link(root.joinpath(*parts[: i + 1])) from None
                raise
            os.close(dir_fd)
            dir_fd = inner
        try:
            fd = os.open(parts[-1], flags | _NOFOLLOW | _NONBLOCK | _CLOEXEC, 0o666, dir_fd=dir_fd)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise _refuse_link(path) from None
            if exc.filename is None:
                exc.filename = str(path)
            raise
    finally:
        os.close(dir_fd)
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise _refuse_kind(path, info.st_mode, "regular file")
        _check_file(path, info, single_link, own)
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_below(
    root: str | os.PathLike, relative: str | os.PathLike, max_bytes: int, *, single_link: bool = False, own: bool = False
) -> bytes:
    """The bytes of the regular file ``root/relative`` (:func:`open_below`), refusing one over ``max_bytes``."""
    path = Path(root).joinpath(relative)
    fd = open_below(root, relative, single_link=single_link, own=own)
    with os.fdopen(fd, "rb") as fh:
        size = os.fstat(fd).st_size
        if size > max_bytes:
            raise UnsafeFileError(
                f"{path} is {size:,d} bytes, more than any such file pimbrl writes ({max_bytes:,d}); it is not read: "
                "remove it, or replace it with the run's own file"
            )
        data = fh.read(size + 1)
        if len(data) > size:  # still growing (a log being appended to): read up to the bound
            data += fh.read(max_bytes + 1 - len(data))
    if len(data) > max_bytes:  # grew while being read
        raise UnsafeFileError(f"{path} grew beyond {max_bytes:,d} bytes while being read; it is not used")
    return data


def append_below(root: str | os.PathLike, relative: str | os.PathLike) -> io.TextIOWrapper:
    """A text file open for appending at ``root/relative`` (created if missing), never through a link.

    Refuses a link, anything but a regular file, and a file with other hard links (:func:`open_below`).
    """
    fd = open_below(root, relative, os.O_WRONLY | os.O_APPEND | os.O_CREAT, single_link=True)
    return open(fd, "a", newline="")


def ensure_directory_below(root: str | os.PathLike, relative: str | os.PathLike) -> Path:
    """Create the folder ``root/relative`` if missing (never through a link) and return its path."""
    path = Path(root).joinpath(relative)
    if check_below(root, relative, want="directory") is None:
        Path(root).mkdir(parents=True, exist_ok=True)
        path.mkdir(exist_ok=True)  # exist_ok: another writer may make it meanwhile; checked again below
        check_below(root, relative, want="directory")
    return path


def private_directory(directory: Path, what: str) -> bool:
    """Create ``directory`` (mode 0700) if missing; whether ``what`` may be cached in it.

    Safe: a real directory (not a symbolic link) owned by this user, not writable by group or others
    (another user could plant files there: code for the kernel cache, data for the KS pool cache). An
    unsafe one is refused with a warning; ``OSError`` if it cannot be created.
    """
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    info = os.lstat(directory)
    problem = None
    if not stat.S_ISDIR(info.st_mode):
        problem = "it is not a directory (a symbolic link?)"
    elif hasattr(os, "getuid") and info.st_uid != os.getuid():
        problem = f"it is owned by user id {info.st_uid}, not by this user ({os.getuid()})"
    elif info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        problem = f"group or others may write it (mode {stat.S_IMODE(info.st_mode):o})"
    if problem is not None:
        warnings.warn(
            f"pimbrl is not caching {what} in {directory}: {problem}; set PIMBRL_CACHE_DIR to a directory of your own "
            "(mode 0700)",
            stacklevel=3,
        )
        return False
    return True


def strict_json(data: bytes, path: str | os.PathLike) -> Any:
    """``data`` parsed as JSON, refusing ``NaN``/``Infinity``, numbers too large for a float and integers beyond 64 bits.

    Errors are :class:`UnsafeFileError` naming ``path`` (a one-line message).
    """

    def constant(name: str) -> Any:
        raise UnsafeFileError(f"{path}: {name} is not a finite number; pimbrl writes finite numbers only (was the file edited?)")

    def number(text: str) -> float:
        value = float(text)
        if not math.isfinite(value):
            raise UnsafeFileError(f"{path}: the number {text} is too large for a float; pimbrl writes finite numbers only")
        return value

    def integer(text: str) -> int:
        if len(text.lstrip("-")) > 19:  # beyond 64 bits: no count, seed or step pimbrl writes
            raise UnsafeFileError(f"{path}: the integer {text[:24]}... is too large; pimbrl writes 64-bit integers at most")
        return int(text)

    try:
        return json.loads(data.decode("utf-8"), parse_constant=constant, parse_float=number, parse_int=integer)
    except UnicodeDecodeError as exc:
        raise UnsafeFileError(f"{path}: not valid JSON (not UTF-8 text: {exc.reason})") from None
    except json.JSONDecodeError as exc:
        raise UnsafeFileError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:
        raise UnsafeFileError(f"{path}: not valid JSON (nested too deeply)") from None
