"""How well does the KS reward computed from a few states of a control step match the environment's?

The environment's KS reward averages its integrand over the states at the start of all 250 RK4
substeps of a control step. A model-based learner only has the model's ``N`` intermediate states (and
the end state), so :meth:`pimbrl.physics.KuramotoSivashinsky.reward` evaluates the integrand on those
and combines them with a quadrature rule. This script measures that rule's error with *exact*
intermediate states - the solver's own states at the sub-step boundaries - so what it reports is the
quadrature error alone, before any model error is added.

Trajectories: ``--states`` states of the training pool, each run for ``--steps`` control steps with
uniformly random actions and with zero actions. At every control step it records the exact reward
(the environment's, ``Physics.advance``) and the integrand at every substep, and compares

* ``library``: what ``KuramotoSivashinsky.reward(u, a, u_next, k, starts)`` returns when ``starts`` are
  the exact states at the starts of the ``N`` sub-steps (what ``ModelEnv`` passes, with model states);
* ``left``: the mean of the integrand over those ``N`` start states (the rule before this benchmark);
* ``trapezoid``: the trapezoid rule over the ``N + 1`` sub-step boundaries (end state included);
* ``trapezoid_corrected``: the trapezoid rule plus the Euler-Maclaurin end correction
  ``(g_0 - g_N) / (2 M)`` that turns an integral into the solver's ``M``-point left sum;
* ``two_point`` and ``two_point_corrected``: the same two rules with the end points only (``N = 1``);
* ``start_only``: the integrand of the start state (``reward(..., path=None)``).

Relative error = ``|rule - exact| / |exact|`` per control step; mean, 99th percentile and max are
reported per policy and over both, then the same for each trajectory's return (the sum over its
steps). Everything is written to benchmarks/results/ks_reward_quadrature.json.

Usage: ``python benchmarks/bench_ks_reward_quadrature.py [--states 64] [--steps 400] [--n 5]``
"""

from __future__ import annotations

import argparse
import time

import _common
import numpy as np

from pimbrl.systems import KuramotoSivashinsky, ks_initial_state_pool


def _rules(g: np.ndarray, n: int, m: int) -> dict[str, np.ndarray]:
    """Quadrature rules on the integrand ``g`` (``(B, M + 1)``: every substep start and the end state)."""
    idx = np.arange(0, m + 1, m // n)  # the N + 1 sub-step boundaries
    gb = g[:, idx]
    trap = (0.5 * gb[:, 0] + gb[:, 1:-1].sum(1) + 0.5 * gb[:, -1]) / n
    two = 0.5 * (g[:, 0] + g[:, m])
    corr = (g[:, 0] - g[:, m]) / (2 * m)
    return {
        "left": gb[:, :-1].mean(1),
        "trapezoid": trap,
        "trapezoid_corrected": trap + corr,
        "two_point": two,
        "two_point_corrected": two + corr,
        "start_only": g[:, 0],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--states", type=int, default=64, help="training-pool states (one trajectory each)")
    parser.add_argument("--steps", type=int, default=400, help="control steps per trajectory")
    parser.add_argument("--n", type=int, default=5, help="intermediate states per control step (N)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--reward", default="code", choices=["code", "physical"])
    _common.add_load_argument(parser)
    args = parser.parse_args()

    ks = KuramotoSivashinsky(reward=args.reward)
    m = ks.substeps
    if m % args.n:
        raise SystemExit(f"--n must divide the {m} substeps of a control step")
    one = KuramotoSivashinsky(reward=args.reward, substeps=1)  # the same kernel, one substep per call
    rng = np.random.default_rng(args.seed)
    pool = ks_initial_state_pool("train").states
    u_start = pool[rng.choice(len(pool), size=args.states, replace=False)]
    b = len(u_start)
    boundaries = np.arange(0, m, m // args.n)  # the N sub-step starts the library receives

    errors: dict[str, dict[str, list[np.ndarray]]] = {}
    returns: dict[str, dict[str, np.ndarray]] = {}  # relative error of each trajectory's return
    worst_state_gap = 0.0
    t0 = time.perf_counter()
    for policy in ("random", "zero"):
        errs: dict[str, list[np.ndarray]] = {}
        sums: dict[str, np.ndarray] = {}
        exact_sum = np.zeros(b)
        u = u_start.copy()
        for _ in range(args.steps):
            a = rng.uniform(ks.action_low, ks.action_high, (b, ks.action_dim)) if policy == "random" else np.zeros((b, 4))
            u_next, exact = ks.advance(u, a, np.zeros(b, dtype=np.int64))
            states = np.empty((b, m + 1, ks.n))
            g = np.empty((b, m + 1))
            v = u
            for s in range(m):
                states[:, s] = v
                v, _, g[:, s] = one.advance_terms(v, a)  # reward of one substep = integrand at its start
            states[:, m] = v
            f = ks.forcing(a)
            g[:, m] = ks.reward_from_terms(ks.reward_terms(v, f))
            worst_state_gap = max(worst_state_gap, float(np.abs(v - u_next).max()))
            rules = _rules(g, args.n, m)
            rules["substep_mean"] = g[:, :m].mean(1)  # sanity: reproduces the environment's reward
            rules["library"] = np.asarray(ks.reward(u, a, u_next, 0, states[:, boundaries]))
            for name, r in rules.items():
                errs.setdefault(name, []).append(np.abs(r - exact) / np.abs(exact))
                sums[name] = sums.get(name, 0.0) + r
            exact_sum += exact
            u = u_next
        errors[policy] = errs
        returns[policy] = {name: np.abs(r - exact_sum) / np.abs(exact_sum) for name, r in sums.items()}
    elapsed = time.perf_counter() - t0

    def stats(parts: list[np.ndarray]) -> dict[str, float]:
        e = np.concatenate([p.ravel() for p in parts])
        return {"mean": float(e.mean()), "p99": float(np.percentile(e, 99)), "max": float(e.max()), "n": int(e.size)}

    out: dict = {
        "settings": {**vars(args), "substeps": m},
        "max_state_gap_chained_vs_env": worst_state_gap,
        "wall_s": elapsed,
    }
    names = list(errors["random"])
    for name in names:
        out[name] = {p: stats(errors[p][name]) for p in ("random", "zero")}
        out[name]["all"] = stats(errors["random"][name] + errors["zero"][name])
        out[name]["return"] = stats([returns["random"][name], returns["zero"][name]])
    print(f"KS reward={args.reward}: {b} training-pool states x {args.steps} control steps per policy, N = {args.n}, M = {m}")
    print(f"chained single substeps vs the environment's control step: max |du| = {worst_state_gap:.1e}")
    print(f"{'rule':22s} {'policy':7s} {'mean rel. err.':>15s} {'p99':>11s} {'max':>11s}")
    for name in names:
        for p in ("random", "zero", "all"):
            s = out[name][p]
            print(f"{name:22s} {p:7s} {s['mean']:15.3e} {s['p99']:11.3e} {s['max']:11.3e}")
    print(f"relative error of each trajectory's {args.steps}-step return (both policies):")
    for name in names:
        s = out[name]["return"]
        print(f"{name:22s} {'return':7s} {s['mean']:15.3e} {s['p99']:11.3e} {s['max']:11.3e}")
    print(f"recorded {_common.record('ks_reward_quadrature', out, load=args.load)} ({elapsed:.0f} s)")


if __name__ == "__main__":
    main()
