"""The final evaluation on the holdout pool: fresh draws that nothing during training plays.

A confirmatory study judges each run once, on states no evaluation, selection or switch has read
(``holdout_episodes``; :meth:`pimbrl.envs.task.Task.holdout_initial_states`). The final policy (or
controller) plays them after the last step; the returns go to ``holdout.json`` in the run directory with
the step they belong to, so that a resumed or extended run plays them again for its new final policy and
a finished one never twice.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..fileio import MAX_JSON_BYTES, UnsafeFileError, read_below, strict_json
from .rundir import RunDirectory

__all__ = ["HOLDOUT_FILE", "holdout_summary", "read_holdout", "write_holdout"]

HOLDOUT_FILE = "holdout.json"


def write_holdout(run_dir: RunDirectory, step: int, returns: np.ndarray, lengths: np.ndarray) -> dict[str, Any]:
    """Write the holdout episodes' returns at real step ``step`` atomically; returns the payload."""
    returns = np.asarray(returns, dtype=float)
    if not np.isfinite(returns).all():
        raise FloatingPointError(
            f"{run_dir.path}: a holdout episode's return is not finite; the final policy blew the system up "
            "(its test evaluations in evaluations.csv show where)"
        )
    payload = {
        "step": int(step),
        "episodes": len(returns),
        "return_mean": float(returns.mean()),
        "return_std": float(returns.std()),
        "returns": returns.tolist(),
        "lengths": np.asarray(lengths, dtype=int).tolist(),
    }
    run_dir.write_json(HOLDOUT_FILE, payload)
    return payload


def read_holdout(run_dir: RunDirectory, step: int | None = None) -> dict[str, Any] | None:
    """The holdout evaluation of ``run_dir`` (of real step ``step`` where given), else ``None``.

    A file that is not one pimbrl wrote (not strict JSON, wrong types, a mean that disagrees with its
    returns) is a :class:`~pimbrl.fileio.UnsafeFileError` naming it.
    """
    path = run_dir.path / HOLDOUT_FILE
    try:
        raw = read_below(run_dir.path, HOLDOUT_FILE, MAX_JSON_BYTES)
    except FileNotFoundError:
        return None
    payload = strict_json(raw, path)
    returns = payload.get("returns") if isinstance(payload, dict) else None
    ok = (
        isinstance(payload, dict)
        and isinstance(payload.get("step"), int)
        and isinstance(returns, list)
        and len(returns) > 0
        and all(isinstance(r, (int, float)) and not isinstance(r, bool) for r in returns)
        and isinstance(payload.get("return_mean"), (int, float))
        and payload.get("episodes") == len(returns)
    )
    if not ok or not math.isclose(
        float(np.mean(returns or [math.nan])), float(payload["return_mean"]), rel_tol=1e-9, abs_tol=1e-12
    ):
        raise UnsafeFileError(
            f"{path}: not a holdout evaluation pimbrl wrote; restore it from a copy (a run plays its holdout pool once: "
            "deleting the file and resuming the run plays it again, which a confirmatory study must report)"
        )
    if step is not None and payload["step"] != step:
        return None  # an earlier final policy's (the run was extended since)
    return payload


def holdout_summary(run_dir: RunDirectory, step: int, episodes: int) -> dict[str, Any]:
    """The summary's holdout fields of a run at real step ``step`` that asks for ``episodes`` (none played: empty)."""
    holdout = read_holdout(run_dir, step) if episodes else None
    if holdout is None:
        return {}
    return {"holdout_return_mean": float(holdout["return_mean"]), "holdout_episodes": int(holdout["episodes"])}
