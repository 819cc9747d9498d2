"""The controller interface and the loop that plays a controller on the real environment.

A :class:`Controller` reads the physical state (not only the observation): it is the knowledge these
methods assume. :func:`play` runs it from given initial states on a native vector environment of the task
(the same environment and states the RL methods are evaluated on) and measures the wall time spent inside
the controller per control step and state: its inference cost.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from ..envs import PhysicsEnv, Task

__all__ = ["ControlResult", "Controller", "env_actions", "play", "task_of"]


class Controller(ABC):
    """A state-feedback policy: physical states ``(B, n)`` and step indices ``(B,)`` to physical actions ``(B, m)``.

    :meth:`reset` is called with the batch size before each batch of episodes (a controller with memory, e.g.
    MPC's warm start, clears it there). :attr:`transitions` counts the transitions of a model or scheme the
    controller has stepped (0 for feedback and a policy network).
    """

    #: scheme/model transitions stepped while acting (MPC's optimisation), summed over every call
    transitions: int = 0
    #: decisions (one state at one control step) on which the scheme blew up during planning, so that some of
    #: the plan's optimisation steps were not taken (MPC), summed over every call
    blown_up: int = 0

    def reset(self, batch: int) -> None:  # noqa: B027 - optional hook: a memoryless controller has nothing to clear
        """Start a new batch of ``batch`` episodes."""

    @abstractmethod
    def __call__(self, states: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Physical actions ``(B, action_dim)`` for physical states ``(B, state_dim)`` at control steps ``k``."""


@dataclass(frozen=True)
class ControlResult:
    """Returns and lengths of a batch of episodes played by a controller, and what acting cost."""

    returns: np.ndarray
    lengths: np.ndarray
    #: seconds inside the controller, over all control steps and states
    inference_s: float
    #: control steps summed over the episodes (each state's steps while it was alive): real simulator steps
    control_steps: int
    #: scheme/model transitions the controller stepped while acting
    scheme_transitions: int
    #: states the controller computed actions for (a batched call acts for ended episodes too); default:
    #: ``control_steps``
    acted: int | None = None
    #: decisions on which the scheme blew up while planning (:attr:`Controller.blown_up`)
    blown_up: int = 0

    @property
    def mean(self) -> float:
        """Mean return over the episodes."""
        return float(self.returns.mean())

    @property
    def inference_s_per_step(self) -> float:
        """Wall seconds of the controller per state it computed an action for (batched calls share their time)."""
        acted = self.control_steps if self.acted is None else self.acted
        return self.inference_s / max(acted, 1)


def task_of(env_id: str, env_kwargs: dict[str, Any]) -> Task:
    """The task of a pimbrl environment (a clear ``ValueError`` for an environment without one)."""
    base = gym.make(env_id, **env_kwargs).unwrapped
    if not isinstance(base, PhysicsEnv):
        raise ValueError(
            f"{env_id} is not a pimbrl system: feedback, MPC and DPC need its equation (declare it, docs/systems.md)"
        )
    return base.task


def env_actions(task: Task, physical: np.ndarray) -> Any:
    """What the environment's ``step`` takes for physical actions ``(B, m)``: the Box action, Cart-Pole's push side."""
    space = task.action_space
    if isinstance(space, gym.spaces.Discrete):  # a force on a two-sided push (Cart-Pole): push the force's way
        return (np.asarray(physical)[:, 0] >= 0).astype(np.int64) + int(space.start)
    return np.asarray(physical, dtype=space.dtype)


def play(
    env_id: str, env_kwargs: dict[str, Any], controller: Controller, initial_states: np.ndarray, seed: int = 0
) -> ControlResult:
    """Play ``controller`` for one episode from each of ``initial_states`` on the real environment, all at once."""
    initial_states = np.asarray(initial_states, dtype=np.float64)
    n = len(initial_states)
    vec = gym.make_vec(
        env_id, num_envs=n, vectorization_mode="vector_entry_point", autoreset_mode=AutoresetMode.DISABLED, **env_kwargs
    )
    base = vec.unwrapped
    task: Task = base.task  # type: ignore[attr-defined]
    vec.reset(seed=seed, options={"initial_state": initial_states})
    before, blown_before = controller.transitions, getattr(controller, "blown_up", 0)  # a duck-typed one may lack it
    controller.reset(n)
    returns = np.zeros(n)
    lengths = np.zeros(n, dtype=np.int64)
    alive = np.ones(n, dtype=bool)
    k = np.zeros(n, dtype=np.int64)
    spent = 0.0
    steps = acted = 0
    while alive.any():
        states = base.states  # type: ignore[attr-defined]
        start = time.perf_counter()
        actions = controller(states, k.copy())
        spent += time.perf_counter() - start
        if not np.all(np.isfinite(actions)):
            raise FloatingPointError(
                f"the controller gave a non-finite action at step {int(k.max())}; for MPC or DPC, give the scheme more "
                "steps per control step (--model.n-intermediate) or a smaller --model.lr"
            )
        _, reward, terminated, truncated, _ = vec.step(env_actions(task, actions))
        steps += int(alive.sum())
        acted += n
        returns += np.where(alive, reward, 0.0)
        lengths += alive
        alive &= ~(terminated | truncated)
        k += 1
    vec.close()
    return ControlResult(
        returns, lengths, spent, steps, controller.transitions - before, acted, getattr(controller, "blown_up", 0) - blown_before
    )
