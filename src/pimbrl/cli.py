"""The ``pimbrl`` command line."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["main", "build_parser"]


def _cmd_simulate(args: argparse.Namespace) -> int:
    import gymnasium as gym

    from . import plotting
    from .envs import PhysicsEnv
    from .simulate import make_simple_policy, resolve_env_id, run_episode

    env_id = resolve_env_id(args.env)
    kwargs = {}
    if args.initial_states is not None:
        if "KuramotoSivashinsky" not in env_id:
            raise ValueError("--initial-states applies to the KS environment only")
        kwargs["initial_states"] = args.initial_states
    env = gym.make(env_id, max_episode_steps=args.steps, **kwargs) if args.steps else gym.make(env_id, **kwargs)
    value = None if args.value is None else [float(v) for v in args.value.split(",")]
    policy = make_simple_policy(env.action_space, args.policy, np.random.default_rng(args.seed), value)
    record = run_episode(env, policy, seed=args.seed)
    out = Path(args.out) if args.out else Path("out") / f"{env_id.split('/')[-1]}_{args.policy}_seed{args.seed}.png"
    base = env.unwrapped
    x = getattr(base.physics, "x", None) if isinstance(base, PhysicsEnv) and base.physics.state_dim > 4 else None
    plotting.plot_episode(record, out, x=x)
    print(f"{env_id}  policy={args.policy}  seed={args.seed}  steps={record.length}  return={record.total_return:.4f}")
    print(f"figure: {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pimbrl", description="Physics-informed model-based RL for dynamic control.")
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("simulate", help="run one episode with a simple policy, print the return and plot it")
    sim.add_argument("env", help="ks | burgers | cartpole | pendulum, or a registered Gymnasium id")
    sim.add_argument("--policy", choices=["zero", "random", "constant"], default="zero")
    sim.add_argument("--value", help="for --policy constant: one number, or comma-separated per action component")
    sim.add_argument("--seed", type=int, default=0, help="seeds the initial state and the random policy")
    sim.add_argument("--steps", type=int, default=None, help="episode length (default: the env's time limit)")
    sim.add_argument("--initial-states", choices=["train", "test"], default=None, help="KS only: which initial-state pool")
    sim.add_argument("--out", help="PNG path (default: out/<env>_<policy>_seed<seed>.png)")
    sim.set_defaults(func=_cmd_simulate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "steps", None) is not None and args.steps < 1:
        parser.error("--steps must be >= 1")
    try:
        return int(args.func(args))
    except (ValueError, FileNotFoundError) as exc:
        print(f"pimbrl {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
