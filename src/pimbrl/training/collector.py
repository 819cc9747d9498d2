"""Real interaction: one environment, the current observation, episode bookkeeping.

The collector steps the real environment with the agent (or uniformly random actions during warm-up) and
returns each step as :class:`~pimbrl.buffers.Transitions`. For the model-based methods it also records
the physical side of the step - state, next state, physical action, step index - which it reads from the
documented ``info`` keys of pimbrl environments (:data:`pimbrl.envs.PHYSICS_INFO_KEYS`), never from
private fields of the environment.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from ..agents import Agent
from ..buffers import Transitions
from ..envs import PHYSICS_INFO_KEYS, PhysicsEnv
from ..physics import Physics
from ..spaces import ActionAdapter
from ..systems.observed import ObservedEnv
from .streams import RandomStreams

__all__ = ["Collector", "EpisodeEnd", "StepResult"]


@dataclass(frozen=True, slots=True)
class StepResult:
    """One real step: the stored transition, whether the episode ended, and whether the step blew up."""

    transition: Transitions
    done: bool
    valid: bool


@dataclass(frozen=True, slots=True)
class EpisodeEnd:
    """A finished training episode (a row of ``episodes.csv``)."""

    episode: int
    return_: float
    length: int


class Collector:
    """Steps one real environment and keeps the episode counters.

    Args:
        env_id, env_kwargs: what ``gymnasium.make`` builds.
        streams: the run's random streams (``env`` seeds the first reset; ``exploration`` draws warm-up
            actions and the stochastic ``Discrete(2)`` mapping).
        record_physics: also return the physical side of each step (model-based methods): a pimbrl
            environment's, or, for any other env with Box spaces, its observation as the state
            (:class:`~pimbrl.systems.observed.ObservedEnv`).
    """

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], streams: RandomStreams, record_physics: bool) -> None:
        self.env = gym.make(env_id, **env_kwargs)
        space = self.env.observation_space
        if not isinstance(space, gym.spaces.Box):
            raise ValueError(f"{env_id}: pimbrl agents need a Box observation space, got {space}")
        self.obs_dim = int(np.prod(space.shape))
        self.adapter = ActionAdapter(self.env.action_space)
        self.streams = streams
        base = self.env.unwrapped
        self.physics: Physics | None = base.physics if isinstance(base, PhysicsEnv) else None
        if record_physics and self.physics is None:  # any other env: its observation is the state (data-only)
            observed = ObservedEnv(self.env)
            self.env = observed
            self.physics = observed.task.physics
        self.record_physics = record_physics
        self.episode = 0
        self.episode_return = 0.0
        self.episode_length = 0
        self._obs: np.ndarray | None = None
        self._state: np.ndarray | None = None

    @property
    def task(self) -> Any:
        """The pimbrl task of the environment (an observed env's for a model-based run on another env; else ``None``)."""
        if isinstance(self.env, ObservedEnv):
            return self.env.task
        return getattr(self.env.unwrapped, "task", None)

    def reset(self, first: bool) -> None:
        """Start an episode; the first one of a run is seeded from the ``env`` stream."""
        obs, info = self.env.reset(seed=self.streams.integer_seed("env") if first else None)
        self._obs = obs
        if self.record_physics:
            self._state = self._canonical(info)

    def step(self, agent: Agent, random_action: bool) -> StepResult:
        """One real step with a uniformly random action (warm-up) or the agent's exploring action."""
        if self._obs is None:
            raise RuntimeError("Collector.reset() must come before step()")
        obs = self._obs
        action = self.adapter.sample(self.streams.exploration) if random_action else agent.act(obs)[0]
        next_obs, reward, terminated, truncated, info = self.env.step(self.adapter.to_env(action, self.streams.exploration))
        physics: dict[str, np.ndarray] = {}
        if self.record_physics:
            missing = [key for key in PHYSICS_INFO_KEYS if key not in info]
            if missing:
                raise KeyError(f"the environment's info lacks {missing}: a model-based run needs a pimbrl environment")
            next_state = self._canonical(info)
            physics = {
                "state": self._state[None],  # type: ignore[index]
                "next_state": next_state[None],
                "physical_action": np.asarray(info["physical_action"], dtype=np.float64)[None],
                "k": np.array([int(info["step_index"]) - 1]),
            }
            self._state = next_state
        self.episode_return += float(reward)
        self.episode_length += 1
        self._obs = next_obs
        tr = Transitions(
            obs=np.asarray(obs)[None],
            action=np.asarray(action, dtype=np.float32)[None],
            reward=np.array([reward], dtype=np.float64),
            next_obs=np.asarray(next_obs)[None],
            terminated=np.array([terminated]),
            truncated=np.array([truncated]),
            **physics,
        )
        return StepResult(tr, bool(terminated or truncated), not info.get("diverged", False))

    def end_episode(self) -> EpisodeEnd:
        """Close the current episode's counters (the caller resets the environment)."""
        self.episode += 1
        end = EpisodeEnd(self.episode, self.episode_return, self.episode_length)
        self.episode_return = 0.0
        self.episode_length = 0
        return end

    def _canonical(self, info: dict[str, Any]) -> np.ndarray:
        assert self.physics is not None
        return np.asarray(self.physics.canonical(np.asarray(info["state"], dtype=np.float64)), dtype=np.float64)

    def state_dict(self) -> dict[str, Any]:
        """Episode counters and the environment's generator (checkpoints are taken at episode ends)."""
        return {"episode": self.episode, "env_rng": self.env.np_random.bit_generator.state}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; the next :meth:`reset` continues the environment's stream."""
        self.episode = int(state["episode"])
        self.episode_return = 0.0
        self.episode_length = 0
        rng = np.random.Generator(np.random.PCG64())
        rng.bit_generator.state = state["env_rng"]
        self.env.np_random = rng
