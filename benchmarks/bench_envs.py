"""Control steps per second of the four environments, one thread, against a plain NumPy implementation.

For each env and batch size B in {1, 16, 256} this times, in one run:

* ``kernel``: the fast simulator ``Physics.advance`` (compiled float64 kernel for KS and Burgers,
  vectorised NumPy for the ODEs) - one control step for B environments, reward included;
* ``vector env``: ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")`` ``step`` (API,
  validation, observation and divergence checks included);
* ``numpy``: the same scheme through the Physics object's reference methods on NumPy arrays
  (``np.roll`` stencils, batched): the plain NumPy batched implementation.

Usage: ``python benchmarks/bench_envs.py`` (prints a table, writes benchmarks/results/envs.json).
"""

from __future__ import annotations

import argparse

import _common
import gymnasium as gym
import numpy as np

import pimbrl  # noqa: F401
from pimbrl.systems import Burgers, CartPole, KuramotoSivashinsky, Pendulum

ENVS = {
    "KS": ("pimbrl/KuramotoSivashinsky-v0", KuramotoSivashinsky),
    "Burgers": ("pimbrl/Burgers-v0", Burgers),
    "CartPole": ("pimbrl/CartPole-v0", CartPole),
    "Pendulum": ("pimbrl/Pendulum-v0", Pendulum),
}


def _states(name: str, phys, rng: np.random.Generator, b: int) -> tuple[np.ndarray, np.ndarray]:
    if name == "KS":
        x = 2 * np.pi * phys.x / phys.length
        u = sum(rng.normal(0, 1 / m, (b, 1)) * np.sin(m * x + rng.uniform(0, 6.3, (b, 1))) for m in range(1, 6))
    elif name == "Burgers":
        u = 0.3 + 0.1 * np.sin(2 * np.pi * phys.x)[None] * rng.uniform(0.5, 1.5, (b, 1))
    elif name == "CartPole":
        u = rng.uniform(-0.05, 0.05, (b, 4))
    else:
        u = rng.uniform([-np.pi, -1], [np.pi, 1], (b, 2))
    a = rng.uniform(phys.action_low, phys.action_high, (b, phys.action_dim))
    return np.ascontiguousarray(u), a


def _numpy_reference(phys, u: np.ndarray, a: np.ndarray, k: np.ndarray) -> None:
    if isinstance(phys, KuramotoSivashinsky):
        path = phys.path(u, a)
        u_next = phys.substep(path[..., -1, :], a)
        phys.reward(u, a, u_next, k, path)
    else:
        u_next = phys.step(u, a)
        phys.reward(u, a, u_next, k)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", default="1,16,256")
    parser.add_argument("--numpy-max-batch", type=int, default=256, help="skip the slow NumPy reference above this batch")
    _common.add_load_argument(parser)
    args = parser.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    rng = np.random.default_rng(0)
    rows = []
    for name, (env_id, cls) in ENVS.items():
        phys = cls()
        for b in batches:
            u, a = _states(name, phys, rng, b)
            k = np.zeros(b, dtype=np.int64)
            t_kernel = _common.time_call(lambda: phys.advance(u, a, k))
            vec = gym.make_vec(env_id, num_envs=b, vectorization_mode="vector_entry_point")
            vec.reset(seed=0, options={"initial_state": u})
            act = (a[:, 0] > 0).astype(np.int64) if name == "CartPole" else a.astype(np.float32)
            t_vec = _common.time_call(lambda: vec.step(act))
            t_np = None
            if b <= args.numpy_max_batch:
                t_np = _common.time_call(lambda: _numpy_reference(phys, u, a, k), min_time=0.5, repeats=3)
            row = {
                "env": name,
                "batch": b,
                "kernel_us_per_env_step": 1e6 * t_kernel / b,
                "vector_env_us_per_env_step": 1e6 * t_vec / b,
                "numpy_us_per_env_step": None if t_np is None else 1e6 * t_np / b,
                "kernel_env_steps_per_s": b / t_kernel,
                "vector_env_env_steps_per_s": b / t_vec,
                "numpy_env_steps_per_s": None if t_np is None else b / t_np,
            }
            rows.append(row)
            np_txt = "-" if t_np is None else f"{1e6 * t_np / b:10.1f}"
            speedup = "-" if t_np is None else f"{t_np / t_kernel:7.1f}x"
            print(
                f"{name:9s} B={b:4d}  kernel {1e6 * t_kernel / b:9.2f} us/env-step ({b / t_kernel:10.0f}/s)  "
                f"vector-env {1e6 * t_vec / b:9.2f} us  numpy {np_txt} us  kernel speed-up {speedup}",
                flush=True,
            )
    path = _common.record("envs", {"rows": rows}, load=args.load)
    print(f"recorded {path}")


if __name__ == "__main__":
    main()
