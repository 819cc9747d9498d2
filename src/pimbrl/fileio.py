"""Writing files so that a process killed at any moment leaves either the old file or the new one.

One module at the bottom of the package, used by the run directories, the experiment summaries and the
figures alike. Written files get the mode a newly created file would get (``0o666`` less the umask, e.g.
0644), not the 0600 of the temporary file they are written through.
"""

from __future__ import annotations

import io
import os
import tempfile
from pathlib import Path

__all__ = ["atomic_write_bytes", "new_file_mode"]


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


def atomic_write_bytes(path: str | os.PathLike, data: bytes | io.BytesIO) -> None:
    """Write ``data`` to ``path`` via a fsynced temporary file in the same directory and an atomic rename."""
    path = Path(path)
    payload = data.getvalue() if isinstance(data, io.BytesIO) else data
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        if hasattr(os, "fchmod"):
            os.fchmod(fd, new_file_mode())
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    try:  # make the rename itself durable
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError:
        pass
