#!/usr/bin/env bash
# CrossQ and REDQ on Pendulum against SAC: model-free runs, one process at a time, then a table of the
# evaluation returns (return_mean of evaluations.csv) by step, and the time per agent update against TD3.
#
# Published (Bhatt et al. 2024, Chen et al. 2021): CrossQ and REDQ reach about -150..-200 on Pendulum
# within 5,000-10,000 steps.
#
# Usage: benchmarks/agents_pendulum.sh [ROOT]          (runs under ROOT, default runs/bench/agents-pendulum)
# Environment: SEEDS ("0 1 2"), STEPS (6000), AGENTS ("sac crossq redq"), TIMING (1: also time the updates),
#              RUN (1; 0: only the tables, of the runs there are),
#              PIMBRL (.venv/bin/pimbrl), PYTHON (.venv/bin/python), and per agent extra flags
#              SAC_FLAGS, CROSSQ_FLAGS, REDQ_FLAGS. A finished run is kept (rerun: delete its folder).
#
# The agents' defaults are their papers' (CrossQ: critics 2x2048, policy delay 3, Adam beta1 0.5; REDQ:
# 10 critics, subsets of 2); REDQ_FLAGS defaults to the paper's update-to-data ratio 20 with one policy
# update per 20 critic updates. Everything else is the pendulum recipe's (1,000 random warm-up steps,
# updates every 50 steps, an evaluation of 100 episodes every 500 steps).
set -euo pipefail
cd "$(dirname "$0")/.."

ROOT=${1:-runs/bench/agents-pendulum}
SEEDS=${SEEDS:-"0 1 2"}
STEPS=${STEPS:-6000}
AGENTS=${AGENTS:-"sac crossq redq"}
TIMING=${TIMING:-1}
RUN=${RUN:-1}
PIMBRL=${PIMBRL:-.venv/bin/pimbrl}
PYTHON=${PYTHON:-.venv/bin/python}
SAC_FLAGS=${SAC_FLAGS:-""}
CROSSQ_FLAGS=${CROSSQ_FLAGS:-""}
REDQ_FLAGS=${REDQ_FLAGS:-"--utd 20 --agent.policy-delay 20"}

for agent in $AGENTS; do
    [ "$RUN" = 1 ] || break
    case $agent in
        sac) extra=$SAC_FLAGS ;;
        crossq) extra=$CROSSQ_FLAGS ;;
        redq) extra=$REDQ_FLAGS ;;
        *) extra="" ;;
    esac
    for seed in $SEEDS; do
        dir="$ROOT/$agent-$seed"
        if [ -f "$dir/config.json" ] && grep -q '"status": "finished"' "$dir/config.json"; then
            echo "$dir: finished, kept"
            continue
        fi
        rm -rf "$dir"
        # shellcheck disable=SC2086  # the extra flags are words
        "$PIMBRL" train pendulum --agent "$agent" --seed "$seed" --total-steps "$STEPS" --run-dir "$dir" --quiet $extra
    done
done

"$PYTHON" - "$ROOT" "$AGENTS" "$SEEDS" <<'EOF'
import csv
import sys
from pathlib import Path

root, agents, seeds = Path(sys.argv[1]), sys.argv[2].split(), sys.argv[3].split()
steps = [1000, 2000, 3000, 4000, 5000, 6000, 8000, 10000]
rows = {}
for agent in agents:
    for seed in seeds:
        path = root / f"{agent}-{seed}" / "evaluations.csv"
        if path.exists():
            with path.open() as f:
                rows[agent, seed] = {int(r["step"]): (float(r["return_mean"]), float(r["wall_s"])) for r in csv.DictReader(f)}
shown = [s for s in steps if any(s in r for r in rows.values())]
print("| run | " + " | ".join(f"{s:,}" for s in shown) + " | best | wall s |")
print("|---" * (len(shown) + 3) + "|")
for agent in agents:
    runs = [rows[agent, s] for s in seeds if (agent, s) in rows]
    for seed in seeds:
        r = rows.get((agent, seed))
        if r is None:
            continue
        cells = [f"{r[s][0]:.0f}" if s in r else "" for s in shown]
        print(f"| {agent} seed {seed} | " + " | ".join(cells) + f" | {max(v[0] for v in r.values()):.0f} | {r[max(r)][1]:.0f} |")
    if len(runs) > 1:
        cells = [f"{sum(r[s][0] for r in runs) / len(runs):.0f}" if all(s in r for r in runs) else "" for s in shown]
        best = sum(max(v[0] for v in r.values()) for r in runs) / len(runs)
        print(f"| **{agent} mean** | " + " | ".join(cells) + f" | {best:.0f} | |")
EOF

if [ "$TIMING" = 1 ]; then
    # time per agent update on Pendulum's sizes (obs 3, action 1), each agent's defaults, one thread
    "$PYTHON" - "$AGENTS" <<'EOF'
import sys
import time

import numpy as np
import torch

from pimbrl.agents import AGENT_TYPES, make_agent
from pimbrl.buffers import ReplayBuffer

torch.set_num_threads(1)
rng = np.random.default_rng(0)
buf = ReplayBuffer(10_000, 3, 1)
buf.add(rng.standard_normal((10_000, 3)), rng.uniform(-1, 1, (10_000, 1)), rng.standard_normal(10_000),
        rng.standard_normal((10_000, 3)), np.zeros(10_000), np.zeros(10_000))  # fmt: skip
variants = [("td3", {})] + [(a, {}) for a in sys.argv[1].split()]
variants += [("redq", {"policy_delay": 20})] if "redq" in sys.argv[1].split() else []
print("| agent | settings | batch | ms per update |")
print("|---|---|---|---|")
for name, over in variants:
    cfg = AGENT_TYPES[name](**over)
    agent = make_agent(cfg, 3, 1, seed=0)
    batches = [buf.sample(cfg.batch_size, rng) for _ in range(60)]
    for b in batches[:10]:
        agent.update(b)
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        for b in batches[10:]:
            agent.update(b)
        best = min(best, (time.perf_counter() - t) / 50)
    print(f"| {name} | {over or 'defaults'} | {cfg.batch_size} | {best * 1e3:.1f} |")
EOF
fi
