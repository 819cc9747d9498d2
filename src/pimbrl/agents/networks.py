"""Neural networks for the actor-critic agents.

The twin (or single) critics are one :class:`CriticEnsemble`: the weights of all members are stacked
and every layer is one batched matrix product (``torch.baddbmm``), so evaluating two critics costs one
kernel launch per layer instead of two. Optionally every hidden layer of the critics is layer-normalised
before its ReLU (Ba et al. 2016, no learned gain or bias: the next layer's weights can rescale), which
keeps Q-values bounded when the critic takes many gradient steps per real step (Ball et al. 2023, RLPD).
:meth:`CriticEnsemble.subset` evaluates some members only (REDQ's target). CrossQ's critics are a
:class:`NormalizedCriticEnsemble`, stacked the same way, with :class:`BatchRenorm` before every linear layer.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["BatchRenorm", "CriticEnsemble", "DeterministicActor", "GaussianActor", "NormalizedCriticEnsemble", "mlp"]


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

    def subset(self, obs: torch.Tensor, action: torch.Tensor, members: torch.Tensor) -> torch.Tensor:
        """Q-values of the members ``members`` (a 1-D tensor of indices) only, ``(len(members), B)``.

        One batched product per layer over the chosen members' weights: REDQ's target evaluates ``M`` of its
        ``N`` target critics for the cost of ``M``.
        """
        x = torch.cat([obs, action], dim=-1).unsqueeze(0).expand(members.shape[0], -1, -1)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(b[members], x, w[members])
            if i < last:
                x = torch.relu(self._normalise(x))
        return x.squeeze(-1)


class BatchRenorm(nn.Module):
    """Batch renormalisation (Ioffe 2017) of ``(n, B, F)``: each of ``n`` ensemble members over its own batch axis.

    In training mode the features are normalised with the batch's mean and (biased) variance; once the layer
    has been trained ``warmup`` times, the result is corrected towards the running statistics,
    ``x_hat r + d`` with ``r = std_B / std_run`` clipped to ``[1/r_max, r_max]`` and
    ``d = (mean_B - mean_run) / std_run`` clipped to ``[-d_max, d_max]`` (both without gradient). Plain batch
    normalisation is ``renorm=False`` (or a warm-up that never ends). Every training call moves the running
    statistics, ``stat <- momentum stat + (1 - momentum) batch_stat`` (the momentum convention of the
    CrossQ paper, 0.99; PyTorch's ``BatchNorm1d`` would write 0.01). In eval mode the running statistics
    normalise. A learned scale and shift follow; the running statistics and the count of training calls
    are buffers, so a ``state_dict`` holds them.
    """

    def __init__(
        self,
        n: int,
        features: int,
        momentum: float = 0.99,
        eps: float = 1e-3,
        renorm: bool = True,
        warmup: int = 100_000,
        r_max: float = 3.0,
        d_max: float = 5.0,
    ) -> None:
        super().__init__()
        self.momentum, self.eps, self.renorm, self.warmup, self.r_max, self.d_max = momentum, eps, renorm, warmup, r_max, d_max
        self.weight = nn.Parameter(torch.ones(n, 1, features))
        self.bias = nn.Parameter(torch.zeros(n, 1, features))
        self.running_mean: torch.Tensor
        self.running_var: torch.Tensor
        self.steps: torch.Tensor
        self.register_buffer("running_mean", torch.zeros(n, 1, features))
        self.register_buffer("running_var", torch.ones(n, 1, features))
        self.register_buffer("steps", torch.zeros((), dtype=torch.long))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``(n, B, F)`` normalised, scaled and shifted (training mode: the batch's statistics)."""
        if not self.training:
            return (x - self.running_mean) * torch.rsqrt(self.running_var + self.eps) * self.weight + self.bias
        mean = x.mean(dim=1, keepdim=True)
        var = x.var(dim=1, unbiased=False, keepdim=True)
        std = (var + self.eps).sqrt()
        y = (x - mean) / std
        if self.renorm:
            with torch.no_grad():
                run_std = (self.running_var + self.eps).sqrt()
                r = (std / run_std).clamp(1.0 / self.r_max, self.r_max)
                d = ((mean - self.running_mean) / run_std).clamp(-self.d_max, self.d_max)
                warm = (self.steps >= self.warmup).to(x.dtype)  # a tensor: no host synchronisation on a GPU
                r = 1.0 + warm * (r - 1.0)
                d = warm * d
            y = y * r + d
        with torch.no_grad():
            self.running_mean.lerp_(mean, 1.0 - self.momentum)
            self.running_var.lerp_(var, 1.0 - self.momentum)
            self.steps += 1
        return y * self.weight + self.bias


class NormalizedCriticEnsemble(nn.Module):
    """``n`` Q-networks with batch (re)normalisation, CrossQ's critics; ``forward`` returns ``(n, B)``.

    Layers: normalise the input ``(s, a)``, then per hidden layer linear -> ReLU -> normalise, then the
    linear output (normalisation before every linear layer, as in the CrossQ authors' networks). The
    members are stacked as in :class:`CriticEnsemble`. Mode matters: in training mode a forward pass
    normalises with (and updates the running statistics from) its own batch, so CrossQ evaluates
    ``(s, a)`` and ``(s', a')`` in one call; in eval mode the running statistics are used.
    """

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        hidden: Sequence[int],
        n: int = 2,
        momentum: float = 0.99,
        renorm: bool = True,
        warmup: int = 100_000,
    ) -> None:
        super().__init__()
        self.n = n
        sizes = [obs_dim + act_dim, *hidden, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        self.norms = nn.ModuleList()
        for fan_in, fan_out in itertools.pairwise(sizes):
            bound = 1.0 / math.sqrt(fan_in)
            self.weights.append(nn.Parameter(torch.empty(n, fan_in, fan_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(n, 1, fan_out).uniform_(-bound, bound)))
            self.norms.append(BatchRenorm(n, fan_in, momentum=momentum, renorm=renorm, warmup=warmup))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Q-values of every member, ``(n, B)``."""
        x = torch.cat([obs, action], dim=-1).unsqueeze(0).expand(self.n, -1, -1)
        last = len(self.weights) - 1
        for i, (w, b, norm) in enumerate(zip(self.weights, self.biases, self.norms)):
            x = torch.baddbmm(b, norm(x), w)
            if i < last:
                x = torch.relu(x)
        return x.squeeze(-1)
