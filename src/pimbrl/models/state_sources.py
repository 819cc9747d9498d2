"""Label-free states for the physics loss: where the equation can teach a model what no label shows.

The physics loss needs a state and an action, never a label, so it can be evaluated far beyond the
transitions a run has observed. Applied only where the labels already are (real states with the
policy's actions), it barely moves the prediction, because the data loss pins it there already; applied on
broad, label-free states it teaches the model the dynamics of states it has not seen. Sources, each
derived from observed *seed* states or from the physics alone:

=============  ==========================================================================================
source         states (actions: uniform over the physical action box, or bang-bang, half and half)
=============  ==========================================================================================
``symmetry``   circular shifts and the reflection ``u(x) -> -u(-x)`` of observed fields (the symmetries
               the :class:`~pimbrl.physics.Physics` declares; PDEs)
``scaled``     observed fields scaled by a factor uniform in ``[0, 1.5]``: toward rest and beyond
``noise``      observed fields plus smooth random fields (low Fourier modes) of comparable amplitude
``box``        states uniform over the physics' admissible box (ODEs: e.g. Cart-Pole's termination box)
=============  ==========================================================================================

``policy`` (observed states with the policy's actions) and ``imagined`` (pairs the model imagined) are the
two sources the training loop itself holds; :data:`BROAD_SOURCES` are the ones made here.
:class:`PhysicsPairs` draws from all of them, for the training loop and for the model study alike.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from ..config import BROAD_SOURCES, LOOP_SOURCES, PHYSICS_SOURCES
from ..physics import Physics
from .trainer import TransitionData

__all__ = [
    "BROAD_SOURCES",
    "LOOP_SOURCES",
    "SOURCES",
    "PhysicsPairs",
    "available_sources",
    "broad_actions",
    "broad_pairs",
    "broad_states",
    "even_shares",
]

#: every source: those held by the training loop (:data:`LOOP_SOURCES`: real buffer, imagined buffer), then those
#: made from seed states and the physics by :func:`broad_states` (:data:`BROAD_SOURCES`)
SOURCES = PHYSICS_SOURCES


def available_sources(physics: Physics) -> tuple[str, ...]:
    """The sources that exist for ``physics`` (``box`` needs an admissible box, the field sources a PDE)."""
    out = list(LOOP_SOURCES)
    if physics.shift_symmetric or physics.reflection_symmetric:
        out += ["symmetry", "scaled", "noise"]
    if physics.admissible_box() is not None:
        out.append("box")
    return tuple(out)


def broad_states(physics: Physics, source: str, seeds: torch.Tensor, n: int, rng: np.random.Generator) -> torch.Tensor:
    """``n`` label-free states ``(n, state_dim)`` (float32) of ``source`` from ``seeds`` (observed states)."""
    if source not in available_sources(physics) or source in LOOP_SOURCES:
        raise ValueError(f"{source!r} is not a broad state source of {physics.name} (have {available_sources(physics)})")
    if source == "box":
        box = physics.admissible_box()
        assert box is not None
        return torch.as_tensor(rng.uniform(box[0], box[1], size=(n, physics.state_dim)), dtype=torch.float32)
    u = seeds.index_select(0, torch.from_numpy(rng.integers(0, len(seeds), size=n))).double()
    if source == "symmetry":
        if physics.shift_symmetric:
            shifts = rng.integers(0, physics.state_dim, size=n)
            idx = (torch.arange(physics.state_dim)[None, :] - torch.from_numpy(shifts)[:, None]) % physics.state_dim
            u = torch.gather(u, 1, idx)
        if physics.reflection_symmetric:
            flip = torch.from_numpy(rng.random(n) < 0.5)
            reflected = -torch.roll(torch.flip(u, dims=[1]), shifts=1, dims=1)  # u'[j] = -u[-j mod n]
            u = torch.where(flip[:, None], reflected, u)
    elif source == "scaled":
        u = u * torch.from_numpy(rng.uniform(0.0, 1.5, size=(n, 1)))
    else:  # noise
        u = u + _smooth_noise(physics.state_dim, n, rng) * u.std(dim=1, keepdim=True).clamp_min(1e-6)
    return u.float()


def broad_actions(physics: Physics, n: int, rng: np.random.Generator) -> torch.Tensor:
    """``n`` physical actions: uniform over the action box for half of them, bang-bang for the other half."""
    low, high = np.asarray(physics.action_low, np.float64), np.asarray(physics.action_high, np.float64)
    uniform = rng.uniform(low, high, size=(n, physics.action_dim))
    bang = np.where(rng.random((n, physics.action_dim)) < 0.5, low, high)
    a = np.where(rng.random((n, 1)) < 0.5, uniform, bang)
    return torch.as_tensor(a, dtype=torch.float32)


def broad_pairs(
    physics: Physics, source: str, seeds: torch.Tensor, n: int, rng: np.random.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` label-free states of ``source`` (:func:`broad_states`) with their actions (:func:`broad_actions`)."""
    states = broad_states(physics, source, seeds, n, rng)
    return states, broad_actions(physics, n, rng)


def even_shares(total: int, parts: int) -> list[int]:
    """``total`` split into ``parts`` shares that differ by at most one, the larger ones first."""
    return [total // parts + (1 if i < total % parts else 0) for i in range(parts)]


def _smooth_noise(dim: int, n: int, rng: np.random.Generator, modes: int = 6) -> torch.Tensor:
    """Random periodic fields of unit RMS built from the lowest ``modes`` Fourier modes."""
    k = np.arange(1, modes + 1)
    x = np.arange(dim) / dim
    amp = rng.standard_normal((n, modes)) / k
    phase = rng.uniform(0, 2 * np.pi, size=(n, modes))
    field = (amp[:, :, None] * np.cos(2 * np.pi * k[None, :, None] * x[None, None, :] + phase[:, :, None])).sum(1)
    field /= np.sqrt((field**2).mean(axis=1, keepdims=True)) + 1e-12
    return torch.as_tensor(field)


def choose_sources(sources: Sequence[str], physics: Physics) -> tuple[str, ...]:
    """The physics-loss sources ``sources`` checked against what ``physics`` offers; empty: all it offers.

    All it offers: the loop's two (``policy``, ``imagined``) plus ``symmetry, scaled, noise`` for the PDEs
    and ``box`` for the ODEs.
    """
    have = available_sources(physics)
    if not sources:
        return have
    bad = [s for s in sources if s not in have]
    if bad:
        raise ValueError(f"physics sources {bad} are not available for {physics.name}; choose from {', '.join(have)}")
    return tuple(sources)


class PhysicsPairs:
    """Unlabelled state-action pairs for the physics loss, an equal share per source: the model phase's sampler.

    Configuration-free: what differs between the training loop and the model study is given as functions.

    Args:
        physics: the physics the run believes (its prior), which the broad sources consult.
        sources: the sources to draw from (:func:`choose_sources`).
        states: ``rows -> (len(rows), n)`` observed training states (``n_observed`` of them).
        n_observed: how many observed states there are.
        actions: ``(rows, rng) -> (len(rows), m)`` physical actions at those observed states: the training
            loop's current policy (with its exploration noise), the study's uniformly random one.
        n_imagined: ``() -> int`` how many imagined pairs there are now (the loop's imagined buffer, the study's
            model rollouts); while there are none, the ``imagined`` share goes to the other sources (to
            ``policy`` when it is the only one).
        imagined: ``rows -> (states, actions)`` those imagined pairs.
        rng: draws the policy's actions and the broad sources' seeds and states (the rows and the imagined
            pairs are drawn from the generator given to :meth:`sample`; the training loop gives the same one).
    """

    def __init__(
        self,
        physics: Physics,
        sources: Sequence[str],
        states: Callable[[torch.Tensor], torch.Tensor],
        n_observed: int,
        actions: Callable[[torch.Tensor, np.random.Generator], torch.Tensor],
        n_imagined: Callable[[], int],
        imagined: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
        rng: np.random.Generator,
    ) -> None:
        self.physics = physics
        self.sources = tuple(sources)
        self.states = states
        self.n_observed = int(n_observed)
        self.actions = actions
        self.n_imagined = n_imagined
        self.imagined = imagined
        self.rng = rng

    def __len__(self) -> int:
        return self.n_observed + self.n_imagined()

    def sample(self, batch: int, rng: np.random.Generator) -> TransitionData:
        """``batch`` unlabelled pairs, an equal share per source (rows and imagined pairs drawn from ``rng``)."""
        n_imagined = self.n_imagined() if "imagined" in self.sources else 0
        sources = [s for s in self.sources if s != "imagined" or n_imagined] or ["policy"]
        states: list[torch.Tensor] = []
        acts: list[torch.Tensor] = []
        for source, n in zip(sources, even_shares(batch, len(sources)), strict=True):
            if n == 0:
                continue
            if source == "policy":
                rows = torch.from_numpy(rng.integers(0, self.n_observed, size=n))
                acts_now = self.actions(rows, self.rng)
                states.append(self.states(rows))
                acts.append(acts_now)
            elif source == "imagined":
                pair = self.imagined(torch.from_numpy(rng.integers(0, n_imagined, size=n)))
                states.append(pair[0])
                acts.append(pair[1])
            else:  # broad_states draws n seeds among those it is given: gather just n rows (none for the box)
                rows = torch.from_numpy(self.rng.integers(0, self.n_observed, size=n))
                seeds = self.states(rows if source != "box" else rows[:1])
                pair = broad_pairs(self.physics, source, seeds, n, self.rng)
                states.append(pair[0])
                acts.append(pair[1])
        return TransitionData(torch.cat(states), torch.cat(acts))
