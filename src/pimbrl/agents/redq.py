"""REDQ (Chen, Wang, Zhou and Ross, ICLR 2021): randomized ensembled double Q-learning on top of SAC.

An ensemble of ``N`` critics (one :class:`CriticEnsemble`, every layer one batched product) with Polyak-averaged
targets. Each update draws ``M`` distinct members at random from the agent's update generator, and the TD
target is the minimum over those ``M`` target critics only,

    y = r + gamma (1 - terminated) (min_{i in subset} Q_targ,i(s', a') - alpha log pi(a'|s')),   a' ~ pi(.|s'),

on which all ``N`` critics regress; the targets move after every critic update. The actor ascends the MEAN
of all ``N`` critics (minus ``alpha log pi``), and it and the temperature take a step every
``policy_delay`` critic updates.

The update-to-data ratio is the run's (``--utd``; the paper's is 20). The paper updates the policy once per
real step, i.e. once per 20 critic updates: ``--utd 20 --agent.policy-delay 20`` reproduces it (the default
delay 1 updates the policy with every critic update).
"""

from __future__ import annotations

import math
from typing import cast

import torch

from ..buffers import Batch
from .base import make_optimizer, polyak_update, target_copy
from .config import REDQConfig
from .networks import CriticEnsemble, GaussianActor
from .sac import SAC

__all__ = ["REDQ", "draw_subset"]


def draw_subset(n: int, m: int, generator: torch.Generator) -> torch.Tensor:
    """``m`` distinct member indices of ``range(n)`` drawn uniformly at random (int64, on the CPU), sorted."""
    if not 0 < m <= n:
        raise ValueError(f"a subset of {m} of {n} critics: need 0 < m <= n")
    return torch.randperm(n, generator=generator)[:m].sort().values


class REDQ(SAC):
    """REDQ: SAC with ``n_critics`` critics, targets from the minimum of a random ``target_subset`` of them."""

    name = "redq"
    config: REDQConfig
    critic_targ: CriticEnsemble

    def _build(self) -> None:
        cfg = self.config
        self.actor = GaussianActor(self.obs_dim, self.act_dim, cfg.hidden)
        self.critic = CriticEnsemble(self.obs_dim, self.act_dim, cfg.hidden, n=cfg.n_critics, layer_norm=self.critic_layer_norm)
        self.critic_targ = cast(CriticEnsemble, target_copy(self.critic))
        self.actor_opt = make_optimizer(self.actor.parameters(), cfg.actor_lr)
        self.critic_opt = make_optimizer(self.critic.parameters(), cfg.critic_lr)
        self.log_alpha = torch.nn.Parameter(torch.tensor(math.log(cfg.init_alpha)))
        self.alpha_opt = make_optimizer([self.log_alpha], cfg.alpha_lr)
        self.target_entropy = -float(self.act_dim) if cfg.target_entropy is None else float(cfg.target_entropy)

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One critic step of the ensemble and a target update; every ``policy_delay`` updates an actor and a temperature step."""
        cfg = self.config
        batch = batch.to(self.device)
        alpha = self.alpha
        with torch.no_grad():
            next_a, next_logp = self.actor(batch.next_obs, generator=self.generator)
            members = draw_subset(cfg.n_critics, cfg.target_subset, self.generator).to(self.device)
            q_next = self.critic_targ.subset(batch.next_obs, next_a, members).min(dim=0).values - alpha * next_logp
            target = self._td_target(batch, q_next)
        critic_loss, q = self._critic_step(batch, target)
        polyak_update(self.critic_targ.parameters(), self.critic.parameters(), cfg.polyak)
        self.n_updates += 1
        metrics = {"agent/critic_loss": critic_loss, "agent/q_mean": q.mean(), "agent/alpha": alpha}
        if self.n_updates % cfg.policy_delay == 0:
            metrics.update(self._actor_and_temperature_step(batch.obs, alpha, lambda qs: qs.mean(dim=0)))
        return metrics
