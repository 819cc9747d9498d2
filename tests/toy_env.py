"""A toy control task for learning tests: drive a point to the origin.

State ``x`` in ``[-1, 1]^2``; action ``a`` in ``[-1, 1]^2``; ``x' = clip(x + 0.25 a)``; reward ``-|x'|^2``;
20 steps. A random policy returns about -5, the optimal one about -0.4.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class ReachEnv(gym.Env):
    metadata = {"render_modes": []}  # noqa: RUF012 - Gymnasium declares it as an attribute

    def __init__(self, discrete: bool = False) -> None:
        self.observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.discrete = discrete
        self.action_space = spaces.Discrete(2) if discrete else spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.x = np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = self.np_random.uniform(-1, 1, 2) if not self.discrete else np.array([self.np_random.uniform(-1, 1), 0.0])
        return self.x.astype(np.float32), {}

    def step(self, action):
        a = np.array([1.0 if action == 1 else -1.0, 0.0]) if self.discrete else np.asarray(action, dtype=np.float64)
        self.x = np.clip(self.x + 0.25 * a, -1, 1)
        return self.x.astype(np.float32), -float(self.x @ self.x), False, False, {}


def register() -> None:
    if "toy/Reach-v0" not in gym.registry:
        gym.register("toy/Reach-v0", entry_point=ReachEnv, max_episode_steps=20)
        gym.register("toy/ReachDiscrete-v0", entry_point=ReachEnv, kwargs={"discrete": True}, max_episode_steps=20)
