"""`pimbrl compare`: every method and seed on one environment, then one figure and one table.

Each (method, seed) is a run directory ``DIR/<method>/seed<k>`` trained in its own process; finished runs
are skipped, interrupted ones resumed, so re-running the command only does what is missing. The method
``mfrl-matched`` is MFRL with the agent-update budget of the model-based runs (their update-to-data
ratio), which separates the effect of the model from the effect of more updates.

Every run's configuration is resolved here, as a :class:`~pimbrl.training.TrainConfig`, before anything
starts. A new run's child process gets it as a file, ``DIR/<method>/seed<k>/config.request.json``
(``pimbrl train --config FILE``); the run's ``config.json`` then records the same configuration.

Overrides common to all runs (``{"total_steps": 5000, "fit.steps": 5}``, the arguments after
``--`` of ``pimbrl compare``) go to every run they apply to: a ``fit.*`` override goes to the methods that
fit a model and not to the mfrl ones, an agent field of SAC only to SAC runs, and so on
(:func:`~pimbrl.training.config.inapplicable_reason`). An override that applies to none of the runs is an
error.

A run directory that already holds a run (finished or interrupted) is reused only if its configuration
is the one requested; otherwise :func:`compare` stops with an error naming the run and the fields that
differ, and ``rerun=True`` (``pimbrl compare --rerun``) moves such a run aside, to
``DIR/<method>/seed<k>.replaced-<time>``, and trains it again.

While the runs train, one status line per running child (steps done of the budget, last test return,
steps per second) is read from its run directory and shown on stderr: refreshed every few seconds on a
terminal, as plain lines at most every 30 s otherwise. Each child's own output goes to
``DIR/<method>/seed<k>/compare.log``.

Outputs: ``curves.png`` (per method: the mean over seeds of the mean test return, with the band from the
lowest to the highest test episode of any seed), ``summary.csv`` (per run and per method: steps to the
threshold, final and best mean test return, wall-clock, updates and the update-to-data ratio) and
``summary.json`` (the same plus the PiMBRL/MBRL and PiMBRL/MFRL step ratios).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import MAX_SEED, ConfigError
from ..fileio import UnsafeFileError, atomic_write_bytes, check_below, open_below
from ..training.cli_args import parse_train_args
from ..training.config import (
    TrainConfig,
    applicable_overrides,
    config_from_dict,
    config_to_dict,
    did_you_mean,
    resolve_config,
    run_names,
    typed_overrides,
)
from ..training.methods import METHODS
from ..training.rundir import RunDirectory

__all__ = [
    "CHILD_LOG",
    "COMPARE_LOCK",
    "COMPARE_METHODS",
    "MAX_SEEDS",
    "REQUEST_FILE",
    "RunSpec",
    "check_reuse",
    "child_status",
    "compare",
    "config_differences",
    "lock_comparison",
    "plan_runs",
    "run_all",
    "step_ratio",
    "summarize_method",
    "summarize_runs",
]

COMPARE_METHODS = (*METHODS, "mfrl-matched")
#: the most seeds one comparison runs (planning more would take minutes before the first error)
MAX_SEEDS = 10_000
#: the file in a new run's directory that hands its configuration to the child process
REQUEST_FILE = "config.request.json"
#: the file in a run's directory that takes its child process's output
CHILD_LOG = "compare.log"
#: the lock file of a comparison's directory (one comparison runs there at a time)
COMPARE_LOCK = "compare.lock"
#: seconds between status refreshes: on a terminal, and as plain lines otherwise
STATUS_EVERY_TTY = 2.0
STATUS_EVERY_PLAIN = 30.0


@dataclass(frozen=True)
class RunSpec:
    """One run to make: its directory and its configuration."""

    label: str  # method label, e.g. "pimbrl" or "mfrl-matched"
    seed: int
    path: Path
    config: TrainConfig


def _as_overrides(overrides: Mapping[str, Any] | Sequence[str] | None) -> dict[str, Any]:
    """Typed overrides; a list of `pimbrl train` flags (the old form) is parsed."""
    if overrides is None:
        return {}
    if isinstance(overrides, Mapping):
        return typed_overrides(overrides)
    return parse_train_args([str(a) for a in overrides])


def plan_runs(
    env_id: str,
    methods: Sequence[str],
    seeds: Sequence[int],
    root: Path,
    overrides: Mapping[str, Any] | Sequence[str] | None = None,
    preset: str | None = None,
) -> list[RunSpec]:
    """The runs of a comparison, each with its resolved configuration.

    ``overrides`` (field paths -> values, or `pimbrl train` flags) go to every run they apply to; one that
    applies to none is a :class:`ConfigError` with the reason. ``mfrl-matched`` takes the update-to-data
    ratio of the model-based preset unless ``overrides`` set ``utd``. A seed given twice is a
    ``ValueError`` (it would be one run counted as two seeds).
    """
    overrides = _as_overrides(overrides)
    for key in ("method", "seed"):
        if key in overrides:
            raise ConfigError(f"compare sets {key} itself (--methods, --seeds); it cannot be overridden")
    if not seeds:
        raise ValueError("a comparison needs at least one seed")
    bad = [s for s in seeds if isinstance(s, bool) or not isinstance(s, int)]
    if bad:
        raise ConfigError(f"seed must be an integer, got {bad[0]!r}")
    if len(seeds) > MAX_SEEDS:
        raise ValueError(f"{len(seeds):,} seeds are more than a comparison runs ({MAX_SEEDS:,} at most); give fewer")
    seen: set[int] = set()
    for s in seeds:  # each seed is one run directory: a repeated seed would be one run counted as two seeds
        if s in seen:
            raise ValueError(f"seed {s} is given twice in the seeds; give each seed once")
        seen.add(s)
    root = Path(root)
    specs = []
    used: set[str] = set()
    reasons: dict[str, str] = {}
    agent = run_names(env_id, overrides, preset)[1]
    for label in methods:
        if label not in COMPARE_METHODS:
            raise ValueError(
                f"unknown method {label!r}{did_you_mean(label, COMPARE_METHODS)}: choose from {', '.join(COMPARE_METHODS)}"
            )
        method = "mfrl" if label == "mfrl-matched" else label
        fields: dict[str, Any] = {"method": method}
        if label == "mfrl-matched":  # the user's utd wins
            fields["utd"] = resolve_config(env_id, {"method": "pimbrl"}, preset=preset).utd
        applied = applicable_overrides(env_id, method, agent, overrides, reasons)
        fields.update(applied)
        used.update(applied)
        first = resolve_config(env_id, {**fields, "seed": seeds[0]}, preset=preset)  # checked once per method
        for seed in seeds:
            if not 0 <= seed <= MAX_SEED:
                raise ConfigError(f"seed must be in [0, {MAX_SEED:,}], got {seed}")
            specs.append(RunSpec(label, seed, root / label / f"seed{seed}", dataclasses.replace(first, seed=seed)))
    unused = [reasons[k] for k in overrides if k not in used]
    if unused:
        raise ConfigError(f"{'; '.join(unused)} (methods compared: {', '.join(methods)})")
    return specs


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
            f"{root} is in use by another pimbrl compare ({holder}); wait for it to end, or give another --run-dir "
            "(two comparisons in one directory would each summarise the other's unfinished runs)"
        ) from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}: {' '.join(sys.argv)}\n".encode(), 0)
    except OSError:
        pass  # the lock holds without the description
    return fd


def check_reuse(specs: Sequence[RunSpec], rerun: bool = False, log: Callable[[str], None] = print) -> None:
    """Refuse to reuse a run (finished or interrupted) whose configuration is not the requested one.

    Raises :class:`ConfigError` naming the first such run directory and the fields that differ; with
    ``rerun`` each such run is moved aside (to ``<dir>.replaced-<time>``, under its lock) so that it is trained
    again. A run whose lock another process holds (training, resumed, extended) is a :class:`ConfigError`
    whatever its configuration: it is never moved, replaced or resumed from here.
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
    if not stale:
        return
    if not rerun:
        spec, diffs = stale[0]
        more = f" (and {len(stale) - 1} more run(s) of this comparison)" if len(stale) > 1 else ""
        raise ConfigError(
            f"{spec.path} holds a run made with another configuration: {', '.join(diffs)}{more}; add --rerun to move "
            "such runs aside and train them again, or choose another --run-dir"
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


def child_status(spec: RunSpec) -> str:
    """One status line of a running child, read from its run directory.

    ``"pimbrl seed 0: 12,400/200,000 steps  test return -63.20  41 steps/s"`` (what is known so far).
    """
    head = f"{spec.label} seed {spec.seed}: "
    evaluation = _last_row(spec.path / "evaluations.csv")
    metrics = _last_row(spec.path / "metrics.csv")
    episode = _last_row(spec.path / "episodes.csv")
    steps = [v for v in (_number(r, "step") for r in (evaluation, metrics, episode)) if v is not None]
    if not steps:
        return head + "starting"
    parts = [f"{int(max(steps)):,d}/{spec.config.total_steps:,d} steps"]
    test = _number(evaluation, "return_mean")
    if test is not None:
        parts.append(f"test return {test:.2f}")
    sps = _number(metrics, "steps_per_s")
    if sps is not None:
        parts.append(f"{sps:,.0f} steps/s")
    return head + "  ".join(parts)


class _StatusLines:
    """The running children's status lines on stderr: a live display on a terminal, plain lines otherwise."""

    def __init__(self, enabled: bool) -> None:
        from rich.console import Console

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
        lines = [child_status(spec) for spec in specs]
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
) -> list[RunSpec]:
    """Train (or resume) every unfinished run, ``jobs`` processes at a time; returns the failed runs.

    A new run's configuration is written to ``<run>/config.request.json`` and its process started as
    ``pimbrl train --config <that file> --run-dir <run> --quiet``; an interrupted run is resumed
    (``pimbrl resume <run>``). A child's output goes to ``<run>/compare.log``. With ``status``, one line
    per running child is shown on stderr (:func:`child_status`). ``imports``: the ``--import`` arguments each
    child gets (the modules or files that declare a user's system).
    """
    pending = []
    imported = [arg for spec in imports for arg in ("--import", spec)]
    for spec in specs:
        run_status = RunDirectory(spec.path).status
        if run_status == "finished":
            continue
        if run_status is None:
            request = Path(spec.path) / REQUEST_FILE
            atomic_write_bytes(request, (json.dumps(config_to_dict(spec.config), indent=2) + "\n").encode())
            cmd = [
                sys.executable,
                "-m",
                "pimbrl.cli",
                "train",
                "--config",
                str(request),
                "--run-dir",
                str(spec.path),
                "--quiet",
                *imported,
            ]
        else:
            cmd = [sys.executable, "-m", "pimbrl.cli", "resume", str(spec.path), "--quiet", *imported]
        pending.append((spec, cmd))
    failed: list[RunSpec] = []
    running: list[tuple[RunSpec, subprocess.Popen, Any]] = []
    lines = _StatusLines(status and bool(pending))
    try:
        while pending or running:
            while pending and len(running) < max(1, jobs):
                spec, cmd = pending.pop(0)
                log(f"start {spec.label} seed {spec.seed}: {' '.join(cmd[3:])}")
                Path(spec.path).mkdir(parents=True, exist_ok=True)
                # never through a link or into a file with other names (the run directory may be someone else's)
                fd = open_below(spec.path, CHILD_LOG, os.O_WRONLY | os.O_APPEND | os.O_CREAT, single_link=True)
                out = os.fdopen(fd, "ab")
                running.append((spec, subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT), out))
            time.sleep(0.5)
            for item in list(running):
                spec, proc, out = item
                if proc.poll() is None:
                    continue
                running.remove(item)
                out.close()
                if proc.returncode != 0:
                    failed.append(spec)
                    child_log = Path(spec.path) / CHILD_LOG
                    log(
                        f"FAILED {spec.label} seed {spec.seed} (exit code {proc.returncode}): {_last_line(child_log)} "
                        f"(its output: {child_log}); the others go on"
                    )
                else:
                    log(f"done {spec.label} seed {spec.seed}")
            lines.show([spec for spec, _, _ in running])
    finally:
        lines.close()
        for _, proc, out in running:  # interrupted: the children get the same signal; wait for them
            proc.wait()
            out.close()
    return failed


def summarize_runs(specs: Sequence[RunSpec], threshold: float | None) -> dict[str, Any]:
    """Per-run and per-method results of finished (or partly finished) runs."""
    runs = []
    for spec in specs:
        result = RunDirectory(spec.path).result(threshold)
        if result is not None:
            runs.append({"method": spec.label, "seed": spec.seed, **result})
    methods = {
        label: summarize_method([r for r in runs if r["method"] == label]) for label in dict.fromkeys(r["method"] for r in runs)
    }
    ratios = {}
    pim = methods.get("pimbrl", {})
    for other in ("mbrl", "mfrl", "mfrl-matched"):
        if other in methods and pim:
            ratios[f"pimbrl/{other}"] = step_ratio(pim, methods[other])
    return {"threshold": threshold, "runs": runs, "methods": methods, "ratios": ratios}


def summarize_method(mine: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate of the runs of one method (each a ``RunDirectory.result`` with its seed)."""
    reached = [r["steps_to_threshold"] for r in mine if r["steps_to_threshold"] is not None]
    return {
        "seeds": len(mine),
        "reached": len(reached),
        "steps_to_threshold_mean": float(np.mean(reached)) if len(reached) == len(mine) and reached else None,
        "steps_to_threshold": [r["steps_to_threshold"] for r in mine],
        "wall_s_to_threshold": [r.get("wall_s_to_threshold") for r in mine],
        # a run that never reached the threshold needed more than its budget: the mean with those runs
        # counted at their budget is a lower bound on the mean steps to the threshold
        "steps_to_threshold_lower_bound": float(
            np.mean([r["steps"] if r["steps_to_threshold"] is None else r["steps_to_threshold"] for r in mine])
        ),
        **median_steps_to_threshold(mine),
        "max_steps": max(r["steps"] for r in mine),
        "final_return_mean": float(np.mean([r["final_return"] for r in mine])),
        "wall_s_mean": float(np.mean([r["wall_s"] for r in mine])),
        "update_to_data": float(np.mean([r["update_to_data"] for r in mine])),
    }


def median_steps_to_threshold(mine: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The median over runs of the steps to the threshold, where runs that never reached it are censored.

    A run that never reached the threshold needed more than its budget (``steps``). Counting such runs at
    their budgets gives a lower bound on the median, counting them at infinity an upper bound; where the two
    agree the median is measured (``steps_to_threshold_median``), else it lies above the first
    (``steps_to_threshold_median_above``) and at most at the second where that is finite
    (``steps_to_threshold_median_at_most``, else ``None``). All three ``None`` for no runs.
    """
    reached = [float(r["steps_to_threshold"]) for r in mine if r["steps_to_threshold"] is not None]
    budgets = [float(r["steps"]) for r in mine if r["steps_to_threshold"] is None]
    out: dict[str, Any] = {
        "steps_to_threshold_median": None,
        "steps_to_threshold_median_above": None,
        "steps_to_threshold_median_at_most": None,
    }
    if not mine:
        return out
    low = float(np.median(reached + budgets))
    high = float(np.median(reached + [math.inf] * len(budgets)))
    if low == high:
        out["steps_to_threshold_median"] = low
    else:
        out["steps_to_threshold_median_above"] = low
        out["steps_to_threshold_median_at_most"] = high if math.isfinite(high) else None
    return out


def steps_text(measured: float | None, above: float | None, at_most: float | None = None) -> str:
    """Steps to a threshold as measured (``"55,000"``) or bounded (``"> 400,000"``, ``"> 50,000 and <= 60,000"``).

    For one run (``above``: its budget where it did not reach the threshold) or a median of
    :func:`median_steps_to_threshold`; ``"unknown"`` where nothing bounds it.
    """
    if measured is not None:
        return f"{measured:,.0f}"
    if above is None:
        return "unknown"
    return f"> {above:,.0f}" + ("" if at_most is None else f" and <= {at_most:,.0f}")


def step_ratio(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Ratio of the mean steps to the threshold, a/b, and the ratio of the medians.

    Where some runs of b never reached the threshold, they count at their budget, which makes the ratio
    an upper bound. The ratio of the medians (``median``, see :func:`median_steps_to_threshold`) is a
    measurement where both medians are measured; an upper bound (a's measured median or its upper bound,
    over b's measured median or its lower bound) where either is censored; ``None`` where a's median has
    no upper bound (its middle run did not reach the threshold).
    """
    result: dict[str, Any]
    if a["steps_to_threshold_mean"] is None:
        result = {"value": None, "note": "pimbrl did not reach the threshold on every seed"}
    elif b["steps_to_threshold_mean"] is None:
        result = {
            "value": a["steps_to_threshold_mean"] / b["steps_to_threshold_lower_bound"],
            "note": f"upper bound: {b['seeds'] - b['reached']} of {b['seeds']} seeds did not reach it, counted at their budget",
        }
    else:
        result = {"value": a["steps_to_threshold_mean"] / b["steps_to_threshold_mean"], "note": "mean over seeds"}
    a_med, b_med = a.get("steps_to_threshold_median"), b.get("steps_to_threshold_median")
    a_high = a_med if a_med is not None else a.get("steps_to_threshold_median_at_most")
    b_low = b_med if b_med is not None else b.get("steps_to_threshold_median_above")
    if a_med is not None and b_med is not None:
        median = {"value": a_med / b_med, "note": "ratio of the medians over seeds"}
    elif a_high is None:
        median = {"value": None, "note": "the first method's median run did not reach the threshold: no upper bound"}
    elif b_low is None:
        median = {"value": None, "note": "the second method has no runs"}
    else:
        why = "the other method's median run did not reach it" if b_med is None else "the first method's median is censored"
        median = {
            "value": a_high / b_low,
            "note": f"upper bound on the ratio of the medians ({why}; runs that did not reach it counted at their budgets)",
        }
    result["median"] = median
    return result


def ratio_lines(ratios: dict[str, dict[str, Any]], missing: str = "-") -> list[str]:
    """One line per ratio of a summary (``name: value (note)``), each followed by its ratio of the medians.

    ``missing`` stands for a ratio that is unknown (``-`` on a terminal, ``—`` in Markdown).
    """
    lines = []
    for name, r in ratios.items():
        for label, ratio in ((name, r), (f"{name}, medians", r.get("median"))):
            if ratio is not None:
                value = missing if ratio["value"] is None else f"{ratio['value']:.3f}"
                lines.append(f"{label}: {value} ({ratio['note']})")
    return lines


def write_outputs(result: dict[str, Any], root: Path, env_id: str) -> None:
    """``summary.csv``, ``summary.json`` and ``curves.png`` in ``root``."""
    lines = ["method,seed,steps_to_threshold,wall_s_to_threshold,final_return,best_return,wall_s,updates,update_to_data"]
    for r in result["runs"]:
        s2t = "" if r["steps_to_threshold"] is None else r["steps_to_threshold"]
        w2t = "" if r.get("wall_s_to_threshold") is None else f"{r['wall_s_to_threshold']:.1f}"
        lines.append(
            f"{r['method']},{r['seed']},{s2t},{w2t},{r['final_return']!r},{r['best_return']!r},{r['wall_s']:.1f},"
            f"{r['updates']},{r['update_to_data']:.3f}"
        )
    for label, m in result["methods"].items():
        s2t = m["steps_to_threshold_mean"]
        if s2t is None:  # some runs never reached it: a lower bound, written as ">=N"
            s2t = f">={m['steps_to_threshold_lower_bound']:.0f}" if m["reached"] else ""
        lines.append(f"{label},mean,{s2t},,{m['final_return_mean']!r},,{m['wall_s_mean']:.1f},,{m['update_to_data']:.3f}")
    atomic_write_bytes(root / "summary.csv", ("\n".join(lines) + "\n").encode())
    slim = {**result, "runs": [{k: v for k, v in r.items() if k != "curve"} for r in result["runs"]], "env": env_id}
    atomic_write_bytes(root / "summary.json", (json.dumps(slim, indent=2, allow_nan=False) + "\n").encode())
    plot_method_curves(result, root / "curves.png", env_id)


def plot_method_curves(result: dict[str, Any], path: Path, title: str) -> None:
    from ..plotting import plot_learning_curves, seed_band

    curves = [seed_band(label, [r["curve"] for r in result["runs"] if r["method"] == label]) for label in result["methods"]]
    plot_learning_curves(curves, path, title=title, threshold=result["threshold"])


def compare(
    env_id: str,
    methods: Sequence[str],
    seeds: Sequence[int],
    root: str | Path,
    overrides: Mapping[str, Any] | Sequence[str] | None = None,
    jobs: int = 1,
    threshold: float | None = None,
    log: Callable[[str], None] = print,
    run: bool = True,
    rerun: bool = False,
    status: bool = True,
    imports: Sequence[str] = (),
    preset: str | None = None,
) -> dict[str, Any]:
    """Run (what is missing of) a comparison and write its figure and tables.

    ``preset`` names the system's recipe every run starts from (``None``: its default).

    With ``run=False`` nothing is started: the runs are summarised as they stand (unfinished ones up to
    their last evaluation). A run directory holding a run of another configuration is an error, or, with
    ``rerun``, moved aside and trained again (:func:`check_reuse`). ``status``: live status lines of the
    running children on stderr.

    ``overrides``: field paths -> values (``{"total_steps": 5000, "fit.steps": 5}``; a list of
    `pimbrl train` flags is read as such), applied to the runs they fit (see :func:`plan_runs`).
    ``threshold`` is the return the summaries count as solved (default: the preset's); to also record it
    in the runs' configurations, add it to ``overrides``.
    """
    root = Path(root)
    specs = plan_runs(env_id, methods, seeds, root, overrides, preset)  # every configuration checked before anything runs
    for spec in specs:  # DIR/<method>/seed<k>: no link on the way below DIR (it would lead the runs elsewhere)
        check_below(root, spec.path.relative_to(root), "directory")
    lock = None
    try:
        if run:
            root.mkdir(parents=True, exist_ok=True)
            lock = lock_comparison(root)  # before any run is looked at: one comparison runs in a directory at a time
            check_reuse(specs, rerun=rerun, log=log)
        failed = run_all(specs, jobs=jobs, log=log, status=status, imports=imports) if run else []
    finally:
        if lock is not None:
            os.close(lock)  # releases the lock
    if threshold is None:
        threshold = resolve_config(env_id, {"method": "mfrl"}, preset=preset).threshold
    result = summarize_runs(specs, threshold)
    result["failed"] = [f"{s.label}/seed{s.seed}" for s in failed]
    if result["runs"]:
        write_outputs(result, root, env_id)
    return result
