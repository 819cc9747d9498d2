"""Neural networks for the actor-critic agents.

The twin (or single) critics are one :class:`CriticEnsemble`: the weights of all members are stacked
and every layer is one batched matrix product (``torch.baddbmm``), so evaluating two critics costs one
kernel launch per layer instead of two. Optionally every hidden layer of the critics is layer-normalised
before its ReLU (Ba et al. 2016, no learned gain or bias: the next layer's weights can rescale), which
keeps Q-values bounded when the critic takes many gradient steps per real step (Ball et al. 2023, RLPD).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["CriticEnsemble", "DeterministicActor", "GaussianActor", "mlp"]


def mlp(
    sizes: Sequence[int], activation: type[nn.Module] = nn.ReLU, output_activation: type[nn.Module] | None = None
) -> nn.Sequential:
    """A multilayer perceptron ``sizes[0] -> ... -> sizes[-1]``."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(activation())
        elif output_activation is not None:
            layers.append(output_activation())
    return nn.Sequential(*layers)


class DeterministicActor(nn.Module):
    """``mu(s)`` in ``[-1, 1]^act_dim`` (tanh output)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: Sequence[int]) -> None:
        super().__init__()
        self.net = mlp([obs_dim, *hidden, act_dim], output_activation=nn.Tanh)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Actions ``(B, act_dim)`` in ``[-1, 1]`` for observations ``(B, obs_dim)``."""
        return self.net(obs)

    def preactivation(self, obs: torch.Tensor) -> torch.Tensor:
        """The output before the tanh (``forward`` is its tanh, computed by the same layers)."""
        return self.net[:-1](obs)


class GaussianActor(nn.Module):
    """Tanh-squashed Gaussian policy (SAC): returns an action in ``[-1, 1]`` and its log-probability."""

    LOG_STD_MIN = -20.0
    LOG_STD_MAX = 2.0

    def __init__(self, obs_dim: int, act_dim: int, hidden: Sequence[int]) -> None:
        super().__init__()
        self.body = mlp([obs_dim, *hidden], output_activation=nn.ReLU)
        self.mu = nn.Linear(hidden[-1], act_dim)
        self.log_std = nn.Linear(hidden[-1], act_dim)

    def forward(
        self, obs: torch.Tensor, deterministic: bool = False, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """A sampled (or, if ``deterministic``, the mean) squashed action and its log-probability ``(B,)``."""
        h = self.body(obs)
        mu = self.mu(h)
        if deterministic:
            return torch.tanh(mu), torch.zeros(obs.shape[0], device=obs.device)
        log_std = self.log_std(h).clamp(self.LOG_STD_MIN, self.LOG_STD_MAX)
        std = log_std.exp()
        eps = torch.randn(mu.shape, generator=generator, dtype=mu.dtype).to(mu.device)  # drawn on the CPU: any device
        pre = mu + std * eps
        # log N(pre; mu, std) minus the log-det of tanh, in the numerically stable softplus form
        log_prob = (-0.5 * eps.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
        log_prob = log_prob - (2 * (math.log(2) - pre - nn.functional.softplus(-2 * pre))).sum(-1)
        return torch.tanh(pre), log_prob


class CriticEnsemble(nn.Module):
    """``n`` independent Q-networks ``Q_i(s, a)`` evaluated together; ``forward`` returns ``(n, B)``.

    Each layer is initialised like ``nn.Linear`` (uniform in ``+-1/sqrt(fan_in)``), independently per member.
    With ``layer_norm`` every hidden pre-activation is normalised over its units (zero mean, unit variance).
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden: Sequence[int], n: int = 2, layer_norm: bool = False) -> None:
        super().__init__()
        self.n = n
        self.layer_norm = layer_norm
        sizes = [obs_dim + act_dim, *hidden, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in itertools.pairwise(sizes):
            bound = 1.0 / math.sqrt(fan_in)
            self.weights.append(nn.Parameter(torch.empty(n, fan_in, fan_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(n, 1, fan_out).uniform_(-bound, bound)))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Q-values of every member, ``(n, B)``."""
        x = torch.cat([obs, action], dim=-1).unsqueeze(0).expand(self.n, -1, -1)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(b, x, w)
            if i < last:
                x = torch.relu(self._normalise(x))
        return x.squeeze(-1)

    def first(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``Q_1(s, a)`` only (the TD3/DDPG actor objective), shape ``(B,)``."""
        x = torch.cat([obs, action], dim=-1)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = torch.addmm(b[0], x, w[0])
            if i < last:
                x = torch.relu(self._normalise(x))
        return x.squeeze(-1)

    def _normalise(self, x: torch.Tensor) -> torch.Tensor:
        """Layer normalisation over the last (units) axis if enabled, else ``x`` unchanged."""
        return nn.functional.layer_norm(x, x.shape[-1:]) if self.layer_norm else x
