"""Initial-state pools for the Kuramoto-Sivashinsky task, taken from chaotic transients.

At L = 8 pi the unforced discretised KS system is chaotic only for a while: after ~40-200 time units most
runs settle onto a steady state (energy mean(u^2) ~ 2.8, reward ~ -2.3 per step). "Sampled from the
attractor" therefore means here: snapshots from the chaotic phase of unforced runs (see
docs/environments.md, section "KS initial states", for the reasons and the resulting statistics).

Generation, fully seeded:

1. start ``runs`` unforced runs from random smooth fields (Fourier modes 1-4 with amplitudes ~ N(0, 1/m^2));
2. simulate ``max_steps`` control steps; a run is *settled* from the first step at which
   ``max |du/dt|`` drops below ``settle_rate`` (settled states drift at ~1e-3, chaotic ones at ~0.1-1);
3. keep snapshots every ``spacing`` control steps after ``burn_in``, as long as the run's uncontrolled
   continuation stays unsettled for a whole episode plus ``margin`` steps: then every pool state starts
   a fully chaotic uncontrolled episode, as the authors' states do (their 400-step uncontrolled returns are
   -234.6 ... -244.7);
4. at most ``per_run`` snapshots per run; runs are added until the pool is full.

Train, validation and test pools come from disjoint sets of runs (independent seed streams), so no test
state is ever a training or validation state. Training reads the training pool (resets) and, for the
decisions it makes (the switch to model-free fine-tuning), the validation pool; only evaluation reads the
test pool. Pools are cached under :func:`pimbrl.physics.kernels.cache_dir`, keyed by the
numerics, the simulator kernel's version and every generation parameter, and written atomically. The cache
is used only in a directory of this user's that nobody else may write, and an entry is checked when it is
loaded (a regular file, plain arrays of the expected shapes, dtypes, finite and bounded values): an invalid
one is generated anew, with a warning, never used. The runs
are chaotic, so round-off (another kernel, another CPU) changes the states slightly (the test pool by up to
2.3e-9 from kernel version 4 to 5) and can change which runs qualify (the training pool's composition).
Since the unforced runs *are* the uncontrolled episodes, the uncontrolled return of every pool state is recorded for free.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import sys
import tempfile
import warnings
import zipfile
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Literal

import numpy as np

from ..fileio import UnsafeFileError, private_directory, read_below
from ..physics import KuramotoSivashinsky
from ..physics.kernels import GENERATOR_VERSION, cache_dir

__all__ = ["KSPool", "KSPoolConfig", "ks_initial_state_pool"]

_POOL_VERSION = 1
Split = Literal["train", "validation", "test"]
#: each split's seed stream (spawn key of the pool seed): the train and test keys are those of every earlier
#: release, so their pools are unchanged by the validation split's addition
_SPLIT_KEYS: dict[str, int] = {"train": 0, "test": 1, "validation": 2}


#: the memory a pool generator's batch of trajectories may take
_MAX_GENERATION_BYTES = 2 << 30


@dataclass(frozen=True)
class KSPoolConfig:
    """Parameters of the pool generator (all in control steps of 0.25 time units unless noted)."""

    n_train: int = 600
    n_test: int = 200
    #: states of the validation pool, which decisions during training read (never the test pool)
    n_validation: int = 50
    seed: int = 0
    burn_in: int = 40
    spacing: int = 20
    per_run: int = 8
    max_steps: int = 700
    episode_steps: int = 400
    margin: int = 100
    settle_rate: float = 0.01
    batch: int = 64

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "settle_rate":
                ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                if not ok:
                    raise TypeError(f"KSPoolConfig.settle_rate must be a finite number, got {value!r}")
            elif isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise TypeError(f"KSPoolConfig.{f.name} must be an integer, got {value!r}")
            elif value < 0:
                raise ValueError(f"KSPoolConfig.{f.name} must be >= 0, got {value!r}")
        for name in ("n_train", "n_test", "n_validation", "spacing", "per_run", "max_steps", "episode_steps", "batch"):
            if getattr(self, name) < 1:
                raise ValueError(f"KSPoolConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.burn_in + self.episode_steps + self.margin >= self.max_steps:
            raise ValueError("KSPoolConfig: max_steps must exceed burn_in + episode_steps + margin")
        for name, most in (("n_train", 10**5), ("n_test", 10**5), ("n_validation", 10**5), ("batch", 4096), ("max_steps", 10**5)):
            if getattr(self, name) > most:
                raise ValueError(f"KSPoolConfig.{name} must be at most {most:,d}, got {getattr(self, name):,d}")
        trajectory_bytes = (self.max_steps + 1) * self.batch * 68 * 8  # the batch's states and reward terms
        if trajectory_bytes > _MAX_GENERATION_BYTES:
            raise ValueError(
                f"KSPoolConfig: batch x max_steps = {self.batch:,d} x {self.max_steps:,d} needs "
                f"{trajectory_bytes / 2**30:.1f} GiB while generating (at most {_MAX_GENERATION_BYTES / 2**30:.0f} GiB): "
                "lower batch or max_steps"
            )


@dataclass(frozen=True)
class KSPool:
    """A pool of initial states with their uncontrolled episode statistics."""

    states: np.ndarray  # (n, 64) float64
    uncontrolled_terms: np.ndarray  # (n, 4): sum over one uncontrolled episode of the step-averaged reward integrands
    run_ids: np.ndarray  # (n,) index of the generating run (within the split)

    def uncontrolled_returns(self, physics: KuramotoSivashinsky) -> np.ndarray:
        """Return of the uncontrolled (a = 0) episode from each state, under ``physics``' reward."""
        return physics.reward_from_terms(self.uncontrolled_terms)


def _random_smooth_fields(rng: np.random.Generator, n_fields: int, physics: KuramotoSivashinsky) -> np.ndarray:
    x = physics.x * 2 * np.pi / physics.length
    u = np.zeros((n_fields, physics.n))
    for m in range(1, 5):
        u += rng.normal(0, 1 / m, (n_fields, 1)) * np.cos(m * x) + rng.normal(0, 1 / m, (n_fields, 1)) * np.sin(m * x)
    return 0.5 * u


def _generate_split(physics: KuramotoSivashinsky, cfg: KSPoolConfig, split: Split, verbose: bool) -> KSPool:
    n_target = split_size(cfg, split)
    stream = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(_SPLIT_KEYS[split],)))
    zeros = np.zeros((cfg.batch, 4))
    states: list[np.ndarray] = []
    terms: list[np.ndarray] = []
    runs: list[np.ndarray] = []
    run0 = 0
    # a setting under which (almost) no run qualifies (e.g. settle_rate far too high) would loop for ever
    max_runs = 50 * (-(-n_target // cfg.per_run)) + 10 * cfg.batch
    while sum(len(s) for s in states) < n_target:
        if run0 >= max_runs:
            got = sum(len(s) for s in states)
            raise ValueError(
                f"KS {split} pool: only {got}/{n_target} states from {run0:,d} runs; the pool settings let too few runs "
                f"qualify (settle_rate {cfg.settle_rate:g}, max_steps {cfg.max_steps:,d}, burn_in {cfg.burn_in}, margin "
                f"{cfg.margin}): use the defaults (KSPoolConfig())"
            )
        u = _random_smooth_fields(stream, cfg.batch, physics)
        traj = np.empty((cfg.max_steps + 1, cfg.batch, physics.n))
        step_terms = np.empty((cfg.max_steps, cfg.batch, 4))
        traj[0] = u
        for k in range(cfg.max_steps):
            u, step_terms[k], _ = physics.advance_terms(u, zeros)
            traj[k + 1] = u
        rate = np.abs(traj[1:] - traj[:-1]).max(-1) / physics.control_dt  # (T, B)
        for b in range(cfg.batch):
            if not np.isfinite(traj[:, b]).all():
                continue  # a run that blew up contributes nothing
            slow = np.nonzero(rate[:, b] < cfg.settle_rate)[0]
            settle = int(slow[0]) if len(slow) else cfg.max_steps
            last_start = min(settle, cfg.max_steps) - cfg.episode_steps - cfg.margin
            starts = np.arange(cfg.burn_in, last_start + 1, cfg.spacing)[: cfg.per_run]
            if len(starts) == 0:
                continue
            cum = np.concatenate([np.zeros((1, 4)), np.cumsum(step_terms[:, b], axis=0)])
            states.append(traj[starts, b])
            terms.append(cum[starts + cfg.episode_steps] - cum[starts])
            runs.append(np.full(len(starts), run0 + b))
        run0 += cfg.batch
        if verbose:
            got = sum(len(s) for s in states)
            print(f"pimbrl: KS {split} pool: {min(got, n_target)}/{n_target} states from {run0} runs", file=sys.stderr)
    return KSPool(np.concatenate(states)[:n_target], np.concatenate(terms)[:n_target], np.concatenate(runs)[:n_target])


def split_size(cfg: KSPoolConfig, split: str) -> int:
    """The number of states of the pool ``split`` under ``cfg``."""
    return {"train": cfg.n_train, "validation": cfg.n_validation, "test": cfg.n_test}[split]


def _cache_key(physics: KuramotoSivashinsky, cfg: KSPoolConfig) -> str:
    # the kernel's version too: a new kernel changes the pool's chaotic runs at round-off, enough to change
    # which runs qualify and the recorded uncontrolled returns
    numerics = {
        "n": physics.n,
        "length": physics.length,
        "dt": physics.dt,
        "substeps": physics.substeps,
        "kernel": GENERATOR_VERSION,
    }
    blob = json.dumps({"v": _POOL_VERSION, "numerics": numerics, "cfg": asdict(cfg)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


_MEMO: dict[tuple[str, str], KSPool] = {}


def ks_initial_state_pool(
    split: Split = "train",
    config: KSPoolConfig | None = None,
    physics: KuramotoSivashinsky | None = None,
    verbose: bool = True,
) -> KSPool:
    """The KS initial-state pool ``split`` ("train", "validation" or "test"), generated once and cached on disk."""
    if split not in _SPLIT_KEYS:
        raise ValueError(f"split must be 'train', 'validation' or 'test', got {split!r}")
    cfg = config or KSPoolConfig()
    phys = physics or KuramotoSivashinsky()
    key = _cache_key(phys, cfg)
    if (key, split) in _MEMO:
        return _MEMO[(key, split)]
    directory = cache_dir() / "ks_pools"
    try:
        cacheable = private_directory(directory, "KS pools (the KS pool cache)")
    except OSError:
        cacheable = False
    path = directory / f"ks_pool_{key}_{split}.npz"
    n_target = split_size(cfg, split)
    pool = _load_cached(path, n_target, phys.n) if cacheable else None
    if pool is None:
        pool = _generate_split(phys, cfg, split, verbose)
        if cacheable:
            _save_atomic(path, pool)
    _MEMO[(key, split)] = pool
    return pool


#: no state of the chaotic KS transient comes near this (|u| stays below about 4); a cached one beyond it is poisoned
_STATE_BOUND = 1e3


def _load_cached(path: Path, rows: int, n: int) -> KSPool | None:
    """The pool cached at ``path``, checked; ``None`` (with a warning where an entry exists) if it is not usable.

    The entry must be a regular file of this user's (no link, no FIFO), an ``.npz`` of plain arrays (never
    unpickled) holding ``rows`` states of ``n`` finite float64 values within :data:`_STATE_BOUND`, their
    ``(rows, 4)`` finite uncontrolled terms and ``rows`` integer run ids.
    """
    try:
        raw = read_below(path.parent, path.name, _MAX_POOL_BYTES, own=True)
    except FileNotFoundError:
        return None
    except UnsafeFileError as exc:
        warnings.warn(f"KS pool cache: {exc}; the pool is generated anew", stacklevel=3)
        return None
    problem = None
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as data:
            arrays = {k: np.asarray(data[k]) for k in ("states", "uncontrolled_terms", "run_ids")}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        problem = f"it cannot be read ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
    if problem is None:
        states, terms, run_ids = arrays["states"], arrays["uncontrolled_terms"], arrays["run_ids"]
        if states.dtype != np.float64 or states.shape != (rows, n):
            problem = f"its states are {states.dtype} of shape {states.shape}, expected float64 of shape {(rows, n)}"
        elif terms.dtype != np.float64 or terms.shape != (rows, 4):
            problem = f"its uncontrolled terms are {terms.dtype} of shape {terms.shape}, expected float64 of shape {(rows, 4)}"
        elif run_ids.shape != (rows,) or run_ids.dtype.kind not in "iu":
            problem = f"its run ids are {run_ids.dtype} of shape {run_ids.shape}, expected integers of shape {(rows,)}"
        elif not (np.isfinite(states).all() and np.isfinite(terms).all()):
            problem = "it holds non-finite numbers"
        elif np.abs(states).max(initial=0.0) > _STATE_BOUND:
            problem = f"it holds states beyond +-{_STATE_BOUND:g}, which no KS transient reaches"
    if problem is not None:
        warnings.warn(f"KS pool cache: {path} is not a valid pool ({problem}); the pool is generated anew", stacklevel=3)
        return None
    return KSPool(states, terms, run_ids)


#: a cached pool of a few thousand 64-point states is a few MB
_MAX_POOL_BYTES = 1 << 30


def _save_atomic(path: os.PathLike, pool: KSPool) -> None:
    directory = os.path.dirname(path)
    try:
        os.makedirs(directory, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=directory, suffix=".npz.tmp")
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, states=pool.states, uncontrolled_terms=pool.uncontrolled_terms, run_ids=pool.run_ids)
        os.replace(tmp, path)
    except OSError as exc:  # a read-only cache only costs regeneration next time
        print(f"pimbrl: could not cache the KS pool at {path}: {exc}", file=sys.stderr)
