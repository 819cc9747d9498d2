"""Seed-free runs: a controller whose runs cannot differ between seeds runs twice, and its other seeds copy it.

Feedback and gradient MPC with a given model (the known equation, or a fixed prior; nothing identified
from random transitions) draw no random number: their evaluations are the same states, planned the same
way, for every seed. A study still gives such an arm as many runs as the arms it is compared with (so
that each comparison has the runs a verdict needs), but training ten identical KS MPC runs costs ten
times an hour for nothing new.

So the engine runs the first two seeds of such an arm. Where the two agree on every episode of every pool
(returns, lengths, scheme transitions), each further seed's directory is a copy of the first's. The copy
holds its own seed in ``config.json`` and names its source under ``replicate_of``; the record keeps that
name with the run. Where the two probes differ, nothing is copied: the other seeds run as usual. The test
is a measurement, not an assumption: an environment with noise of its own fails it.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..fileio import atomic_write_bytes, read_below
from ..training.rundir import RunDirectory

if TYPE_CHECKING:
    from .engine import StudyRun

__all__ = ["REPLICA_KEY", "plan_replicas", "replicate", "same_episodes", "seed_free"]

#: the key of ``config.json`` naming a copied run's source (and the probe it was checked against)
REPLICA_KEY = "replicate_of"
#: what a controller run records per pool; the timings are left out of the comparison
_TIMINGS = ("inference_s", "wall_s")


def seed_free(run: StudyRun) -> bool:
    """Whether ``run`` draws no random number: feedback, or MPC that identifies no coefficient."""
    method = run.config.method
    if method.name == "feedback":
        return True
    return method.name == "mpc" and not method.learn.coefficients  # type: ignore[union-attr]


def plan_replicas(runs: Sequence[StudyRun], todo: Sequence[StudyRun]) -> dict[Path, tuple[StudyRun, StudyRun]]:
    """The runs of ``todo`` to copy if their arm's first two seeds agree: run path -> (first, second seed's run).

    Only seed-free arms with three or more seeds, and only runs not started yet (no directory): a started
    run resumes as itself.
    """
    groups: dict[tuple[str, str, Any], list[StudyRun]] = {}
    for run in runs:
        if seed_free(run):
            groups.setdefault((run.system, run.arm, run.setting), []).append(run)
    waiting = {r.path for r in todo if not r.path.exists()}
    out: dict[Path, tuple[StudyRun, StudyRun]] = {}
    for group in groups.values():
        if len(group) < 3:
            continue
        first, second, *rest = group
        out.update({r.path: (first, second) for r in rest if r.path in waiting})
    return out


def _episodes(run: StudyRun) -> dict[str, Any] | None:
    """A finished controller run's episodes per pool without their timings (``None`` unless finished)."""
    rd = RunDirectory(run.path)
    if rd.status != "finished" or rd.holder() is not None:
        return None
    try:
        state = json.loads(read_below(run.path, "control.json", 64 << 20))
    except (FileNotFoundError, ValueError):
        return None
    pools = {k: v for k, v in state.items() if isinstance(v, dict) and "chunks" in v}
    return {pool: [{k: v for k, v in c.items() if k not in _TIMINGS} for c in body["chunks"]] for pool, body in pools.items()}


def same_episodes(first: StudyRun, second: StudyRun) -> bool:
    """Whether two finished controller runs played the same episodes with the same outcomes, exactly."""
    a, b = _episodes(first), _episodes(second)
    return a is not None and a == b and bool(a)


def replicate(source: StudyRun, target: StudyRun, checked: StudyRun, root: Path) -> None:
    """Make ``target``'s run directory a copy of ``source``'s with ``target``'s seed, naming both probes.

    ``root``: the study's directory (the names of the probes are relative to it).

    The copy is assembled beside the target and renamed into place: a crash leaves no half-made run.
    """
    parent = target.path.parent
    parent.mkdir(parents=True, exist_ok=True)
    staging = parent / f".{target.path.name}.replica"
    if staging.exists():
        shutil.rmtree(staging)
    shutil.copytree(source.path, staging, symlinks=True, ignore=shutil.ignore_patterns("run.lock", "*.log"))
    for name in ("config.json", "config.request.json"):
        if not (staging / name).is_file():
            continue
        payload = json.loads(read_below(staging, name, 16 << 20))
        if name == "config.json":
            payload["config"]["seed"] = target.seed
            payload[REPLICA_KEY] = {
                "source": os.path.relpath(source.path, root),
                "checked_against": os.path.relpath(checked.path, root),
                "why": "a seed-free controller: its first two seeds played every episode identically",
            }
        else:
            payload["seed"] = target.seed
        atomic_write_bytes(staging / name, (json.dumps(payload, indent=2) + "\n").encode())
    os.replace(staging, target.path)
