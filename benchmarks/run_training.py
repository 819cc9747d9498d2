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
import json
import subprocess
import sys
import time
from pathlib import Path

import _common  # noqa: F401  (pins threads first)

from pimbrl.training import RunDirectory, steps_to_threshold


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
    pending = []
    for seed in seeds:
        run = out / f"seed{seed}"
        cfg_path = run / "config.json"
        if cfg_path.exists() and json.loads(cfg_path.read_text()).get("status") == "finished":
            continue
        if cfg_path.exists():
            cmd = [sys.executable, "-m", "pimbrl.cli", "resume", str(run), "--quiet"]
        else:
            cmd = [
                sys.executable,
                "-m",
                "pimbrl.cli",
                "train",
                args.env,
                "--seed",
                str(seed),
                "--run-dir",
                str(run),
                "--threads",
                "1",
                "--quiet",
                *extra,
            ]
        pending.append(cmd)
    running: list[subprocess.Popen] = []
    while pending or running:
        while pending and len(running) < args.jobs:
            cmd = pending.pop(0)
            print("$", " ".join(cmd), flush=True)
            running.append(subprocess.Popen(cmd))
        time.sleep(1.0)
        for p in list(running):
            if p.poll() is not None:
                running.remove(p)
                if p.returncode != 0:
                    print(f"run failed with exit code {p.returncode}: {' '.join(p.args)}", file=sys.stderr)
    rows = []
    for seed in seeds:
        run = RunDirectory(out / f"seed{seed}")
        payload = run.read_config()
        evals = run.evaluations.read()
        threshold = payload["config"].get("threshold")
        summary = payload.get("summary", {})
        rows.append(
            {
                "seed": seed,
                "steps_to_threshold": steps_to_threshold(evals, threshold),
                "final_return_mean": float(evals[-1]["return_mean"]),
                "best_return_mean": max(float(r["return_mean"]) for r in evals),
                "wall_s": summary.get("wall_s"),
                "updates": summary.get("updates"),
                "threshold": threshold,
            }
        )
        r = rows[-1]
        print(
            f"seed {seed}: steps to {threshold} = {r['steps_to_threshold']}, final {r['final_return_mean']:.2f}, "
            f"best {r['best_return_mean']:.2f}, wall {r['wall_s']:.0f} s"
        )
    reached = [r["steps_to_threshold"] for r in rows if r["steps_to_threshold"] is not None]
    print(f"reached the threshold: {len(reached)}/{len(rows)} seeds; steps {reached}")
    _common.record(args.name or out.name, {"env": args.env, "train_args": extra, "runs": rows})


if __name__ == "__main__":
    main()
