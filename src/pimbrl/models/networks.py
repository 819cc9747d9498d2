"""Transition models of the physical systems.

An MLP serves the ODE systems; for the PDE systems a convolutional encoder + LSTM + MLP decoder emits
intermediate states (the paper's architecture, Fig. 3).

A model maps a physical state ``u_t`` ``(B, state_dim)`` and a physical action ``a_t`` ``(B, action_dim)`` to
``N`` states at times ``t + i/N`` (``(B, N, state_dim)``); the last one is the prediction of ``u_{t+1}``.
Actions are rescaled to ``[-1, 1]`` with the physics' action bounds; states are normalised with
statistics fitted once from data (:meth:`TransitionModel.fit_normalization`). By default the networks
predict increments from ``u_t`` (``predict_increment``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from ..physics import Physics
from ..physics.pde import SemilinearPDE

__all__ = ["ConvLSTMModel", "EquivariantConvModel", "MLPModel", "TransitionModel"]


class TransitionModel(nn.Module):
    """Base class: action scaling, normalisation buffers and the output convention."""

    n_intermediate: int = 1
    # buffers registered in __init__ (declared here for the type checker)
    action_low: torch.Tensor
    action_high: torch.Tensor
    state_mean: torch.Tensor
    state_std: torch.Tensor
    delta_std: torch.Tensor
    fitted: torch.Tensor

    def __init__(self, physics: Physics, per_feature: bool) -> None:
        super().__init__()
        self.physics = physics
        dim = physics.state_dim if per_feature else 1
        self.per_feature = per_feature
        self.register_buffer("action_low", torch.as_tensor(physics.action_low, dtype=torch.float32))
        self.register_buffer("action_high", torch.as_tensor(physics.action_high, dtype=torch.float32))
        self.register_buffer("state_mean", torch.zeros(dim))
        self.register_buffer("state_std", torch.ones(dim))
        self.register_buffer("delta_std", torch.ones(dim))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))

    def scale_action(self, a: torch.Tensor) -> torch.Tensor:
        """Map physical actions from ``[action_low, action_high]`` to ``[-1, 1]``."""
        return 2.0 * (a - self.action_low) / (self.action_high - self.action_low) - 1.0

    @torch.no_grad()
    def fit_normalization(self, u: torch.Tensor, u_next: torch.Tensor) -> None:
        """Set the state and increment statistics from data (per feature, or one scalar for fields)."""
        delta = self.physics.state_difference(u_next, u)
        dims = 0 if self.per_feature else (0, 1)
        self.state_mean.copy_(u.mean(dim=dims).reshape(self.state_mean.shape))
        self.state_std.copy_(u.std(dim=dims).clamp_min(1e-6).reshape(self.state_std.shape))
        self.delta_std.copy_(delta.std(dim=dims).clamp_min(1e-6).reshape(self.delta_std.shape))
        self.fitted.fill_(True)

    @torch.no_grad()
    def fit_state_normalization(self, u: torch.Tensor) -> None:
        """Set the state statistics from unlabelled states (the increment scale stays 1)."""
        dims = 0 if self.per_feature else (0, 1)
        self.state_mean.copy_(u.mean(dim=dims).reshape(self.state_mean.shape))
        self.state_std.copy_(u.std(dim=dims).clamp_min(1e-6).reshape(self.state_std.shape))
        self.fitted.fill_(True)

    def normalize(self, u: torch.Tensor) -> torch.Tensor:
        """Standardise states with the fitted mean and standard deviation."""
        return (u - self.state_mean) / self.state_std

    def set_actuator_shapes(self, shapes: np.ndarray | torch.Tensor) -> None:
        """Take the actuator shapes ``(action_dim, n)`` a learned width gives; a model with no forcing input ignores them."""

    def forward(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        """Predicted states ``(B, n_intermediate, state_dim)`` from ``u`` ``(B, state_dim)`` and ``a`` ``(B, action_dim)``."""
        raise NotImplementedError

    def predict_next(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """``u_{t+1}`` only."""
        return self(u, a)[:, -1]


def silu_mlp(sizes: Sequence[int]) -> nn.Sequential:
    """A multilayer perceptron ``sizes[0] -> ... -> sizes[-1]`` with SiLU between its linear layers (none after the last)."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.SiLU())
    return nn.Sequential(*layers)


class MLPModel(TransitionModel):
    """``u_{t+1} = canonical(u_t + delta_std * MLP(normalised u_t, scaled a_t))`` (or the absolute state).

    With ``n_intermediate = N > 1`` (an ODE with ``N`` solver steps per control step) the MLP emits ``N``
    states, ``u_{t+i/N} = canonical(u_t + delta_std * MLP_i(...))``, the last being ``u_{t+1}``: the physics loss
    checks each solver step. ``canonical`` is the physics' state map (it wraps the pendulum's angle), so increments never see the
    jump at +-pi; ``constrain`` its hard constraints (the pendulum's speed limit), which a prediction then
    cannot violate.
    """

    def __init__(
        self, physics: Physics, hidden: Sequence[int] = (256, 256), predict_increment: bool = True, n_intermediate: int = 1
    ) -> None:
        super().__init__(physics, per_feature=True)
        if n_intermediate < 1:
            raise ValueError(f"n_intermediate must be >= 1, got {n_intermediate}")
        self.n_intermediate = int(n_intermediate)
        self.predict_increment = predict_increment
        self.net = silu_mlp([physics.state_dim + physics.action_dim, *hidden, physics.state_dim * self.n_intermediate])

    def increments(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The predicted increments ``delta_std * MLP(...)`` ``(B, N, state_dim)`` (``predict_increment`` models)."""
        out = self.net(torch.cat([self.normalize(u), self.scale_action(a)], dim=-1))
        return out.reshape(len(u), self.n_intermediate, -1) * self.delta_std

    def forward(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The ``N`` states of the control step ``(B, N, state_dim)`` (one for an ODE with one solver step)."""
        if self.predict_increment:
            states = u[:, None, :] + self.increments(u, a)
        else:
            out = self.net(torch.cat([self.normalize(u), self.scale_action(a)], dim=-1))
            states = out.reshape(len(u), self.n_intermediate, -1) * self.state_std + self.state_mean
        return self.physics.constrain(self.physics.canonical(states))


class CircularConv(nn.Module):
    """1-D convolution with periodic (circular) padding: the periodic boundary is built in."""

    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int = 1, dilation: int = 1) -> None:
        super().__init__()
        self.pad = dilation * (kernel // 2)
        self.conv = nn.Conv1d(c_in, c_out, kernel, stride=stride, dilation=dilation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(nn.functional.pad(x, (self.pad, self.pad), mode="circular"))


class ConvLSTMModel(TransitionModel):
    """Convolutional encoder -> LSTM fed the action N times -> MLP decoder of N intermediate fields.

    The encoder maps the normalised field to a latent vector that initialises the LSTM's hidden and cell
    states; the LSTM receives the scaled action at each of its ``N`` steps; the decoder maps each LSTM
    output to a full field increment, so ``u_{t+i/N} = u_t + delta_std * decoder(h_i)``.
    """

    def __init__(
        self,
        physics: SemilinearPDE,
        n_intermediate: int = 5,
        channels: Sequence[int] = (8, 16),
        kernel: int = 5,
        latent: int = 96,
        decoder_hidden: int = 192,
        predict_increment: bool = True,
    ) -> None:
        super().__init__(physics, per_feature=False)
        if n_intermediate < 1:
            raise ValueError(f"n_intermediate must be >= 1, got {n_intermediate}")
        self.n_intermediate = int(n_intermediate)
        self.predict_increment = predict_increment
        layers: list[nn.Module] = []
        c_prev, length = 1, physics.state_dim
        for i, c in enumerate(channels):
            stride = 1 if i == 0 else 2
            layers += [CircularConv(c_prev, c, kernel, stride), nn.SiLU()]
            c_prev = c
            length = (length + 2 * (kernel // 2) - kernel) // stride + 1
        self.encoder = nn.Sequential(*layers, nn.Flatten(), nn.Linear(c_prev * length, 2 * latent))
        self.lstm = nn.LSTM(physics.action_dim, latent, batch_first=True)
        self.decoder = nn.Sequential(nn.Linear(latent, decoder_hidden), nn.SiLU(), nn.Linear(decoder_hidden, physics.state_dim))

    def _latent_path(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        z = self.encoder(self.normalize(u)[:, None, :])
        h0, c0 = z.chunk(2, dim=-1)
        seq = self.scale_action(a)[:, None, :].expand(-1, self.n_intermediate, -1)
        out, _ = self.lstm(seq, (torch.tanh(h0)[None].contiguous(), c0[None].contiguous()))
        return out  # (B, N, latent)

    def _decode(self, u: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """Fields ``(B, k, n)`` from latent states ``(B, k, latent)``."""
        d = self.decoder(h)
        if self.predict_increment:
            return u[:, None, :] + d * self.delta_std
        return d * self.state_std + self.state_mean

    def forward(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The ``n_intermediate`` predicted fields ``(B, N, n)``; the last is ``u_{t+1}``."""
        return self._decode(u, self._latent_path(u, a))

    def predict_next(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """``u_{t+1}`` only: the decoder runs on the last LSTM output alone."""
        return self._decode(u, self._latent_path(u, a)[:, -1:])[:, 0]


class EquivariantConvModel(TransitionModel):
    """A fully convolutional model on the periodic grid: translation-equivariant by construction.

    Input channels: the normalised field and the forcing field of the scaled action (``sum_i a_i g_i(x)``
    with ``a`` in ``[-1, 1]``), so shifting the state and the actuators together shifts the prediction.
    Circular convolutions with growing dilation, residual blocks, and an output of ``N`` channels: the
    increments of the ``N`` intermediate states, ``u_{t+i/N} = u_t + delta_std * out_i``. About 16.6k
    parameters with the defaults, ten times fewer than :class:`ConvLSTMModel`.
    """

    def __init__(
        self,
        physics: SemilinearPDE,
        n_intermediate: int = 5,
        channels: int = 32,
        kernel: int = 5,
        dilations: Sequence[int] = (1, 2, 4),
    ) -> None:
        super().__init__(physics, per_feature=False)
        if n_intermediate < 1:
            raise ValueError(f"n_intermediate must be >= 1, got {n_intermediate}")
        self.n_intermediate = int(n_intermediate)
        self.register_buffer("shapes", torch.as_tensor(physics.actuator_shapes, dtype=torch.float32))
        self.inp = CircularConv(2, channels, kernel)
        self.blocks = nn.ModuleList(CircularConv(channels, channels, kernel, dilation=d) for d in dilations)
        self.out = CircularConv(channels, self.n_intermediate, kernel)

    shapes: torch.Tensor

    @torch.no_grad()
    def set_actuator_shapes(self, shapes: np.ndarray | torch.Tensor) -> None:
        """Use ``shapes`` ``(action_dim, n)`` for the forcing input from now on (a copy, without gradient).

        With a learned actuator width the forcing input follows the width the equation identified; the
        network's data loss never moves the width (it is not a parameter of the network).
        """
        new = torch.as_tensor(shapes).detach().to(self.shapes.dtype)
        if new.shape != self.shapes.shape:
            raise ValueError(f"actuator shapes must have shape {tuple(self.shapes.shape)}, got {tuple(new.shape)}")
        if not bool(torch.isfinite(new).all()):
            raise ValueError("actuator shapes must be finite")
        self.shapes.copy_(new)

    def increments(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The predicted increments ``v_i - u`` ``(B, N, n)``: ``delta_std`` times the network's output."""
        forcing = self.scale_action(a) @ self.shapes  # (B, n): the actuators' field at full scale = 1
        h = nn.functional.silu(self.inp(torch.stack([self.normalize(u), forcing], dim=1)))
        for block in self.blocks:
            h = h + nn.functional.silu(block(h))
        return self.out(h) * self.delta_std

    def forward(self, u: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """The ``n_intermediate`` predicted fields ``(B, N, n)``; the last is ``u_{t+1}``."""
        return u[:, None, :] + self.increments(u, a)
