"""Soft actor-critic (Haarnoja et al. 2018) with twin critics and automatic entropy tuning."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from ..buffers import Batch
from .base import Agent, frozen, make_optimizer, polyak_update, target_copy
from .config import SACConfig
from .networks import CriticEnsemble, GaussianActor

__all__ = ["SAC"]


class SAC(Agent):
    """Soft actor-critic; the temperature ``alpha`` is learned towards ``target_entropy`` (default ``-act_dim``)."""

    name = "sac"
    config: SACConfig

    def _build(self) -> None:
        cfg = self.config
        self.actor = GaussianActor(self.obs_dim, self.act_dim, cfg.hidden)
        self.critic = CriticEnsemble(self.obs_dim, self.act_dim, cfg.hidden, n=2, layer_norm=self.critic_layer_norm)
        self.critic_targ = target_copy(self.critic)
        self.actor_opt = make_optimizer(self.actor.parameters(), cfg.actor_lr)
        self.critic_opt = make_optimizer(self.critic.parameters(), cfg.critic_lr)
        self.log_alpha = torch.nn.Parameter(torch.tensor(math.log(cfg.init_alpha)))
        self.alpha_opt = make_optimizer([self.log_alpha], cfg.alpha_lr)
        self.target_entropy = -float(self.act_dim) if cfg.target_entropy is None else float(cfg.target_entropy)

    def _modules(self) -> dict[str, Any]:
        return {
            "actor": self.actor,
            "critic": self.critic,
            "critic_targ": self.critic_targ,
            "actor_opt": self.actor_opt,
            "critic_opt": self.critic_opt,
            "alpha": _ParamHolder(self.log_alpha),
            "alpha_opt": self.alpha_opt,
        }

    @property
    def alpha(self) -> torch.Tensor:
        """The entropy temperature ``exp(log_alpha)`` (detached)."""
        return self.log_alpha.detach().exp()

    def policy(self, obs: torch.Tensor) -> torch.Tensor:
        """The squashed mean action (no sampling)."""
        return self.actor(obs, deterministic=True)[0]

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False, rng: np.random.Generator | None = None) -> np.ndarray:
        """A sample of the squashed Gaussian policy (its mean if deterministic).

        The sample's noise is seeded from ``rng`` if given, else from the agent's exploration stream
        (never from the update noise).
        """
        obs_t = torch.as_tensor(np.asarray(obs, dtype=np.float32)).reshape(-1, self.obs_dim).to(self.device)
        generator = None
        if not deterministic:
            source = self.rng if rng is None else rng
            generator = torch.Generator().manual_seed(int(source.integers(0, 2**62)))
        a, _ = self.actor(obs_t, deterministic=deterministic, generator=generator)
        return a.cpu().numpy().astype(np.float32)

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One critic step, one actor step, one temperature step (if tuned), then a target update."""
        cfg = self.config
        batch = batch.to(self.device)
        alpha = self.alpha
        with torch.no_grad():
            next_a, next_logp = self.actor(batch.next_obs, generator=self.generator)
            q_next = self.critic_targ(batch.next_obs, next_a).min(dim=0).values - alpha * next_logp
            target = self._td_target(batch, q_next)
        critic_loss, q = self._critic_step(batch, target)

        metrics = {"agent/critic_loss": critic_loss, "agent/q_mean": q.mean(), "agent/alpha": alpha}
        metrics.update(self._actor_and_temperature_step(batch.obs, alpha, lambda qs: qs.min(dim=0).values))
        polyak_update(self.critic_targ.parameters(), self.critic.parameters(), cfg.polyak)
        self.n_updates += 1
        return metrics

    def _actor_and_temperature_step(
        self, obs: torch.Tensor, alpha: torch.Tensor, reduce: Callable[[torch.Tensor], torch.Tensor]
    ) -> dict[str, torch.Tensor]:
        """One actor step on ``alpha log pi(a|s) - reduce(Q(s, a))``, then one temperature step if it is tuned.

        ``reduce`` turns the critics' stacked values ``(n_critics, B)`` into one value per sample (SAC and
        CrossQ: their minimum; REDQ: their mean). The critics are frozen for the step.
        """
        a, logp = self.actor(obs, generator=self.generator)
        with frozen(self.critic):
            actor_loss = (alpha * logp - reduce(self.critic(obs, a))).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()
        if self.config.autotune_alpha:
            alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
            self.alpha_opt.zero_grad(set_to_none=True)
            alpha_loss.backward()
            self.alpha_opt.step()
        return {"agent/actor_loss": actor_loss.detach(), "agent/entropy": -logp.detach().mean()}


class _ParamHolder(torch.nn.Module):
    """Lets a bare parameter be saved and restored through ``state_dict`` like a module."""

    def __init__(self, p: torch.nn.Parameter) -> None:
        super().__init__()
        self.p = p
