"""A stop asked of a training run (SIGTERM, or SIGINT), kept until the run can checkpoint.

A batch scheduler (SLURM, a cloud's preemption, ``kill``) ends a job with SIGTERM and a grace period before
SIGKILL. Without a handler, the process dies at once and the run goes back to its last checkpoint, which for
a short run (3,000 steps, a checkpoint due every 5,000) is its start. While the command line's ``train`` and
``resume`` (and so a study's runs) train, the first SIGTERM or SIGINT is only noted; at the next episode end
the loop writes a checkpoint and raises :class:`RunStopped`, and ``pimbrl resume`` continues from there
exactly. A SIGINT after that stops at once (Ctrl-C twice); a repeated SIGTERM does not, since a scheduler
signals every process of a job and a study's driver passes its SIGTERM on, so a run often gets two (SIGKILL
stops at once). A signal the process ignores (SIGINT in a job a shell started in the background) stays
ignored. Python code calling :func:`~pimbrl.training.train` keeps the usual KeyboardInterrupt unless it asks
for this (``stop_on_signal=True``).
"""

from __future__ import annotations

import signal
import sys
import threading
from types import FrameType, TracebackType
from typing import Any

__all__ = ["STOP_SIGNALS", "RunStopped", "StopRequest", "TimeLimitReached", "take_signal"]

#: the signals that ask a run to stop at its next checkpoint
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


def take_signal(sig: int, handler: Any) -> Any:
    """Install ``handler`` for ``sig`` and return the handler it replaced; ``None`` where it installs nothing.

    Nothing is installed off the main thread (where Python cannot set handlers), where ``sig`` is ignored (by
    whoever started the process: it stays so) or where its handler was set outside Python.
    """
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.getsignal(sig)
    if previous is signal.SIG_IGN or previous is None:
        return None
    signal.signal(sig, handler)
    return previous


class RunStopped(Exception):  # noqa: N818 - not an error: the stop that was asked for
    """A run stopped by a signal after writing its checkpoint at ``step``; ``pimbrl resume`` continues it."""

    def __init__(self, signum: int, step: int) -> None:
        self.signum = signum
        self.step = step
        super().__init__(f"stopped by {signal.Signals(signum).name} at step {step:,d}, its checkpoint written")

    @property
    def exit_status(self) -> int:
        """128 + the signal's number, as a shell reports a command a signal ended (143 for SIGTERM)."""
        return 128 + self.signum


class TimeLimitReached(Exception):  # noqa: N818 - not an error: the stop that was asked for
    """A study's driver stopped at its time limit (``pimbrl study run --time-limit``).

    Every running child was sent SIGTERM and has ended: an RL run at its next episode end with a checkpoint, a
    control run (feedback, MPC, DPC) at once, to resume from its last saved stage (DPC's last validation, MPC's
    last finished chunk of episodes). The same command again continues.
    """

    def __init__(self, minutes: float) -> None:
        super().__init__(
            f"stopped at its time limit ({minutes:g} minutes): each running run stopped at a checkpoint (an RL run at "
            "its next episode end, a control run at its last saved stage); the same command again continues"
        )
        self.minutes = minutes


class StopRequest:
    """While entered (and ``active``), SIGTERM and SIGINT set :attr:`signum` instead of ending the process.

    After a stop was noted, a SIGINT raises KeyboardInterrupt at once; another SIGTERM is noted again and
    changes nothing. Off the main thread signal handlers cannot be set; it then does nothing and
    :attr:`signum` stays ``None``, as it does when not ``active``.
    """

    def __init__(self, active: bool = True) -> None:
        self.active = active
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    @property
    def requested(self) -> bool:
        """Whether a stop was asked."""
        return self.signum is not None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is not None:
            if signum == signal.SIGINT:  # Ctrl-C again: stop now, as without the handler
                self.__exit__(None, None, None)
                raise KeyboardInterrupt
            return  # the same stop asked again (a job's SIGTERM, and the driver's copy of it)
        self.signum = signum
        again = "Ctrl-C again stops at once" if signum == signal.SIGINT else "SIGKILL stops at once"
        print(
            f"pimbrl: {signal.Signals(signum).name}: stopping at the end of this episode, with a checkpoint ({again})",
            file=sys.stderr,
            flush=True,
        )

    def __enter__(self) -> StopRequest:
        if self.active:
            for sig in STOP_SIGNALS:
                previous = take_signal(sig, self._handle)
                if previous is not None:
                    self._previous[sig] = previous
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous.clear()
