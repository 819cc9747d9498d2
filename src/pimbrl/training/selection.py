"""Model-based policy selection: rank the evaluated policies by their return *in the model*.

A run's latest policy is not its best one: between two evaluations the mean test return of a KS agent
moves by several units while the trend rises slowly. The held-out test states may not be used to pick a
policy (the pick would be scored on the states it was picked on). A model-based run has another judge
to hand: its model. At every evaluation :class:`PolicySelector` runs the deterministic policy for whole
episodes in the model, from the task's fixed *validation* initial states, and keeps the
policy whose mean imagined return is the highest so far. What is reported for the selected policy is the
test return it got at that evaluation, on states the selection never saw.

How good the judge is depends on the model: with the physics in the model (``dyna.model physics``) an
imagined episode is the simulator's episode to round-off; a learned model ranks policies only as well as
it predicts whole episodes. Selection draws nothing from the run's random streams (its start states are
the validation draws, the same whatever the evaluation seed; a ``Discrete(2)`` action maps to its more probable value, as in
evaluation) and changes no weight, so a run with selection trains exactly as the same run without it.

An imagined episode ends like a real one: at the time limit or at a termination. A prediction that blows
up ends the episode with the task's ``divergence_penalty`` (as a real blow-up does), counted in
``blown_up``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..agents import Agent
from ..models import ModelEnv

__all__ = ["ImaginedEvaluation", "PolicySelector"]


@dataclass(frozen=True)
class ImaginedEvaluation:
    """Returns of whole imagined episodes of the deterministic policy."""

    returns: np.ndarray  # (episodes,)
    blown_up: int  # episodes ended by a prediction outside the physics' divergence bound

    @property
    def mean(self) -> float:
        """Mean imagined return."""
        return float(self.returns.mean())


class PolicySelector:
    """Scores each evaluated policy in the model and keeps the best one (see the module docstring).

    Args:
        env: the run's imagined environment (shared: the current model judges, with the physics the run's
            imagination uses, learned coefficients included).
        episodes: imagined episodes per evaluation, from that many validation initial states.
    The start states are the task's validation draws (:meth:`~pimbrl.envs.Task.validation_initial_states`):
    fixed, disjoint from the test states, and the same whatever the run's evaluation seed, so that the test
    set decides nothing.
    """

    def __init__(self, env: ModelEnv, episodes: int) -> None:
        if episodes <= 0:
            raise ValueError(f"policy selection needs at least one imagined episode, got {episodes}")
        self.env = env
        self.task = env.task
        self.states = self.task.validation_initial_states(episodes)
        self.best_return: float | None = None
        self.best_step: int | None = None
        self.best_test_return: float | None = None
        self.best_policy: dict[str, Any] | None = None

    def evaluate(self, agent: Agent) -> ImaginedEvaluation:
        """Whole imagined episodes of ``agent``'s deterministic policy from the fixed start states."""
        state = self.states.copy()
        n = len(state)
        k = np.zeros(n, dtype=np.int64)
        returns = np.zeros(n)
        alive = np.ones(n, dtype=bool)
        blown = np.zeros(n, dtype=bool)
        for _ in range(self.task.max_episode_steps):
            if not alive.any():
                break
            idx = np.flatnonzero(alive)
            s, kk = state[idx], k[idx]
            action = agent.act(self.task.observe(s, kk), deterministic=True)
            nxt, reward, terminated, valid, _ = self.env.step(s, kk, action, deterministic=True)
            returns[idx] += np.where(valid, reward, self.task.divergence_penalty)
            blown[idx[~valid]] = True
            state[idx[valid]] = nxt[valid]
            k[idx] += 1
            alive[idx] = valid & ~terminated & (kk + 1 < self.task.max_episode_steps)
        return ImaginedEvaluation(returns, int(blown.sum()))

    def observe(self, step: int, agent: Agent, test_return: float) -> dict[str, Any]:
        """Score the current policy and keep it if it is the best so far.

        Returns the row of ``selection.csv`` (:attr:`~pimbrl.training.rundir.RunDirectory.SELECTION_COLUMNS`).
        """
        result = self.evaluate(agent)
        if self.best_return is None or result.mean > self.best_return:
            self.best_return, self.best_step, self.best_test_return = result.mean, step, test_return
            self.best_policy = agent.policy_state()
        return {
            "step": step,
            "model_return_mean": result.mean,
            "model_return_min": float(result.returns.min()),
            "blown_up": result.blown_up,
            "return_mean": test_return,
            "selected_step": self.best_step,
            "selected_return_mean": self.best_test_return,
        }

    def state_dict(self) -> dict[str, Any]:
        """The best policy so far, its step, imagined and test returns."""
        return copy.deepcopy(
            {
                "best_return": self.best_return,
                "best_step": self.best_step,
                "best_test_return": self.best_test_return,
                "best_policy": self.best_policy,
            }
        )

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.best_return = state["best_return"]
        self.best_step = state["best_step"]
        self.best_test_return = state["best_test_return"]
        self.best_policy = copy.deepcopy(state["best_policy"])
