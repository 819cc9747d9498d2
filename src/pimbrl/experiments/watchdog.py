"""A watchdog that ends a driver's helper processes when the driver dies, also by SIGKILL.

A local Ray instance started by a study (``ray.init``) runs helper processes (the GCS server, the raylet,
its workers) in sessions of their own: when the driver is killed they are reparented and live on, holding
cores and memory. :func:`watch_descendants` starts a small process that, while the driver lives, notes every
process descending from it (pid and start time, read from ``/proc``); when the driver is gone it kills
those and their own descendants (a pid reused by another process is left alone: its start time differs;
the processes the driver had before the watchdog started are spared, and with them their descendants).
It ignores SIGINT and SIGHUP (a Ctrl-C reaches the driver, which shuts Ray down itself) and ends with the
driver. Linux only (``/proc``); elsewhere it does nothing.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Collection
from pathlib import Path

__all__ = ["Watchdog", "descendants", "watch_descendants"]

#: seconds between looks at the driver's process tree
POLL_S = 0.2


def _stat(pid: int) -> tuple[int, int] | None:
    """``(parent pid, start time)`` of ``pid`` from ``/proc/<pid>/stat`` (``None`` if it is gone or a zombie)."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rfind(")") + 2 :].split()  # the command name may hold spaces and parentheses
    if fields[0] in ("Z", "X"):  # dead, waiting to be reaped: gone
        return None
    return int(fields[1]), int(fields[19])


def descendants(roots: set[int]) -> dict[int, int]:
    """Every living process below the pids ``roots`` (not the roots): pid -> start time."""
    parents: dict[int, list[int]] = {}
    starts: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        info = _stat(int(entry))
        if info is not None:
            parents.setdefault(info[0], []).append(int(entry))
            starts[int(entry)] = info[1]
    out: dict[int, int] = {}
    todo = list(roots)
    while todo:
        for child in parents.get(todo.pop(), []):
            if child not in out and child not in roots:
                out[child] = starts[child]
                todo.append(child)
    return out


def _watch(driver: int, me: int, spared: Collection[int] = ()) -> None:
    """The watchdog's loop (run in its own process): note the driver's descendants, kill them once it is gone.

    ``spared``: processes the driver had before the watchdog started (not its helpers: never killed).
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    driver_start = _stat(driver)
    if driver_start is None:
        return
    before = set(spared)
    seen: dict[int, int] = {}
    while True:
        info = _stat(driver)
        if info is None or info[1] != driver_start[1]:
            break
        tree = descendants({driver})
        protected = before | set(descendants(before & set(tree)))
        seen.update({pid: start for pid, start in tree.items() if pid not in protected})
        seen.pop(me, None)
        time.sleep(POLL_S)
    # the driver is gone: its helpers, and whatever they started since the last look
    for _ in range(3):
        living = {pid: start for pid, start in seen.items() if (s := _stat(pid)) is not None and s[1] == start}
        living.update(descendants(set(living)))
        living.pop(me, None)
        if not living:
            return
        for pid in living:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        seen = living
        time.sleep(POLL_S)


class Watchdog:
    """A running watchdog process; :meth:`stop` ends it (the driver's helpers ended normally)."""

    def __init__(self, process: subprocess.Popen[bytes] | None) -> None:
        self.process = process

    def stop(self) -> None:
        """End the watchdog (it kills nothing when stopped)."""
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=10)


def watch_descendants() -> Watchdog:
    """Start a watchdog over this process's descendants (see the module docstring)."""
    if not Path("/proc/self/stat").exists():
        return Watchdog(None)
    code = (
        "import os, sys; from pimbrl.experiments.watchdog import _watch; "
        "_watch(int(sys.argv[1]), os.getpid(), {int(p) for p in sys.argv[2:]})"
    )
    spared = [str(pid) for pid in descendants({os.getpid()})]  # what the driver had already: not Ray's
    process = subprocess.Popen(
        [sys.executable, "-c", code, str(os.getpid()), *spared],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    return Watchdog(process)
