"""Gradient MPC on a system's validation draws: how its horizon and iterations were chosen (never on test states).

    python benchmarks/mpc_validation.py burgers 20 5 0.1 5 20   # system horizon iterations lr n_intermediate episodes

Plays :class:`pimbrl.control.mpc.GradientMPC` with the known equation's coarse scheme from the first
``episodes`` validation initial states (KS: its validation pool, disjoint from the training and test pools),
one thread, and records the mean return, its spread and the inference cost in
``benchmarks/results/mpc_validation_<system>_h<horizon>_i<iterations>_n<n>_lr<lr>_e<episodes>.json``
(``--name`` another; an existing record is never overwritten), with the machine, the commit and the
measurement spec (:func:`_common.record`). The three records of 2026-11-28 were written by the version before,
whose names had neither ``lr`` nor ``episodes``.

Records written before 2026-11-28 are the rows of ``mpc_validation.json``: copied from a probe script's
printout, with the CPU model and no commit.
"""

from __future__ import annotations

import argparse
import re
import time

import _common  # noqa: F401  (pins every thread pool to one thread first)
from _common import RESULTS, add_load_argument, record

from pimbrl.control.base import play, task_of
from pimbrl.control.mpc import GradientMPC
from pimbrl.control.plant import make_plant
from pimbrl.systems import resolve_env_id


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("system")
    parser.add_argument("horizon", type=int)
    parser.add_argument("iterations", type=int)
    parser.add_argument("lr", type=float)
    parser.add_argument("n_intermediate", type=int)
    parser.add_argument("episodes", type=int)
    parser.add_argument("--name", default=None, help="record benchmarks/results/<name>.json")
    add_load_argument(parser)
    args = parser.parse_args()
    system = re.sub(r"[^A-Za-z0-9+\-]+", "-", args.system).strip("-")
    default = f"mpc_validation_{system}_h{args.horizon}_i{args.iterations}_n{args.n_intermediate}_lr{args.lr:g}_e{args.episodes}"
    name = args.name or default
    if (RESULTS / f"{name}.json").exists():
        parser.error(f"benchmarks/results/{name}.json exists: pass --name NAME to record this run under another name")
    env = resolve_env_id(args.system)
    task = task_of(env, {})
    plant = make_plant(task.physics, args.n_intermediate)
    mpc = GradientMPC(plant, args.horizon, args.iterations, args.lr, 3 * args.iterations, task.max_episode_steps)
    start = time.perf_counter()
    result = play(env, {}, mpc, task.validation_initial_states(args.episodes))
    row = {
        "env": env,
        "horizon": args.horizon,
        "iterations": args.iterations,
        "first_iterations": 3 * args.iterations,
        "lr": args.lr,
        "n_intermediate": args.n_intermediate,
        "validation_episodes": args.episodes,
        "return_mean": result.mean,
        "return_std": float(result.returns.std()),
        "inference_s_per_step": result.inference_s_per_step,
        "wall_s": time.perf_counter() - start,
    }
    print(", ".join(f"{k} {v}" for k, v in row.items()))
    print(f"recorded {record(name, row, load=args.load)}")


if __name__ == "__main__":
    main()
