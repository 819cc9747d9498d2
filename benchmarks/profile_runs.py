"""Where a training run's wall-clock goes, phase by phase, from the timings every run logs.

Every run's ``metrics.csv`` carries the cumulative seconds of each phase of the loop (``time/<phase>_s``:
env_step, model_train, model_check, imagine, agent_update, evaluate, select, checkpoint; a phase a run
did not log is left out); this prints, per run
directory, each phase's seconds and share of the total, the seconds per 1,000 real steps and the
milliseconds per agent update, and the mean over the runs given. The remainder (``other``) is the loop's
own bookkeeping: logging, batch assembly outside the timed phases. Each run's entry carries its own
``provenance`` (the commit and CPU of the process that last trained it, from its ``config.json``).

Timings of runs that shared the cores with others are those of a loaded machine; compare shares and
ratios within one set of runs, not absolute seconds across sessions.

Usage::

    python benchmarks/profile_runs.py runs/ks/pimbrl/seed0 runs/ks/pimbrl/seed1 --name profile_ks_pimbrl
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
from pathlib import Path

import _common

from pimbrl.training import PHASES


def profile(run_dir: Path) -> dict:
    """Phase seconds and derived figures of one run directory (its last ``metrics.csv`` row)."""
    with open(run_dir / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise SystemExit(f"{run_dir}: metrics.csv has no rows yet")
    last = rows[-1]
    steps = int(float(last["step"]))
    wall = float(last["wall_s"])
    updates = int(float(last["agent_updates"]))
    phases = {p: float(last[f"time/{p}_s"]) for p in PHASES if last.get(f"time/{p}_s") not in (None, "")}
    phases["other"] = max(wall - sum(phases.values()), 0.0)
    written = json.loads((run_dir / "config.json").read_text())
    config = written["config"]
    return {
        "run": str(run_dir),
        "method": config["method"],
        "env": config["env"],
        # the machine and code the run itself trained on (its last process's), beside the record's own
        "provenance": written.get("provenance"),
        "steps": steps,
        "agent_updates": updates,
        "wall_s": wall,
        "phase_s": phases,
        "phase_share": {p: s / wall for p, s in phases.items()},
        "s_per_1000_steps": 1000 * wall / max(steps, 1),
        "ms_per_agent_update": 1000 * phases.get("agent_update", 0.0) / max(updates, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+")
    parser.add_argument("--name", default=None, help="record as benchmarks/results/<name>.json")
    args = parser.parse_args()
    runs = [profile(Path(d)) for d in args.run_dirs]
    names = [*PHASES, "other"]
    print(f"{'run':>40} " + " ".join(f"{p:>13}" for p in names) + "   s/1k steps  ms/update")
    for r in runs:
        cells = " ".join(f"{r['phase_s'].get(p, 0.0):7.0f} ({r['phase_share'].get(p, 0.0):3.0%})" for p in names)
        print(f"{r['run'][-40:]:>40} {cells}   {r['s_per_1000_steps']:10.1f}  {r['ms_per_agent_update']:9.2f}")
    mean_share = {p: statistics.mean(r["phase_share"].get(p, 0.0) for r in runs) for p in names}
    print(f"{'mean share':>40} " + " ".join(f"{mean_share[p]:13.0%}" for p in names))
    if args.name:
        _common.record(args.name, {"runs": runs, "mean_share": mean_share})


if __name__ == "__main__":
    main()
