"""Run `pimbrl train` for one environment over several seeds and summarise the learning benchmark.

Each run is a separate process (`pimbrl train ... --threads 1`), `--jobs` of them at a time; finished runs
are not redone (their run directories are reused). Prints and records, per seed: steps to the threshold,
final and best mean test return, wall-clock; then the aggregate.

Usage, e.g.::

    python benchmarks/run_training.py pendulum --seeds 0,1,2 --out-dir benchmarks/runs/td3-pendulum
    python benchmarks/run_training.py Pendulum-v1 --seeds 0,1,2 --out-dir benchmarks/runs/td3-pendulum-v1
    python benchmarks/run_training.py cartpole --seeds 0,1,2 --out-dir benchmarks/runs/td3-cartpole

Extra arguments after ``--`` go to `pimbrl train` unchanged.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import _common

from pimbrl.experiments.compare import RunSpec, run_all
from pimbrl.training import RunDirectory
from pimbrl.training.cli_args import config_from_argv


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("env")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--out-dir", required=True)
    parser.add_argument("--jobs", type=int, default=1, help="runs in parallel (one thread each)")
    parser.add_argument("--name", default=None, help="name of the recorded result (default: out-dir name)")
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    args = parser.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    out = Path(args.out_dir)
    seeds = [int(s) for s in args.seeds.split(",")]
    specs = [
        RunSpec("mfrl", seed, out / f"seed{seed}", config_from_argv([args.env, "--seed", str(seed), "--threads", "1", *extra]))
        for seed in seeds
    ]
    failed = run_all(specs, jobs=args.jobs)  # finished runs are skipped, interrupted ones resumed
    rows = []
    for spec in specs:
        run = RunDirectory(spec.path)
        res = run.result()
        if res is None:  # failed before its first evaluation: report it, keep the others
            print(f"seed {spec.seed}: no evaluations in {spec.path}; left out", file=sys.stderr)
            continue
        threshold = run.read_config()["config"].get("threshold")
        rows.append(
            {
                "seed": spec.seed,
                "steps_to_threshold": res["steps_to_threshold"],
                "final_return_mean": res["final_return"],
                "best_return_mean": res["best_return"],
                "wall_s": res["wall_s"],
                "updates": res["updates"],
                "threshold": threshold,
            }
        )
        r = rows[-1]
        print(
            f"seed {spec.seed}: steps to {threshold} = {r['steps_to_threshold']}, final {r['final_return_mean']:.2f}, "
            f"best {r['best_return_mean']:.2f}, wall {r['wall_s']:.0f} s"
        )
    reached = [r["steps_to_threshold"] for r in rows if r["steps_to_threshold"] is not None]
    print(f"reached the threshold: {len(reached)}/{len(rows)} seeds; steps {reached}")
    _common.record(args.name or out.name, {"env": args.env, "train_args": extra, "runs": rows})
    if failed:
        sys.exit(f"{len(failed)} run(s) failed: {', '.join(str(s.path) for s in failed)}")


if __name__ == "__main__":
    main()
