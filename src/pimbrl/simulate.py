"""Run one episode of an environment with a simple policy and record it (for plots and the CLI)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from .envs import PhysicsEnv
from .systems import resolve_env_id

__all__ = ["EpisodeRecord", "make_simple_policy", "resolve_env_id", "run_episode"]

Policy = Callable[[np.ndarray], Any]


@dataclass
class EpisodeRecord:
    """One recorded episode.

    ``states`` are physical states when the env exposes them (pimbrl envs), else observations;
    ``actions`` are the actions passed to ``env.step``.
    """

    env_id: str
    states: np.ndarray  # (T + 1, state_dim)
    actions: np.ndarray  # (T, ...) as given to the env
    rewards: np.ndarray  # (T,)
    terminated: bool
    truncated: bool
    control_dt: float
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def total_return(self) -> float:
        """Undiscounted sum of the episode's rewards."""
        return float(self.rewards.sum())

    @property
    def length(self) -> int:
        """Number of steps taken."""
        return len(self.rewards)


def make_simple_policy(space: gym.Space, kind: str, rng: np.random.Generator, value: Any = None) -> Policy:
    """``zero``, ``random`` (uniform over the space, seeded by ``rng``) or ``constant`` (``value``)."""
    if kind == "zero":
        zero = space.sample() * 0 if not isinstance(space, gym.spaces.Discrete) else 0
        return lambda obs: zero
    if kind == "random":
        return lambda obs: _sample(space, rng)
    if kind == "constant":
        if value is None:
            raise ValueError("--policy constant needs --value (one number, or one per action component)")
        if isinstance(space, gym.spaces.Discrete):
            const: Any = int(np.asarray(value).reshape(-1)[0])
            if not space.contains(const):
                raise ValueError(f"constant action {const} is not in {space}")
        else:
            if space.shape is None:
                raise TypeError(f"no constant policy for {space}: it has no shape")
            const = np.broadcast_to(np.asarray(value, dtype=space.dtype), space.shape).copy()
        return lambda obs: const
    raise ValueError(f"unknown policy {kind!r}: use zero, random or constant")


def _sample(space: gym.Space, rng: np.random.Generator) -> Any:
    if isinstance(space, gym.spaces.Discrete):
        return int(rng.integers(space.n)) + int(space.start)
    if isinstance(space, gym.spaces.Box):
        return rng.uniform(space.low, space.high).astype(space.dtype)
    raise TypeError(f"no random policy for {space}")


def run_episode(env: gym.Env, policy: Policy, seed: int | None = None, options: dict[str, Any] | None = None) -> EpisodeRecord:
    """Run ``policy`` for one episode of ``env`` and record states, actions and rewards."""
    obs, _ = env.reset(seed=seed, options=options)
    base = env.unwrapped
    physical = base if isinstance(base, PhysicsEnv) else None
    states = [physical.state if physical is not None else np.asarray(obs, dtype=np.float64)]
    actions: list[np.ndarray] = []
    rewards: list[float] = []
    terminated = truncated = False
    info: dict[str, Any] = {}
    while not (terminated or truncated):
        action = policy(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        actions.append(np.asarray(action))
        rewards.append(float(reward))
        states.append(physical.state if physical is not None else np.asarray(obs, dtype=np.float64))
    control_dt = physical.physics.control_dt if physical is not None else float(getattr(base, "dt", getattr(base, "tau", 1.0)))
    spec_id = env.spec.id if env.spec is not None else type(base).__name__
    return EpisodeRecord(spec_id, np.array(states), np.array(actions), np.array(rewards), terminated, truncated, control_dt, info)
