"""controlgym's Burgers and Allen-Cahn steps: controlgym's own env against the adapter's, bit for bit and in time.

The adapter (``benchmarks/controlgym_systems.py``) answers controlgym's zero-covariance noise draws without an
SVD and computes the actuators' forcing once per step. This script drives controlgym's unchanged env
(``make_controlgym``) and the adapter's (``ControlGymPDE``) through the same resets (by seed, by state, and
with neither) and the same random actions, and fails unless every state, reward and the generator's state
are identical in their bytes. It then times ``--steps`` steps of each, alternating ``--repeats`` times, in
this one process pinned to one thread (CPU seconds; the fastest of each kept), and records the ratio.

    python benchmarks/bench_controlgym_step.py --load "two study processes"   # benchmarks/results/controlgym_step.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import _common  # noqa: F401  (pins the thread pools before numpy starts them)
import numpy as np
from _common import REPOSITORY, add_load_argument, record

sys.path.insert(0, str(REPOSITORY / "benchmarks"))
from controlgym_systems import ControlGymPDE, make_controlgym

LIMITS = {"burgers": 3.0, "allen_cahn": 5.0}  # the adapters' action bounds


class Plain:
    """controlgym's env, driven through its own ``reset``/``step``."""

    def __init__(self, name: str) -> None:
        self.pde = make_controlgym(name)

    def reset(self, seed: int | None = None, state: np.ndarray | None = None) -> None:
        self.pde.reset(seed=seed, state=state)

    def step(self, action: np.ndarray) -> float:
        with np.errstate(all="ignore"):
            return float(self.pde.step(action)[1])


class Adapted(Plain):
    """The adapter's env (``ControlGymPDE``), driven through gymnasium's ``reset``/``step``."""

    def __init__(self, name: str) -> None:
        self.env = ControlGymPDE(name)
        self.pde = self.env.pde

    def reset(self, seed: int | None = None, state: np.ndarray | None = None) -> None:
        self.env.reset(seed=seed, options=None if state is None else {"state": state})

    def step(self, action: np.ndarray) -> float:
        return self.env.step(action)[1]


def trace(env: Plain, actions: np.ndarray, episode: int) -> list[bytes]:
    """States, rewards and the generator's state, as bytes, over ``actions`` from the reset of ``episode``."""
    if episode == 0:
        env.reset(seed=7)
    elif episode == 1:
        env.reset(state=np.linspace(-0.5, 0.5, env.pde.n_state) ** 2)
    else:
        env.reset()  # the generator goes on from the previous episode
    out = [np.asarray(env.pde.state).tobytes()]
    for a in actions:
        reward = env.step(a)
        out += [np.asarray(env.pde.state).tobytes(), np.float64(reward).tobytes()]
    out.append(repr(env.pde.rng.bit_generator.state).encode())
    return out


def check(name: str, steps: int) -> int:
    """Compare controlgym's env and the adapter's over three episodes of ``steps``; the number of values compared."""
    rng = np.random.default_rng(0)
    plain, adapted = Plain(name), Adapted(name)
    compared = 0
    for episode in range(3):
        actions = rng.uniform(-LIMITS[name], LIMITS[name], size=(steps, plain.pde.n_action))
        a, b = trace(plain, actions, episode), trace(adapted, actions, episode)
        mismatch = next((i for i, (x, y) in enumerate(zip(a, b, strict=True)) if x != y), None)
        if mismatch is not None:
            raise SystemExit(f"{name}: episode {episode} differs from controlgym's at value {mismatch}")
        compared += len(a)
    return compared


def cpu_seconds(env: Plain, steps: int) -> float:
    """CPU seconds of ``steps`` steps of random actions from a seeded reset."""
    rng = np.random.default_rng(1)
    env.reset(seed=3)
    actions = rng.uniform(-1.0, 1.0, size=(steps, env.pde.n_action))
    start = time.process_time()
    for a in actions:
        env.step(a)
    return time.process_time() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100, help="timed steps per measurement (and per checked episode)")
    parser.add_argument("--repeats", type=int, default=3, help="measurements of each env, alternating")
    add_load_argument(parser)
    args = parser.parse_args()
    systems: dict[str, dict[str, Any]] = {}
    for name in LIMITS:
        compared = check(name, args.steps)
        plain, adapted = Plain(name), Adapted(name)
        runs: dict[str, list[float]] = {"controlgym": [], "adapter": []}
        for _ in range(args.repeats):
            runs["controlgym"].append(cpu_seconds(plain, args.steps))
            runs["adapter"].append(cpu_seconds(adapted, args.steps))
        best = {k: min(v) for k, v in runs.items()}
        ratio = best["controlgym"] / best["adapter"]
        print(
            f"{name}: {compared} values identical; {args.steps} steps in {best['controlgym']:.2f} s (controlgym) "
            f"and {best['adapter']:.2f} s (adapter) of CPU, {ratio:.2f} times faster"
        )
        systems[name] = {"values_compared": compared, "identical": True, "cpu_s": runs, "best_cpu_s": best,
                         "speedup": ratio}  # fmt: skip
    path = record("controlgym_step", {"steps": args.steps, "repeats": args.repeats, "systems": systems}, load=args.load)
    print(f"recorded in {Path(path).relative_to(REPOSITORY)}")


if __name__ == "__main__":
    main()
