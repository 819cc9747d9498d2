"""Mapping between an agent's normalised continuous actions and an environment's action space.

Agents always act in ``[-1, 1]^d``. The adapter turns that into what ``env.step`` expects:

* ``Box(low, high)``: the affine map ``low + (a + 1) (high - low) / 2``, so exploration noise of standard
  deviation ``sigma`` in the agent's space is ``sigma (high - low) / 2`` in each physical dimension;
* ``Discrete(2)`` (Cart-Pole): a one-dimensional actor output ``a`` read as the probability
  ``p = (a + 1) / 2`` of action ``1``. While training (a ``numpy.random.Generator`` is given) the action is
  drawn with that probability, so the expected outcome is linear in ``a`` and the critic's ``dQ/da``
  carries a policy gradient everywhere; a hard threshold would make ``Q`` flat in ``a`` except at 0 and
  leave a deterministic actor without gradient (measured: TD3 stuck at a constant push). For evaluation
  (no generator) the more probable action is taken: ``1`` where ``a >= 0``;
* ``Discrete(n > 2)``: an ``n``-dimensional output, action ``argmax(a)`` (offset by ``space.start``).

The critic always sees the continuous action, which is what is stored in replay buffers.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

__all__ = ["ActionAdapter"]


class ActionAdapter:
    """Maps normalised actions ``(..., dim)`` in ``[-1, 1]`` to environment actions."""

    def __init__(self, space: spaces.Space) -> None:
        self.space = space
        if isinstance(space, spaces.Box):
            if not (np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high))):
                raise ValueError(f"the action space {space} must be bounded for an actor with a tanh output")
            self.kind = "box"
            self.dim = int(np.prod(space.shape))
            self.box_shape = space.shape
            self.low = space.low.astype(np.float64).reshape(-1)
            self.high = space.high.astype(np.float64).reshape(-1)
        elif isinstance(space, spaces.Discrete):
            self.kind = "discrete"
            self.n = int(space.n)
            self.start = int(space.start)
            self.dim = 1 if self.n == 2 else self.n
        else:
            raise TypeError(f"unsupported action space {space}: pimbrl agents handle Box and Discrete")

    def to_env(self, a: np.ndarray, rng: np.random.Generator | None = None) -> Any:
        """Environment action(s) for normalised ``a`` of shape ``(dim,)`` or ``(B, dim)``.

        ``rng`` samples the ``Discrete(2)`` mapping (training); without it the more probable action is
        taken (evaluation).
        """
        a = np.asarray(a)
        if self.kind == "box":
            env_a = self.low + (np.clip(a, -1.0, 1.0) + 1.0) * 0.5 * (self.high - self.low)
            return env_a.astype(self.space.dtype).reshape(a.shape[:-1] + self.box_shape)
        if self.n == 2:
            if rng is None:
                out = (a[..., 0] >= 0).astype(np.int64) + self.start
            else:
                p = (np.clip(a[..., 0], -1.0, 1.0) + 1.0) * 0.5
                out = (rng.random(p.shape) < p).astype(np.int64) + self.start
        else:
            out = np.argmax(a, axis=-1).astype(np.int64) + self.start
        return int(out) if out.ndim == 0 else out

    def sample(self, rng: np.random.Generator, batch: int | None = None) -> np.ndarray:
        """Uniform random normalised actions (random warm-up)."""
        shape = (self.dim,) if batch is None else (batch, self.dim)
        return rng.uniform(-1.0, 1.0, size=shape).astype(np.float32)
