"""Gradient MPC on a system's validation draws: how its horizon and iterations were chosen (never on test states).

    python benchmarks/mpc_validation.py ks 80 10 0.1 1 50      # env horizon iterations lr n_intermediate episodes

Plays :class:`pimbrl.control.mpc.GradientMPC` with the known equation's coarse scheme from the first
``episodes`` validation initial states (KS: its validation pool, disjoint from the training and test pools),
one thread, and appends the mean return, its spread and the inference cost to
``benchmarks/results/mpc_validation.json``.
"""

from __future__ import annotations

import json
import sys
import time

import _common  # noqa: F401  (pins every thread pool to one thread first)
from _common import RESULTS, machine

from pimbrl.control.base import play, task_of
from pimbrl.control.mpc import GradientMPC
from pimbrl.control.plant import make_plant
from pimbrl.systems import resolve_env_id


def main(argv: list[str]) -> None:
    name, horizon, iterations, lr, n, episodes = argv[0], int(argv[1]), int(argv[2]), float(argv[3]), int(argv[4]), int(argv[5])
    env = resolve_env_id(name)
    task = task_of(env, {})
    mpc = GradientMPC(make_plant(task.physics, n), horizon, iterations, lr, 3 * iterations, task.max_episode_steps)
    start = time.perf_counter()
    result = play(env, {}, mpc, task.validation_initial_states(episodes))
    row = {
        "env": env,
        "horizon": horizon,
        "iterations": iterations,
        "first_iterations": 3 * iterations,
        "lr": lr,
        "n_intermediate": n,
        "validation_episodes": episodes,
        "return_mean": result.mean,
        "return_std": float(result.returns.std()),
        "inference_s_per_step": result.inference_s_per_step,
        "wall_s": time.perf_counter() - start,
        "machine": machine(),
        "command": "python benchmarks/mpc_validation.py " + " ".join(argv),
    }
    print(json.dumps(row, indent=2))
    path = RESULTS / "mpc_validation.json"
    rows = json.loads(path.read_text())["runs"] if path.exists() else []
    path.write_text(json.dumps({"runs": [*rows, row]}, indent=2) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
