"""Evaluate a TD3/DDPG run's latest checkpoint twice on its held-out test states: the actor and its target.

The target actor is the Polyak average of the actor (``polyak`` 0.995 by default: a memory of about 200
actor steps). Evaluating it instead of the actor asks whether averaging the policy's recent weights steadies
or lifts the test return, as averaged policies sometimes do. Both policies are deterministic and run on the
same states, so the difference is the averaging alone. Runs are only read.

Usage::

    python benchmarks/eval_target_actor.py R/seed0 R/seed1 R/seed2 [--name NAME]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import _common
import numpy as np
import torch


def evaluate(run_dir: Path) -> dict:
    """Step and mean test return of the actor and of the target actor of the run's latest checkpoint."""
    run = _common.load_checkpointed_run(run_dir)
    agent = run.agent
    target = getattr(agent, "actor_targ", None)
    if target is None:
        raise SystemExit(f"{run_dir}: agent {run.cfg.agent!r} has no target actor (only td3 and ddpg have one)")

    @torch.no_grad()
    def target_policy(obs: np.ndarray) -> np.ndarray:
        obs_t = torch.as_tensor(np.asarray(obs, dtype=np.float32)).reshape(-1, agent.obs_dim)
        return target(obs_t).numpy()

    evaluator = run.evaluator_for("test")
    actor = evaluator.run(lambda o: agent.act(o, deterministic=True)).summary()["return_mean"]
    averaged = evaluator.run(target_policy).summary()["return_mean"]
    return {"run_dir": str(run_dir), "seed": run.cfg.seed, "step": run.t, "actor": actor, "target_actor": averaged}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", type=Path)
    parser.add_argument("--name", default=None, help="record benchmarks/results/<name>.json")
    args = parser.parse_args()
    rows = []
    for run_dir in args.run_dirs:
        row = evaluate(run_dir)
        rows.append(row)
        print(
            f"{run_dir} seed {row['seed']} step {row['step']:,d}: actor {row['actor']:.2f}, "
            f"target actor {row['target_actor']:.2f} ({row['target_actor'] - row['actor']:+.2f})",
            flush=True,
        )
    if args.name:
        print(f"recorded {_common.record(args.name, {'runs': rows})}")


if __name__ == "__main__":
    main()
