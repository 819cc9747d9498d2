"""Independent random streams, one per purpose, all spawned from the run seed.

Each purpose draws from its own ``numpy.random.Generator`` (``SeedSequence(seed, spawn_key=(key,))``), so
that changing how much one part of the loop draws never shifts another part's numbers. In particular a
model-phase setting (model steps, rollouts, physics-loss sources, ...) changes neither which real
transitions are held out nor what the agent does in the real environment before the model is used.

========================  ===================================================================================
stream                    draws
========================  ===================================================================================
``env``                   the seed of the real environment's initial states
``exploration``           random warm-up actions and the stochastic ``Discrete(2)`` mapping of real actions
``replay``                the indices of the agent's training batches (real and imagined)
``holdout``               one flag per real transition: held out of model training to measure its accuracy
``model_batches``         the model's labelled training batches
``physics_states``        the unlabelled state-action pairs of the physics loss (states and their actions)
``imagination``           imagined rollouts: start states, exploration noise, ``Discrete(2)`` mapping
``model_init``            the model's initial weights (a torch seed)
========================  ===================================================================================

The agent owns three more streams, spawned from the same seed (network initialisation, exploration noise
of real actions, update noise; see :class:`pimbrl.agents.Agent`). The evaluation states are not drawn
from the run seed at all but from ``eval_seed`` (the KS test pool for KS), so that every run of a
comparison, whatever its seed and method, is tested on the same states.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["STREAM_KEYS", "RandomStreams"]

#: Spawn key of each stream (fixed forever: changing one changes every result recorded with it). The
#: agent uses keys 1-3.
STREAM_KEYS: dict[str, int] = {
    "env": 10,
    "exploration": 11,
    "replay": 12,
    "holdout": 13,
    "model_batches": 14,
    "physics_states": 15,
    "imagination": 16,
    "model_init": 17,
}


class RandomStreams:
    """The run's generators by purpose (attributes named as in :data:`STREAM_KEYS`)."""

    env: np.random.Generator
    exploration: np.random.Generator
    replay: np.random.Generator
    holdout: np.random.Generator
    model_batches: np.random.Generator
    physics_states: np.random.Generator
    imagination: np.random.Generator
    model_init: np.random.Generator

    def __init__(self, seed: int) -> None:
        self.seed = int(seed)
        for name, key in STREAM_KEYS.items():
            setattr(self, name, np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(key,))))

    def integer_seed(self, name: str) -> int:
        """A 32-bit seed derived from stream ``name`` (for APIs that take an integer, e.g. ``env.reset``)."""
        return int(np.random.SeedSequence(self.seed, spawn_key=(STREAM_KEYS[name],)).generate_state(1)[0])

    def state_dict(self) -> dict[str, Any]:
        """The bit-generator state of every stream."""
        return {name: getattr(self, name).bit_generator.state for name in STREAM_KEYS}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (the generators keep their identity: components hold references)."""
        for name in STREAM_KEYS:
            getattr(self, name).bit_generator.state = state[name]
