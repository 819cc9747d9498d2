"""Seed-free runs: a controller whose runs cannot differ between seeds runs twice, and its other seeds copy it.

Feedback and gradient MPC with a given model (the known equation, or a fixed prior; nothing identified
from random transitions) draw no random number: their evaluations are the same states, planned the same
way, for every seed. A study still gives such an arm as many runs as the arms it is compared with (so
that each comparison has the runs a verdict needs), but training ten identical KS MPC runs costs ten
times an hour for nothing new.

So the engine runs the first two seeds of such an arm. Where the two agree on every episode of every pool
(returns, lengths, scheme transitions), each further seed's directory is a copy of the first's. The copy
holds its own seed in ``config.json`` and names its source under ``replicate_of``; the record keeps that
name with the run. Where the two probes differ, or a copy cannot be made, the other seeds run as usual. The
test checks what the argument above says should hold; a controller that did use its seed would fail it.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..fileio import MAX_JSON_BYTES, read_below, strict_json
from ..training.rundir import RunDirectory
from .archive import copy_run_files

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
    groups: dict[tuple[str, str, str], list[StudyRun]] = {}
    for run in runs:
        if seed_free(run):
            groups.setdefault((run.system, run.arm, run.setting_text), []).append(run)
    waiting = {r.path for r in todo if not r.path.exists()}
    out: dict[Path, tuple[StudyRun, StudyRun]] = {}
    for group in groups.values():
        if len(group) < 3:
            continue
        first, second, *rest = group
        out.update({r.path: (first, second) for r in rest if r.path in waiting})
    return out


def _episodes(run: StudyRun) -> dict[str, Any] | None:
    """A finished controller run's episodes per pool without their timings (``None`` unless finished and readable)."""
    rd = RunDirectory(run.path)
    try:
        if rd.status != "finished" or rd.holder() is not None:
            return None
        state = strict_json(read_below(run.path, "control.json", MAX_JSON_BYTES), run.path / "control.json")
    except (OSError, ValueError):  # missing, damaged or planted: no copy (the seeds train)
        return None
    if not isinstance(state, dict):
        return None
    out = {}
    for pool, body in state.items():
        if isinstance(body, dict) and "chunks" in body:
            chunks = body["chunks"]
            if not isinstance(chunks, list) or not all(isinstance(c, dict) for c in chunks):
                return None
            out[pool] = [{k: v for k, v in c.items() if k not in _TIMINGS} for c in chunks]
    return out


def same_episodes(first: StudyRun, second: StudyRun) -> bool:
    """Whether two finished controller runs played the same episodes with the same outcomes, exactly."""
    a, b = _episodes(first), _episodes(second)
    return a is not None and a == b and bool(a)


#: the files a finished controller run holds that a copy takes (regular files only; nothing else is read)
_COPIED = ("config.json", "config.request.json", "control.json", "evaluations.csv", "holdout.json", "episodes.csv")


def replicate(source: StudyRun, target: StudyRun, checked: StudyRun, root: Path) -> None:
    """Make ``target``'s run directory a copy of ``source``'s with ``target``'s seed, naming both probes.

    ``root``: the study's directory (the names of the probes are relative to it). Only the run's own regular
    files are copied, each read without following a link and within its size bound; the copy is assembled
    beside the target and renamed into place, so a crash leaves no half-made run. Raises ``OSError`` or
    ``ValueError`` (the caller trains that seed instead) where the source is not a finished run's files or the
    target exists.
    """

    def edit(name: str, data: bytes) -> bytes:
        if name not in ("config.json", "config.request.json"):
            return data
        payload = strict_json(data, source.path / name)
        if not isinstance(payload, dict) or (name == "config.json" and not isinstance(payload.get("config"), dict)):
            raise ValueError(f"{source.path / name} is not a run's configuration")
        if name == "config.json":
            payload["config"]["seed"] = target.seed
            payload[REPLICA_KEY] = {
                "source": os.path.relpath(source.path, root),
                "checked_against": os.path.relpath(checked.path, root),
                "why": "a seed-free controller: its first two seeds played every episode identically",
            }
        else:
            payload["seed"] = target.seed
        return (json.dumps(payload, indent=2) + "\n").encode()

    copy_run_files(source.path, target.path, _COPIED, edit)
