"""MFRL, MBRL and PiMBRL on controlgym's Burgers and Allen-Cahn (someone else's simulator), with a feedback floor.

For each system of ``benchmarks/controlgym_systems.py``: ``pimbrl compare`` runs mfrl, mbrl and pimbrl (the
prior: the equation controlgym integrates, declared there) over the seeds with the system's preset (3,000
steps, 10 test episodes every 500 steps), one thread per run, ``--jobs`` at a time; finished runs are
skipped and interrupted ones resumed. Then a proportional feedback controller, ``a_i = -k * mean(u over
actuator i's support)`` clipped to the action bounds, is the floor: its gain is chosen among ``GAINS`` on
the validation draws (as many episodes as the test), and it is scored on the runs' test states (the same states as the
agents' evaluations). The record (``benchmarks/results/<name>.json``) holds, per method, the final test
return of each seed (the last evaluation, not the best), their mean, minimum and maximum, and the floor's
mean and range over the test states; the commands that produced them; the machine.

Usage::

    pip install -e ".[controlgym]" && pip install --no-deps controlgym==1.0.0
    python benchmarks/run_controlgym.py --seeds 3 --jobs 2
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from pimbrl.experiments.runner import pinned_environment

ROOT = Path(__file__).resolve().parents[1]
IMPORT = "benchmarks/controlgym_systems.py"
SYSTEMS = {"cg-burgers": "controlgym/Burgers-v0", "cg-allen-cahn": "controlgym/AllenCahn-v0"}
METHODS = ("mfrl", "mbrl", "pimbrl")
GAINS = (0.0, 1.0, 2.0, 5.0, 10.0, 20.0)


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def run_compare(alias: str, seeds: int, jobs: int, root: Path) -> list[str]:
    """``pimbrl compare`` of the three methods on one system; returns the command."""
    cmd = [sys.executable, "-m", "pimbrl.cli", "compare", alias, "--import", IMPORT, "--methods", ",".join(METHODS)]
    cmd += ["--seeds", str(seeds), "--jobs", str(jobs), "--run-dir", str(root / alias)]
    subprocess.run(cmd, check=True, cwd=ROOT, env=pinned_environment(1))  # every pool of the driver at one thread
    return cmd


def floor(env_id: str, eval_seed: int, episodes: int) -> dict[str, Any]:
    """The proportional controller: gain chosen on the validation draws, scored on the test states."""
    import gymnasium as gym

    task = gym.make(env_id).unwrapped.task
    shapes = task.physics.actuator_shapes > 0.5
    low, high = task.physics.action_low, task.physics.action_high

    def returns(states: np.ndarray, gain: float) -> np.ndarray:
        u, total = states.copy(), np.zeros(len(states))
        alive = np.ones(len(states), dtype=bool)
        for k in range(task.max_episode_steps):
            a = np.clip(-gain * np.stack([u[:, m].mean(1) for m in shapes], 1), low, high)
            out = task.advance(u, a, np.full(len(u), k))
            total += np.where(alive, out.reward, 0.0)
            alive &= ~out.terminated
            u = out.state
            if not alive.any():
                break
        return total

    validation = task.validation_initial_states(episodes)
    on_validation = {g: float(returns(validation, g).mean()) for g in GAINS}
    best = max(on_validation, key=lambda g: on_validation[g])
    test = returns(task.test_initial_states(episodes, eval_seed), best)
    uncontrolled = returns(task.test_initial_states(episodes, eval_seed), 0.0)
    return {
        "gain_chosen_on_validation": best,
        "validation_mean_by_gain": on_validation,
        "test_mean": float(test.mean()),
        "test_min": float(test.min()),
        "test_max": float(test.max()),
        "uncontrolled_test_mean": float(uncontrolled.mean()),
    }


def summarise(root: Path, alias: str, seeds: int) -> dict[str, Any]:
    """Per method: the final test return of each seed (its last evaluation) and the wall time."""
    out: dict[str, Any] = {}
    for method in METHODS:
        finals, walls, steps = [], [], []
        for seed in range(seeds):
            run = root / alias / method / f"seed{seed}"
            rows = (run / "evaluations.csv").read_text().splitlines()
            header = rows[0].split(",")
            last = dict(zip(header, rows[-1].split(",")))
            finals.append(float(last["return_mean"]))
            steps.append(int(last["step"]))
            walls.append(json.loads((run / "config.json").read_text()).get("summary", {}).get("wall_s"))
        out[method] = {
            "final_return_per_seed": finals,
            "final_return_mean": float(np.mean(finals)),
            "final_return_min": float(np.min(finals)),
            "final_return_max": float(np.max(finals)),
            "steps": steps,
            "wall_s": walls,
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--root", default=str(ROOT / "benchmarks" / "runs" / "controlgym"))
    parser.add_argument("--name", default="controlgym_pde_study")
    parser.add_argument("--only", choices=sorted(SYSTEMS), default=None, help="one system")
    args = parser.parse_args()
    root = Path(args.root)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import controlgym_systems  # noqa: F401 - registers the two systems

    record: dict[str, Any] = {"machine": {"cpu": _cpu(), "threads_per_run": 1}, "systems": {}}
    for alias, env_id in SYSTEMS.items():
        if args.only and alias != args.only:
            continue
        cmd = run_compare(alias, args.seeds, args.jobs, root)
        cfg = json.loads((root / alias / "mfrl" / "seed0" / "config.json").read_text())["config"]
        result = {
            "command": " ".join(["pimbrl", *cmd[3:]]).replace(str(root), "RUNS"),
            "steps": cfg["total_steps"],
            "eval_episodes": cfg["eval_episodes"],
            "methods": summarise(root, alias, args.seeds),
            "proportional_floor": floor(env_id, cfg["eval_seed"], cfg["eval_episodes"]),
        }
        record["systems"][env_id] = result
        print(json.dumps({env_id: result}, indent=1))
    path = ROOT / "benchmarks" / "results" / f"{args.name}.json"
    path.write_text(json.dumps(record, indent=1) + "\n")
    print(f"recorded: {path}")


if __name__ == "__main__":
    main()
