"""Kuramoto-Sivashinsky equation with four Gaussian actuators (Liu & Wang 2021, section 3.3).

    u_t + u_xx + u_xxxx + u u_x = f(x, t),   x in [0, L) periodic,

discretised exactly as the authors' code computes it (docs/environments.md, section "Kuramoto-Sivashinsky"):

    du/dt = -D4 u / dx^4 - D2 u / dx^2 - Dup(u^2; u) / (2 dx) + f

with 6th-order central D2, D4, a sign-switched 4th-order one-sided upwind difference ``Dup`` of
``w = u^2``, and classic RK4 (dt = 0.001, 250 steps per control step, forcing frozen).

Initial-state pools (below, :func:`ks_initial_state_pool`)
-----------------------------------------------------------

Initial-state pools for the Kuramoto-Sivashinsky task, taken from chaotic transients.

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

import functools
import hashlib
import io
import json
import math
import os
import sys
import tempfile
import warnings
import zipfile
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import torch
from gymnasium import spaces

from ..envs.base import PhysicsEnv, PhysicsVectorEnv
from ..envs.task import Task, check_bool, check_finite_number
from ..fileio import UnsafeFileError, private_directory, read_below
from ..physics.base import Array, check_coefficient, records_arguments, xp_of
from ..physics.kernels import GENERATOR_VERSION, PDEKernel, PDEKernelSpec, cache_dir
from ..physics.pde import SemilinearPDE
from ..physics.stencil import Stencil, apply_upwind
from .registry import System

__all__ = [
    "KS_D1",
    "KS_D2",
    "KS_D4",
    "KS_UPWIND_BACKWARD",
    "KS_UPWIND_FORWARD",
    "SYSTEM",
    "KSPool",
    "KSPoolConfig",
    "KSTask",
    "KuramotoSivashinsky",
    "KuramotoSivashinskyEnv",
    "KuramotoSivashinskyVectorEnv",
    "ks_initial_state_pool",
]


#: 6th-order central second difference (raw: divide by dx^2).
KS_D2 = Stencil.centered((1 / 90, -3 / 20, 3 / 2, -49 / 18, 3 / 2, -3 / 20, 1 / 90), "D2")
#: 6th-order central fourth difference (raw: divide by dx^4).
KS_D4 = Stencil.centered((7 / 240, -2 / 5, 169 / 60, -122 / 15, 91 / 8, -122 / 15, 169 / 60, -2 / 5, 7 / 240), "D4")
#: 4th-order one-sided backward first difference (used where u >= 0).
KS_UPWIND_BACKWARD = Stencil((-4, -3, -2, -1, 0), (1 / 4, -4 / 3, 3.0, -4.0, 25 / 12), "Dup-")
#: 4th-order one-sided forward first difference (used where u < 0).
KS_UPWIND_FORWARD = Stencil((0, 1, 2, 3, 4), (-25 / 12, 4.0, -3.0, 4 / 3, -1 / 4), "Dup+")
#: 6th-order central first difference (only for ``reward="physical"``).
KS_D1 = Stencil.centered((-1 / 60, 3 / 20, -3 / 4, 0.0, 3 / 4, -3 / 20, 1 / 60), "D1")

RewardMode = Literal["code", "physical"]


class KuramotoSivashinsky(SemilinearPDE):
    """The controlled KS system.

    Args:
        n: grid points (64).
        length: domain length L (8 pi).
        dt: RK4 step (0.001; RK4 is stable only below ~0.00199 on this grid).
        substeps: RK4 steps per control step (250, i.e. 0.25 time units).
        action_bound: actuator amplitudes lie in ``[-action_bound, action_bound]`` (0.5).
        reward: ``"code"`` (default) is the authors' reward on their scale:
            ``-(1/S) sum_s [mean((D2 u_s)^2) + mean((Dup(u_s^2))^2) + mean(u_s f)]`` with raw stencil
            sums; ``"physical"`` is the paper's formula with scaled derivatives,
            ``-(1/S) sum_s mean(u_xx^2 + u_x^2 + u f)`` with ``u_xx = D2 u/dx^2`` and ``u_x = D1 u/dx``
            (6th-order central).
        periodic_actuators: wrap the Gaussian actuator shapes around the periodic domain (the
            authors' code does not, so the actuator at x = 0 is half a bump).
        divergence_bound: ``|u|`` beyond this counts as blown up (100; chaotic states stay below ~5).
        anti_diffusion, hyper_diffusion, convection: factors of the terms ``u_xx``, ``u_xxxx`` and ``u u_x``
            (1 each: ``u_t + a u_xx + b u_xxxx + c u u_x = f``).
        damping: coefficient ``mu`` of a linear damping term ``-mu u`` on the right-hand side (0: none; a term
            a physics prior may miss).
        actuator_width: standard deviation ``s`` of the Gaussian actuators
            ``exp(-(x - x_i)^2 / (2 s^2)) / (sqrt(2 pi) s)`` (1).
        drift: speed ``c`` of a linear advection term ``-c u_x`` on the right-hand side (0: none; a term of a
            form a physics prior may lack altogether; 6th-order central difference).

    The physical coefficients (:attr:`coefficients`) are ``anti_diffusion``, ``hyper_diffusion``,
    ``convection``, ``damping``, ``actuator_width`` and ``drift``.
    """

    name = "ks"
    coefficients = ("anti_diffusion", "hyper_diffusion", "convection", "damping", "actuator_width", "drift")

    @records_arguments
    def __init__(
        self,
        n: int = 64,
        length: float = 8 * np.pi,
        dt: float = 0.001,
        substeps: int = 250,
        action_bound: float = 0.5,
        reward: RewardMode = "code",
        periodic_actuators: bool = False,
        divergence_bound: float = 100.0,
        anti_diffusion: float = 1.0,
        hyper_diffusion: float = 1.0,
        convection: float = 1.0,
        damping: float = 0.0,
        actuator_width: float = 1.0,
        drift: float = 0.0,
    ) -> None:
        if n < 2 * KS_D4.halo + 1:
            raise ValueError(f"KS needs at least {2 * KS_D4.halo + 1} grid points, got n={n}")
        if reward not in ("code", "physical"):
            raise ValueError(f"reward must be 'code' or 'physical', got {reward!r}")
        if dt <= 0 or substeps < 1:
            raise ValueError(f"need dt > 0 and substeps >= 1, got dt={dt}, substeps={substeps}")
        hyper_diffusion = check_coefficient(self.name, "hyper_diffusion", hyper_diffusion, positive=True, high=100.0)
        actuator_width = check_coefficient(self.name, "actuator_width", actuator_width, low=1e-2, high=30.0)
        for name, value in (
            ("anti_diffusion", anti_diffusion),
            ("convection", convection),
            ("damping", damping),
            ("drift", drift),
        ):
            check_coefficient(self.name, name, value, low=-1e3, high=1e3)
        self.n = int(n)
        self.length = float(length)
        self.dx = self.length / self.n
        self.dt = float(dt)
        self.substeps = int(substeps)
        self.state_dim = self.n
        self.action_dim = 4
        self.action_low = np.full(4, -float(action_bound))
        self.action_high = np.full(4, float(action_bound))
        self.reward_mode: RewardMode = reward
        self.periodic_actuators = bool(periodic_actuators)
        self.divergence_bound = float(divergence_bound)

        self.anti_diffusion = float(anti_diffusion)
        self.hyper_diffusion = float(hyper_diffusion)
        self.convection = float(convection)
        self.damping = float(damping)
        self.actuator_width = float(actuator_width)
        self.drift = float(drift)

        self.x = np.arange(self.n) * self.dx
        self.actuator_centres = np.array([0.0, 0.25, 0.5, 0.75]) * self.length
        #: ``(4, n)`` actuator shape functions; the forcing is ``f = a @ actuator_shapes``.
        self.actuator_shapes = self._shapes(self.actuator_width)

        dx = self.dx
        #: the linear operator ``-D4/dx^4 - D2/dx^2`` as one stencil (with its coefficients; ``- mu`` with damping)
        self.linear = self._with_added_terms(
            KS_D4.scaled(-self.hyper_diffusion / dx**4, "-D4/dx^4") + KS_D2.scaled(-self.anti_diffusion / dx**2, "-D2/dx^2")
        )
        #: coefficient of the upwind term ``Dup(u^2)``
        self.nonlinear_coef = -self.convection / (2.0 * dx)
        # weights of the reward integrands [mean (D2u)^2, mean (Dup u^2)^2, mean (D1u)^2, mean u f]
        if reward == "code":
            self.reward_weights = np.array([1.0, 1.0, 0.0, 1.0])
        else:
            self.reward_weights = np.array([1.0 / dx**4, 0.0, 1.0 / dx**2, 1.0])
        self.method = "rk4"
        self._kernel: PDEKernel | None = None  # compiled on first use

    drift_stencil = KS_D1

    def _shapes(self, width: Any) -> Any:
        dist: Any = self.x[None, :] - self.actuator_centres[:, None]
        if self.periodic_actuators:
            dist = (dist + self.length / 2) % self.length - self.length / 2
        xp = xp_of(width)
        if xp is torch:
            dist = torch.as_tensor(dist)
        return xp.exp(-(dist**2) / (2 * width**2)) / (np.sqrt(2 * np.pi) * width)

    def operators(self, values: Mapping[str, Any]) -> tuple[Any, Any, Any]:
        """``lam = -b D4/dx^4 - a D2/dx^2 - mu``, ``-c / (2 dx)`` and the actuator shapes (see the base class)."""
        get = functools.partial(self._coefficient, values)
        d2, d4 = self._symbol(KS_D2, 2, values), self._symbol(KS_D4, 4, values)
        lam = self._added_eigenvalues(-get("hyper_diffusion") * d4 - get("anti_diffusion") * d2, values)
        return lam, -get("convection") / (2.0 * self.dx), self._shapes(get("actuator_width"))

    # ------------------------------------------------------------------ equation
    def upwind(self, u: Array) -> Array:
        """Raw sign-switched upwind difference ``Dup(u^2)`` (divide by dx for a derivative of u^2)."""
        return apply_upwind(KS_UPWIND_BACKWARD, KS_UPWIND_FORWARD, u * u, u)

    # ------------------------------------------------------------------ reward
    def reward_terms(self, u: Array, f: Array) -> Array:
        """Integrands ``[mean (D2u)^2, mean (Dup u^2)^2, mean (D1u)^2, mean u f]`` of state(s) ``u``."""
        xp = xp_of(u)
        d2 = KS_D2.apply(u)
        dup = self.upwind(u)
        d1 = KS_D1.apply(u)
        return xp.stack([(d2 * d2).mean(-1), (dup * dup).mean(-1), (d1 * d1).mean(-1), (u * f).mean(-1)], -1)

    def reward_from_terms(self, terms: Array) -> Array:
        """Reward from step-averaged integrands (``(..., 4)``, as returned by the kernel)."""
        w = self.reward_weights
        # an explicit sum: its rounding does not depend on the batch shape (a reduction's may)
        return -(terms[..., 0] * w[0] + terms[..., 1] * w[1] + terms[..., 2] * w[2] + terms[..., 3] * w[3])

    def reward(self, u: Array, a: Array, u_next: Array, k: Array | int, path: Array | None = None) -> Array:
        """The control step's reward: the integrand averaged over the step as the simulator averages it.

        The simulator averages the integrand ``g`` over the states at the start of its ``M = substeps``
        solver steps (a left sum). ``path`` holds the states at the start of ``N`` equal sub-steps of the
        control step (axis ``-2``, ``u`` first); ``None`` means ``N = 1`` (the start state only).

        * ``N == M`` (the solver's own states): that left sum, exactly as the simulator computes it.
        * ``N < M`` (e.g. a model's intermediate states): the trapezoid rule over the ``N + 1`` sub-step
          boundaries (``u_next`` closes the last sub-step) plus the end correction
          ``(g_0 - g_N) / (2 M)`` by which an ``M``-point left sum exceeds the integral. Fed the
          solver's own states with ``N = 5`` it was within 0.12 % of the simulator's reward at every
          control step measured; the left sum over the ``N`` start states alone was up to 4.4 % off
          (docs/environments.md, section "KS reward from a model's intermediate states").
        """
        f = self.forcing(a)[..., None, :]
        states = u[..., None, :] if path is None else path
        terms = self.reward_terms(states, f)
        n, m = terms.shape[-2], self.substeps
        if n >= m:
            return self.reward_from_terms(terms.mean(-2))
        first = terms[..., 0, :]
        last = self.reward_terms(u_next, f[..., 0, :])
        trapezoid = (terms.sum(-2) + 0.5 * (last - first)) / n
        return self.reward_from_terms(trapezoid + (first - last) / (2 * m))

    # ------------------------------------------------------------------ fast simulator
    def kernel_spec(self) -> PDEKernelSpec:
        """The compiled kernel's operators: exactly this object's stencils and RK4."""
        return PDEKernelSpec(
            linear=self.linear,
            nonlinear_coef=self.nonlinear_coef,
            upwind_backward=KS_UPWIND_BACKWARD,
            upwind_forward=KS_UPWIND_FORWARD,
            method="rk4",
            integrand_a=KS_D2,
            integrand_c=KS_D1,  # always: terms then serve every reward mode (the pools rely on it)
            n=self.n,
        )

    def advance_terms(self, u: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Like :meth:`advance`, but also returns the step-averaged reward integrands ``(B, 4)``.

        Returns ``(u_next, terms, reward)``.
        """
        return self.run_kernel(u, a, True, self.reward_weights)

    def advance(self, u: np.ndarray, a: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step of the compiled kernel with the step-averaged reward."""
        u_next, _, reward = self.advance_terms(u, a)
        return u_next, reward


_POOL_VERSION = 1
Split = Literal["train", "validation", "test", "holdout"]
#: each split's seed stream (spawn key of the pool seed): the train and test keys are those of every earlier
#: release, so their pools are unchanged by the validation and holdout splits' additions
_SPLIT_KEYS: dict[str, int] = {"train": 0, "test": 1, "validation": 2, "holdout": 3}


#: the memory a pool generator's batch of trajectories may take
_MAX_GENERATION_BYTES = 2 << 30


@dataclass(frozen=True)
class KSPoolConfig:
    """Parameters of the pool generator (all in control steps of 0.25 time units unless noted)."""

    n_train: int = 600
    n_test: int = 200
    #: states of the validation pool, which decisions during training read (never the test pool)
    n_validation: int = 50
    #: states of the holdout pool, the fresh test pool only a run's final evaluation reads (confirmatory studies)
    n_holdout: int = 200
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
        for name in (
            "n_train",
            "n_test",
            "n_validation",
            "n_holdout",
            "spacing",
            "per_run",
            "max_steps",
            "episode_steps",
            "batch",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"KSPoolConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.burn_in + self.episode_steps + self.margin >= self.max_steps:
            raise ValueError("KSPoolConfig: max_steps must exceed burn_in + episode_steps + margin")
        for name, most in (
            ("n_train", 10**5),
            ("n_test", 10**5),
            ("n_validation", 10**5),
            ("n_holdout", 10**5),
            ("batch", 4096),
            ("max_steps", 10**5),
        ):
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
    return {"train": cfg.n_train, "validation": cfg.n_validation, "test": cfg.n_test, "holdout": cfg.n_holdout}[split]


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
    # the holdout pool's size is in its file name instead: its addition leaves every earlier cache valid
    settings = {k: v for k, v in asdict(cfg).items() if k != "n_holdout"}
    blob = json.dumps({"v": _POOL_VERSION, "numerics": numerics, "cfg": settings}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


_MEMO: dict[tuple[str, str], KSPool] = {}


def ks_initial_state_pool(
    split: Split = "train",
    config: KSPoolConfig | None = None,
    physics: KuramotoSivashinsky | None = None,
    verbose: bool = True,
) -> KSPool:
    """The KS initial-state pool ``split`` ("train", "validation", "test" or "holdout"), generated once and cached on disk."""
    if split not in _SPLIT_KEYS:
        raise ValueError(f"split must be 'train', 'validation', 'test' or 'holdout', got {split!r}")
    cfg = config or KSPoolConfig()
    phys = physics or KuramotoSivashinsky()
    key = _cache_key(phys, cfg)
    name = f"holdout{cfg.n_holdout}" if split == "holdout" else split  # the holdout's size is not in the key
    memo_key = (key, name)
    if memo_key in _MEMO:
        return _MEMO[memo_key]
    directory = cache_dir() / "ks_pools"
    try:
        cacheable = private_directory(directory, "KS pools (the KS pool cache)")
    except OSError:
        cacheable = False
    path = directory / f"ks_pool_{key}_{name}.npz"
    n_target = split_size(cfg, split)
    pool = _load_cached(path, n_target, phys.n) if cacheable else None
    if pool is None:
        pool = _generate_split(phys, cfg, split, verbose)
        if cacheable:
            _save_atomic(path, pool)
    _MEMO[memo_key] = pool
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


class KSTask(Task):
    """KS task: observation ``u``, 4 actuator amplitudes in ``[-0.5, 0.5]``, 400 control steps.

    Args:
        reward: ``"code"`` (the authors' reward scale, default) or ``"physical"``.
        periodic_actuators: wrap the actuator Gaussians periodically (a bool; default False, as the authors).
        initial_states: ``"train"`` (default) or ``"test"`` pool, or an array ``(n, 64)`` of states.
        pool_config: generator settings of the pools (a :class:`KSPoolConfig` or a dict of its fields; see
            :mod:`pimbrl.systems.ks`).
        divergence_penalty: reward of a step that blows up, a finite number (default -100; a settled uncontrolled episode
            returns about -920, and with gamma = 0.977 the discounted cost of the rest of any episode
            is below 100).
        **coefficients: physical coefficients of :class:`pimbrl.systems.KuramotoSivashinsky` that differ from
            the paper's (``anti_diffusion``, ``hyper_diffusion``, ``convection``, ``damping``,
            ``actuator_width``, ``drift``), e.g. ``convection=1.3``. The initial-state pools are drawn from the paper's
            system whatever the coefficients.
    """

    max_episode_steps = 400
    render_fps = 4  # a control step is 0.25 time units
    render_scale = 4.0  # chaotic states stay within about |u| < 3
    physics: KuramotoSivashinsky
    action_space: spaces.Box

    def __init__(
        self,
        reward: Literal["code", "physical"] = "code",
        periodic_actuators: bool = False,
        initial_states: str | np.ndarray = "train",
        pool_config: KSPoolConfig | dict | None = None,
        divergence_penalty: float = -100.0,
        **coefficients: float,
    ) -> None:
        self.physics = KuramotoSivashinsky(
            reward=reward, periodic_actuators=check_bool(periodic_actuators, "periodic_actuators")
        ).with_coefficients(**coefficients)
        self.physics.check_stability()  # a one-line error now rather than at the first step
        self.divergence_penalty = check_finite_number(divergence_penalty, "divergence_penalty")
        if pool_config is not None and not isinstance(pool_config, (KSPoolConfig, dict)):
            raise TypeError(f"pool_config must be a KSPoolConfig or a dict of its fields, got {pool_config!r}")
        self.pool_config = KSPoolConfig(**pool_config) if isinstance(pool_config, dict) else pool_config
        if isinstance(initial_states, str):
            if initial_states not in ("train", "test"):
                raise ValueError(f"initial_states must be 'train', 'test' or an array of states, got {initial_states!r}")
            self._pool: np.ndarray | None = None
            self._pool_split = initial_states
        else:
            pool = np.asarray(initial_states, dtype=np.float64)
            if pool.ndim != 2 or pool.shape[1] != self.physics.n or len(pool) == 0 or not np.isfinite(pool).all():
                raise ValueError(f"initial_states must be a finite array of shape (n, {self.physics.n}), got shape {pool.shape}")
            self._pool = pool
            self._pool_split = "custom"
        bound = np.float32(self.physics.divergence_bound)
        self.observation_space = spaces.Box(-bound, bound, shape=(self.physics.n,), dtype=np.float32)
        self.action_space = spaces.Box(
            self.physics.action_low.astype(np.float32), self.physics.action_high.astype(np.float32), dtype=np.float32
        )

    @property
    def pool(self) -> np.ndarray:
        """The initial-state pool (generated and cached on first use)."""
        if self._pool is None:
            # a pool is given as an array exactly when the split is "custom": here it is "train" or "test"
            split = cast(Split, self._pool_split)
            self._pool = ks_initial_state_pool(split, self.pool_config).states
        return self._pool

    def sample_initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` states drawn with replacement from the initial-state pool."""
        return self.pool[rng.integers(len(self.pool), size=n)].copy()

    @property
    def test_pool_size(self) -> int:
        """Number of states in the test pool of :attr:`pool_config` (known without generating it)."""
        return (self.pool_config or KSPoolConfig()).n_test

    def pool_size(self, protocol: str) -> int | None:
        """States of the pool ``protocol`` draws from: KS's pools are finite (known without generating them)."""
        if protocol == "authors":
            return len(self.AUTHORS_EVAL_ROWS)
        return split_size(self.pool_config or KSPoolConfig(), protocol) if protocol in _SPLIT_KEYS else None

    def _first_pool_states(self, split: Split, n: int) -> np.ndarray:
        """The first ``n`` states of the pool ``split`` of :attr:`pool_config`, in pool order (a one-line error past its size)."""
        size = split_size(self.pool_config or KSPoolConfig(), split)
        if not 0 <= n <= size:
            raise ValueError(
                f"{n} KS {split} states requested, but the {split} pool holds {size} "
                f"(raise KSPoolConfig.n_{split} through pool_config, or ask for fewer {split} episodes)"
            )
        return ks_initial_state_pool(split, self.pool_config).states[:n].copy()

    def test_initial_states(self, n: int, seed: int) -> np.ndarray:
        """The first ``n`` states of the test pool of :attr:`pool_config`, in pool order; ``seed`` is unused.

        The test pool comes from runs disjoint from the training pool's, whatever ``initial_states`` this
        task samples its training episodes from.
        """
        return self._first_pool_states("test", n)

    #: rows of the training pool evaluated by the ``"authors"`` protocol, as the authors' code evaluates rows
    #: 0, 49, 99, 149 and 199 of its array of training initial states
    AUTHORS_EVAL_ROWS = (0, 49, 99, 149, 199)

    @property
    def eval_protocols(self) -> tuple[str, ...]:
        """``"test"`` (the test pool), ``"validation"``, ``"holdout"`` and ``"authors"`` (5 fixed training states)."""
        return ("test", "validation", "holdout", "authors")

    def validation_initial_states(self, n: int) -> np.ndarray:
        """The first ``n`` states of the validation pool of :attr:`pool_config`, in pool order.

        The validation pool comes from runs disjoint from the training and test pools' (its own seed stream).
        """
        return self._first_pool_states("validation", n)

    def holdout_initial_states(self, n: int) -> np.ndarray:
        """The first ``n`` states of the holdout pool of :attr:`pool_config`, in pool order.

        The holdout pool comes from runs disjoint from the other pools' (its own seed stream); only the final
        evaluation of a run reads it (``holdout_episodes``).
        """
        return self._first_pool_states("holdout", n)

    def protocol_initial_states(self, protocol: str, n: int | None, seed: int) -> np.ndarray:
        """``"test"``: the first ``n`` test-pool states; ``"authors"``: rows :data:`AUTHORS_EVAL_ROWS` of the training pool.

        The authors report the mean return over 5 states the agent trained on (rows 0, 49, 99, 149, 199 of
        their array of training states, snapshots of one trajectory); ``"authors"`` takes the same rows of
        this task's training pool (snapshots of several chaotic transients, so the 5 states come from
        different runs). ``n`` must then be 5 or ``None``.
        """
        if protocol != "authors":
            return super().protocol_initial_states(protocol, n, seed)
        rows = list(self.AUTHORS_EVAL_ROWS)
        if n is not None and n != len(rows):
            raise ValueError(f"the 'authors' KS protocol has {len(rows)} episodes, not {n}; leave the number of episodes unset")
        pool = ks_initial_state_pool("train", self.pool_config).states
        if len(pool) <= rows[-1]:
            raise ValueError(
                f"the 'authors' KS protocol evaluates training-pool row {rows[-1]}, but the pool holds {len(pool)} states "
                "(raise KSPoolConfig.n_train through pool_config)"
            )
        return pool[rows].copy()

    def observe(self, u: np.ndarray, k: np.ndarray) -> np.ndarray:
        """The field itself, as float32."""
        return u.astype(np.float32)

    def physical_action(self, actions: Any, batch: int) -> np.ndarray:
        """Check the actions' shape and finiteness and clip them to the actuator bounds."""
        return self._box_action(actions, batch, self.action_space, self.physics.action_low, self.physics.action_high)


_DOC = """Kuramoto-Sivashinsky chaos suppression with four actuators (Liu & Wang 2021, section 3.3).

    ## Description
    A periodic 1-D field ``u(x, t)`` on ``[0, 8 pi)`` obeys the Kuramoto-Sivashinsky equation and is,
    unforced, spatiotemporally chaotic for a long transient. Four Gaussian actuators at
    ``x in {0, L/4, L/2, 3L/4}`` inject forcing; the goal is to suppress the chaotic dynamics with
    little dissipation and input power.

    ## Governing equation
    ``u_t + u_xx + u_xxxx + u u_x = f(x, t)``, ``f = sum_i a_i exp(-(x - x_i)^2 / 2) / sqrt(2 pi)``
    (the Gaussians are not wrapped periodically unless ``periodic_actuators=True``).

    ## Discretisation
    64 points, ``dx = L/64``; ``du/dt = -D4 u/dx^4 - D2 u/dx^2 - Dup(u^2)/(2 dx) + f`` with 6th-order
    central D2 and D4 and a 4th-order one-sided upwind ``Dup`` switched point by point on the sign of
    ``u``; classic RK4 with ``dt = 0.001``, 250 steps per control step (0.25 time units), forcing frozen.
    The simulator is a compiled float64 kernel generated from the same stencil tables as the torch
    right-hand side (:class:`pimbrl.systems.KuramotoSivashinsky`).

    ## Action Space
    ``Box(-0.5, 0.5, (4,), float32)``: actuator amplitudes; values outside are clipped.

    ## Observation Space
    ``Box(-100, 100, (64,), float32)``: the field ``u`` on the grid.

    ## Rewards
    Default (``reward="code"``, the authors' scale, on which the paper's goal -55 is stated):
    ``r = -(1/250) sum_s [mean((D2 u_s)^2) + mean((Dup(u_s^2))^2) + mean(u_s f)]`` over the states
    ``u_s`` at the start of the 250 solver steps, with raw stencil sums. ``reward="physical"``:
    ``-(1/250) sum_s mean(u_xx^2 + u_x^2 + u f)`` with properly scaled derivatives.

    ## Starting State
    A state drawn from the seeded training pool of chaotic-transient snapshots
    (:mod:`pimbrl.systems.ks`); ``initial_states="test"`` draws from the disjoint test pool.
    ``reset(options={"initial_state": u})`` starts from a given field (shape ``(64,)``).

    ## Episode End
    Truncation after 400 control steps (100 time units). Termination only if the state blows up
    (non-finite or ``|u| > 100``): then the reward is ``divergence_penalty`` (-100),
    ``info["diverged"]`` is True and the last finite observation is returned.

    ## Rendering
    ``render_mode="rgb_array"``: the field over the grid (vertical axis ``[-4, 4]``, widened to fit),
    4 frames per second (one per control step).

    ## Arguments
    ``reward``, ``periodic_actuators`` (a bool), ``initial_states``, ``pool_config``, ``divergence_penalty``
    (see :class:`pimbrl.systems.ks.KSTask`); the physical coefficients ``anti_diffusion``, ``hyper_diffusion``,
    ``convection`` (1 each), ``damping`` (0: a term ``-mu u`` added to the right-hand side), ``actuator_width``
    (1) and ``drift`` (0: a term ``-c u_x``), e.g. ``gym.make("pimbrl/KuramotoSivashinsky-v0", convection=1.3)``.

    ## Version History
    * v0: initial version, numerics of the authors' code (docs/environments.md, section
      "Kuramoto-Sivashinsky", lists them in full).
    """


class KuramotoSivashinskyEnv(PhysicsEnv):  # noqa: D101 - docstring set below, __doc__ = _DOC
    __doc__ = _DOC
    task_class = KSTask
    metadata = {"render_modes": ["rgb_array"], "render_fps": KSTask.render_fps}  # noqa: RUF012


class KuramotoSivashinskyVectorEnv(PhysicsVectorEnv):  # noqa: D101 - docstring set below, __doc__ = _DOC
    __doc__ = _DOC + "\n    Native vector version: all sub-environments advance in one compiled call.\n"
    task_class = KSTask


#: control steps of the strongest alternating actuation that drives KS test states off the chaotic set
KS_FORCING_STEPS = 20


def forced_states(task: Task, rng: np.random.Generator, n: int) -> np.ndarray:
    """Out of sample: KS test-pool states driven far from the chaotic set.

    The drive is the strongest alternating actuation (+max, -max, ...) for :data:`KS_FORCING_STEPS`
    control steps.
    """
    phys = task.physics
    pool = task.test_initial_states(task.test_pool_size, seed=0)  # type: ignore[attr-defined]  # KSTask
    u = pool[rng.integers(len(pool), size=n)]
    pattern = np.where(np.arange(phys.action_dim) % 2 == 0, phys.action_high, phys.action_low)
    a = np.tile(pattern, (n, 1)) * rng.choice([-1.0, 1.0], size=(n, 1))
    for _ in range(KS_FORCING_STEPS):
        u, _ = phys.advance(u, a, np.zeros(n))
    return u


#: the declaration: recipes in ks.yaml beside this file, out-of-sample set and model-study settings
SYSTEM = System(
    id="pimbrl/KuramotoSivashinsky-v0",
    env=KuramotoSivashinskyEnv,
    vector_env=KuramotoSivashinskyVectorEnv,
    episode_steps=400,
    aliases=("ks", "kuramoto-sivashinsky"),
    label="KS",
    preset=Path(__file__).with_suffix(".yaml"),  # default, paper (and best where one is recorded)
    out_of_sample=forced_states,
    model_eval={"transitions": 6_000, "steps": 3_000},
    feedback="proportional",
)
