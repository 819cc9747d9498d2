"""Gymnasium shells around a :class:`~pimbrl.envs.task.Task`: a single env and a native vector env.

Both hold float64 physical states and step them through the task's batched ``advance``; the vector env
steps all sub-environments in one call, with no Python loop over environments.

Common behaviour (docs/environments.md, section 'Common behaviour'):

* ``reset(seed=..., options={"initial_state": u})`` starts from a given physical state;
* actions outside the box are clipped; NaN/inf actions raise ``ValueError`` with a clear message;
* a state that blows up ends the episode with ``terminated=True``, the task's finite
  ``divergence_penalty`` as reward and ``info["diverged"] = True``; the observation returned is the
  last finite one, so no NaN ever reaches a replay buffer;
* every ``info`` carries the physical side of the step, the documented interface of the model-based
  methods (:data:`PHYSICS_INFO_KEYS`): ``info["state"]``, the physical state after the step (a float64
  copy, the last finite one where the step blew up); ``info["physical_action"]``, the clipped physical
  action that was applied (e.g. the force of Cart-Pole's discrete action); ``info["step_index"]``, the
  number of control steps since the reset (0 after ``reset``). ``reset`` returns ``state`` and
  ``step_index`` too. (The vector env exposes its states as the ``states`` property instead.);
* the time limit truncates (``truncated=True``, never ``terminated``): for the single env through
  Gymnasium's ``TimeLimit`` wrapper that ``gymnasium.make`` adds, for the vector env internally;
* ``options["initial_state"]`` must be finite, within the physics' divergence bound and have its
  observation in the observation space, else ``reset`` raises a one-line ``ValueError``;
* stepping the single env again after it returned ``terminated=True`` warns once per episode through
  ``gymnasium.logger.warn``, as Gymnasium's own environments do (the step still runs from the current
  state; call ``reset()``);
* ``render_mode="rgb_array"`` (single env): ``render()`` returns an ``(H, W, 3)`` ``uint8`` frame of the
  current state (:meth:`Task.render`); the default ``render_mode`` is ``None``;
* constructor arguments are type-checked, not coerced: ``num_envs=1.5`` or ``periodic_actuators="false"``
  is an error.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from .task import Task, check_positive_int

__all__ = ["PHYSICS_INFO_KEYS", "PhysicsEnv", "PhysicsVectorEnv"]

#: Keys of the physical side of a step in ``info`` (see the module docstring).
PHYSICS_INFO_KEYS = ("state", "physical_action", "step_index")


def _checked_options(options: Any) -> dict[str, Any]:
    """``reset``'s ``options``: a dict (or ``None``), else a one-line ``TypeError`` saying what it must be."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise TypeError(f"reset(options=...) must be a dict such as {{'initial_state': u}} or None, got {options!r}")
    return options


class PhysicsEnv(gym.Env):
    """Single-environment shell; subclasses set :attr:`task_class` and document the task."""

    task_class: ClassVar[type[Task]]
    #: subclasses set ``render_fps`` to their task's (one frame per control step, in real time)
    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 30}  # noqa: RUF012 - Gymnasium's attribute

    def __init__(self, render_mode: str | None = None, **task_kwargs: Any) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(
                f"render_mode={render_mode!r} is not supported (only 'rgb_array', or None); "
                "use `pimbrl simulate` or pimbrl.plotting for figures"
            )
        self.task = self.task_class(**task_kwargs)
        self.physics = self.task.physics
        self.observation_space = self.task.observation_space
        self.action_space = self.task.action_space
        self.render_mode = render_mode
        self._u: np.ndarray | None = None  # (1, state_dim) float64
        self._k = np.zeros(1, dtype=np.int64)
        self._terminated = False  # the last step ended the episode (terminated=True)
        self._warned_after_termination = False

    @property
    def state(self) -> np.ndarray:
        """The current physical state (a copy)."""
        if self._u is None:
            raise RuntimeError("call reset() before reading the state")
        return self._u[0].copy()

    @property
    def elapsed_steps(self) -> int:
        """Control steps taken since the last reset."""
        return int(self._k[0])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode from ``options["initial_state"]`` if given, else from a sampled initial state."""
        super().reset(seed=seed)
        options = _checked_options(options)
        if options.get("initial_state") is not None:
            self._u = self.task.check_initial_state(options["initial_state"])[None].copy()
        else:
            self._u = self.task.sample_initial_states(self.np_random, 1)
        self._k = np.zeros(1, dtype=np.int64)
        self._terminated = False
        self._warned_after_termination = False
        return self.task.observe(self._u, self._k)[0], {"diverged": False, "state": self._u[0].copy(), "step_index": 0}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply one action for one control step; ``info`` carries the physical side of the step."""
        if self._u is None:
            raise RuntimeError("call reset() before step()")
        if self._terminated and not self._warned_after_termination:
            gym.logger.warn(
                "You are calling 'step()' even though this environment has already returned terminated = True. "
                "You should always call 'reset()' once you receive 'terminated = True' -- any further steps are "
                "undefined behavior."
            )
            self._warned_after_termination = True
        a = self.task.physical_action(action, 1)
        out = self.task.advance(self._u, a, self._k)
        self._u = out.state
        self._k = self._k + 1
        obs = self.task.observe(self._u, self._k)[0]
        info = {
            "diverged": bool(out.diverged[0]),
            "state": self._u[0].copy(),
            "physical_action": a[0].copy(),
            "step_index": int(self._k[0]),
        }
        self._terminated = self._terminated or bool(out.terminated[0])
        return obs, float(out.reward[0]), bool(out.terminated[0]), False, info

    def render(self) -> np.ndarray | None:
        """The current state as an ``(H, W, 3)`` ``uint8`` RGB frame (``render_mode="rgb_array"``).

        With ``render_mode=None`` (the default) it warns and returns ``None``, as Gymnasium's environments do.
        """
        if self.render_mode is None:
            gym.logger.warn(
                "You are calling render method without specifying any render mode. "
                f'You can specify the render_mode at initialization, e.g. gym.make("{self.spec.id if self.spec else ""}", '
                'render_mode="rgb_array")'
            )
            return None
        if self._u is None:
            raise RuntimeError("call reset() before render()")
        return self.task.render(self._u[0], int(self._k[0]))


class PhysicsVectorEnv(VectorEnv):
    """Native vector-environment shell: all sub-environments advance in one batched call.

    Args:
        num_envs: number of sub-environments.
        max_episode_steps: time limit (``truncated=True``); defaults to the task's episode length.
        autoreset_mode: Gymnasium's ``AutoresetMode`` (or its value): ``NEXT_STEP`` (default, as
            Gymnasium's own vector envs), ``SAME_STEP`` (the final observation is in
            ``info["final_obs"]``) or ``DISABLED`` (reset with ``options={"reset_mask": mask}``).
        **task_kwargs: passed to the task.
    """

    task_class: ClassVar[type[Task]]
    metadata: dict[str, Any] = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int = 1,
        max_episode_steps: int | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        render_mode: str | None = None,
        **task_kwargs: Any,
    ) -> None:
        self.num_envs = check_positive_int(num_envs, "num_envs")
        if render_mode is not None:
            raise ValueError(
                f"render_mode={render_mode!r} is not supported by pimbrl's vector envs; render a single env "
                "(gymnasium.make(..., render_mode='rgb_array'))"
            )
        self.task = self.task_class(**task_kwargs)
        self.physics = self.task.physics
        self.max_episode_steps = (
            self.task.max_episode_steps
            if max_episode_steps is None
            else check_positive_int(max_episode_steps, "max_episode_steps")
        )
        self.autoreset_mode = AutoresetMode(autoreset_mode)
        self.metadata = {**self.metadata, "autoreset_mode": self.autoreset_mode}
        self.render_mode = None
        self.single_observation_space = self.task.observation_space
        self.single_action_space = self.task.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._u = np.zeros((self.num_envs, self.task.state_dim))
        self._k = np.zeros(self.num_envs, dtype=np.int64)
        self._needs_reset = np.zeros(self.num_envs, dtype=bool)
        self._has_reset = False

    @property
    def states(self) -> np.ndarray:
        """Current physical states ``(num_envs, state_dim)`` (a copy)."""
        return self._u.copy()

    def reset(
        self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset the sub-environments selected by ``options["reset_mask"]`` (default: all).

        They start from ``options["initial_state"]`` (one state for all, or one per sub-environment) if
        given, else from sampled initial states. A list of seeds uses its first seed.
        """
        if isinstance(seed, list):
            seed = seed[0] if seed else None
        super().reset(seed=seed)
        options = _checked_options(options)
        mask = np.asarray(options.get("reset_mask", np.ones(self.num_envs, dtype=bool)), dtype=bool)
        if mask.shape != (self.num_envs,):
            raise ValueError(f"options['reset_mask'] must have shape ({self.num_envs},), got {mask.shape}")
        init = options.get("initial_state")
        if init is not None:
            init = np.asarray(init, dtype=np.float64)
            if init.shape == (self.task.state_dim,):
                init = np.broadcast_to(init, (self.num_envs, self.task.state_dim))
            if init.shape != (self.num_envs, self.task.state_dim):
                raise ValueError(
                    f"options['initial_state'] must have shape ({self.task.state_dim},) or "
                    f"({self.num_envs}, {self.task.state_dim}), got {init.shape}"
                )
            new = np.stack([self.task.check_initial_state(s) for s in init[mask]]) if mask.any() else init[mask]
        else:
            new = self.task.sample_initial_states(self.np_random, int(mask.sum()))
        self._u[mask] = new
        self._k[mask] = 0
        self._needs_reset[mask] = False
        self._has_reset = True
        return self.task.observe(self._u, self._k), {}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Advance all sub-environments by one control step in one batched call, autoresetting per ``autoreset_mode``."""
        if not self._has_reset:
            raise RuntimeError("call reset() before step()")
        a = self.task.physical_action(actions, self.num_envs)
        out = self.task.advance(self._u, a, self._k)
        resetting = self._needs_reset if self.autoreset_mode == AutoresetMode.NEXT_STEP else np.zeros(self.num_envs, dtype=bool)
        stepped = ~resetting
        self._u[stepped] = out.state[stepped]
        self._k[stepped] += 1
        reward = np.where(stepped, out.reward, 0.0)
        terminated = out.terminated & stepped
        truncated = (self._k >= self.max_episode_steps) & stepped & ~terminated
        diverged = out.diverged & stepped
        if resetting.any():
            self._u[resetting] = self.task.sample_initial_states(self.np_random, int(resetting.sum()))
            self._k[resetting] = 0
        done = terminated | truncated
        infos: dict[str, Any] = {"diverged": diverged, "_diverged": np.ones(self.num_envs, dtype=bool)}
        obs = self.task.observe(self._u, self._k)
        if self.autoreset_mode == AutoresetMode.SAME_STEP and done.any():
            infos["final_obs"] = np.where(done[:, None], obs, 0).astype(obs.dtype)
            infos["_final_obs"] = done.copy()
            self._u[done] = self.task.sample_initial_states(self.np_random, int(done.sum()))
            self._k[done] = 0
            obs = self.task.observe(self._u, self._k)
        self._needs_reset = done if self.autoreset_mode == AutoresetMode.NEXT_STEP else np.zeros(self.num_envs, dtype=bool)
        return obs, reward, terminated, truncated, infos
