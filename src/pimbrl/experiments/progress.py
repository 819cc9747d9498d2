"""A study's progress without its outcomes.

Which runs have finished, are running, were interrupted or have not started, how far each has come, and
about how much compute is left. ``pimbrl study status SPEC`` prints it. It reads each run's state, its step
count and its wall-clock, and never a return: a confirmatory study can be watched while it runs without
anyone reading its results early.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..training.control_run import dpc_progress
from ..training.methods import DPC
from ..training.rundir import RunDirectory
from .engine import StudyRun, plan_study
from .runner import dpc_steps_text
from .spec import StudySpec

__all__ = ["QueueTotals", "RunProgress", "progress_lines", "study_progress"]

#: a run's states, in the order the table lists them
STATES = ("finished", "running", "interrupted", "not started", "unreadable")


@dataclass(frozen=True)
class RunProgress:
    """Where one run of a study stands.

    Attributes:
        run: the planned run.
        state: ``finished``, ``running`` (another process holds its lock), ``interrupted`` (started, not
            finished, nobody writing it: ``pimbrl study run`` resumes it), ``not started`` or ``unreadable``
            (a damaged file: ``why`` says which).
        steps: its real steps at its last evaluation (0 before the first); a DPC run's gradient steps
            through the scheme so far (from its ``control.json``).
        wall_s: its training wall-clock so far in seconds (a finished run's whole), ``None`` before the first
            evaluation.
    """

    run: StudyRun
    state: str
    steps: int
    wall_s: float | None
    why: str = ""

    @property
    def total_steps(self) -> int:
        """The real steps the run is configured to take (a DPC run: its gradient steps through the scheme)."""
        method = self.run.config.method
        return int(method.iterations) if isinstance(method, DPC) else int(self.run.config.total_steps)

    @property
    def steps_text(self) -> str:
        """How far a running run has come: ``"1,200/3,000"``, ``"750/3,000 DPC steps"`` or ``"a controller"``."""
        if isinstance(self.run.config.method, DPC):
            return dpc_steps_text(self.steps, self.total_steps)
        return "a controller" if self.run.config.control else f"{self.steps:,}/{self.total_steps:,}"


def _progress(run: StudyRun) -> RunProgress:
    try:
        return _read_progress(run)
    except (OSError, ValueError) as exc:  # one damaged run is named; the others are still listed
        return RunProgress(run, "unreadable", 0, None, str(exc).splitlines()[0] if str(exc) else type(exc).__name__)


def _read_progress(run: StudyRun) -> RunProgress:
    rd = RunDirectory(run.path)
    try:
        payload = rd.read_config()
    except FileNotFoundError:
        return RunProgress(run, "not started", 0, None)
    if isinstance(run.config.method, DPC):  # no evaluations while it trains: its steps are in control.json
        steps, wall = dpc_progress(rd)
    else:
        rows = rd.evaluations.read()
        steps = int(float(rows[-1]["step"])) if rows else 0
        wall = float(rows[-1]["wall_s"]) if rows else None
    if rd.holder() is not None:
        state = "running"
    elif payload.get("status") == "finished":
        state = "finished"
        wall = float((payload.get("summary") or {}).get("wall_s", wall if wall is not None else math.nan))
    else:
        state = "interrupted"
    return RunProgress(run, state, steps, wall)


def study_progress(spec: StudySpec, root: str | Path, runs: Sequence[StudyRun] | None = None) -> list[RunProgress]:
    """Every planned run of ``spec`` under ``root`` with its state, steps and wall-clock (no returns).

    ``runs``: the study's plan where the caller has made it already (``plan_study(spec, root)``).
    """
    return [_progress(run) for run in (plan_study(spec, root) if runs is None else runs)]


def _kind(run: StudyRun) -> tuple[str, ...]:
    """What an RL run's wall-clock mostly follows: its system, method, agent, updates per real step and budget.

    An RL arm none of whose runs has finished is timed by the finished runs of arms of its kind (another
    learning rate, rollout length or physics weight of the same method): a rough figure, said so.
    """
    cfg = run.config
    agent = "" if cfg.control else f"{cfg.agent.name} utd {cfg.utd:g}"
    return (run.system, cfg.method.name, agent, f"{cfg.total_steps}")


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:,.1f} min"


@dataclass
class QueueTotals:
    """What several studies' estimates add up to (`pimbrl study status A B ...`): see :func:`progress_lines`."""

    left_s: float = 0.0  # CPU-seconds left that finished runs time
    untimed: list[str] = field(default_factory=list)  # "STUDY (arms no finished run times yet)"

    def line(self, studies: int, jobs: int) -> str:
        """``Queue of N studies: about X CPU-minutes left ...``."""
        text = (
            f"Queue of {studies} studies: about {self.left_s / 60:,.0f} CPU-minutes left that finished runs time, "
            f"{self.left_s / 60 / max(jobs, 1):,.0f} minutes at --jobs {jobs}"
        )
        return text + (f"; not timed yet: {'; '.join(self.untimed)}." if self.untimed else ".")


def progress_lines(
    spec: StudySpec, progress: Sequence[RunProgress], jobs: int = 1, totals: QueueTotals | None = None
) -> list[str]:
    """A table per arm and an estimate of the compute left, as lines of text (added to ``totals`` if given).

    The table gives each arm's finished, running (with steps), interrupted and unstarted runs and the mean
    wall-clock of its finished runs. The estimate charges each unfinished run its arm's mean finished
    wall-clock, less the fraction of steps it has done. An RL arm with no finished run is charged the mean of
    the finished runs of its kind (:func:`_kind`: another setting of its method), and named; a controller
    arm with none is named, not guessed.
    """
    counts = {s: sum(p.state == s for p in progress) for s in STATES}
    hide = spec.kind == "confirmatory"  # an arm's wall-clock can follow its episodes' lengths (Cart-Pole: its return)
    lines = [
        f"study {spec.name} ({spec.kind}): {len(progress)} runs; "
        + ", ".join(f"{n} {s}" for s, n in counts.items() if n or s != "unreadable"),
        "",
        "| arm | finished | running (steps) | interrupted | not started | wall per finished run |",
        "|---|---|---|---|---|---|",
    ]
    groups: dict[str, list[RunProgress]] = {}
    for p in progress:
        groups.setdefault(p.run.label(spec.compact), []).append(p)
    from .replicas import plan_replicas, same_episodes  # seeds a seed-free controller will copy cost nothing

    state = {p.run.path: p.state for p in progress}
    planned = plan_replicas([p.run for p in progress], [p.run for p in progress if p.state == "not started"])
    copies = {  # not where both probes have finished and disagree: those seeds train (as with --no-replicas)
        path for path, (a, b) in planned.items() if not (state[a.path] == state[b.path] == "finished" and not same_episodes(a, b))
    }
    left_s, unknown, borrowed = 0.0, [], []
    walls = {  # each finished run's wall-clock, read once
        p.run.path: p.wall_s for p in progress if p.state == "finished" and p.wall_s is not None and math.isfinite(p.wall_s)
    }
    kin: dict[tuple[str, ...], list[float]] = {}  # finished wall-clocks of every arm of one kind (see _kind)
    for p in progress:
        if p.run.path in walls:
            kin.setdefault(_kind(p.run), []).append(walls[p.run.path])
    for label, ps in groups.items():
        done = [walls[p.run.path] for p in ps if p.run.path in walls]
        mean = sum(done) / len(done) if done else None
        running = [p.steps_text for p in ps if p.state == "running"]
        cells = [
            label,
            f"{sum(p.state == 'finished' for p in ps)}/{len(ps)}",
            f"{len(running)} ({', '.join(running)})" if running else "0",
            str(sum(p.state == "interrupted" for p in ps)),
            str(sum(p.state == "not started" for p in ps)),
            "hidden (confirmatory)" if hide and mean is not None else _minutes(mean) if mean is not None else "—",
        ]
        lines.append("| " + " | ".join(cells) + " |")
        todo = [p for p in ps if p.state != "finished" and p.run.path not in copies]
        if todo and mean is None and not ps[0].run.config.control and kin.get(_kind(ps[0].run)):  # a controller's
            # cost follows its horizon (DPC at 10, 20, 40: 7, 14, 28 min on Burgers): never borrowed
            others = kin[_kind(ps[0].run)]
            mean = sum(others) / len(others)
            borrowed.append(label)
        if todo and mean is None:
            unknown.append(label)
        elif mean is not None:
            left_s += sum(mean * max(0.0, 1.0 - p.steps / max(p.total_steps, 1)) for p in todo)
    lines.append("")
    estimate = f"about {left_s / 60:,.0f} CPU-minutes left, {left_s / 60 / max(jobs, 1):,.0f} minutes at --jobs {jobs}"
    if borrowed:
        estimate += (
            f" ({', '.join(borrowed)} timed by the finished runs of the other settings of their method and agent, "
            "at the same budget)"
        )
    if unknown:
        estimate += (
            f", plus {', '.join(unknown)}, which no finished run times yet"
            f" (the spec's plan: {spec.plan.strip() if spec.plan else 'not stated'})"
        )
    if copies:
        estimate += (
            f"; {len(copies)} seed{'s' if len(copies) != 1 else ''} of seed-free controllers left out: copied if their "
            "first two seeds agree (not with --no-replicas)"
        )
    if totals is not None:
        totals.left_s += left_s
        if unknown:
            totals.untimed.append(f"{spec.name} ({', '.join(unknown)})")
    bad = [p for p in progress if p.state == "unreadable"]
    lines += [f"Unreadable: {p.run.path}: {p.why}" for p in bad] + ([""] if bad else [])
    lines += [
        f"Estimate: {estimate}.",
        "No return is shown: a study's outcomes are read from its record once it has finished (`pimbrl study report`).",
    ]
    return lines
