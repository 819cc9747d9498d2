"""Run one episode of an environment with a simple policy and record it (for plots and the CLI)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from .envs import PhysicsEnv
from .systems import resolve_env_id

__all__ = ["EpisodeRecord", "make_simple_policy", "proportional_feedback", "resolve_env_id", "run_episode"]

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


def proportional_feedback(env: gym.Env, gain: float) -> Policy:
    """Proportional feedback for a PDE system with localised actuators: ``a_i = -gain * <obs>_i``, clipped.

    ``<obs>_i`` is the observation averaged under actuator ``i``'s shape (weights ``shape_i / sum(shape_i)``):
    for Burgers the local tracking error ``u - ref``, for KS the local ``u``. The actions are clipped to the
    action space. A floor that needs no learning and no model: any method should beat it.
    """
    if not np.isfinite(gain):
        raise ValueError(f"--gain must be a finite number, got {gain}")
    physics = getattr(env.unwrapped, "physics", None)
    shapes = getattr(physics, "actuator_shapes", None)
    space = env.action_space
    if shapes is None or not isinstance(space, gym.spaces.Box):
        raise ValueError(
            f"--policy feedback is for PDE systems with localised actuators (ks, burgers, a declared 1-D PDE), not "
            f"{env.spec.id if env.spec is not None else type(env.unwrapped).__name__}"
        )
    weights = np.asarray(shapes, dtype=np.float64)
    weights = weights / weights.sum(axis=1, keepdims=True)
    obs_dim = int(np.prod(env.observation_space.shape or (0,)))
    if weights.shape[1] != obs_dim:
        raise ValueError(
            f"--policy feedback averages the observation under each actuator: the actuators cover {weights.shape[1]} "
            f"points, the observation has {obs_dim}"
        )
    low, high = space.low, space.high
    return lambda obs: np.clip(-gain * (weights @ np.asarray(obs, dtype=np.float64).reshape(-1)), low, high).astype(space.dtype)


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
