"""`pimbrl model-eval` with its defaults: is the physics-informed model better out of sample, per seed?

Runs ``pimbrl model-eval ENV --labels L --seeds S`` with nothing else set (the physics loss with the training's
defaults: every source the system offers, control-step units) and records, per seed, the one-step next-state
MSE of the data-only and the physics-informed model, in and out of sample, and their ratio, in
``benchmarks/results/model_eval_defaults_<env>_<labels>.json``. An existing study in ``--run-dir`` is read
instead of run again. One torch thread (the command's default).

    python benchmarks/model_eval_defaults.py cartpole --labels 400 --seeds 3 --run-dir DIR
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

import _common


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("env")
    parser.add_argument("--labels", type=int, default=400)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--run-dir", required=True)
    _common.add_load_argument(parser)
    args = parser.parse_args()
    out = Path(args.run_dir)
    cmd = ["pimbrl", "model-eval", args.env, "--labels", str(args.labels), "--seeds", str(args.seeds), "--run-dir", str(out)]
    if not (out / "study.json").exists():
        subprocess.run([sys.executable, "-m", "pimbrl.cli", *cmd[1:]], check=True)
    study = json.loads((out / "study.json").read_text())
    with open(out / "study.csv") as fh:
        rows = [r for r in csv.DictReader(fh) if r["horizon"] == "1"]
    per_seed = []
    for seed in sorted({int(r["seed"]) for r in rows}):
        mse = {(r["model"], r["split"]): float(r["mean"]) for r in rows if int(r["seed"]) == seed}
        entry = {"seed": seed}
        for split in ("in", "out"):
            entry[f"data_{split}"] = mse[("data", split)]
            entry[f"physics_{split}"] = mse[("physics", split)]
            entry[f"ratio_{split}"] = mse[("data", split)] / mse[("physics", split)]
        per_seed.append(entry)
        print(
            f"seed {seed}: out of sample data {entry['data_out']:.3e}  physics {entry['physics_out']:.3e}  "
            f"ratio {entry['ratio_out']:.1f}x;  in sample ratio {entry['ratio_in']:.2f}x"
        )
    ratios = [e["ratio_out"] for e in per_seed]
    print(f"out-of-sample ratio data/physics: {min(ratios):.1f}x to {max(ratios):.1f}x over {len(ratios)} seeds")
    _common.record(
        f"model_eval_defaults_{args.env}_{args.labels}",
        {
            "command": " ".join([*cmd[:-1], "DIR"]),
            "env": args.env,
            "labels": args.labels,
            "sources": study["sources"],
            "units": study["units"],
            "network": study["model_kind"],
            "per_seed": per_seed,
            "ratio_out_min": min(ratios),
            "ratio_out_max": max(ratios),
            "wall_s": study["wall_s"],
        },
        load=args.load,
    )


if __name__ == "__main__":
    main()
