"""Steps to a threshold of one group of runs against another, with runs that never reached it censored.

Each group is a list of run directories (``--a``, ``--b``) or the runs of one method in a record written by
``pimbrl compare`` / ``collect_results.py`` (``--b-record FILE --b-method mfrl``; their run directories may be
gone). For every run: the first evaluation whose mean test return reaches ``--threshold`` (nothing is
re-run). Printed and recorded:

* per run: the seed, steps to the threshold (or "not within" its budget);
* per group: how many reached it, the mean with non-reachers at their budget (a lower bound), and the
  median, which is a measurement where the middle run(s) reached it and bounded otherwise
  (:func:`pimbrl.experiments.compare.median_steps_to_threshold`);
* the ratio a/b of the medians (measured, an upper bound, or unknown) and, for each seed in both groups
  where both runs reached it, the per-seed ratio.

Usage::

    python benchmarks/steps_ratio.py --a R/seed0 R/seed1 R/seed2 --b-record benchmarks/results/compare_ks.json \
        --b-method mfrl --threshold -55 --name ks_steps_ratio
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import _common

from pimbrl.experiments.compare import step_ratio, steps_text, summarize_method
from pimbrl.training import RunDirectory


def from_dirs(paths: list[Path], threshold: float) -> list[dict[str, Any]]:
    """One record per run directory: its seed and what :meth:`RunDirectory.result` reads."""
    runs = []
    for path in paths:
        run_dir = RunDirectory(path)
        result = run_dir.result(threshold)
        if result is None:
            raise SystemExit(f"{path} holds no evaluated run (no config.json or no evaluations yet)")
        result.pop("curve")
        runs.append({"run_dir": str(path), "seed": int(run_dir.read_config()["config"]["seed"]), **result})
    return runs


def from_record(path: Path, method: str, threshold: float) -> list[dict[str, Any]]:
    """The runs of ``method`` in a comparison record, which must have been summarised at ``threshold``."""
    data = json.loads(path.read_text())
    if data.get("threshold") != threshold:
        raise SystemExit(f"{path} was summarised at threshold {data.get('threshold')}, not {threshold}: re-collect it")
    runs = [dict(r) for r in data["runs"] if r["method"] == method]
    if not runs:
        raise SystemExit(f"{path} holds no runs of {method!r} (it has {sorted({r['method'] for r in data['runs']})})")
    for r in runs:
        r.pop("curve", None)
    return runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--a", nargs="+", type=Path, required=True, help="run directories of the first group")
    ap.add_argument("--b", nargs="+", type=Path, help="run directories of the second group")
    ap.add_argument("--b-record", type=Path, help="or: a comparison record holding the second group's runs")
    ap.add_argument("--b-method", help="the method of --b-record's runs to take")
    ap.add_argument("--threshold", type=float, required=True)
    ap.add_argument("--name", default=None, help="record benchmarks/results/<name>.json")
    args = ap.parse_args()
    if (args.b is None) == (args.b_record is None) or (args.b_record is not None) != (args.b_method is not None):
        ap.error("give --b DIR ..., or --b-record FILE with --b-method METHOD")
    a = from_dirs(args.a, args.threshold)
    b = from_dirs(args.b, args.threshold) if args.b else from_record(args.b_record, args.b_method, args.threshold)
    groups = {"a": summarize_method(a), "b": summarize_method(b)}
    ratio = step_ratio(groups["a"], groups["b"])
    by_seed = {r["seed"]: r for r in b}
    paired = {
        r["seed"]: r["steps_to_threshold"] / by_seed[r["seed"]]["steps_to_threshold"]
        for r in a
        if r["seed"] in by_seed and r["steps_to_threshold"] is not None and by_seed[r["seed"]]["steps_to_threshold"] is not None
    }
    for name, runs in (("a", a), ("b", b)):
        g = groups[name]
        cells = [f"seed {r['seed']}: {steps_text(r['steps_to_threshold'], r['steps'])}" for r in runs]
        median = steps_text(
            g["steps_to_threshold_median"], g["steps_to_threshold_median_above"], g["steps_to_threshold_median_at_most"]
        )
        print(f"{name}: reached {g['reached']}/{g['seeds']}; median {median}; " + "; ".join(cells))
    med = ratio["median"]
    print(f"a/b, medians: {'-' if med['value'] is None else format(med['value'], '.3f')} ({med['note']})")
    for seed, value in paired.items():
        print(f"a/b, seed {seed}: {value:.3f}")
    if args.name:
        path = _common.record(
            args.name,
            {"threshold": args.threshold, "a": a, "b": b, "groups": groups, "ratio": ratio, "paired_by_seed": paired},
        )
        print(f"recorded {path}")


if __name__ == "__main__":
    main()
