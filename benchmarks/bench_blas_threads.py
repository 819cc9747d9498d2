"""controlgym's Burgers (a numpy simulator) with numpy's OpenBLAS pool at its default size and pinned to one thread.

Each measurement is a fresh child process that makes the env, takes 20 warm-up steps and times ``--steps``
steps of random actions (wall-clock and CPU seconds of the process, all its threads): once with the thread
variables (``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``) removed, so that OpenBLAS starts
its pool of one thread per core, and once with them at 1, as a study's children start
(``pimbrl.experiments.runner.pinned_environment``). The two alternate ``--repeats`` times; the fastest of each
is kept, and their ratio is the figure (measured in this one run, so it holds on this machine). What else
shares the cores changes it most: say it with ``--load``.

    python benchmarks/bench_blas_threads.py --load "two study processes"   # benchmarks/results/blas_threads.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import _common  # noqa: F401  (pins this process's pools; the children get their own environment)
from _common import REPOSITORY, add_load_argument, record

from pimbrl.experiments.runner import THREAD_VARIABLES

CHILD = """
import json, sys, time
sys.path.insert(0, {benchmarks!r})
import numpy as np
from controlgym_systems import ControlGymPDE
env = ControlGymPDE("burgers")
env.reset(seed=0)
rng = np.random.default_rng(0)
for _ in range(20):
    env.step(rng.uniform(-1.0, 1.0, env.pde.n_action))
wall, cpu = time.perf_counter(), time.process_time()
for _ in range({steps}):
    env.step(rng.uniform(-1.0, 1.0, env.pde.n_action))
print(json.dumps({{"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu}}))
"""


def measure(steps: int, pinned: bool) -> dict[str, float]:
    """One child's seconds for ``steps`` steps, its pools at their default size or at one thread."""
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    if pinned:
        env.update(dict.fromkeys(THREAD_VARIABLES, "1"))
    code = CHILD.format(benchmarks=str(REPOSITORY / "benchmarks"), steps=steps)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200, help="timed steps per measurement")
    parser.add_argument("--repeats", type=int, default=3, help="measurements of each setting, alternating")
    add_load_argument(parser)
    args = parser.parse_args()
    runs: dict[str, list[dict[str, float]]] = {"default_pool": [], "one_thread": []}
    for _ in range(args.repeats):
        runs["default_pool"].append(measure(args.steps, pinned=False))
        runs["one_thread"].append(measure(args.steps, pinned=True))
    best = {name: {k: min(r[k] for r in rs) for k in ("wall_s", "cpu_s")} for name, rs in runs.items()}
    ratio = best["default_pool"]["wall_s"] / best["one_thread"]["wall_s"]
    for name, b in best.items():
        print(f"{name:>12}: {args.steps} steps in {b['wall_s']:.2f} s wall, {b['cpu_s']:.2f} s CPU (fastest of {args.repeats})")
    print(f"default pool / one thread, wall-clock: {ratio:.2f}")
    path = record(
        "blas_threads",
        {"env": "controlgym/Burgers-v0", "steps": args.steps, "cores": os.cpu_count(), "runs": runs, "best": best,
         "wall_ratio_default_over_one_thread": ratio},
        load=args.load,
    )  # fmt: skip
    print(f"recorded in {Path(path).relative_to(REPOSITORY)}")


if __name__ == "__main__":
    main()
