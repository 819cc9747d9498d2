"""Where a KS-sized TD3 update's time goes: fixed per-update overhead, and whether ``torch.compile`` pays on CPU.

Agent updates are most of a KS model-based run's wall-clock (``profile_runs.py``). This times, in one
process, interleaved (fastest of ``--repeats`` blocks of ``--updates`` updates each), one thread:

* ``eager``: pimbrl's TD3 update (batch 128, 2x256 networks, obs 64, action 4: the KS preset);
* ``eager_batch1``: the same with batch 1, where the arithmetic is negligible: the per-update cost of
  Python, operator dispatch and the optimisers, i.e. the most that removing overhead could save;
* ``compiled``: the same agent with every network's forward passes wrapped in ``torch.compile`` (default
  mode; needs a C++ compiler), after a warm-up that includes the compilation (its seconds are reported).

Usage::

    python benchmarks/bench_td3_compile.py --name td3_compile
"""

from __future__ import annotations

import argparse
import time

import _common
import torch

from pimbrl.agents import TD3Config, make_agent
from pimbrl.buffers import Batch

OBS, ACT, HIDDEN = 64, 4, (256, 256)


def _batch(size: int) -> Batch:
    g = torch.Generator().manual_seed(0)
    return Batch(
        obs=torch.randn(size, OBS, generator=g),
        action=torch.rand(size, ACT, generator=g) * 2 - 1,
        reward=torch.randn(size, generator=g),
        next_obs=torch.randn(size, OBS, generator=g),
        terminated=torch.zeros(size),
        truncated=torch.zeros(size),
    )


def _agent(batch_size: int):
    return make_agent(TD3Config(batch_size=batch_size, hidden=HIDDEN), OBS, ACT, seed=0)


def _compile(agent) -> None:
    """Wrap the agent's forward passes in ``torch.compile`` (compiled lazily, at the first updates)."""
    for module in (agent.actor, agent.actor_targ, agent.critic, agent.critic_targ):
        module.forward = torch.compile(module.forward)
    agent.critic.first = torch.compile(agent.critic.first)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--updates", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=6)
    parser.add_argument("--name", default=None, help="record benchmarks/results/<name>.json")
    _common.add_load_argument(parser)
    args = parser.parse_args()
    cases = {"eager": (_agent(128), _batch(128)), "eager_batch1": (_agent(1), _batch(1)), "compiled": (_agent(128), _batch(128))}
    _compile(cases["compiled"][0])
    warm = {}
    for name, (agent, batch) in cases.items():
        t0 = time.perf_counter()
        for _ in range(20):  # the policy delay is 2: both kinds of update are compiled and warmed
            agent.update(batch)
        warm[name] = time.perf_counter() - t0
    best = {name: float("inf") for name in cases}
    for _ in range(args.repeats):
        for name, (agent, batch) in cases.items():
            t0 = time.perf_counter()
            for _ in range(args.updates):
                agent.update(batch)
            best[name] = min(best[name], (time.perf_counter() - t0) / args.updates)
    ms = {name: 1e3 * s for name, s in best.items()}
    ratios = {"compiled_over_eager": ms["compiled"] / ms["eager"], "batch1_over_eager": ms["eager_batch1"] / ms["eager"]}
    for name, value in ms.items():
        print(f"{name:>13s}: {value:.2f} ms per update")
    print(
        f"compiled / eager {ratios['compiled_over_eager']:.2f}; batch-1 overhead / batch-128 update "
        f"{ratios['batch1_over_eager']:.2f}; compilation and warm-up {warm['compiled']:.0f} s"
    )
    if args.name:
        _common.record(args.name, {"ms_per_update": ms, "ratios": ratios, "compile_warmup_s": warm["compiled"]}, load=args.load)


if __name__ == "__main__":
    main()
