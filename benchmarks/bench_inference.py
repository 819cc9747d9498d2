"""Inference cost per control step: an RL policy (one network call), a DPC policy, gradient MPC; ratios in one run.

For each system: the TD3 actor of the default agent (a batch of states, deterministic), a DPC policy of the
default width, and one MPC control step (warm-started, after its first step), each timed at batch 1 (one
system being controlled) and at the size of the test batch. Seconds per control step and state; the ratio
MPC / RL is measured within this one process (one thread), so it holds on this machine, not its absolute
figures on another.

    python benchmarks/bench_inference.py            # writes benchmarks/results/inference_cost.json
"""

from __future__ import annotations

import argparse

import _common  # noqa: F401  (pins every thread pool to one thread first)
import numpy as np
import torch
from _common import add_load_argument, record, time_call

from pimbrl.agents import TD3Config, make_agent
from pimbrl.control.base import task_of
from pimbrl.control.dpc import DPCPolicy
from pimbrl.control.mpc import GradientMPC
from pimbrl.control.plant import make_plant

#: system, MPC settings (horizon, iterations, ETDRK4 steps per control step), test batch
SYSTEMS = {
    "pimbrl/KuramotoSivashinsky-v0": ((80, 10, 1), 200),
    "pimbrl/Burgers-v0": ((20, 5, 5), 100),
    "pimbrl/Pendulum-v0": ((20, 5, 5), 100),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_load_argument(parser)
    args = parser.parse_args()
    rows = []
    for env, ((horizon, iterations, n), batch) in SYSTEMS.items():
        task = task_of(env, {})
        states = task.validation_initial_states(min(batch, 50))
        states = np.concatenate([states] * (batch // len(states) + 1))[:batch]
        obs = task.observe(states, np.zeros(batch, dtype=np.int64))
        agent = make_agent(TD3Config(), obs.shape[1], task.physics.action_dim, seed=0)
        plant = make_plant(task.physics, n)
        dpc = DPCPolicy(plant, (256, 256), seed=0)
        row: dict[str, object] = {"env": env, "mpc": {"horizon": horizon, "iterations": iterations, "n_intermediate": n}}
        for size in (1, batch):
            o, u, k = obs[:size], states[:size], np.ones(size, dtype=np.int64)
            rl = time_call(lambda o=o: agent.act(o, deterministic=True)) / size
            net = time_call(lambda u=u, k=k: dpc(u, k)) / size
            mpc = GradientMPC(plant, horizon, iterations, 0.1, iterations, task.max_episode_steps)
            mpc.reset(size)
            mpc(u, k)  # after the first step, as in an episode (warm start)
            step = time_call(lambda u=u, k=k: mpc(u, k), min_time=0.5, repeats=3) / size
            row[f"batch_{size}"] = {"rl_s": rl, "dpc_s": net, "mpc_s": step, "mpc_over_rl": step / rl, "mpc_over_dpc": step / net}
            print(
                f"{env} batch {size}: RL {rl * 1e3:.4f} ms, DPC {net * 1e3:.4f} ms, MPC {step * 1e3:.2f} ms per step and "
                f"state; MPC / RL = {step / rl:,.0f}x, MPC / DPC = {step / net:,.0f}x"
            )
        rows.append(row)
    path = record("inference_cost", {"systems": rows}, load=args.load)
    print(f"wrote {path}")


if __name__ == "__main__":
    torch.manual_seed(0)
    main()
