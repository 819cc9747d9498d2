"""Evaluation protocol: the deterministic policy on a fixed, held-out set of initial states.

* pimbrl environments: all test episodes run at once in one native vector env, from the fixed initial
  states ``Task.test_initial_states(episodes, eval_seed)`` - the first states of the KS test pool
  (disjoint from the training pool), or states drawn once with ``eval_seed`` for the others;
* other Gymnasium environments: episodes one after another, reset with seeds ``seed + i`` (``eval_seed``
  for the test episodes, :data:`~pimbrl.envs.VALIDATION_SEED` for the validation episodes and
  64-bit seeds drawn from :data:`~pimbrl.envs.HOLDOUT_SEED`'s stream for the holdout episodes, whatever
  seed is passed).

The ``"validation"`` protocol runs the validation draws (:meth:`pimbrl.envs.task.Task.validation_initial_states`),
which the decisions made during training read (the switch to model-free fine-tuning); the test states decide
nothing. The ``"holdout"`` protocol runs the holdout draws (:meth:`pimbrl.envs.task.Task.holdout_initial_states`),
a fresh test pool that only a run's final evaluation plays (``holdout_episodes``: a confirmatory study's outcome).

A pimbrl task may define further protocols (``protocol=``): KS has ``"authors"``, the 5 fixed training
states the paper's mean return is reported on (:meth:`pimbrl.systems.ks.KSTask.protocol_initial_states`).

The same states are used at every evaluation of a run and by every run with the same settings, so
learning curves of different methods are comparable point by point.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from ..envs import HOLDOUT_SEED, VALIDATION_SEED, PhysicsEnv
from ..spaces import ActionAdapter

__all__ = ["EvalResult", "Evaluator", "check_pool_sizes"]

Policy = Callable[[np.ndarray], np.ndarray]  # batched observations -> normalised actions


@dataclass(frozen=True)
class EvalResult:
    """Returns and lengths of the test episodes of one evaluation."""

    returns: np.ndarray  # (episodes,)
    lengths: np.ndarray  # (episodes,)
    #: wall seconds spent inside the policy, and the control steps it acted on (summed over episodes)
    inference_s: float = 0.0
    control_steps: int = 0

    @property
    def inference_s_per_step(self) -> float | None:
        """Wall seconds of the policy per control step and episode (``None`` where nothing was timed)."""
        return self.inference_s / self.control_steps if self.control_steps else None

    @property
    def mean(self) -> float:
        """Mean return over the episodes."""
        return float(self.returns.mean())

    def quartiles(self) -> dict[str, float]:
        """First quartile, median and third quartile of the returns (linear interpolation, as ``numpy.quantile``)."""
        q25, q50, q75 = np.quantile(self.returns, [0.25, 0.5, 0.75])
        return {"return_q25": float(q25), "return_median": float(q50), "return_q75": float(q75)}

    def summary(self) -> dict[str, float]:
        """Mean, min, max and standard deviation of the returns, mean length and number of episodes."""
        r = self.returns
        return {
            "return_mean": float(r.mean()),
            "return_min": float(r.min()),
            "return_max": float(r.max()),
            "return_std": float(r.std()),
            "length_mean": float(self.lengths.mean()),
            "episodes": len(r),
        }


def check_pool_sizes(task: Any, eval_protocol: str, eval_episodes: int, holdout_episodes: int) -> None:
    """A one-line ``ConfigError`` where the run asks a finite pool (KS's) for more states than it holds.

    Checked when a run is built, so that a run never finds out at its end (the holdout evaluation).
    """
    from ..config import ConfigError

    if task is None:
        return
    for protocol, wanted, setting in (
        (eval_protocol, eval_episodes, "eval_episodes"),
        ("holdout", holdout_episodes, "holdout_episodes"),
    ):
        size = task.pool_size(protocol)
        if wanted and size is not None and wanted > size:
            raise ConfigError(
                f"{setting} {wanted:,d}: the {protocol} pool holds {size:,d} states; ask for at most {size:,d} or enlarge "
                f'the pool (KS: --env-kwargs \'{{"pool_config": {{"n_{protocol}": {wanted}}}}}\')'
            )


class Evaluator:
    """Runs test episodes of ``env_id`` for a policy; the initial states are fixed at construction.

    ``protocol`` chooses the initial states of a pimbrl environment (``"test"``, the default: the held-out
    test states; see :meth:`pimbrl.envs.task.Task.protocol_initial_states`); a protocol with a fixed number
    of episodes (KS ``"authors"``: 5) takes ``episodes=None``.
    """

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], episodes: int | None, seed: int, protocol: str = "test") -> None:
        self.env_id = env_id
        self.seed = int(seed)
        self.protocol = protocol
        probe = gym.make(env_id, **env_kwargs)
        self.adapter = ActionAdapter(probe.action_space)
        base = probe.unwrapped
        self.native = isinstance(base, PhysicsEnv)
        if not self.native and protocol not in ("test", "validation", "holdout"):
            raise ValueError(
                f"evaluation protocol {protocol!r} is not defined for {env_id}: environments outside pimbrl have only "
                "'test', 'validation' and 'holdout'"
            )
        if not self.native:  # the draws are the reset seeds: each pool has its own
            self.seed = {"validation": VALIDATION_SEED, "holdout": HOLDOUT_SEED}.get(protocol, self.seed)
        if isinstance(base, PhysicsEnv):
            self.initial_states = base.task.protocol_initial_states(protocol, episodes, self.seed)
            self.episodes = len(self.initial_states)
            self.vec = gym.make_vec(
                env_id,
                num_envs=self.episodes,
                vectorization_mode="vector_entry_point",
                autoreset_mode=AutoresetMode.DISABLED,
                **env_kwargs,
            )
        else:
            if episodes is None:
                raise ValueError(f"evaluating {env_id} needs a number of episodes")
            self.episodes = int(episodes)
            self.env = probe
            if protocol == "holdout":  # 64-bit seeds of its own stream: no run of consecutive seeds meets another pool's
                self.reset_seeds = [int(x) for x in np.random.SeedSequence(HOLDOUT_SEED).generate_state(self.episodes, np.uint64)]
            else:  # the test and validation episodes: seed + i, as every earlier release
                self.reset_seeds = [self.seed + i for i in range(self.episodes)]

    def run(self, policy: Policy) -> EvalResult:
        """Run the test episodes with ``policy``, all at once on a pimbrl vector env, else one after another."""
        return self._run_vector(policy) if self.native else self._run_sequential(policy)

    def _run_vector(self, policy: Policy) -> EvalResult:
        obs, _ = self.vec.reset(seed=self.seed, options={"initial_state": self.initial_states})
        n = self.episodes
        returns = np.zeros(n)
        lengths = np.zeros(n, dtype=np.int64)
        alive = np.ones(n, dtype=bool)
        spent, steps = 0.0, 0
        while alive.any():
            start = time.perf_counter()
            normalised = policy(obs)
            spent += time.perf_counter() - start
            steps += int(alive.sum())
            obs, reward, terminated, truncated, _ = self.vec.step(self.adapter.to_env(normalised))
            returns += np.where(alive, reward, 0.0)
            lengths += alive
            alive &= ~(terminated | truncated)
        return EvalResult(returns, lengths, spent, steps)

    def _run_sequential(self, policy: Policy) -> EvalResult:
        returns, lengths = [], []
        spent = 0.0
        for i in range(self.episodes):
            obs, _ = self.env.reset(seed=self.reset_seeds[i])
            total, steps, done = 0.0, 0, False
            while not done:
                start = time.perf_counter()
                normalised = policy(np.asarray(obs)[None])[0]
                spent += time.perf_counter() - start
                action = self.adapter.to_env(normalised)
                obs, reward, terminated, truncated, _ = self.env.step(action)
                total += float(reward)
                steps += 1
                done = terminated or truncated
            returns.append(total)
            lengths.append(steps)
        return EvalResult(np.array(returns), np.array(lengths), spent, int(np.sum(lengths)))
