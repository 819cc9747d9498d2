"""An imagined environment: batched rollouts of a learned model.

Rewards and terminations come from the same :class:`~pimbrl.physics.Physics` methods the simulator uses,
evaluated on the predicted states (the KS reward integrates over the model's intermediate states);
observations from the same :class:`~pimbrl.envs.Task`. Each imagined step is one batched model call for
all rollouts.

Blow-ups differ from the real environment on purpose. A real step that blows up ends the episode with the
task's ``divergence_penalty`` (the physics did it). An imagined prediction that is non-finite or leaves
the physics' divergence bound is an error of the *model*, not an outcome of the action: the rollout stops
there and that step is not returned (no penalty is taught for it), so no NaN, runaway state or
model-made penalty reaches a replay buffer. ``tests/test_models.py`` checks both behaviours.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from ..buffers import Transitions
from ..envs import Task
from ..physics import Physics
from ..spaces import ActionAdapter
from .networks import TransitionModel

__all__ = ["ModelEnv"]

Policy = Callable[[np.ndarray], np.ndarray]  # observations (B, obs_dim) -> normalised actions (B, act_dim)


class ModelEnv:
    """Rolls a transition model forward from given states under a policy.

    Args:
        model: the learned transition model.
        task: the environment's task (observation, action mapping, episode length).
        adapter: maps normalised agent actions to environment actions.
        rng: draws the stochastic ``Discrete(2)`` action mapping during imagination (as in training); the
            training loop gives it the imagination stream, never the real environment's.
        use_path: rewards that integrate over a control step (KS) use the model's intermediate states;
            ``False``: the step's two endpoints only, the same rule for a model whose intermediate states
            were never trained (data-only) as for one whose were (physics-informed).
        physics: the physics whose reward, termination and divergence bound judge imagined steps (default:
            the task's; a run with a physics prior gives the prior, since it does not know the true system).
    """

    def __init__(
        self,
        model: TransitionModel,
        task: Task,
        adapter: ActionAdapter,
        rng: np.random.Generator | None = None,
        use_path: bool = True,
        physics: Physics | None = None,
    ) -> None:
        self.model = model
        self.task = task
        self.physics = task.physics if physics is None else physics
        self.adapter = adapter
        self.rng = rng  # samples stochastic action mappings (Discrete(2)), as in the real environment
        self.use_path = use_path
        self.model_calls = 0
        #: transitions the model has stepped (every row of every call: rollouts, whole-episode selection)
        self.transitions = 0

    @torch.no_grad()
    def step(
        self, state: np.ndarray, k: np.ndarray, action: np.ndarray, deterministic: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One imagined control step for a batch: ``(next_state, reward, terminated, valid, physical_action)``.

        ``valid`` is False where the prediction blew up (those rows must be discarded). ``deterministic``: a
        ``Discrete(2)`` action maps to its more probable value, as in evaluation, and nothing is drawn from ``rng``.
        """
        phys_a = self.task.physical_action(self.adapter.to_env(action, None if deterministic else self.rng), len(state))
        path = self.model(torch.as_tensor(state, dtype=torch.float32), torch.as_tensor(phys_a, dtype=torch.float32))
        self.model_calls += 1
        self.transitions += len(state)
        path_np = path.double().numpy()
        nxt = path_np[:, -1]
        valid = ~self.physics.diverged(nxt)
        # states at the start of each of the model's sub-steps: u_t, v_1, ..., v_{N-1}
        multi = path_np.shape[1] > 1 and self.use_path
        starts = np.concatenate([state[:, None, :], path_np[:, :-1]], axis=1) if multi else None
        with np.errstate(all="ignore"):
            reward = np.asarray(self.physics.reward(state, phys_a, nxt, k, starts), dtype=np.float64) + np.zeros(len(state))
            terminated = np.asarray(self.physics.terminated(nxt), dtype=bool)
        valid &= np.isfinite(reward)
        return nxt, reward, terminated, valid, phys_a

    def rollout(self, state: np.ndarray, k: np.ndarray, policy: Policy, length: int) -> Transitions:
        """Up to ``length`` imagined steps from each start state (``(B, n)`` physical states, steps ``k``)."""
        state = np.asarray(state, dtype=np.float64)
        k = np.asarray(k, dtype=np.int64).copy()
        horizon = self.task.max_episode_steps
        parts: list[Transitions] = []
        alive = np.ones(len(state), dtype=bool)
        for _ in range(length):
            if not alive.any():
                break
            s, kk = state[alive], k[alive]
            obs = self.task.observe(s, kk)
            action = np.asarray(policy(obs), dtype=np.float32)
            nxt, reward, terminated, valid, phys_a = self.step(s, kk, action)
            truncated = (kk + 1) >= horizon
            keep = valid
            parts.append(
                Transitions(
                    obs=obs[keep],
                    action=action[keep],
                    reward=reward[keep],
                    next_obs=self.task.observe(nxt[keep], kk[keep] + 1),
                    terminated=terminated[keep],
                    truncated=truncated[keep] & ~terminated[keep],
                    state=s[keep],
                    next_state=nxt[keep],
                    physical_action=phys_a[keep],
                    k=kk[keep],
                )
            )
            idx = np.flatnonzero(alive)
            state[idx[valid]] = nxt[valid]
            k[idx] += 1
            alive[idx] = valid & ~terminated & ~truncated
        if not parts:
            return self._empty()
        return Transitions.concat(parts)

    def _empty(self) -> Transitions:
        n, m = self.physics.state_dim, self.physics.action_dim
        shape = self.task.observation_space.shape
        assert shape is not None, "pimbrl tasks have Box observation spaces"
        obs_dim = int(np.prod(shape))
        z = np.zeros
        return Transitions(
            z((0, obs_dim), np.float32), z((0, self.adapter.dim), np.float32), z(0), z((0, obs_dim), np.float32),
            z(0, bool), z(0, bool), z((0, n)), z((0, n)), z((0, m)), z(0, np.int64),
        )  # fmt: skip
