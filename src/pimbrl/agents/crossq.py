"""CrossQ (Bhatt, Palenicek et al., ICLR 2024): SAC without target networks, with batch-normalised critics.

Each update evaluates the critics once, in training mode, on the concatenation of ``(s, a)`` from the batch
and ``(s', a')`` with ``a' ~ pi(.|s')``: the batch (re)normalisation then normalises both with the
statistics of their mixture, which is what lets the critic bootstrap from itself without a target
network. The halves are split again; the TD target

    y = r + gamma (1 - terminated) (min_i Q_i(s', a') - alpha log pi(a'|s'))

is taken from the second half without gradient, and the critics regress ``Q_i(s, a)`` of the first half
on it. Every ``policy_delay`` critic updates the actor (and the temperature) take a SAC step against the
minimum of the critics evaluated in eval mode, on their running statistics (as the authors' code does).
Outside an update the critics stay in eval mode; acting uses the actor only.

Differences from the paper: the actor is this package's plain squashed Gaussian (the authors' code can
batch-normalise the actor too); the critic loss is the sum over the critics of their mean squared
errors (the authors': half of it; Adam does not see the factor); ``r_max = 3``, ``d_max = 5`` and the
normalisation's ``eps = 1e-3`` are fixed.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from ..buffers import Batch
from ..config import ConfigError
from .base import make_optimizer
from .config import CrossQConfig
from .networks import GaussianActor, NormalizedCriticEnsemble
from .sac import SAC, _ParamHolder

__all__ = ["CrossQ"]


class CrossQ(SAC):
    """CrossQ: twin batch-renormalised critics, no target networks, a delayed SAC actor.

    Acting (:meth:`act`, :meth:`policy`) and the temperature are SAC's; the networks and the update are its own.
    """

    name = "crossq"
    config: CrossQConfig  # type: ignore[assignment]  # SAC's fields, less polyak, plus CrossQ's own
    critic: NormalizedCriticEnsemble  # type: ignore[assignment]

    def _build(self) -> None:
        cfg = self.config
        if self.critic_layer_norm:
            raise ConfigError(
                "experimental.critic_layer_norm does not apply to crossq: its critics are batch-normalised (agent.critic_norm)"
            )
        self.actor = GaussianActor(self.obs_dim, self.act_dim, cfg.hidden)
        self.critic = NormalizedCriticEnsemble(
            self.obs_dim,
            self.act_dim,
            cfg.critic_hidden,
            n=2,
            momentum=cfg.norm_momentum,
            renorm=cfg.critic_norm == "renorm",
            warmup=cfg.renorm_warmup,
        )
        self.critic.eval()
        betas = (cfg.adam_beta1, cfg.adam_beta2)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr, betas=betas, fused=True)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr, betas=betas, fused=True)
        self.log_alpha = torch.nn.Parameter(torch.tensor(math.log(cfg.init_alpha)))
        self.alpha_opt = make_optimizer([self.log_alpha], cfg.alpha_lr)
        self.target_entropy = -float(self.act_dim) if cfg.target_entropy is None else float(cfg.target_entropy)

    def _modules(self) -> dict[str, Any]:
        return {
            "actor": self.actor,
            "critic": self.critic,  # its state_dict holds the running statistics and the renorm step count
            "actor_opt": self.actor_opt,
            "critic_opt": self.critic_opt,
            "alpha": _ParamHolder(self.log_alpha),
            "alpha_opt": self.alpha_opt,
        }

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One critic step on the joint forward pass; every ``policy_delay`` updates an actor and a temperature step."""
        cfg = self.config
        batch = batch.to(self.device)
        alpha = self.alpha
        with torch.no_grad():
            next_a, next_logp = self.actor(batch.next_obs, generator=self.generator)
        self.critic.train()
        try:
            q_both = self.critic(torch.cat([batch.obs, batch.next_obs]), torch.cat([batch.action, next_a]))
        finally:
            self.critic.eval()
        q, q_next = q_both.split(len(batch), dim=1)
        with torch.no_grad():
            target = self._td_target(batch, q_next.min(dim=0).values - alpha * next_logp)
        critic_loss = (q - target).pow(2).mean(dim=1).sum()
        self._check_finite(critic_loss, "the critic loss")
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()
        self.n_updates += 1
        metrics = {"agent/critic_loss": critic_loss.detach(), "agent/q_mean": q.detach().mean(), "agent/alpha": alpha}
        if self.n_updates % cfg.policy_delay == 0:
            # the critics stay in eval mode: their running statistics, which this step leaves alone
            metrics.update(self._actor_and_temperature_step(batch.obs, alpha, lambda qs: qs.min(dim=0).values))
        return metrics
