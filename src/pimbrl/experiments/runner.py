"""Running a study's runs as child processes: one directory per run, resumable, one driver per directory.

Each run is trained in its own process (``pimbrl train --config DIR/config.request.json``, or ``pimbrl
resume`` for an interrupted one), ``jobs`` at a time; its output goes to its ``compare.log``. While they
train, one status line per running child is shown on stderr. A directory holding runs is locked for the
driver (``compare.lock``: two drivers in one directory would each train, or wait on, and summarise the
other's unfinished runs); a run whose configuration differs from the requested one is never reused
silently, and a run another process holds is never moved.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import ConfigError
from ..fileio import UnsafeFileError, atomic_write_bytes, open_below
from ..training.config import TrainConfig, config_from_dict, config_to_dict
from ..training.control_run import dpc_progress
from ..training.methods import DPC
from ..training.rundir import RunDirectory
from ..training.stopping import TimeLimitReached, take_signal

__all__ = [
    "CHILD_LOG",
    "COMPARE_LOCK",
    "REQUEST_FILE",
    "RunSpec",
    "TimeLimitReached",
    "check_reuse",
    "child_status",
    "config_differences",
    "dpc_steps_text",
    "lock_comparison",
    "pinned_environment",
    "run_all",
    "thread_variables",
]

#: the file in a new run's directory that hands its configuration to the child process
REQUEST_FILE = "config.request.json"
#: the file in a run's directory that takes its child process's output
CHILD_LOG = "compare.log"
#: the lock file of a comparison's directory (one comparison runs there at a time)
COMPARE_LOCK = "compare.lock"
#: seconds between status refreshes: on a terminal, and as plain lines otherwise
STATUS_EVERY_TTY = 2.0
STATUS_EVERY_PLAIN = 30.0
#: a child's exit statuses when a signal stopped it (SIGINT, SIGTERM: 128 + the signal; checkpointed where it could)
STOPPED_STATUSES = (128 + signal.SIGINT, 128 + signal.SIGTERM)
#: the variables that size the thread pools of the numerical libraries a run's process may load: OpenMP (and
#: torch's pool, before ``torch.set_num_threads``), OpenBLAS (numpy's and scipy's linear algebra) and MKL
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def pinned_environment(threads: int, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """``base`` (default: this process's environment) with every thread pool of a child sized to ``threads``.

    ``torch.set_num_threads`` pins torch only; numpy's OpenBLAS starts a thread per core when it loads, and a
    simulator built on numpy (controlgym's) then runs on two cores while its neighbour waits: on a 2-core
    machine beside other runs, 200 steps of controlgym's Burgers took 3.2 times as long with OpenBLAS's default
    pool as with one thread (``benchmarks/bench_blas_threads.py``). The variables are read when the libraries
    load, so they are set for the child, before it starts; they override the parent's (a run's ``threads`` is
    its whole budget).
    """
    return {**(os.environ if base is None else base), **thread_variables(threads)}


def thread_variables(threads: int) -> dict[str, str]:
    """Each of :data:`THREAD_VARIABLES` set to ``threads`` (a Ray task's worker gets them as its ``runtime_env``)."""
    return {name: str(threads) for name in THREAD_VARIABLES}


@dataclass(frozen=True)
class RunSpec:
    """One run to make: its directory and its configuration."""

    label: str  # method label, e.g. "pimbrl" or "mfrl-matched"
    seed: int
    path: Path
    config: TrainConfig
    #: the ``--import`` arguments of this run's child besides :func:`run_all`'s (its study's, in a queue)
    imports: tuple[str, ...] = ()


def _flat(config: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"agent.gamma": 0.99, "method.fit.steps": 50, ...}`` from a nested configuration dict."""
    out: dict[str, Any] = {}
    for key, value in config.items():
        if isinstance(value, dict) and key != "env_kwargs" and key not in ("prior", "coefficients"):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def config_differences(recorded: Any, requested: TrainConfig) -> list[str]:
    """The fields in which a run's recorded configuration differs from ``requested``.

    ``recorded`` is the ``config`` of a ``config.json``; each difference reads
    ``"total_steps (300 there, 200 requested)"``. A configuration that cannot be read is one difference.
    """
    try:
        there = _flat(json.loads(json.dumps(config_to_dict(config_from_dict(dict(recorded))))))
    except (ConfigError, TypeError, ValueError):
        return ["the recorded configuration (unreadable)"]
    wanted = _flat(json.loads(json.dumps(config_to_dict(requested))))
    return [f"{k} ({there.get(k)!r} there, {wanted.get(k)!r} requested)" for k in wanted if there.get(k) != wanted.get(k)]


def lock_comparison(root: Path) -> int:
    """Take the exclusive lock of a comparison's directory (``compare.lock``); returns its descriptor.

    Two comparisons running in one directory would each train, or wait on, and summarise the other's unfinished
    runs: the second is a :class:`ConfigError` naming the first. The lock is the OS's (released when the
    descriptor is closed or the process ends, also a killed one). ``--no-run`` summaries take no lock.
    """
    import fcntl

    fd = open_below(root, COMPARE_LOCK, os.O_RDWR | os.O_CREAT, single_link=True)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        if not isinstance(exc, BlockingIOError):
            os.close(fd)
            raise
        try:
            holder = os.pread(fd, 512, 0).decode(errors="replace").strip() or "another process"
        finally:
            os.close(fd)
        raise ConfigError(
            f"{root} is in use by another pimbrl driver ({holder}); wait for it to end, or give another --run-dir "
            "(two drivers in one directory would each summarise the other's unfinished runs)"
        ) from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}: {' '.join(sys.argv)}\n".encode(), 0)
    except OSError:
        pass  # the lock holds without the description
    return fd


def check_reuse(specs: Sequence[RunSpec], rerun: bool = False, log: Callable[[str], None] = print, move: bool = True) -> None:
    """Refuse to reuse a run (finished or interrupted) whose configuration is not the requested one.

    Raises :class:`ConfigError` naming the first such run directory and the fields that differ; with
    ``rerun`` each such run is moved aside (to ``<dir>.replaced-<time>``, under its lock) so that it is trained
    again (``move=False``: only checked, nothing moved). A run whose lock another process holds (training,
    resumed, extended) is a :class:`ConfigError` whatever its configuration: it is never moved, replaced or
    resumed from here.
    """
    stale = []
    for spec in specs:
        run_dir = RunDirectory(spec.path)
        if not spec.path.is_dir():
            continue
        holder = run_dir.holder()
        if holder is not None:  # a run in use is never moved, replaced or resumed by a second driver
            raise ConfigError(
                f"{spec.path} is in use by another pimbrl process ({holder}): wait for it to end or stop it, then run "
                "the comparison again (a run in use is never moved, replaced or summarised as finished)"
            )
        run_dir.check_entries(writing=True)  # links, FIFOs, shared files: refused before any run starts
        if not run_dir.config_path.exists():
            continue
        try:
            recorded = run_dir.read_config().get("config")
        except ValueError:  # not JSON
            recorded = None
        diffs = config_differences(recorded, spec.config)
        if diffs:
            stale.append((spec, diffs))
    if not stale or (rerun and not move):
        return
    if not rerun:
        spec, diffs = stale[0]
        more = f" (and {len(stale) - 1} more run(s) of this comparison)" if len(stale) > 1 else ""
        raise ConfigError(
            f"{spec.path} holds a run made with another configuration: {', '.join(diffs)}{more}; choose another --run-dir, "
            "or move such runs aside and train them again (pimbrl compare or pimbrl study run: --rerun)"
        )
    for spec, diffs in stale:
        stamp = time.strftime("%Y%m%dT%H%M%S")
        target = spec.path.with_name(f"{spec.path.name}.replaced-{stamp}")
        n = 1
        while target.exists():
            n += 1
            target = spec.path.with_name(f"{spec.path.name}.replaced-{stamp}-{n}")
        run_dir = RunDirectory(spec.path)
        run_dir.lock("compare --rerun: moving the run aside")  # RunLockedError if a process took it since the check
        try:
            spec.path.rename(target)
        finally:
            run_dir.unlock()
        log(f"moved {spec.path} aside to {target} ({', '.join(diffs)}); it runs again")


def _last_row(path: Path) -> dict[str, str] | None:
    """The last complete row of the CSV log ``path`` (its header and tail only are read); ``None`` if none.

    Opened like every file of a run (:func:`~pimbrl.fileio.open_below`): a link or a FIFO there gives ``None``.
    """
    try:
        fd = open_below(path.parent, path.name)
    except (OSError, UnsafeFileError):
        return None
    try:
        with os.fdopen(fd, "rb") as fh:
            header = fh.readline(8192).decode(errors="replace").strip().split(",")
            start = fh.tell()
            fh.seek(0, 2)
            fh.seek(max(start, fh.tell() - 8192))
            tail = fh.read(8192).decode(errors="replace")
    except OSError:
        return None
    lines = tail.split("\n")[:-1]  # the part after the last newline is a row still being written
    for line in reversed(lines):
        values = line.strip().split(",")
        if len(values) == len(header) and line.strip():
            return dict(zip(header, values))
    return None


def _number(row: dict[str, str] | None, key: str) -> float | None:
    try:
        value = None if row is None else float(row[key])
    except (KeyError, ValueError):
        return None
    return value if value is not None and math.isfinite(value) and abs(value) < 1e15 else None


def dpc_steps_text(steps: int, total: int) -> str:
    """How far a DPC run has come, as the driver's lines and ``pimbrl study status`` say it: ``"750/3,000 DPC steps"``."""
    return f"{steps:,}/{total:,} DPC steps"


def child_status(spec: RunSpec, returns: bool = True) -> str:
    """One status line of a running child, read from its run directory.

    ``"pimbrl seed 0: 12,400/200,000 steps  test return -63.20  41 steps/s"`` (what is known so far; a
    tuning run's evaluations say ``validation return``). A DPC run, which evaluates only once it has trained,
    shows its gradient steps through the scheme: ``"dpc seed 0: 1,250/3,000 DPC steps"``. ``returns=False``
    (a confirmatory study's runs) leaves the return out: its outcomes are read once the study has finished.
    """
    head = f"{spec.label} seed {spec.seed}: "
    if isinstance(spec.config.method, DPC):
        try:
            done = dpc_progress(RunDirectory(spec.path))[0]
        except (OSError, ValueError):
            done = 0
        return head + (dpc_steps_text(done, int(spec.config.method.iterations)) if done else "starting")
    evaluation = _last_row(spec.path / "evaluations.csv")
    metrics = _last_row(spec.path / "metrics.csv")
    episode = _last_row(spec.path / "episodes.csv")
    steps = [v for v in (_number(r, "step") for r in (evaluation, metrics, episode)) if v is not None]
    if not steps:
        return head + "starting"
    parts = [f"{int(max(steps)):,d}/{spec.config.total_steps:,d} steps"]
    mean = _number(evaluation, "return_mean")
    if mean is not None and returns:  # a tuning run's evaluations play the validation draws, not the test pool
        parts.append(f"{spec.config.eval_protocol} return {mean:.2f}")
    sps = _number(metrics, "steps_per_s")
    if sps is not None:
        parts.append(f"{sps:,.0f} steps/s")
    return head + "  ".join(parts)


class _StatusLines:
    """The running children's status lines on stderr: a live display on a terminal, plain lines otherwise."""

    def __init__(self, enabled: bool, returns: bool = True) -> None:
        from rich.console import Console

        self.returns = returns  # False: a confirmatory study's lines show no return
        self.console = Console(stderr=True)
        self.enabled = enabled
        self.live: Any = None
        self.last = time.monotonic()
        if enabled and self.console.is_terminal:
            from rich.live import Live

            self.live = Live(console=self.console, auto_refresh=False, transient=True, redirect_stdout=True)
            self.live.start()

    def show(self, specs: Sequence[RunSpec]) -> None:
        """Refresh the lines of ``specs`` (the running children), when due."""
        if not self.enabled:
            return
        every = STATUS_EVERY_TTY if self.live is not None else STATUS_EVERY_PLAIN
        now = time.monotonic()
        if now - self.last < every:
            return
        self.last = now
        lines = [child_status(spec, self.returns) for spec in specs]
        if self.live is not None:
            from rich.text import Text

            self.live.update(Text("\n".join(lines)), refresh=True)
        else:
            for line in lines:
                print(line, file=sys.stderr, flush=True)

    def close(self) -> None:
        """Stop the live display, if there is one."""
        if self.live is not None:
            self.live.stop()
            self.live = None


def _last_line(path: Path) -> str:
    """The last non-empty line of a child's output file (``""`` if none)."""
    try:
        lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return ""
    return lines[-1].strip() if lines else ""


def run_all(
    specs: Sequence[RunSpec],
    jobs: int = 1,
    log: Callable[[str], None] = print,
    status: bool = True,
    imports: Sequence[str] = (),
    on_done: Callable[[RunSpec], None] | None = None,
    returns: bool = True,
    on_end: Callable[[RunSpec, bool], Sequence[RunSpec]] | None = None,
    more: Callable[[], Sequence[RunSpec]] | None = None,
    drop: Callable[[RunSpec], bool] | None = None,
    time_limit: float | None = None,
) -> list[RunSpec]:
    """Train (or resume) every unfinished run, ``jobs`` processes at a time; returns the failed runs.

    A new run's configuration is written to ``<run>/config.request.json`` and its process started as
    ``pimbrl train --config <that file> --run-dir <run> --quiet``; an interrupted run is resumed
    (``pimbrl resume <run>``). Each child's thread pools are sized to its ``threads``
    (:func:`pinned_environment`). A child's output goes to ``<run>/compare.log``. With ``status``, one line
    per running child is shown on stderr (:func:`child_status`). ``imports``: the ``--import`` arguments each
    child gets (the modules or files that declare a user's system). ``on_done(spec)`` is called as each run
    finishes well (while the others train). ``returns=False``: the status lines leave the returns out (a
    confirmatory study's).

    For a queue of studies (:func:`~.engine.run_studies`): ``on_end(spec, ok)`` is called as each run ends
    (``ok``: it finished well; a run a signal stopped while the driver goes on is not ok), also for a run
    that is already finished when it comes up, and returns runs to make next, which go before every run
    still waiting; ``more()`` is called when a process is free and no run waits, and returns the next runs
    (none: the queue is done); a waiting run for which ``drop(spec)`` is true is not started (its study
    broke). Once a SIGTERM is noted no ``on_end`` is called: the driver stops.

    ``time_limit``: minutes after which no run starts and every running child is sent SIGTERM, as if the driver
    had got one; once they have ended (an RL run at its next episode end, checkpointed; a control run at once,
    back to its last saved stage) :class:`TimeLimitReached` is raised.
    """

    def waiting(batch: Sequence[RunSpec]) -> list[tuple[RunSpec, list[str]]]:
        out: list[tuple[RunSpec, list[str]]] = []
        todo = list(batch)
        while todo:
            spec = todo.pop(0)
            command = _command(spec, [*imports, *spec.imports])
            if command is not None:
                out.append((spec, command))
            elif on_end is not None:  # finished already: it ends here
                todo[:0] = on_end(spec, True)
        return out

    pending = waiting(specs)
    failed: list[RunSpec] = []
    running: list[tuple[RunSpec, subprocess.Popen, Any]] = []
    lines = _StatusLines(status and (bool(pending) or more is not None), returns)
    sigterm = _SigtermFlag()
    deadline = None if time_limit is None else time.monotonic() + 60.0 * time_limit
    try:
        while True:
            if deadline is not None and time.monotonic() >= deadline and sigterm.signum is None:
                log(f"time limit ({time_limit:g} minutes): the running runs are stopped at their next episode end")
                sigterm.signum, sigterm.by_time_limit = signal.SIGTERM, True
            sigterm.forward(running)  # a safe point: every child started so far gets it, then the driver stops
            while len(running) < max(1, jobs):
                while not pending and more is not None:  # a free process: the queue's next runs
                    batch = more()
                    if not batch:
                        more = None
                    pending = waiting(batch)
                if not pending:
                    break
                spec, cmd = pending.pop(0)
                if drop is not None and drop(spec):
                    continue
                log(f"start {spec.label} seed {spec.seed}: {' '.join(cmd[3:])}")
                Path(spec.path).mkdir(parents=True, exist_ok=True)
                # never through a link or into a file with other names (the run directory may be someone else's)
                fd = open_below(spec.path, CHILD_LOG, os.O_WRONLY | os.O_APPEND | os.O_CREAT, single_link=True)
                out = os.fdopen(fd, "ab")
                env = pinned_environment(spec.config.threads)
                running.append((spec, subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env), out))
            if not running:
                break
            time.sleep(0.5)
            sigterm.forward(running)
            for item in list(running):
                spec, proc, out = item
                if proc.poll() is None:
                    continue
                running.remove(item)
                out.close()
                if _stopped(proc.returncode):  # a signal stopped it (checkpointed where it could)
                    failed.append(spec)
                    log(_stopped_line(spec, proc.returncode))
                elif proc.returncode != 0:
                    failed.append(spec)
                    child_log = Path(spec.path) / CHILD_LOG
                    log(
                        f"FAILED {spec.label} seed {spec.seed} (exit code {proc.returncode}): {_last_line(child_log)} "
                        f"(its output: {child_log}); the others go on"
                    )
                else:
                    log(f"done {spec.label} seed {spec.seed}")
                    if on_done is not None:
                        on_done(spec)
                if on_end is not None and sigterm.signum is None:  # a noted SIGTERM: the driver stops, nothing ends
                    pending[:0] = waiting(on_end(spec, proc.returncode == 0))
            lines.show([spec for spec, _, _ in running])
    except KeyboardInterrupt:
        if not sigterm.by_time_limit:
            raise
        raise TimeLimitReached(time_limit or 0.0) from None  # once the children ended (below)
    finally:
        sigterm.restore()
        lines.close()
        for spec, proc, out in running:  # interrupted: the children got the signal (they checkpoint); wait for them
            proc.wait()
            out.close()
            if _stopped(proc.returncode):
                log(_stopped_line(spec, proc.returncode))
    return failed


def _command(spec: RunSpec, imports: Sequence[str]) -> list[str] | None:
    """The child's command line for ``spec`` (``None``: the run is finished).

    A new run's configuration is written to ``<run>/config.request.json`` and trained from it; an interrupted
    one is resumed.
    """
    imported = [arg for module in imports for arg in ("--import", module)]
    run_status = RunDirectory(spec.path).status
    if run_status == "finished":
        return None
    if run_status is not None:
        return [sys.executable, "-m", "pimbrl.cli", "resume", str(spec.path), "--quiet", *imported]
    request = Path(spec.path) / REQUEST_FILE
    atomic_write_bytes(request, (json.dumps(config_to_dict(spec.config), indent=2) + "\n").encode())
    train = ["train", "--config", str(request), "--run-dir", str(spec.path), "--quiet"]
    return [sys.executable, "-m", "pimbrl.cli", *train, *imported]


def _stopped(returncode: int) -> bool:
    """Whether a child's exit status says a SIGINT or SIGTERM stopped it (handled: 130, 143; or not: -2, -15)."""
    return returncode in STOPPED_STATUSES or -returncode in (signal.SIGINT, signal.SIGTERM)


def _stopped_line(spec: RunSpec, returncode: int) -> str:
    """The driver's line for a child a signal stopped."""
    return (
        f"stopped {spec.label} seed {spec.seed} (exit code {returncode}): the same command again resumes it "
        "from its last checkpoint"
    )


class _SigtermFlag:
    """While the driver runs, a SIGTERM sent to it alone is noted, then passed on to its children at a safe point.

    Ctrl-C reaches the whole process group; ``kill PID`` or a scheduler's SIGTERM may reach the driver only, and
    the children would train on unrecorded. The handler only notes the signal; :meth:`forward`, called where no
    child is being started, sends it to every running child (each stops at its next episode end with a
    checkpoint, :mod:`pimbrl.training.stopping`; one that got it already ignores the copy) and interrupts the
    driver, which then waits for them. Off the main thread, or where SIGTERM is ignored or handled outside
    Python, nothing is installed.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        #: the signal was set by :func:`run_all`'s time limit, not sent
        self.by_time_limit = False
        self.previous: Any = take_signal(signal.SIGTERM, self._note)

    def _note(self, signum: int, frame: Any) -> None:
        self.signum = signum

    def forward(self, running: list[tuple[RunSpec, subprocess.Popen, Any]]) -> None:
        """Where a SIGTERM was noted: send it to every running child and raise KeyboardInterrupt."""
        if self.signum is None:
            return
        for _, proc, _ in running:
            if proc.poll() is None:
                proc.send_signal(self.signum)
        self.restore()  # a second SIGTERM ends the driver at once
        raise KeyboardInterrupt

    def restore(self) -> None:
        """The handler there was before (once)."""
        if self.previous is not None:
            signal.signal(signal.SIGTERM, self.previous)
            self.previous = None
