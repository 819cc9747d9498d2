"""Time of one model gradient step at batch 256, one thread: data loss and physics loss, KS and Burgers.

Usage: ``python benchmarks/bench_model_step.py`` (prints a table, writes benchmarks/results/model_step.json).
Also measures, for every number of intermediate states N offered, the distance of the coarse ETDRK4
step from the simulator's solver (max and mean-square defect on solver trajectories from pool / random
initial states), i.e. how far the physics loss's target is from the true environment.
"""

from __future__ import annotations

import _common
import numpy as np
import torch

from pimbrl.models import ModelTrainer, PhysicsResidual, TransitionData, make_model
from pimbrl.physics.kernels import build_pde_kernel
from pimbrl.systems import Burgers, KuramotoSivashinsky, ks_initial_state_pool

BATCH = 256


def _states(phys, rng: np.random.Generator, n: int) -> np.ndarray:
    if isinstance(phys, KuramotoSivashinsky):
        pool = ks_initial_state_pool("test").states
        return pool[rng.integers(len(pool), size=n)]
    c = rng.uniform(0, 1, (n, 1))
    x = phys.x[None]
    return 0.2 * c * np.exp(-25 * (x - 0.5) ** 2) + 0.2 * (1 - c) * np.sin(4 * np.pi * x) + 0.2


def timing(phys, rng: np.random.Generator) -> list[dict]:
    rows = []
    u = _states(phys, rng, 2048)
    a = rng.uniform(phys.action_low, phys.action_high, (2048, phys.action_dim))
    un, _ = phys.advance(u, a, np.zeros(2048, dtype=np.int64))
    data = TransitionData(*(torch.tensor(x, dtype=torch.float32) for x in (u, a, un)))
    for n_int, scheme in [(5, "etd"), (10, "etd"), (25, "etd"), (5, "solver")]:
        torch.manual_seed(0)
        model = make_model(phys, n_intermediate=n_int)
        trainer = ModelTrainer(model, PhysicsResidual(phys, n_int, scheme))  # type: ignore[arg-type]
        trainer.ensure_normalization(data)
        t_data = _common.time_call(lambda: trainer.step(labelled=data.sample(BATCH, rng)), min_time=1.0, repeats=5)
        reps = 2 if scheme == "solver" else 5
        t_phys = _common.time_call(lambda: trainer.step(unlabelled=data.sample(BATCH, rng)), min_time=1.0, repeats=reps)
        t_both = _common.time_call(
            lambda: trainer.step(data.sample(BATCH, rng), data.sample(BATCH, rng)), min_time=1.0, repeats=reps
        )
        row = {
            "system": phys.name,
            "N": n_int,
            "scheme": scheme,
            "data_ms": 1e3 * t_data,
            "physics_ms": 1e3 * t_phys,
            "mixed_ms": 1e3 * t_both,
        }
        rows.append(row)
        print(
            f"{phys.name:8s} N={n_int:3d} {scheme:6s}: data-loss step {row['data_ms']:7.1f} ms   "
            f"physics-loss step {row['physics_ms']:8.1f} ms   both {row['mixed_ms']:8.1f} ms",
            flush=True,
        )
    return rows


def etd_accuracy(phys, rng: np.random.Generator) -> list[dict]:
    u0 = _states(phys, rng, 32)
    a = rng.uniform(phys.action_low, phys.action_high, (32, phys.action_dim))
    kernel = build_pde_kernel(phys.kernel_spec())
    rows = []
    for n in [d for d in range(1, phys.substeps + 1) if phys.substeps % d == 0 and d <= 250]:
        m = phys.substeps // n
        u, path = u0, []
        for _ in range(n):
            u, _, _ = kernel(u, a, phys.actuator_shapes, phys.dt, m, False, np.zeros(4))
            path.append(u)
        path_t = torch.tensor(np.stack(path, axis=1))
        res = PhysicsResidual(phys, n, "etd")
        d = res.defects(torch.tensor(u0), path_t, torch.tensor(a))
        coarse = res.rollout(torch.tensor(u0), torch.tensor(a))[:, -1]
        rows.append(
            {
                "system": phys.name,
                "N": n,
                "h": phys.control_dt / n,
                "defect_max": float(d.abs().max()),
                "defect_mse": float(d.pow(2).mean()),
                "control_step_error_max": float((coarse - path_t[:, -1]).abs().max()),
                "control_step_mse": float((coarse - path_t[:, -1]).pow(2).mean()),
            }
        )
        r = rows[-1]
        print(
            f"{phys.name:8s} N={n:4d} h={r['h']:.4f}: defect max {r['defect_max']:.2e} mse {r['defect_mse']:.2e}; "
            f"N coarse steps vs the solver over a control step: "
            f"max {r['control_step_error_max']:.2e} mse {r['control_step_mse']:.2e}",
            flush=True,
        )
    return rows


def main() -> None:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=["all", "accuracy", "timing"], default="all")
    _common.add_load_argument(parser)
    args = parser.parse_args()
    part = args.part
    rng = np.random.default_rng(0)
    if part in ("all", "accuracy"):
        acc = [row for phys in (KuramotoSivashinsky(), Burgers()) for row in etd_accuracy(phys, rng)]
        print(f"recorded {_common.record('model_residual_accuracy', {'rows': acc}, load=args.load)}")
    if part in ("all", "timing"):
        rows = [row for phys in (KuramotoSivashinsky(), Burgers()) for row in timing(phys, rng)]
        print(f"recorded {_common.record('model_step', {'batch': BATCH, 'rows': rows}, load=args.load)}")


if __name__ == "__main__":
    main()
