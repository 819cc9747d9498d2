"""Compiled (Numba) simulator kernels for periodic 1-D PDEs, generated from the stencil tables.

Both PDE systems have the form

    du/dt = L u + c * U(u^2; u) + f,

with ``L`` a linear periodic stencil (diffusion / hyper-diffusion), ``U`` an upwind difference of ``u^2``
(switched point by point on the sign of ``u``, or always backward), ``c`` a constant and ``f`` a forcing
field frozen over the control step.

The kernel has no coefficients of its own: :func:`build_pde_kernel` writes a small Python module whose
stencil sums are spelled out with the coefficients of the :class:`~pimbrl.physics.stencil.Stencil`
tables as literals, and compiles it with Numba. Literal coefficients and fixed offsets let LLVM unroll
and vectorise every stencil; a generic kernel that loops over coefficient arrays runs 3-4 times slower.
The generated source is written under the cache directory (``$PIMBRL_CACHE_DIR``, default
``~/.cache/pimbrl``) so that Numba's on-disk cache makes later imports instant. Since modules are
imported from there, a cache directory is used only if it is owned by the current user and not writable
by group or others (see :func:`_write_source`).

The kernel computes in float64, loops over the batch without Python, and integrates with explicit
Euler or classic RK4. It can also accumulate, at the start of every solver step, the spatial means of
``(A u)^2``, ``U(u^2; u)^2``, ``(C u)^2`` and ``u f`` for two extra stencils ``A`` and ``C`` (the
integrands of the Kuramoto-Sivashinsky rewards), averaged over the control step.

Memory traffic, not arithmetic, bounds these loops, so the generated code keeps it small: the state and
the RK4 stage inputs live in padded buffers (``H`` periodic ghost points each side) that each stage
writes directly, so only the ``2 H`` ghost points are refreshed between stages; every grid value a point
needs is loaded once, and the squares of the upwind sums are formed in registers rather than read from
a padded copy of ``u^2``; the reward integrands are summed in the first stage's pass; and a spec with a
fixed grid size ``n`` compiles it in as a constant. Against the previous kernel (a periodic copy of ``u``
and ``u^2`` before every stage) this made a KS control step about 2x and a Burgers step about 3x faster
(docs/benchmarks.md); results agree to round-off (not bit for bit: LLVM orders the sums differently).
"""

from __future__ import annotations

import atexit
import hashlib
import importlib.util
import os
import shutil
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import llvmlite.binding as llvm
import numpy as np
from numba import boolean, float64, int64

from ..fileio import UnsafeFileError, private_directory, read_below
from .stencil import Stencil

__all__ = ["GENERATOR_VERSION", "N_REWARD_TERMS", "PDEKernel", "PDEKernelSpec", "build_pde_kernel", "cache_dir"]

N_REWARD_TERMS = 4
#: version of the generated kernel source; a new one may change results at round-off (so it keys the caches
#: of anything simulated with the kernel, such as the KS initial-state pools)
GENERATOR_VERSION = "5"


def cache_dir() -> Path:
    """Directory for pimbrl's caches.

    ``$PIMBRL_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/pimbrl``, else ``~/.cache/pimbrl``.
    """
    env = os.environ.get("PIMBRL_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "pimbrl"


@dataclass(frozen=True)
class PDEKernelSpec:
    """Everything that defines a kernel: operators and integrator (hashable; it keys the cache)."""

    linear: Stencil
    nonlinear_coef: float
    upwind_backward: Stencil
    upwind_forward: Stencil | None  # None: always backward
    method: Literal["euler", "rk4"]
    integrand_a: Stencil | None = None
    integrand_c: Stencil | None = None
    n: int | None = None  # grid size compiled in as a constant (then the only one accepted); None: any

    @property
    def halo(self) -> int:
        """Ghost points needed on each side by the widest stencil of the kernel."""
        stencils = [self.linear, self.upwind_backward, self.upwind_forward, self.integrand_a, self.integrand_c]
        return max(s.halo for s in stencils if s is not None)


def _var(prefix: str, offset: int) -> str:
    """Name of the local holding a value at ``offset`` from the current point: ``xm2``, ``xp0``, ``wp3``."""
    return f"{prefix}{'m' if offset < 0 else 'p'}{abs(offset)}"


def _taps(stencil: Stencil | None) -> dict[int, float]:
    """The nonzero taps ``{offset: coefficient}`` of ``stencil`` (none for ``None``)."""
    if stencil is None:
        return {}
    return {o: c for o, c in zip(stencil.offsets, stencil.coeffs) if c != 0.0}


def _sum_expr(stencil: Stencil | None, prefix: str) -> str:
    """``c0*xm2 + c1*(xm1 + xp1) + ...``: the stencil sum over the locals named by :func:`_var`.

    Taps with equal coefficients at offsets ``+o`` and ``-o`` are paired, ``c*(x[+o] + x[-o])``,
    which halves the multiplications of a symmetric stencil.
    """
    taps = _taps(stencil)
    terms = []
    for o in sorted(taps, key=lambda o: (abs(o), o)):
        if o not in taps:
            continue
        c = taps.pop(o)
        if o != 0 and taps.get(-o) == c:
            taps.pop(-o)
            terms.append(f"{c!r} * ({_var(prefix, o)} + {_var(prefix, -o)})")
        else:
            terms.append(f"{c!r} * {_var(prefix, o)}")
    return "(" + " + ".join(terms) + ")" if terms else "0.0"


def _indent(lines: list[str], level: int) -> str:
    """``lines`` joined into source text, each indented by ``level`` levels."""
    return "\n".join("    " * level + line for line in lines)


def _rhs_lines(spec: PDEKernelSpec, array: str) -> list[str]:
    """Loop body computing, at point ``j``, the upwind term ``d`` and the right-hand side ``k``.

    ``array`` is a padded state (interior at ``H..H+n``). Every value the stencils need is loaded once
    into a local ``x..``; the squares ``w.. = x.. * x..`` of the upwind sums are formed in registers
    (no padded copy of ``u^2`` in memory).
    """
    h = spec.halo
    upwind = _taps(spec.upwind_backward) | _taps(spec.upwind_forward)
    offsets = sorted({0} | set(upwind) | set(_taps(spec.linear)) | set(_taps(spec.integrand_a)) | set(_taps(spec.integrand_c)))
    lines = [f"{_var('x', o)} = {array}[j + {h + o}]" for o in offsets]
    lines += [f"{_var('w', o)} = {_var('x', o)} * {_var('x', o)}" for o in sorted(upwind)]
    back = _sum_expr(spec.upwind_backward, "w")
    if spec.upwind_forward is None:
        lines.append(f"d = {back}")
    else:
        # both sides are computed, then selected: a conditional load would stop vectorisation
        lines += [f"db = {back}", f"df = {_sum_expr(spec.upwind_forward, 'w')}", "d = db if xp0 >= 0.0 else df"]
    lines.append(f"k = {_sum_expr(spec.linear, 'x')} + {float(spec.nonlinear_coef)!r} * d + f[j]")
    return lines


def _accumulate_lines(spec: PDEKernelSpec) -> list[str]:
    """Loop body adding the reward integrands of the current state at point ``j`` (after :func:`_rhs_lines`)."""
    return [
        f"av = {_sum_expr(spec.integrand_a, 'x')}",
        f"cv = {_sum_expr(spec.integrand_c, 'x')}",
        "s_a += av * av",
        "s_n += d * d",
        "s_c += cv * cv",
        "s_f += xp0 * f[j]",
    ]


def _stage(spec: PDEKernelSpec, array: str, tail: list[str], accumulate: bool = False) -> list[str]:
    """One pass over the grid: the right-hand side of padded ``array``, then the ``tail`` updates."""
    body = _rhs_lines(spec, array) + (_accumulate_lines(spec) if accumulate else []) + tail
    return ["for j in range(n):"] + ["    " + line for line in body]


def _first_stage(spec: PDEKernelSpec, tail: list[str]) -> list[str]:
    """The stage from the step's start state ``p0``, with or without the reward integrands."""
    return (
        ["if accumulate:"]
        + ["    " + line for line in _stage(spec, "p0", tail, accumulate=True)]
        + ["else:"]
        + ["    " + line for line in _stage(spec, "p0", tail)]
    )


#: RK4 stages after the first: (padded input, what is done with its slope ``k``, padded output). Each
#: stage writes the next stage's input straight into a padded buffer; the last one updates ``p0``.
_RK4_STAGES = (
    ("p1", ["k2[j] = k", "p2[H + j] = p0[H + j] + half * k"], "p2"),
    ("p2", ["k3[j] = k", "p1[H + j] = p0[H + j] + dt * k"], "p1"),
    ("p1", ["p0[H + j] = p0[H + j] + sixth * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k)"], "p0"),
)


def _rk4_lines(spec: PDEKernelSpec) -> list[str]:
    """One classic RK4 step of the padded state ``p0`` (stage inputs in ``p1``/``p2``, slopes in ``k1..k3``)."""
    lines = [*_first_stage(spec, ["k1[j] = k", "p1[H + j] = xp0 + half * k"]), "_ghosts(p1, n)"]
    for source, tail, target in _RK4_STAGES:
        lines += [*_stage(spec, source, tail), f"_ghosts({target}, n)"]
    return lines


def _euler_lines(spec: PDEKernelSpec) -> list[str]:
    """One explicit Euler step of ``p0`` into ``p1``, then the two buffers swap."""
    return [*_first_stage(spec, ["p1[H + j] = xp0 + dt * k"]), "_ghosts(p1, n)", "p0, p1 = p1, p0"]


_TEMPLATE = """\
# Generated by pimbrl.physics.kernels (generator version {version}); do not edit.
import numpy as np
from numba import njit

_FM = {{"reassoc", "contract", "nsz", "arcp"}}
H = {halo}


@njit(inline="always", fastmath=_FM)
def _ghosts(p, n):
    # periodic ghost points (H each side) of a padded array whose interior p[H:H+n] is up to date
    for j in range(H):
        p[j] = p[n + j]
        p[H + n + j] = p[H + j]


@njit(cache=True, fastmath=_FM, error_model="numpy")
def advance(u0, actions, shapes, dt, nsub, accumulate, weights):
{grid}
    out = np.empty((bsz, n))
    terms = np.zeros((bsz, 4))
    reward = np.zeros(bsz)
    f = np.empty(n)
    # padded states: p0 the solver state, p1 and p2 the stage inputs; k1..k3 the RK4 slopes
    p0 = np.empty(n + 2 * H)
    p1 = np.empty(n + 2 * H)
    p2 = np.empty(n + 2 * H)
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    half = 0.5 * dt
    sixth = dt / 6.0
    for b in range(bsz):
        # forcing f = sum_i a_i g_i, frozen over the control step
        for j in range(n):
            f[j] = actions[b, 0] * shapes[0, j]
        for i in range(1, shapes.shape[0]):
            for j in range(n):
                f[j] += actions[b, i] * shapes[i, j]
        for j in range(n):
            p0[H + j] = u0[b, j]
        _ghosts(p0, n)
        s_a = 0.0
        s_n = 0.0
        s_c = 0.0
        s_f = 0.0
        for _ in range(nsub):
{stepper}
        for j in range(n):
            out[b, j] = p0[H + j]
        if accumulate:
            norm = 1.0 / (nsub * n)
            terms[b, 0] = s_a * norm
            terms[b, 1] = s_n * norm
            terms[b, 2] = s_c * norm
            terms[b, 3] = s_f * norm
            reward[b] = -(
                terms[b, 0] * weights[0] + terms[b, 1] * weights[1] + terms[b, 2] * weights[2] + terms[b, 3] * weights[3]
            )
    return out, terms, reward
"""


def generate_source(spec: PDEKernelSpec) -> str:
    """The Python/Numba source of the kernel for ``spec``."""
    stepper = _rk4_lines(spec) if spec.method == "rk4" else _euler_lines(spec)
    return _TEMPLATE.format(
        version=GENERATOR_VERSION, halo=spec.halo, grid=_indent(_grid_lines(spec), 1), stepper=_indent(stepper, 3)
    )


def _grid_lines(spec: PDEKernelSpec) -> list[str]:
    """Batch size ``bsz`` and grid size ``n``; ``n`` is a literal when the spec fixes it.

    A constant grid size lets LLVM lay out the vector loops and their remainders at compile time
    (measured: Burgers, n = 150, about 1.4x faster; KS, n = 64, about 1.1x).
    """
    if spec.n is None:
        return ["bsz, n = u0.shape"]
    return [
        "bsz = u0.shape[0]",
        f"if u0.shape[1] != {spec.n}:",
        f'    raise ValueError("this kernel was compiled for grid size {spec.n}")',
        f"n = {spec.n}",
    ]


#: A compiled kernel: ``advance(u0, actions, shapes, dt, nsub, accumulate, weights) -> (u_next, terms, reward)``.
PDEKernel = Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]]

_LOADED: dict[str, PDEKernel] = {}


def build_pde_kernel(spec: PDEKernelSpec) -> PDEKernel:
    """Compile (or load from cache) the kernel for ``spec``.

    The returned function has the signature ``advance(u0, actions, shapes, dt, nsub, accumulate, weights)``
    with C-contiguous float64 arrays ``u0`` ``(B, n)``, ``actions`` ``(B, m)`` and actuator ``shapes``
    ``(m, n)`` (the forcing is ``actions @ shapes``, summed actuator by actuator) and reward ``weights``
    ``(4,)``; it returns ``(u_next, terms, reward)`` with the step-averaged integrands ``terms``
    ``(B, 4)`` and ``reward = -terms @ weights`` ``(B,)`` (both zeros unless ``accumulate``).
    """
    source = generate_source(spec)
    key = hashlib.sha256(source.encode()).hexdigest()[:16]
    if key in _LOADED:
        return _LOADED[key]
    path = _write_source(f"pimbrl_pde_{key}.py", source)
    module_name = f"_pimbrl_generated_{key}"
    module_spec = importlib.util.spec_from_file_location(module_name, path)
    assert module_spec is not None
    assert module_spec.loader is not None
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[module_name] = module
    module_spec.loader.exec_module(module)
    kernel = module.advance
    with _wide_vectors():
        kernel.compile((float64[:, ::1], float64[:, ::1], float64[:, ::1], float64, int64, boolean, float64[::1]))
    _LOADED[key] = kernel
    return kernel


@contextmanager
def _wide_vectors() -> Iterator[None]:
    """Let LLVM vectorise 8 doubles wide while the kernel compiles, on CPUs with AVX-512.

    LLVM prefers 256-bit vectors on these CPUs; for these short, unrolled stencil loops 512-bit vectors
    make the KS step about 1.4x faster (measured). The option is global to LLVM, so it is set only
    around this compilation and reset afterwards.
    """
    if "+avx512f" not in llvm.get_host_cpu_features().flatten():
        yield
        return
    llvm.set_option("", "-force-vector-width=8")
    try:
        yield
    finally:
        llvm.set_option("", "-force-vector-width=0")


def _write_source(filename: str, source: str) -> Path:
    """Write ``source`` once into the kernel cache (atomically) and return its path.

    The cache is ``cache_dir()/kernels``, else (not creatable) the per-user ``pimbrl-kernels-<uid>``
    under the system temp directory; each is used only if it is a directory owned by this user and not
    writable by group or others (:func:`_private_dir`), since its modules are imported. Where neither is,
    a fresh private temp directory of this process is used (nothing is cached across processes).
    """
    candidates = [cache_dir() / "kernels", Path(tempfile.gettempdir()) / f"pimbrl-kernels-{_uid()}"]
    for directory in candidates:
        try:
            if not _private_dir(directory):
                continue
            return _write_once(directory / filename, source)
        except OSError:
            continue
    global _PROCESS_DIR
    if _PROCESS_DIR is None:
        _PROCESS_DIR = Path(tempfile.mkdtemp(prefix="pimbrl-kernels-"))  # mode 0700, ours
        atexit.register(shutil.rmtree, _PROCESS_DIR, True)
    return _write_once(_PROCESS_DIR / filename, source)


_PROCESS_DIR: Path | None = None


def _uid() -> int:
    return getattr(os, "getuid", lambda: 0)()


def _private_dir(directory: Path) -> bool:
    """Create ``directory`` (mode 0700) if missing; whether it is safe to import modules from.

    :func:`~pimbrl.fileio.private_directory`: a real directory owned by this user, not writable by group or
    others; an unsafe one is refused with a warning (another user could plant code there).
    """
    return private_directory(directory, "compiled kernels")


def _write_once(path: Path, source: str) -> Path:
    """``path`` holding ``source``: kept if it already does, else (re)written atomically.

    An entry that is not a regular file of this user's with one name (a symbolic link, a FIFO, a file with
    other hard links, another user's file) is never read or followed: it is replaced, with a warning.
    """
    if _cached_source(path) != source:
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "w") as fh:
            fh.write(source)
        os.replace(tmp, path)  # replaces a link itself, never its target
    return path


def _cached_source(path: Path) -> str | None:
    """The text of the kernel cache entry ``path``, or ``None`` where it is missing or not to be trusted."""
    try:
        data = read_below(path.parent, path.name, _MAX_KERNEL_SOURCE, single_link=True, own=True)
    except FileNotFoundError:
        return None
    except UnsafeFileError as exc:
        warnings.warn(f"pimbrl kernel cache: {exc}; the entry is replaced", stacklevel=4)
        return None
    return data.decode("utf-8", errors="replace")


#: a generated kernel module is a few tens of kB; a larger cache entry is not one
_MAX_KERNEL_SOURCE = 4 << 20
