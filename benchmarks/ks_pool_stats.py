"""Uncontrolled-return distribution of the KS initial-state pools, next to the authors' states.

The authors' 200 shipped states (one unforced run, t ~ 37-87) give 400-step uncontrolled returns of
-234.6 ... -244.7 (mean -240.0), measured on their code (docs/environments.md, section "KS initial
states"). This prints the same statistics for our train and test
pools (default generator settings) and records them in benchmarks/results/ks_pools.json.

Usage: ``python benchmarks/ks_pool_stats.py``
"""

from __future__ import annotations

import argparse
import time

import _common
import numpy as np

from pimbrl.systems import KSPoolConfig, KuramotoSivashinsky, ks_initial_state_pool


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _common.add_load_argument(parser)
    args = parser.parse_args()
    cfg = KSPoolConfig()
    out = {"config": cfg.__dict__, "authors": {"min": -244.7, "max": -234.6, "mean": -240.0, "n": 200}}
    for split in ("train", "test"):
        t0 = time.perf_counter()
        pool = ks_initial_state_pool(split, cfg)
        elapsed = time.perf_counter() - t0
        for reward in ("code", "physical"):
            r = pool.uncontrolled_returns(KuramotoSivashinsky(reward=reward))
            stats = {
                "n": len(r),
                "runs": len(np.unique(pool.run_ids)),
                "min": float(r.min()),
                "p5": float(np.percentile(r, 5)),
                "median": float(np.median(r)),
                "mean": float(r.mean()),
                "p95": float(np.percentile(r, 95)),
                "max": float(r.max()),
                "std": float(r.std()),
                "load_or_build_s": elapsed,
            }
            out[f"{split}_{reward}"] = stats
            print(
                f"{split:5s} reward={reward:8s} n={stats['n']:4d} from {stats['runs']:3d} runs: "
                f"min {stats['min']:8.1f}  p5 {stats['p5']:8.1f}  median {stats['median']:8.1f}  mean {stats['mean']:8.1f}  "
                f"p95 {stats['p95']:8.1f}  max {stats['max']:8.1f}  (load/build {elapsed:.1f} s)"
            )
    print("authors' 200 states (reward=code): min -244.7  max -234.6  mean -240.0")
    print(f"recorded {_common.record('ks_pools', out, load=args.load)}")


if __name__ == "__main__":
    main()
