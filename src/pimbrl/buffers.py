"""Preallocated replay storage: transitions go in as :class:`Transitions`, come out as :class:`Batch`.

The vocabulary of transition containers is small on purpose:

* :class:`Transitions` (NumPy, leading dimension B): what the real-environment collector and the imagined
  environment produce and a replay buffer stores, with the physical side (state, next state, physical
  action, step index) where a model needs it;
* :class:`Batch` (torch): an agent's training minibatch;
* :class:`pimbrl.models.TransitionData` (torch): a model's training data (state, physical action, next
  state), gathered from a buffer's physical fields.

Transitions are stored as torch tensors (float32) in preallocated ring buffers; sampling draws indices
from a caller-supplied ``numpy.random.Generator`` and gathers with one ``index_select`` per field.
``terminated`` and ``truncated`` are stored apart: a TD target bootstraps through a time-limit
truncation and only stops at a true termination.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch

__all__ = ["PHYSICS_FIELDS", "Batch", "ReplayBuffer", "Transitions", "available_memory", "physics_extras"]


@dataclass(frozen=True)
class Batch:
    """A batch of transitions (torch tensors, leading dimension B)."""

    obs: torch.Tensor  # (B, obs_dim)
    action: torch.Tensor  # (B, act_dim), the agent's normalised action
    reward: torch.Tensor  # (B,)
    next_obs: torch.Tensor  # (B, obs_dim)
    terminated: torch.Tensor  # (B,) float: 1 where the episode truly ended (no bootstrap)
    truncated: torch.Tensor  # (B,) float: 1 where a time limit cut the episode (bootstrap anyway)

    def __len__(self) -> int:
        return self.obs.shape[0]

    def to(self, device: torch.device) -> Batch:
        """The batch on ``device`` (itself where it is there already: the CPU's, without a copy)."""
        if self.obs.device == device:
            return self
        return Batch(
            *(t.to(device) for t in (self.obs, self.action, self.reward, self.next_obs, self.terminated, self.truncated))
        )

    @staticmethod
    def concat(parts: list[Batch]) -> Batch:
        """Concatenate batches along the batch dimension."""
        return Batch(*(torch.cat([getattr(p, f.name) for p in parts]) for f in fields(Batch)))


#: Physical fields of a :class:`Transitions` (``None`` for model-free collection).
PHYSICS_FIELDS = ("state", "next_state", "physical_action", "k")


@dataclass(frozen=True)
class Transitions:
    """Transitions to store (NumPy arrays, leading dimension B).

    ``action`` is the agent's normalised action; ``physical_action`` the clipped physical input the
    system received; ``k`` the step index of ``state`` within its episode. ``state``, ``next_state``,
    ``physical_action`` and ``k`` are ``None`` where no model needs them.
    """

    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    state: np.ndarray | None = None
    next_state: np.ndarray | None = None
    physical_action: np.ndarray | None = None
    k: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.reward)

    def select(self, mask: np.ndarray) -> Transitions:
        """The rows where ``mask`` is true (or at the given indices)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = None if v is None else v[mask]
        return Transitions(**out)

    @staticmethod
    def concat(parts: list[Transitions]) -> Transitions:
        """Concatenate along the batch dimension (the physical fields must be given in all parts or none)."""
        out: dict[str, Any] = {}
        for f in fields(Transitions):
            values = [getattr(p, f.name) for p in parts]
            out[f.name] = None if values[0] is None else np.concatenate(values)
        return Transitions(**out)

    def physics(self) -> dict[str, np.ndarray]:
        """The physical fields as buffer extras (``k`` as a column)."""
        if self.state is None or self.next_state is None or self.physical_action is None or self.k is None:
            raise ValueError("these transitions carry no physical fields (collected without a model)")
        return {
            "state": self.state,
            "next_state": self.next_state,
            "physical_action": self.physical_action,
            "k": np.asarray(self.k, dtype=np.float32).reshape(-1, 1),
        }


def physics_extras(state_dim: int, action_dim: int) -> dict[str, tuple[int, ...]]:
    """Buffer extras of a model-based run: the physical fields plus two per-transition flags.

    The flags are ``holdout`` (kept out of model training to measure its accuracy) and ``valid``
    (0 where the step blew up).
    """
    return {
        "state": (state_dim,),
        "next_state": (state_dim,),
        "physical_action": (action_dim,),
        "k": (1,),
        "holdout": (1,),
        "valid": (1,),
    }


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux's ``MemAvailable``), ``None`` where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _bytes(n: int) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e8 else f"{n / 1e6:.1f} MB"


class ReplayBuffer:
    """Ring buffer of ``capacity`` transitions.

    Args:
        capacity: maximum number of transitions kept (the oldest are overwritten).
        obs_dim, act_dim: flat observation and action sizes.
        extras: optional named per-transition arrays, ``{name: shape}``, stored alongside (float32),
            e.g. physical states for model training.
    """

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, extras: dict[str, tuple[int, ...]] | None = None) -> None:
        if capacity < 1:
            raise ValueError(f"buffer capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self.obs_dim = int(obs_dim)
        self.act_dim = int(act_dim)
        self._check_memory(extras or {})
        self.obs = torch.zeros((self.capacity, self.obs_dim))
        self.next_obs = torch.zeros((self.capacity, self.obs_dim))
        self.action = torch.zeros((self.capacity, self.act_dim))
        self.reward = torch.zeros(self.capacity)
        self.terminated = torch.zeros(self.capacity)
        self.truncated = torch.zeros(self.capacity)
        self.extras = {k: torch.zeros((self.capacity, *shape)) for k, shape in (extras or {}).items()}
        self.pos = 0
        self.size = 0
        self.total_added = 0

    def __len__(self) -> int:
        return self.size

    def _check_memory(self, extras: dict[str, tuple[int, ...]]) -> None:
        """Refuse a preallocation larger than the memory available, with the estimate and the fix."""
        per_row = 2 * self.obs_dim + self.act_dim + 3 + sum(math.prod(shape) for shape in extras.values())
        need = 4 * per_row * self.capacity  # float32
        free = available_memory()
        if free is not None and need > free:
            raise ValueError(
                f"a replay buffer of {self.capacity:,} transitions needs about {_bytes(need)} "
                f"({4 * per_row} bytes each), but only {_bytes(free)} of memory is available: "
                "lower --buffer-size (or --dyna.imagined-buffer-size for the imagined buffer)"
            )

    def add(
        self,
        obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray | float,
        next_obs: np.ndarray,
        terminated: np.ndarray | bool,
        truncated: np.ndarray | bool,
        **extras: np.ndarray,
    ) -> None:
        """Add one transition, or a batch of them (leading dimension B), after checking they are finite."""
        obs_t = torch.as_tensor(np.asarray(obs, dtype=np.float32)).reshape(-1, self.obs_dim)
        n = obs_t.shape[0]
        act_t = torch.as_tensor(np.asarray(action, dtype=np.float32)).reshape(n, self.act_dim)
        rew_t = torch.as_tensor(np.asarray(reward, dtype=np.float32)).reshape(n)
        nxt_t = torch.as_tensor(np.asarray(next_obs, dtype=np.float32)).reshape(n, self.obs_dim)
        for name, t in (("obs", obs_t), ("action", act_t), ("reward", rew_t), ("next_obs", nxt_t)):
            if not torch.isfinite(t).all():
                raise ValueError(f"refusing to store a non-finite {name} in the replay buffer")
        term_t = torch.as_tensor(np.asarray(terminated, dtype=np.float32)).reshape(n)
        trunc_t = torch.as_tensor(np.asarray(truncated, dtype=np.float32)).reshape(n)
        missing = set(self.extras) - set(extras)
        if missing or set(extras) - set(self.extras):
            raise ValueError(f"extras must be exactly {sorted(self.extras)}, got {sorted(extras)}")
        extras_t = {
            k: torch.as_tensor(np.asarray(v, dtype=np.float32)).reshape(n, *self.extras[k].shape[1:]) for k, v in extras.items()
        }
        skip = max(0, n - self.capacity)  # more rows than the ring holds: only the newest are kept
        if skip:
            obs_t, act_t, rew_t, nxt_t, term_t, trunc_t = (t[skip:] for t in (obs_t, act_t, rew_t, nxt_t, term_t, trunc_t))
            extras_t = {k: v[skip:] for k, v in extras_t.items()}
            self.pos = int((self.pos + skip) % self.capacity)
            self.total_added += skip
            n -= skip
        idx = (self.pos + torch.arange(n)) % self.capacity
        self.obs[idx] = obs_t
        self.action[idx] = act_t
        self.reward[idx] = rew_t
        self.next_obs[idx] = nxt_t
        self.terminated[idx] = term_t
        self.truncated[idx] = trunc_t
        for k, v in extras_t.items():
            self.extras[k][idx] = v
        self.pos = int((self.pos + n) % self.capacity)
        self.size = min(self.size + n, self.capacity)
        self.total_added += n

    def add_transitions(self, tr: Transitions, **flags: np.ndarray) -> None:
        """Store :class:`Transitions`, with their physical fields where the buffer has physical extras.

        ``flags`` (e.g. ``holdout``, ``valid``) fill the remaining extras.
        """
        extras = {**(tr.physics() if self.extras else {}), **flags}
        self.add(tr.obs, tr.action, tr.reward, tr.next_obs, tr.terminated, tr.truncated, **extras)

    def sample_indices(self, batch_size: int, rng: np.random.Generator) -> torch.Tensor:
        """``batch_size`` indices of stored transitions, uniform with replacement; ``ValueError`` if the buffer is empty."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        return torch.from_numpy(rng.integers(0, self.size, size=batch_size))

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        """``batch_size`` transitions drawn uniformly with replacement."""
        return self.gather(self.sample_indices(batch_size, rng))

    def gather(self, idx: torch.Tensor) -> Batch:
        """The transitions at indices ``idx`` as a :class:`Batch` (extras not included)."""
        return Batch(
            self.obs.index_select(0, idx),
            self.action.index_select(0, idx),
            self.reward.index_select(0, idx),
            self.next_obs.index_select(0, idx),
            self.terminated.index_select(0, idx),
            self.truncated.index_select(0, idx),
        )

    def extra(self, name: str, idx: torch.Tensor) -> torch.Tensor:
        """The extra field ``name`` (e.g. ``state``, ``holdout``) at indices ``idx``."""
        return self.extras[name].index_select(0, idx)

    # ------------------------------------------------------------------ checkpointing
    def state_dict(self) -> dict[str, Any]:
        """Contents (only the filled part) and counters."""
        n = self.size
        return {
            "capacity": self.capacity,
            "pos": self.pos,
            "size": n,
            "total_added": self.total_added,
            "data": {
                k: v[:n].clone()
                for k, v in {
                    "obs": self.obs,
                    "next_obs": self.next_obs,
                    "action": self.action,
                    "reward": self.reward,
                    "terminated": self.terminated,
                    "truncated": self.truncated,
                    **{f"extra/{e}": t for e, t in self.extras.items()},
                }.items()
            },
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore contents and counters from :meth:`state_dict`.

        The capacity must match, or be larger where the saved buffer never overwrote an entry (a run whose
        budget was raised: its buffer, sized to the old budget, grows as if it had been sized to the new one).
        """
        n = state["size"]
        grow = state["capacity"] < self.capacity and state["total_added"] == n
        if state["capacity"] != self.capacity and not grow:
            raise ValueError(f"checkpointed buffer capacity {state['capacity']} differs from {self.capacity}")
        for k, v in state["data"].items():
            target = self.extras[k[len("extra/") :]] if k.startswith("extra/") else getattr(self, k)
            target[:n] = v
        # entries 0..n-1 were written in order: in the larger buffer the next one goes to n
        self.pos = n % self.capacity if grow else state["pos"]
        self.size, self.total_added = n, state["total_added"]
