"""Is the prior's coarse scheme stable at a number of intermediate states per control step?

The plant of MPC and DPC, the known-scheme Dyna model and the physics loss step a PDE's prior with ETDRK4 at
``model.n_intermediate`` steps per control step (``pimbrl.control.plant.make_plant``). For each ``--n``, the
script steps the plant for one episode from ``--states`` training start states (seed 0) under uniform random
actions over the whole action box (seed 1), without gradients, and prints when the first row blew up (a
non-finite state), how many rows had blown up by the end, and the largest final ``|u|`` of the others (the
same draws for every ``--n``, so the rows are comparable). The largest ``--n`` is the reference: the script
also prints each ``--n``'s largest final difference from it on the rows where both are finite.

It measures the forward scheme under random actions over the whole box, a harsher input than a policy that
starts near zero control; DPC skips a step when a rollout's gradient is not finite, which a forward blow-up
implies but does not exhaust.

    python benchmarks/bench_scheme_stability.py cg-burgers --import benchmarks/controlgym_systems.py \\
        --n 5 10 15 20 50                               # benchmarks/results/scheme_stability_cg-burgers.json
"""

from __future__ import annotations

import argparse
import time

import _common  # noqa: F401  (pins this process's pools)
import numpy as np
import torch
from _common import add_load_argument, record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("system", help="a system id or alias")
    parser.add_argument("--import", dest="imports", action="append", default=[], help="a module or file declaring it")
    parser.add_argument("--n", type=int, nargs="+", default=[5, 10, 20], help="intermediate states per control step")
    parser.add_argument("--states", type=int, default=64, help="training start states")
    add_load_argument(parser)
    args = parser.parse_args()
    from pimbrl.control.base import task_of
    from pimbrl.control.plant import make_plant
    from pimbrl.systems.registry import import_systems, resolve_env_id

    import_systems(args.imports)
    task = task_of(resolve_env_id(args.system), {})
    physics = task.physics
    u0 = torch.as_tensor(task.sample_initial_states(np.random.default_rng(0), args.states))
    low, high = np.asarray(physics.action_low), np.asarray(physics.action_high)
    steps = int(task.max_episode_steps)
    actions = torch.as_tensor(np.random.default_rng(1).uniform(low, high, (steps, args.states, len(low))))
    finals: dict[int, torch.Tensor] = {}
    rows = []
    for n in sorted(set(args.n)):
        plant = make_plant(physics, n)
        u, k, first = u0.clone(), torch.zeros(args.states, dtype=torch.int64), None
        start = time.perf_counter()
        with torch.no_grad():
            for t in range(steps):
                u, _ = plant.step(u, actions[t], k)
                k = k + 1
                blown = int((~torch.isfinite(u).all(-1)).sum())
                if blown and first is None:
                    first = {"step": t + 1, "rows": blown}
        ok = torch.isfinite(u).all(-1)
        finals[n] = u
        rows.append(
            {
                "n_intermediate": n,
                "first_blow_up": first,
                "blown_up_at_end": int((~ok).sum()),
                "max_abs_u_at_end": float(u[ok].abs().max()) if bool(ok.any()) else None,
                "wall_s": time.perf_counter() - start,
            }
        )
    ref = finals[max(finals)]
    for row in rows:
        u = finals[row["n_intermediate"]]
        both = torch.isfinite(u).all(-1) & torch.isfinite(ref).all(-1)
        row["max_diff_from_largest_n"] = float((u[both] - ref[both]).abs().max()) if bool(both.any()) else None
        print(
            f"n_intermediate {row['n_intermediate']:>3}: first blow-up {row['first_blow_up']}, blown up at step {steps}: "
            f"{row['blown_up_at_end']}/{args.states}, max |u| {row['max_abs_u_at_end']}, "
            f"max diff from n={max(finals)} {row['max_diff_from_largest_n']}, {row['wall_s']:.1f} s"
        )
    payload = {"system": args.system, "states": args.states, "episode_steps": steps, "rows": rows}
    print("wrote", record("scheme_stability_" + args.system.replace("/", "_"), payload, args.load))


if __name__ == "__main__":
    main()
