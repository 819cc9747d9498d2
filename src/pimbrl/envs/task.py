"""A control task: a :class:`~pimbrl.physics.Physics` plus what an environment adds around it.

The task is batched and stateless: it maps agent actions to physical actions, physical states to
observations, draws initial states, and advances a batch of states with the physics' fast simulator,
turning blow-ups into terminations with a finite penalty. Both the single and the vector Gymnasium
environments are thin shells around one task, so their behaviour cannot drift apart.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces

from ..physics import Physics
from .render import BLUE, field_frame

__all__ = ["HOLDOUT_SEED", "VALIDATION_SEED", "StepOutcome", "Task", "check_bool", "check_finite_number", "check_positive_int"]

#: the entropy of the validation draws' seed stream (the ASCII bytes of "pimbrl-validation", truncated to 64
#: bits): fixed, and no run or evaluation seed (those are below 2**32), so validation draws are no test draws
VALIDATION_SEED = int.from_bytes(b"pimbrl-validation"[:8], "big")
#: the held-out draws' seed stream ("pimbrl-holdout"): the fresh test pool of a confirmatory study, which only
#: the final evaluation of a run reads (``holdout_episodes``); no run, evaluation or validation seed
HOLDOUT_SEED = int.from_bytes(b"pimbrl-holdout"[:8], "big")


def check_finite_number(value: Any, name: str) -> float:
    """``value`` as a float if it is a finite real number (an int or a float, not a bool or a string).

    Raises ``TypeError`` for a value of another type and ``ValueError`` for NaN or an infinity, each
    naming ``name``.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return out


def check_positive_int(value: Any, name: str) -> int:
    """``value`` if it is an integer >= 1 (a Python or NumPy int; not a float, a bool or a string)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value!r}")
    return int(value)


def check_bool(value: Any, name: str) -> bool:
    """``value`` if it is a bool (Python or NumPy); a string such as ``"false"`` or a number is an error."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {value!r}")
    return bool(value)


@dataclass
class StepOutcome:
    """What advancing a batch of environments by one control step gives (not a stored transition)."""

    state: np.ndarray  # (B, state_dim) float64: next state (the pre-step state where diverged)
    reward: np.ndarray  # (B,) float64
    terminated: np.ndarray  # (B,) bool: by the task's rule or by divergence
    diverged: np.ndarray  # (B,) bool


class Task(ABC):
    """Batched definition of a control task around one physics object.

    Subclasses set :attr:`physics`, :attr:`observation_space`, :attr:`action_space`,
    :attr:`max_episode_steps` and implement :meth:`sample_initial_states`, :meth:`observe` and
    :meth:`physical_action`.
    """

    physics: Physics
    observation_space: spaces.Space
    action_space: spaces.Space
    max_episode_steps: int
    #: reward given, instead of the physics' reward, on a step that blows up (then the episode ends)
    divergence_penalty: float = -100.0
    #: frames per second of ``render_mode="rgb_array"`` videos: one frame per control step, in real time
    render_fps: int = 30
    #: half-height of the vertical axis of :meth:`render`'s default line plot (widened to fit the state)
    render_scale: float = 1.0

    @abstractmethod
    def sample_initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``(n, state_dim)`` float64 physical initial states."""

    @abstractmethod
    def observe(self, u: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Observations ``(B, obs_dim)`` (float32) of states ``u`` at control steps ``k``."""

    @abstractmethod
    def physical_action(self, actions: Any, batch: int) -> np.ndarray:
        """Validate a batch of agent actions and map them to clipped physical actions ``(B, action_dim)``.

        Raises ``ValueError`` naming the problem for NaN/inf values, wrong shapes or invalid
        discrete actions.
        """

    # ------------------------------------------------------------------ shared behaviour
    @property
    def state_dim(self) -> int:
        """Length of the physical state vector."""
        return self.physics.state_dim

    def check_initial_state(self, state: Any) -> np.ndarray:
        """A user-given physical state as a float64 ``(state_dim,)`` array, or a clear ``ValueError``.

        The state must be finite, within the physics' divergence bound (the rule that ends an episode
        as blown up after a step, :meth:`Physics.diverged`), and its observation must lie in
        :attr:`observation_space` (finite in float32 too).
        """
        arr = np.asarray(state, dtype=np.float64)
        if arr.shape != (self.state_dim,):
            raise ValueError(
                f"options['initial_state'] must be the physical state with shape ({self.state_dim},), got shape {arr.shape}"
            )
        if not np.all(np.isfinite(arr)):
            raise ValueError("options['initial_state'] contains NaN or inf; pass a finite physical state")
        if bool(self.physics.diverged(arr[None])[0]):
            i = int(np.argmax(np.abs(arr)))
            bound = self.physics.divergence_bound
            raise ValueError(
                f"options['initial_state'][{i}] = {arr[i]:.6g} is beyond the divergence bound |u| <= {bound:g} of "
                f"{type(self.physics).__name__} (a step would end there as blown up); pass a state with |u| <= {bound:g}"
            )
        with np.errstate(over="ignore"):  # a float64 beyond float32's range becomes inf, reported below
            obs = self.observe(arr[None], np.zeros(1, dtype=np.int64))[0]
        if not (np.all(np.isfinite(obs)) and self.observation_space.contains(obs)):
            space = self.observation_space
            if isinstance(space, spaces.Box):
                flat = obs.reshape(-1)
                low, high = space.low.reshape(-1), space.high.reshape(-1)
                j = int(np.argmax(~np.isfinite(flat) | (flat < low) | (flat > high)))
                where = f"component {j} of its observation is {flat[j]:.6g}, outside [{low[j]:g}, {high[j]:g}]"
            else:
                where = "its observation is not in the observation space"
            raise ValueError(
                f"options['initial_state'] is outside the observation space: {where}; pass a state whose "
                "observation lies in the observation space"
            )
        return arr

    def advance(self, u: np.ndarray, physical_action: np.ndarray, k: np.ndarray) -> StepOutcome:
        """One control step for a batch (arguments in the order of :meth:`Physics.advance`).

        Blown-up environments keep their pre-step state, are terminated and get the divergence penalty.
        """
        u_next, reward = self.physics.advance(u, physical_action, k)
        return self.outcome(u, u_next, reward)

    def outcome(self, u: np.ndarray, u_next: np.ndarray, reward: np.ndarray) -> StepOutcome:
        """The step's outcome from its simulated next states and rewards: blow-ups and terminations applied."""
        reward = np.asarray(reward, dtype=np.float64) + np.zeros(len(u))
        diverged = self.physics.diverged(u_next) | ~np.isfinite(reward)
        terminated = np.asarray(self.physics.terminated(u_next), dtype=bool) | diverged
        if diverged.any():
            u_next = np.where(diverged[:, None], u, u_next)
            reward = np.where(diverged, self.divergence_penalty, reward)
        return StepOutcome(u_next, reward, terminated, diverged)

    @staticmethod
    def _box_action(actions: Any, batch: int, space: spaces.Box, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        """Validate continuous actions of a Box space and clip them into the physical bounds."""
        arr = np.asarray(actions, dtype=np.float64)
        shape = space.shape
        if arr.shape == shape and batch == 1:
            arr = arr[None]
        if arr.shape != (batch, *shape):
            raise ValueError(f"expected actions of shape {(batch, *shape) if batch > 1 else shape}, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(
                f"action contains NaN or inf ({arr.tolist() if arr.size <= 8 else 'array'}); "
                "the policy produced a non-finite value - check the agent's network and inputs"
            )
        return np.clip(arr, low, high)

    def render(self, u: np.ndarray, k: int) -> np.ndarray:
        """An RGB ``uint8`` frame ``(H, W, 3)`` of the physical state ``u`` at control step ``k``.

        By default a line plot of the state over its index (a PDE's field over the grid), the vertical
        axis spanning ``[-render_scale, render_scale]``; the ODE tasks draw a sketch of the system.
        """
        return field_frame([(u, BLUE)], self.render_scale)

    def test_initial_states(self, n: int, seed: int) -> np.ndarray:
        """``(n, state_dim)`` float64 initial states of the test episodes, the same on every call.

        By default ``n`` states drawn by :meth:`sample_initial_states` from ``np.random.default_rng(seed)``;
        a task with a fixed, held-out test set (KS) returns the first ``n`` states of that set instead.
        """
        return self.sample_initial_states(np.random.default_rng(seed), n)

    def validation_initial_states(self, n: int) -> np.ndarray:
        """``(n, state_dim)`` float64 initial states of the validation episodes, the same on every call.

        The draws that decisions during training read (the switch to model-free fine-tuning), so that the
        test states decide nothing. By default ``n`` states drawn by :meth:`sample_initial_states` from a
        seed stream of their own (:data:`VALIDATION_SEED`, not an evaluation seed, so that changing the test
        set changes no decision); a task with fixed pools (KS) returns the first ``n`` states of its
        validation pool, whose runs are disjoint from the training and test pools'.
        """
        return self.sample_initial_states(np.random.default_rng(np.random.SeedSequence(VALIDATION_SEED)), n)

    def holdout_initial_states(self, n: int) -> np.ndarray:
        """``(n, state_dim)`` float64 initial states of the held-out pool, the same on every call.

        The fresh test pool of a confirmatory study: read once, by the final evaluation of a run
        (``holdout_episodes``), never by an evaluation during training or a choice of settings. By default
        ``n`` states drawn by :meth:`sample_initial_states` from a seed stream of their own
        (:data:`HOLDOUT_SEED`); a task with fixed pools (KS) returns the first ``n`` states of its holdout pool,
        whose runs are disjoint from the other pools'.
        """
        return self.sample_initial_states(np.random.default_rng(np.random.SeedSequence(HOLDOUT_SEED)), n)

    def pool_size(self, protocol: str) -> int | None:
        """The number of states the pool of ``protocol`` holds (``None``: draws without limit, the default)."""
        return None

    def protocol_initial_states(self, protocol: str, n: int | None, seed: int) -> np.ndarray:
        """Initial states of the episodes of an evaluation ``protocol`` (one of :attr:`eval_protocols`).

        ``"test"``: :meth:`test_initial_states` (``n`` required); ``"validation"`` and ``"holdout"``:
        :meth:`validation_initial_states`, :meth:`holdout_initial_states` (``n`` required, ``seed`` unused).
        Other protocols are defined by the tasks that have them (KS: ``"authors"``); asking another task for
        one is a ``ValueError``.
        """
        if protocol in ("test", "validation", "holdout"):
            if n is None:
                raise ValueError(f"the {protocol!r} evaluation protocol needs a number of episodes")
            if protocol == "test":
                return self.test_initial_states(n, seed)
            return self.validation_initial_states(n) if protocol == "validation" else self.holdout_initial_states(n)
        raise ValueError(
            f"evaluation protocol {protocol!r} is not defined for {type(self).__name__}; "
            f"choose from {', '.join(repr(p) for p in self.eval_protocols)}"
        )

    @property
    def eval_protocols(self) -> tuple[str, ...]:
        """The evaluation protocols this task defines (``"test"``, ``"validation"`` and ``"holdout"``, for every task)."""
        return ("test", "validation", "holdout")
