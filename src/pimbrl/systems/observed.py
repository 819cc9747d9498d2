"""Any Gymnasium env with Box spaces as a data-only system: the state is the observation, the reward is learned.

Model-based RL needs a state to predict and a reward to score imagined steps with. A pimbrl system declares
both; an environment from elsewhere declares neither. :class:`ObservedEnv` wraps such an env so that the
observation serves as the state (``info["state"]``, ``info["physical_action"]``, ``info["step_index"]``, as
pimbrl environments report them), and its :class:`ObservedTask` holds an :class:`ObservationPhysics`: no
equation (so no physics loss: ``--method mbrl`` only), an unbounded state, no termination of its own, and a
reward that the run learns from the real transitions (:class:`pimbrl.models.reward.LearnedReward`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..envs.task import StepOutcome, Task
from ..physics.base import Array, Physics

__all__ = ["ObservationPhysics", "ObservedEnv", "ObservedTask"]


class ObservationPhysics(Physics):
    """The physics of an environment known only by its data: the state is the observation.

    The reward of imagined steps is :attr:`reward_fn`, set by the run to its learned reward; there is no
    equation, so nothing can be simulated or checked with it.
    """

    name = "observed"
    #: the reward is not known: the run learns it (pimbrl.training.dyna)
    learned_reward = True

    def __init__(self, state_dim: int, action_low: np.ndarray, action_high: np.ndarray) -> None:
        self.state_dim = int(state_dim)
        self.action_low = np.asarray(action_low, dtype=np.float64).reshape(-1)
        self.action_high = np.asarray(action_high, dtype=np.float64).reshape(-1)
        self.action_dim = len(self.action_low)
        self.dt = 1.0
        self.substeps = 1
        #: ``f(u, a, u_next) -> rewards``: the learned reward (``None`` until a run sets it)
        self.reward_fn: Callable[[Any, Any, Any], np.ndarray] | None = None

    def _no_equation(self) -> ValueError:
        return ValueError(
            "this environment has no declared equation (it is known by its data only): use --method mbrl, or "
            "declare the system (docs/systems.md) to use pimbrl"
        )

    def rhs(self, u: Array, a: Array) -> Array:
        """Not known: raises."""
        raise self._no_equation()

    def substep(self, u: Array, a: Array) -> Array:
        """Not known: raises."""
        raise self._no_equation()

    def advance(self, u: np.ndarray, a: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Not known: the environment itself is stepped."""
        raise self._no_equation()

    def reward(self, u: Array, a: Array, u_next: Array, k: Array | int, path: Array | None = None) -> Array:
        """The learned reward of the transitions ``u --a--> u_next``."""
        if self.reward_fn is None:
            raise ValueError("the learned reward is not set: an observed environment's reward is learned by the run")
        return self.reward_fn(u, a, u_next)  # type: ignore[return-value]


class ObservedTask(Task):
    """The task of an observed environment: its spaces and episode length, the observation as the state."""

    physics: ObservationPhysics
    action_space: spaces.Box

    def __init__(self, env: gym.Env) -> None:
        obs_space, act_space = env.observation_space, env.action_space
        if not (isinstance(obs_space, spaces.Box) and len(obs_space.shape) == 1):
            raise ValueError(f"data-only MBRL needs a 1-D Box observation space, got {obs_space}")
        if not (isinstance(act_space, spaces.Box) and len(act_space.shape) == 1):
            raise ValueError(f"data-only MBRL needs a 1-D Box action space, got {act_space}")
        if not (np.all(np.isfinite(act_space.low)) and np.all(np.isfinite(act_space.high))):
            raise ValueError(f"data-only MBRL needs finite action bounds, got {act_space}")
        self.physics = ObservationPhysics(obs_space.shape[0], act_space.low, act_space.high)
        self.observation_space = spaces.Box(obs_space.low.astype(np.float32), obs_space.high.astype(np.float32), dtype=np.float32)
        self.action_space = act_space
        spec = env.spec
        self.max_episode_steps = int(spec.max_episode_steps) if spec is not None and spec.max_episode_steps else 1_000

    def sample_initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Not available: the environment draws its own initial states at reset."""
        raise ValueError("an observed environment draws its initial states itself (at reset); they cannot be sampled here")

    def observe(self, u: np.ndarray, k: np.ndarray) -> np.ndarray:
        """The state is the observation (as float32)."""
        return np.asarray(u, dtype=np.float32)

    def physical_action(self, actions: Any, batch: int) -> np.ndarray:
        """Check the actions' shape and finiteness and clip them to the action bounds."""
        return self._box_action(actions, batch, self.action_space, self.physics.action_low, self.physics.action_high)

    def advance(self, u: np.ndarray, physical_action: np.ndarray, k: np.ndarray) -> StepOutcome:
        """Not available: the environment itself is stepped."""
        raise ValueError("an observed environment is stepped itself; its task cannot advance states")


class ObservedEnv(gym.Wrapper):
    """Reports an environment's observation as its physical state, as pimbrl environments report theirs."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.task = ObservedTask(env)
        self._k = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Reset the environment; ``info`` gains the state (the observation) and the step index 0."""
        obs, info = self.env.reset(seed=seed, options=options)
        self._k = 0
        return obs, {**info, "state": np.asarray(obs, dtype=np.float64).copy(), "step_index": 0}

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        """Step with the action clipped to the bounds; ``info`` gains the state, the action applied and the step index."""
        a = self.task.physical_action(action, 1)[0]
        obs, reward, terminated, truncated, info = self.env.step(a.astype(self.env.action_space.dtype))
        self._k += 1
        extra = {"state": np.asarray(obs, dtype=np.float64).copy(), "physical_action": a, "step_index": self._k}
        return obs, reward, terminated, truncated, {**info, **extra}
