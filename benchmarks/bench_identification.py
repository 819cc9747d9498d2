"""How many real transitions the inverse problem needs: coefficients identified from labelled transitions.

For each case (an environment whose coefficients differ from the prior's), collects ``N`` real transitions
with uniformly random actions (as the warm-up of a training run does) from the environment's own initial
states, fits the learned coefficients with :meth:`pimbrl.models.PhysicsResidual.coefficient_loss` (Adam,
``--fit-steps`` steps, batches of up to 256) from the prior's values, and reports the relative error of the
identified values against the environment's, per seed.

Usage::

    python benchmarks/bench_identification.py --labels 100,300,1000,2000 --seeds 0,1,2
    python benchmarks/bench_identification.py --cases pendulum,cartpole --name identification_ode
"""

from __future__ import annotations

import argparse
import statistics
import time

import _common
import gymnasium as gym
import numpy as np
import torch

import pimbrl  # noqa: F401 - registers the environments
from pimbrl.config import parse_learned, parse_prior
from pimbrl.models import PhysicsResidual
from pimbrl.models.coefficients import CORRECTION_OF
from pimbrl.physics.pde import SemilinearPDE

#: (name, environment, true coefficients, prior coefficients, learned)
CASES = (
    ("burgers nu +30%", "pimbrl/Burgers-v0", "nu=0.013", "nu=0.01", "nu"),
    ("burgers nu -30%", "pimbrl/Burgers-v0", "nu=0.007", "nu=0.01", "nu"),
    ("burgers missing damping", "pimbrl/Burgers-v0", "damping=0.02", "damping=0", "damping:0:0.1"),
    ("ks convection +30%", "pimbrl/KuramotoSivashinsky-v0", "convection=1.3", "convection=1", "convection"),
    ("ks convection -30%", "pimbrl/KuramotoSivashinsky-v0", "convection=0.7", "convection=1", "convection"),
    ("ks missing damping", "pimbrl/KuramotoSivashinsky-v0", "damping=0.1", "damping=0", "damping:0:1"),
    # a term of a form the prior lacks: a drift -c u_x, found by the learned linear correction (c_1 = -c)
    ("burgers missing drift (correction)", "pimbrl/Burgers-v0", "drift=0.05", "drift=0", "correction"),
    ("ks missing drift (correction)", "pimbrl/KuramotoSivashinsky-v0", "drift=0.2", "drift=0", "correction"),
    # the ODE systems, through their own solver step
    ("pendulum l +30%", "pimbrl/Pendulum-v0", "l=1.3", "l=1", "l"),
    ("pendulum l -30%", "pimbrl/Pendulum-v0", "l=0.7", "l=1", "l"),
    ("pendulum missing damping", "pimbrl/Pendulum-v0", "damping=0.1", "damping=0", "damping:0:1"),
    ("cartpole masspole +30%", "pimbrl/CartPole-v0", "masspole=0.13", "masspole=0.1", "masspole"),
    ("cartpole missing pole friction", "pimbrl/CartPole-v0", "pole_friction=0.002", "pole_friction=0", "pole_friction:0:0.01"),
)


def collect(env_id: str, true: dict[str, float], n: int, seed: int) -> tuple[np.ndarray, ...]:
    """``n`` transitions ``(u, a, u_next)`` under uniformly random actions, episodes from the env's resets."""
    env = gym.make(env_id, **true)
    env.action_space.seed(seed)
    states, actions, nexts = [], [], []
    _, info = env.reset(seed=seed)
    while len(states) < n:
        u = np.asarray(info["state"], dtype=np.float64)
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        states.append(u)
        actions.append(np.asarray(info["physical_action"], dtype=np.float64))
        nexts.append(np.asarray(info["state"], dtype=np.float64))
        if terminated or truncated:
            _, info = env.reset()
    return np.array(states), np.array(actions), np.array(nexts)


def identify(
    env_id: str, true: str, prior: str, learn: str, n: int, seed: int, fit_steps: int, lr: float
) -> tuple[dict[str, float], float]:
    """Identified coefficients and the wall-clock of the fit."""
    truth = parse_prior(true)
    u, a, u1 = (torch.as_tensor(x, dtype=torch.float32) for x in collect(env_id, truth, n, seed))
    physics = gym.make(env_id).unwrapped.task.physics.with_coefficients(**parse_prior(prior))
    n_intermediate = 5 if isinstance(physics, SemilinearPDE) else physics.substeps  # as in training
    residual = PhysicsResidual(physics, n_intermediate, learned=parse_learned(learn))
    assert residual.coefficients is not None
    optimizer = torch.optim.Adam(residual.coefficients.parameters(), lr=lr)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    for _ in range(fit_steps):
        idx = torch.as_tensor(rng.integers(0, n, size=min(256, n)))
        loss = residual.coefficient_loss(u[idx], a[idx], u1[idx])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        residual.coefficients.project()  # ranged coefficients back into their range, as in training
    return residual.coefficients.current(), time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--labels", default="100,300,1000,2000")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--fit-steps", type=int, default=200)
    parser.add_argument("--lr", type=float, default=1e-2)
    parser.add_argument("--cases", default="", help="comma-separated substrings of case names (default: all)")
    parser.add_argument("--name", default="identification", help="record as benchmarks/results/<name>.json")
    args = parser.parse_args()
    labels = [int(x) for x in args.labels.split(",")]
    seeds = [int(x) for x in args.seeds.split(",")]
    wanted = [c.strip() for c in args.cases.split(",") if c.strip()]
    rows = []
    for name, env_id, true, prior, learn in CASES:
        if wanted and not any(w in name for w in wanted):
            continue
        truth = parse_prior(true)
        for n in labels:
            errors = []
            for seed in seeds:
                found, wall = identify(env_id, true, prior, learn, n, seed, args.fit_steps, args.lr)
                if learn == "correction":
                    err = max(abs(found[CORRECTION_OF[k][0]] - CORRECTION_OF[k][1] * v) / abs(v) for k, v in truth.items())
                else:
                    err = max(abs(found[k] - v) / abs(v) for k, v in truth.items())
                errors.append(err)
                rows.append({"case": name, "labels": n, "seed": seed, "identified": found, "relative_error": err, "fit_s": wall})
            print(
                f"{name:>24}  {n:>5} labels  relative error {100 * min(errors):.2g} % .. {100 * max(errors):.2g} % "
                f"(median {100 * statistics.median(errors):.2g} %) over {len(seeds)} seeds"
            )
    _common.record(args.name, {"fit_steps": args.fit_steps, "lr": args.lr, "labels": labels, "seeds": seeds, "rows": rows})


if __name__ == "__main__":
    main()
