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

import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..config import ConfigError
from ..fileio import atomic_write_bytes, check_below
from ..training.cli_args import parse_train_args
from ..training.config import resolve_config, typed_overrides
from ..training.methods import METHODS
from ..training.rundir import RunDirectory
from .engine import env_directory, plan_study, run_study
from .runner import (
    CHILD_LOG,
    COMPARE_LOCK,
    REQUEST_FILE,
    RunSpec,
    check_reuse,
    child_status,
    config_differences,
    lock_comparison,
    run_all,
)
from .spec import MATCHED, MAX_SEEDS, StudySpec, parse_spec, spec_to_yaml
from .stats import censored_median

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
    "compare_spec",
    "config_differences",
    "lock_comparison",
    "plan_runs",
    "run_all",
    "step_ratio",
    "summarize_method",
    "summarize_runs",
]

COMPARE_METHODS = (*METHODS, MATCHED)


def _as_overrides(overrides: Mapping[str, Any] | Sequence[str] | None) -> dict[str, Any]:
    """Typed overrides; a list of `pimbrl train` flags (the old form) is parsed."""
    if overrides is None:
        return {}
    if isinstance(overrides, Mapping):
        return typed_overrides(overrides)
    return parse_train_args([str(a) for a in overrides])


def compare_spec(
    env_id: str,
    methods: Sequence[str],
    seeds: Sequence[int],
    overrides: Mapping[str, Any] | Sequence[str] | None = None,
    preset: str | None = None,
    threshold: float | None = None,
    imports: Sequence[str] = (),
) -> StudySpec:
    """The study spec a comparison is: one system, the methods as arms, the seeds, the shared overrides.

    Its text (``DIR/study.yaml``) is what `pimbrl study run` and `pimbrl study report` read. The seeds and
    methods are checked as every spec's are (:func:`~pimbrl.experiments.spec.parse_spec`).
    """
    overrides = _as_overrides(overrides)
    for key in ("method", "seed"):
        if key in overrides:
            raise ConfigError(f"compare sets {key} itself (--methods, --seeds); it cannot be overridden")
    others = [m for m in methods if m != "pimbrl"]
    data: dict[str, Any] = {
        "name": f"compare-{env_directory(env_id)}",
        "question": f"{', '.join(methods)} on {env_id} (written by pimbrl compare)",
        "systems": [env_id],
        "seeds": list(seeds),  # each seed once, each an integer in range: checked by the spec's parser
        "methods": list(dict.fromkeys(methods)),
        "layout": "compact",
        "comparisons": [["pimbrl", m] for m in others] if "pimbrl" in methods else [],
    }
    if preset is not None:
        data["preset"] = preset
    if overrides:
        data["overrides"] = json.loads(json.dumps(overrides))  # tuples as lists: plain YAML
    if threshold is not None:
        data["thresholds"] = [float(threshold)]
    if imports:
        data["imports"] = [str(Path(i).resolve()) if i.endswith(".py") else i for i in imports]
    text = spec_to_yaml(data)
    return parse_spec(data, where="compare", text=text)


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
    spec = compare_spec(env_id, methods, seeds, overrides, preset)
    return [RunSpec(r.arm, r.seed, r.path, r.config) for r in plan_study(spec, Path(root))]


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
    median = censored_median([r["steps_to_threshold"] for r in mine], [r["steps"] for r in mine])
    return {
        "steps_to_threshold_median": median["median"],
        "steps_to_threshold_median_above": median["above"],
        "steps_to_threshold_median_at_most": median["at_most"],
    }


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
    # no best_return: a maximum over test evaluations is never a result
    lines = ["method,seed,steps_to_threshold,wall_s_to_threshold,final_return,wall_s,updates,update_to_data"]
    for r in result["runs"]:
        s2t = "" if r["steps_to_threshold"] is None else r["steps_to_threshold"]
        w2t = "" if r.get("wall_s_to_threshold") is None else f"{r['wall_s_to_threshold']:.1f}"
        lines.append(
            f"{r['method']},{r['seed']},{s2t},{w2t},{r['final_return']!r},{r['wall_s']:.1f},"
            f"{r['updates']},{r['update_to_data']:.3f}"
        )
    for label, m in result["methods"].items():
        s2t = m["steps_to_threshold_mean"]
        if s2t is None:  # some runs never reached it: a lower bound, written as ">=N"
            s2t = f">={m['steps_to_threshold_lower_bound']:.0f}" if m["reached"] else ""
        lines.append(f"{label},mean,{s2t},,{m['final_return_mean']!r},{m['wall_s_mean']:.1f},,{m['update_to_data']:.3f}")
    atomic_write_bytes(root / "summary.csv", ("\n".join(lines) + "\n").encode())
    slim = {
        **result,
        "runs": [{k: v for k, v in r.items() if k not in ("curve", "best_return")} for r in result["runs"]],
        "env": env_id,
    }
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
    replicas: bool = True,
) -> dict[str, Any]:
    """Run (what is missing of) a comparison and write its figure and tables.

    ``preset`` names the system's recipe every run starts from (``None``: its default). ``replicas``: as
    :func:`~.engine.run_study`'s (a seed-free controller trains two seeds and copies the first where they agree).

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
    spec = compare_spec(env_id, methods, seeds, overrides, preset, threshold, imports)
    specs = [RunSpec(r.arm, r.seed, r.path, r.config) for r in plan_study(spec, root)]  # all checked before anything runs
    for run_spec in specs:  # DIR/<method>/seed<k>: no link on the way below DIR (it would lead the runs elsewhere)
        check_below(root, run_spec.path.relative_to(root), "directory")
    failed: list[str] = []
    if run:
        root.mkdir(parents=True, exist_ok=True)
        record = run_study(spec, root, jobs=jobs, rerun=rerun, replicas=replicas, status=status, log=log)
        failed = record["failed"]
    if threshold is None:
        threshold = resolve_config(env_id, {"method": "mfrl"}, preset=preset).threshold
    result = summarize_runs(specs, threshold)
    result["failed"] = failed
    if result["runs"]:
        write_outputs(result, root, env_id)
    return result
