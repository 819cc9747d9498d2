"""TD3 (Fujimoto et al. 2018) as in the paper's appendix, and DDPG as its one-critic special case.

The update follows Algorithm A1/A2 of the paper: twin critics regress on
``y = r + gamma (1 - terminated) min_i Q_targ,i(s', mu_targ(s') [+ noise])``; every ``policy_delay``-th
update the actor ascends ``Q_1(s, mu(s))`` and the targets move by Polyak averaging. Target-policy
smoothing (clipped Gaussian noise on the target action) is on by default as in Fujimoto et al.; the
paper's pseudocode has none (``target_smoothing=False``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..buffers import Batch
from .base import Agent, frozen, make_optimizer, polyak_update, target_copy
from .config import TD3Config
from .networks import CriticEnsemble, DeterministicActor

__all__ = ["DDPG", "TD3"]


class TD3(Agent):
    """Twin-delayed deep deterministic policy gradient."""

    name = "td3"
    n_critics = 2
    config: TD3Config  # DDPG's is a DDPGConfig: it reads none of TD3's own fields (no delay, no smoothing)

    def _build(self) -> None:
        cfg = self.config
        self.actor = DeterministicActor(self.obs_dim, self.act_dim, cfg.hidden)
        self.critic = CriticEnsemble(self.obs_dim, self.act_dim, cfg.hidden, n=self.n_critics, layer_norm=self.critic_layer_norm)
        self.actor_targ = target_copy(self.actor)
        self.critic_targ = target_copy(self.critic)
        self.actor_opt = make_optimizer(self.actor.parameters(), cfg.actor_lr)
        self.critic_opt = make_optimizer(self.critic.parameters(), cfg.critic_lr)

    @property
    def _delay(self) -> int:
        return self.config.policy_delay

    @property
    def _smoothing(self) -> bool:
        return self.config.target_smoothing

    def _modules(self) -> dict[str, Any]:
        return {
            "actor": self.actor,
            "critic": self.critic,
            "actor_targ": self.actor_targ,
            "critic_targ": self.critic_targ,
            "actor_opt": self.actor_opt,
            "critic_opt": self.critic_opt,
        }

    def policy(self, obs: torch.Tensor) -> torch.Tensor:
        """The actor's action (no exploration noise)."""
        return self.actor(obs)

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False, rng: np.random.Generator | None = None) -> np.ndarray:
        """Actor output plus Gaussian exploration noise (from ``rng`` if given), clipped to ``[-1, 1]``."""
        obs_t = torch.as_tensor(np.asarray(obs, dtype=np.float32)).reshape(-1, self.obs_dim).to(self.device)
        a = self.actor(obs_t).cpu().numpy()
        if not deterministic and self.config.exploration_noise > 0:
            noise = (self.rng if rng is None else rng).standard_normal(a.shape)
            a = np.clip(a + self.config.exploration_noise * noise, -1.0, 1.0)
        return a.astype(np.float32)

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One critic step; every ``policy_delay`` updates (every update for DDPG) also an actor step and target updates."""
        cfg = self.config
        batch = batch.to(self.device)
        with torch.no_grad():
            next_a = self.actor_targ(batch.next_obs)
            if self._smoothing:
                noise = torch.randn(next_a.shape, generator=self.generator).to(self.device) * cfg.target_noise
                next_a = (next_a + noise.clamp(-cfg.noise_clip, cfg.noise_clip)).clamp(-1.0, 1.0)
            target = self._td_target(batch, self.critic_targ(batch.next_obs, next_a).min(dim=0).values)
        critic_loss, q = self._critic_step(batch, target)
        self.n_updates += 1
        metrics = {"agent/critic_loss": critic_loss, "agent/q_mean": q.mean()}
        if self.n_updates % self._delay == 0:
            with frozen(self.critic):
                if cfg.preactivation_penalty > 0:
                    z = self.actor.preactivation(batch.obs)
                    q_pi = self.critic.first(batch.obs, torch.tanh(z))
                    actor_loss = -q_pi.mean() + cfg.preactivation_penalty * z.pow(2).mean()
                else:
                    actor_loss = -self.critic.first(batch.obs, self.actor(batch.obs)).mean()
            self.actor_opt.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.actor_opt.step()
            polyak_update(self.critic_targ.parameters(), self.critic.parameters(), cfg.polyak)
            polyak_update(self.actor_targ.parameters(), self.actor.parameters(), cfg.polyak)
            metrics["agent/actor_loss"] = actor_loss.detach()
        return metrics


class DDPG(TD3):
    """Deep deterministic policy gradient (Lillicrap et al. 2016).

    One critic, actor and targets updated every step, no target-policy smoothing.
    """

    name = "ddpg"
    n_critics = 1

    @property
    def _delay(self) -> int:
        return 1

    @property
    def _smoothing(self) -> bool:
        return False
