"""What model-based policy selection kept, against the latest policy, for runs trained with it.

For each run directory trained with ``--imagine.select-episodes`` this reads ``evaluations.csv`` and
``selection.csv`` (nothing is re-run) and prints and records:

* the mean test return of the latest policy, the best evaluation, the mean of the last five evaluations;
* the selected policy: its step and its test return (scored at its own evaluation, on states the selection
  never saw), and the first step and training wall-clock at which the test return reached ``--threshold``;
* the gap between the imagined return on the training initial states and the test return, per evaluation
  (the ``model_return_mean - return_mean`` column): with the equation as the model the imagined episodes
  are the simulator's, so the gap measures how much better the policy does on the states it trained from
  than on unseen ones;
* the means over the runs given.

Usage::

    python benchmarks/selection_summary.py R/seed0 R/seed1 R/seed2 --threshold -55 --name ks_selection
"""

from __future__ import annotations

import argparse
import csv
import statistics
from pathlib import Path

import _common


def _rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        raise SystemExit(f"{path} does not exist: was the run trained with --imagine.select-episodes N?")
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def summarise(run_dir: Path, threshold: float | None) -> dict:
    """The figures of one run (see the module docstring)."""
    evals = _rows(run_dir / "evaluations.csv")
    selection = _rows(run_dir / "selection.csv")
    if not evals or not selection:
        raise SystemExit(f"{run_dir}: no evaluations yet")
    steps = [int(float(r["step"])) for r in evals]
    test = [float(r["return_mean"]) for r in evals]
    wall = [float(r["wall_s"]) for r in evals]
    imagined = {int(float(r["step"])): float(r["model_return_mean"]) for r in selection}
    gaps = [(s, imagined[s] - t) for s, t in zip(steps, test, strict=True) if s in imagined]
    first = next((i for i, t in enumerate(test) if threshold is not None and t >= threshold), None)
    last = selection[-1]
    return {
        "run_dir": str(run_dir),
        "steps": steps[-1],
        "wall_s": wall[-1],
        "final_return": test[-1],
        "best_return": max(test),
        "last5_return": statistics.fmean(test[-5:]),
        "selected_step": int(float(last["selected_step"])),
        "selected_return": float(last["selected_return_mean"]),
        "steps_to_threshold": None if first is None else steps[first],
        "wall_s_to_threshold": None if first is None else wall[first],
        "gap_by_step": {str(s): g for s, g in gaps},
        "blown_up": sum(int(float(r["blown_up"])) for r in selection),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", type=Path)
    parser.add_argument("--threshold", type=float, default=None, help="report the first evaluation at or above it")
    parser.add_argument("--name", default=None, help="record benchmarks/results/<name>.json")
    args = parser.parse_args()
    runs = [summarise(d, args.threshold) for d in args.run_dirs]
    for r in runs:
        reached = (
            "—" if r["steps_to_threshold"] is None else f"{r['steps_to_threshold']:,d} ({r['wall_s_to_threshold'] / 60:.1f} min)"
        )
        gaps = list(r["gap_by_step"].values())
        print(
            f"{r['run_dir'][-30:]:>30}  {r['steps']:,d} steps {r['wall_s'] / 60:5.1f} min  final {r['final_return']:7.2f}  "
            f"best {r['best_return']:7.2f}  last5 {r['last5_return']:7.2f}  selected {r['selected_return']:7.2f} "
            f"(step {r['selected_step']:,d})  first at threshold {reached}  gap first/last {gaps[0]:+.1f}/{gaps[-1]:+.1f}"
        )
    keys = ("final_return", "best_return", "last5_return", "selected_return")
    means = {k: statistics.fmean(r[k] for r in runs) for k in keys}
    ranges = {k: [min(r[k] for r in runs), max(r[k] for r in runs)] for k in keys}
    print("mean over runs: " + ", ".join(f"{k} {means[k]:.2f} [{ranges[k][0]:.2f}, {ranges[k][1]:.2f}]" for k in keys))
    if args.name:
        path = _common.record(args.name, {"threshold": args.threshold, "runs": runs, "mean": means, "range": ranges})
        print(f"recorded {path}")


if __name__ == "__main__":
    main()
