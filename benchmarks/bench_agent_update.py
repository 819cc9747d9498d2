"""Agent-update cost per real step on KS's sizes: CrossQ at one update against TD3 at five; ratios in one run.

Each agent of the library is built for the KS observation (64) and action (4) sizes and takes updates on
random batches of 256; what is timed is one real step's worth of updates (``utd`` of them). CrossQ's critic
width is the question: the published 2 x 2,048 against the 2 x 512 that control-agents-ks runs. Seconds
are this machine's, one thread; the ratios to TD3 at five updates are what carries over.

    python benchmarks/bench_agent_update.py    # writes benchmarks/results/agent_update_cost.json
"""

from __future__ import annotations

import argparse

import _common  # noqa: F401  (pins every thread pool to one thread first)
import numpy as np
import torch
from _common import add_load_argument, record, time_call

from pimbrl.agents import make_agent
from pimbrl.agents.config import AGENT_TYPES
from pimbrl.buffers import Batch

OBS, ACT, BATCH = 64, 4, 256
#: label, agent, its settings, updates per real step
AGENTS = [
    ("td3-utd5", "td3", {}, 5),
    ("td3-utd1", "td3", {}, 1),
    ("sac-utd1", "sac", {}, 1),
    ("redq-utd1", "redq", {}, 1),
    ("crossq-512-utd1", "crossq", {"critic_hidden": (512, 512)}, 1),
    ("crossq-2048-utd1", "crossq", {}, 1),
]


def random_batch(rng: np.random.Generator) -> Batch:
    """A batch of KS-sized transitions with random contents (the cost does not depend on them)."""

    def normal(*shape: int) -> torch.Tensor:
        return torch.as_tensor(rng.normal(size=shape), dtype=torch.float32)

    zeros = torch.zeros(BATCH)
    return Batch(normal(BATCH, OBS), torch.tanh(normal(BATCH, ACT)), normal(BATCH), normal(BATCH, OBS), zeros, zeros)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_load_argument(parser)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    rows = {}
    for label, name, settings, utd in AGENTS:
        agent = make_agent(AGENT_TYPES[name](**settings), OBS, ACT, seed=0)
        batches = [random_batch(rng) for _ in range(6)]
        for b in batches[:3]:  # the first updates allocate
            agent.update(b)

        def one_real_step(agent=agent, batches=batches, utd=utd) -> None:
            for i in range(utd):
                agent.update(batches[i % len(batches)])

        rows[label] = {
            "agent": name,
            "settings": {k: list(v) for k, v in settings.items()},
            "utd": utd,
            "s_per_real_step": time_call(one_real_step, min_time=1.0, repeats=3),
        }
    base = rows["td3-utd5"]["s_per_real_step"]
    for label, row in rows.items():
        row["over_td3_utd5"] = row["s_per_real_step"] / base
        print(f"{label:18s} {row['s_per_real_step'] * 1e3:9.1f} ms per real step   {row['over_td3_utd5']:6.2f} x TD3 at 5")
    path = record("agent_update_cost", {"obs": OBS, "act": ACT, "batch": BATCH, "agents": rows}, load=args.load)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
