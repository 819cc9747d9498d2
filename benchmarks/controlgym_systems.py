"""controlgym's Burgers and Allen-Cahn PDEs as pimbrl systems: someone else's simulator, our equation as the prior.

controlgym 1.0.0 (Zhang et al. 2023) pins gymnasium 0.29 and numpy<2; its PDE envs need only numpy, gymnasium
and scipy, so it is installed without its dependencies (``pip install -e ".[controlgym]"`` then
``pip install --no-deps controlgym==1.0.0``). Importing this file registers
``controlgym/Burgers-v0`` (alias ``cg-burgers``) and ``controlgym/AllenCahn-v0`` (``cg-allen-cahn``):

    pimbrl train cg-burgers --import benchmarks/controlgym_systems.py --method pimbrl

:class:`ControlGymPDE` turns a controlgym PDE env into the adapter's contract (pimbrl.systems.external) and
undoes controlgym's quirks, measured on 1.0.0:

* ``import controlgym`` runs ``controlgym/__init__.py``, which needs torch and matplotlib and sets
  ``warnings.filterwarnings("error")`` for the whole process: only ``controlgym.envs`` is loaded here, and the
  warnings filters are restored whatever happens;
* ``step`` returns the observation of the state *before* the step: the post-step state is read from the env;
* ``terminated`` (time limit) and ``truncated`` (reward out of range) are swapped: gymnasium's order is restored;
* ``reset`` takes ``state=`` instead of ``options``: ``options={"state": u}`` is mapped to it;
* every step draws its process and sensor noise with ``Generator.multivariate_normal``, which takes an SVD of
  the 256 x 256 covariance even when it is zero, as it is here: two thirds of a step's time. A zero-covariance
  draw is answered by :class:`_ZeroNoiseDraws` with the same zeros and the same draws taken from the
  generator;
* the nonlinear term, evaluated 4 times in each of a step's 50 (Burgers) or 10 (Allen-Cahn) ETDRK4 substeps,
  transforms the 256 x 8 actuator matrix anew each time: :func:`_cached_forcing_op` evaluates the same
  expressions in the same order with the transform and the forcing of the step's action computed once.

With both, states, rewards and the generator's stream are bit for bit controlgym's (checked with numpy 2.4.6),
and a step takes about a fifth of the CPU time (``benchmarks/bench_controlgym_step.py`` checks the equality and
measures the time).

The priors declare the equations controlgym integrates (its source, ``envs/burgers.py`` and
``envs/allen_cahn.py``): pseudo-spectral ETDRK4 there; here the same semi-discrete equations with
the linear part as a Fourier symbol, so the physics loss's ETDRK4 step is the simulator's scheme without its
3/2-rule dealiasing. The reward is controlgym's, ``-(sum u^2 + sum a^2)`` on the state *before* the step (an
unweighted grid sum). The full, noiseless state is observed (``n_observation=256, sensor_noise_cov=0``).
"""

from __future__ import annotations

import importlib.util
import sys
import types
import warnings
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from pimbrl.config import load_yaml
from pimbrl.systems import Coefficient, FourierOperator, PeriodicPDESystem, declare_external, xp_of

N_STATE, N_ACTION = 256, 8


def controlgym_envs() -> Any:
    """The module ``controlgym.envs``, loaded without ``controlgym/__init__.py``; the warnings filters kept."""
    saved = list(warnings.filters)
    try:
        spec = importlib.util.find_spec("controlgym")
        if spec is None or spec.submodule_search_locations is None:
            raise ImportError("controlgym is not installed: pip install --no-deps controlgym==1.0.0 (and scipy)")
        if "controlgym.envs" in sys.modules:
            return sys.modules["controlgym.envs"]
        stub = types.ModuleType("controlgym")
        stub.__path__ = list(spec.submodule_search_locations)
        sys.modules["controlgym"] = stub
        try:
            import controlgym.envs as envs
        finally:
            if sys.modules.get("controlgym") is stub:
                del sys.modules["controlgym"]
        return envs
    finally:
        warnings.filters[:] = saved


class _ZeroNoiseDraws(np.random.Generator):
    """A numpy generator whose zero-covariance Gaussian draws skip numpy's SVD of the covariance.

    ``Generator.multivariate_normal(mean, cov)`` draws ``len(mean)`` standard normals, factors ``cov`` by an SVD
    and returns ``mean + z @ (sqrt(s) * vh)``: with ``cov`` all zeros that is ``mean + 0`` whatever ``z`` is.
    Here the same ``len(mean)`` normals are drawn, so the stream goes on exactly as before, and ``mean + 0.0``
    is returned. Any other call (a ``size`` or ``method``, a nonzero or complex covariance, a complex mean) is
    numpy's own. Built on the bit generator of the env's generator, it carries that generator's stream on; a
    copy or a pickle of it is one too, on the copied bit generator. That the stream is numpy's (the normals
    drawn before the SVD, ``len(mean)`` of them) was checked with numpy 2.4.6 (tests/test_external.py).
    """

    def multivariate_normal(self, mean: Any, cov: Any, *args: Any, **kwargs: Any) -> Any:
        """numpy's draw; for a zero ``cov`` of shape ``(n, n)`` and a 1-d real ``mean`` of ``n``, without the SVD."""
        if args or kwargs or np.iscomplexobj(mean) or np.iscomplexobj(cov):
            return super().multivariate_normal(mean, cov, *args, **kwargs)
        m, c = np.asarray(mean, dtype=np.float64), np.asarray(cov)
        if m.ndim != 1 or c.shape != (m.size, m.size) or c.any():
            return super().multivariate_normal(mean, cov, *args, **kwargs)
        self.standard_normal(m.size)
        return m + 0.0

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        """A copy or a pickle is a :class:`_ZeroNoiseDraws` again (numpy's own would be a plain ``Generator``)."""
        return (type(self), (self.bit_generator,))


def make_controlgym(name: str, **kwargs: Any) -> Any:
    """controlgym's own env ``name`` as the adapter configures it (full, noiseless state), nothing changed."""
    saved = list(warnings.filters)
    try:
        return controlgym_envs().make(name, n_observation=N_STATE, sensor_noise_cov=0.0, **kwargs)
    finally:
        warnings.filters[:] = saved


def _cached_forcing_op(pde: Any) -> Any:
    """controlgym's Fourier-space nonlinear term of Burgers or Allen-Cahn, its forcing ``rfft(B) @ a`` cached.

    The expressions are controlgym 1.0.0's (``envs/burgers.py``, ``envs/allen_cahn.py``), operation for
    operation, so the result is bit for bit the same; only ``rfft(B)`` (once per step) and ``rfft(B) @ a``
    (once per action) are not recomputed on each of the step's calls.
    """
    aa_factor = 3 / 2
    n_fine, n_kept = int(pde.n_state * aa_factor), int(pde.n_state / 2) + 1
    sup_fourier = np.fft.rfft(pde.control_sup, axis=0)
    if pde.id == "burgers":
        scale: Any = -0.5j * pde.domain_wavenumbers * (1 / aa_factor)
        power = 2
    else:
        scale, power = -pde.potential_constant * (1 / aa_factor), 3
    forcing: dict[bytes, np.ndarray] = {}

    def nonlinear_op(state_fourier: np.ndarray, action: np.ndarray) -> np.ndarray:
        key = action.tobytes()
        if key not in forcing:
            forcing.clear()
            forcing[key] = sup_fourier @ action
        aa_state = aa_factor * np.fft.irfft(state_fourier, n=n_fine)
        cube_or_square = aa_state**2 if power == 2 else aa_state**3
        return scale * np.fft.rfft(cube_or_square)[0:n_kept] + forcing[key]

    return nonlinear_op


class _CachedForcingOp:
    """Stands in for a controlgym env's ``_compute_fourier_nonlinear_op``: :func:`_cached_forcing_op` of its env.

    An object, not a closure, so that a deep copy of the env gets one bound to the copy.
    """

    def __init__(self, pde: Any) -> None:
        self.pde = pde

    def __call__(self) -> Any:
        return _cached_forcing_op(self.pde)


class ControlGymPDE(gym.Env):
    """A controlgym PDE env with gymnasium's conventions and the physical state in ``info["state"]``."""

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 - Gymnasium's attribute

    def __init__(self, name: str, **kwargs: Any) -> None:
        self.pde = make_controlgym(name, **kwargs)
        self._skip_zero_noise_svd()
        self._cache_forcing()
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (self.pde.n_action,), np.float64)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.pde.n_state,), np.float32)

    def _skip_zero_noise_svd(self) -> None:
        if not isinstance(self.pde.rng, _ZeroNoiseDraws):
            self.pde.rng = _ZeroNoiseDraws(self.pde.rng.bit_generator)

    def _cache_forcing(self) -> None:
        if self.pde.id in ("burgers", "allen_cahn"):  # the instance's attribute shadows the class's method
            self.pde._compute_fourier_nonlinear_op = _CachedForcingOp(self.pde)

    def _state(self) -> np.ndarray:
        return np.array(self.pde.state, dtype=np.float64, copy=True)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """``reset(seed=s)`` draws controlgym's initial state; ``options={"state": u}`` starts from ``u``."""
        super().reset(seed=seed)
        state = None if options is None or options.get("state") is None else np.array(options["state"], dtype=np.float64)
        if seed is not None:  # controlgym's new generator, default_rng(seed), as the shortcut (its reset's draw too)
            self.pde.rng = _ZeroNoiseDraws(np.random.default_rng(seed).bit_generator)
        with np.errstate(all="ignore"):
            self.pde.reset(seed=None, state=state)  # seed=None: the generator set here is kept
        u = self._state()
        return u.astype(np.float32), {"state": u}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """One control step; the post-step state, gymnasium's flag order, a blow-up as a termination."""
        a = np.asarray(action, dtype=np.float64).reshape(self.pde.n_action)
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            _, reward, time_up, out_of_range, _ = self.pde.step(a)  # controlgym: (time limit, out of range)
        u = self._state()
        diverged = not np.all(np.isfinite(u))
        info = {"state": u, "diverged": diverged}
        return u.astype(np.float32), float(reward), bool(out_of_range or diverged), bool(time_up), info


def actuator_shapes(n: int = N_STATE, n_action: int = N_ACTION) -> np.ndarray:
    """controlgym's control matrix ``B`` transposed: actuator ``i`` is 1 on grid points ``3 + 32 i .. 27 + 32 i``."""
    shapes = np.zeros((n_action, n))
    width = n // n_action
    for i in range(n_action):
        shapes[i, 3 + width * i : 28 + width * i] = 1.0
    return shapes


class _ControlGymPrior(PeriodicPDESystem):
    """What both priors share: controlgym's grid, actuators, episode and reward."""

    n = N_STATE
    method = "rk4"
    episode_steps = 100
    divergence_bound = 20.0
    reflection_symmetric = False  # the actuators' layout is not mirror-symmetric about the domain's centre

    def wavenumbers(self, like: Any) -> Any:
        """``2 pi rfftfreq(n, dx)`` as an array of ``like``'s kind and dtype."""
        k = 2 * np.pi * np.fft.rfftfreq(self.n, self.length / self.n)
        return torch.as_tensor(k, dtype=like.dtype, device=like.device) if isinstance(like, torch.Tensor) else k

    def actuators(self) -> np.ndarray:
        """controlgym's 8 top-hat actuators."""
        return actuator_shapes(self.n)

    def reward(self, u: Any, a: Any, u_next: Any, k: Any, path: Any = None) -> Any:
        """controlgym's ``-(sum u^2 + sum a^2)`` on the state before the step."""
        return -((u * u).sum(-1) + (a * a).sum(-1))


class ControlGymBurgers(_ControlGymPrior):
    """Prior of controlgym's Burgers: ``u_t = nu u_xx - u u_x + B a``, ``nu = 1e-3``, ``L = 1``, control step 0.05."""

    name = "cg-burgers"
    length = 1.0
    dt, substeps = 1e-3, 50
    action_low, action_high = [-3.0] * N_ACTION, [3.0] * N_ACTION
    coefficients = {"nu": Coefficient(1e-3, low=0.0, high=0.1, doc="viscosity")}  # noqa: RUF012

    def linear_operator(self) -> FourierOperator:
        """``nu d^2/dx^2``: the symbol ``-nu k^2``."""
        k = 2 * np.pi * np.fft.fftfreq(self.n, self.length / self.n)
        return FourierOperator(-self.nu * k**2)

    def nonlinearity(self, u: Any) -> Any:
        """``-(u^2 / 2)_x``, spectral (NumPy or torch)."""
        xp = xp_of(u)
        return xp.fft.irfft(-0.5j * self.wavenumbers(u) * xp.fft.rfft(u * u), n=self.n)


class ControlGymAllenCahn(_ControlGymPrior):
    """Prior of controlgym's Allen-Cahn: ``u_t = eps^2 u_xx + c (u - u^3) + B a``, ``eps = 1e-4``, ``c = 5``, ``L = 2``."""

    name = "cg-allen-cahn"
    length = 2.0
    dt, substeps = 1e-3, 10
    action_low, action_high = [-5.0] * N_ACTION, [5.0] * N_ACTION
    coefficients = {  # noqa: RUF012
        "eps": Coefficient(1e-4, low=0.0, high=0.1, doc="interface width (enters squared)"),
        "c": Coefficient(5.0, low=0.0, high=50.0, doc="potential constant"),
    }

    def linear_operator(self) -> FourierOperator:
        """``eps^2 d^2/dx^2 + c``: the symbol ``c - eps^2 k^2``."""
        k = 2 * np.pi * np.fft.fftfreq(self.n, self.length / self.n)
        return FourierOperator(self.c - self.eps**2 * k**2)

    def nonlinearity(self, u: Any) -> Any:
        """``-c u^3``."""
        return -self.c * u**3


#: Burgers's recipes in controlgym_burgers.yaml beside this file; Allen-Cahn has the same default recipe, read from it, alone
BURGERS_PRESET = Path(__file__).with_name("controlgym_burgers.yaml")
PRESET: dict[str, Any] = {"recipes": {"default": load_yaml(BURGERS_PRESET.read_text())["recipes"]["default"]}}

BURGERS = declare_external(
    ControlGymBurgers, lambda: ControlGymPDE("burgers"), "controlgym/Burgers-v0", aliases=("cg-burgers",), preset=BURGERS_PRESET
)
ALLEN_CAHN = declare_external(
    ControlGymAllenCahn, lambda: ControlGymPDE("allen_cahn"), "controlgym/AllenCahn-v0", aliases=("cg-allen-cahn",), preset=PRESET
)
