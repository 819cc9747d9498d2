"""Periodic semilinear PDEs ``du/dt = L u + N(u) + f`` and their coarse exponential integrator.

Both PDE systems share this structure: ``L`` is a linear periodic stencil (diffusion, hyper-diffusion),
``N(u) = c * U(u^2; u)`` an upwind difference of ``u^2``, and ``f = sum_i a_i g_i(x)`` the actuator forcing,
frozen over a control step. :class:`SemilinearPDE` writes the right-hand side, the solver step and the
compiled simulator once for both; the subclasses only give their stencil tables.

:class:`ETDRK4` integrates the same semi-discrete equations with steps much coarser than the solver's:
the circulant linear stencil is treated exactly through its own Fourier symbol (the eigenvalues of the
discrete operator, not of the continuous derivative), the nonlinear term and the forcing explicitly, with
the fourth-order exponential Runge-Kutta scheme of Cox & Matthews (2002). Its phi-function coefficients
are evaluated by contour integrals (Kassam & Trefethen 2005), which avoids the cancellation of the
direct formulas for small ``h lambda``. The KS RK4 solver is unstable beyond dt ~ 0.002 (largest
eigenvalue ~ 1396); the exponential step is stable at any step size, so a transition model can emit
a handful of intermediate states per control step and still be checked against the equation.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable, Mapping
from typing import Any, Literal

import numpy as np
import torch

from .base import Array, Physics, superpose
from .kernels import PDEKernel, PDEKernelSpec, build_pde_kernel
from .stencil import Stencil

__all__ = ["ETDRK4", "SemilinearPDE"]


class SemilinearPDE(Physics):
    """Base class of the periodic PDE systems.

    Subclasses set, in ``__init__``: :attr:`n`, :attr:`x`, :attr:`dx`,
    :attr:`linear`, :attr:`nonlinear_coef`, :attr:`actuator_shapes`, :attr:`method` and the
    :class:`Physics` attributes, and implement :meth:`upwind` and :meth:`kernel_spec`.
    """

    n: int
    x: np.ndarray
    dx: float
    linear: Stencil
    # u_t = L u - c (u^2)_x + f on a periodic grid: a circular shift maps solutions to solutions, and so does
    # u(x) -> -u(-x) (L holds even derivatives only); KS's discrete scheme keeps the reflection exactly (tested),
    # Burgers' upwinding only approximately. Either way a shifted or reflected state is just another state on
    # which the residual (exact for any state) can be evaluated: the symmetries make plausible states.
    is_field = True
    shift_symmetric = True
    reflection_symmetric = True
    nonlinear_coef: float
    actuator_shapes: np.ndarray
    method: Literal["euler", "rk4"]
    _kernel: PDEKernel | None = None

    # ------------------------------------------------------------------ coefficients
    @abstractmethod
    def operators(self, values: Mapping[str, Any]) -> tuple[Any, Any, Any]:
        """The equation's parts as functions of its physical coefficients, for coefficients being learned.

        ``values`` maps some of :attr:`coefficients` to floats or torch tensors (the others keep this object's
        values). Returns ``(lam, nonlinear_coef, actuator_shapes)``: the eigenvalues of ``L`` on the
        ``n // 2 + 1`` rfft modes (real; complex where a ``drift`` term makes ``L`` non-symmetric), the
        coefficient of the upwind term and the ``(action_dim, n)`` actuator shapes; torch tensors,
        differentiable in the tensor values, where any value is a tensor. At this object's own coefficients
        they equal :attr:`linear`'s symbol, :attr:`nonlinear_coef` and :attr:`actuator_shapes` to round-off
        (tested).
        """

    def _coefficient(self, values: Mapping[str, Any], name: str) -> Any:
        return values.get(name, getattr(self, name))

    #: the first difference of the ``drift`` term (raw: divide by dx); subclasses set it
    drift_stencil: Stencil
    damping: float
    drift: float

    def _symbol(self, stencil: Stencil, order: int, values: Mapping[str, Any], real: bool = True) -> Any:
        """Eigenvalues of ``stencil / dx^order`` on the rfft modes (torch where any of ``values`` is a tensor)."""
        symbol = stencil.symbol(self.n)[: self.n // 2 + 1]
        symbol = (symbol.real if real else symbol) / self.dx**order
        if any(isinstance(v, torch.Tensor) for v in values.values()):
            return torch.as_tensor(symbol, dtype=torch.float64 if real else torch.complex128)
        return symbol

    def _with_added_terms(self, linear: Stencil) -> Stencil:
        """``linear`` plus the terms a prior may lack: ``-mu u`` (damping) and ``-c D1 u / dx`` (drift)."""
        if self.damping != 0.0:
            linear = linear + Stencil((0,), (-self.damping,), "-mu")
        if self.drift != 0.0:
            linear = linear + self.drift_stencil.scaled(-self.drift / self.dx, "-c*D1/dx")
        return linear

    def _added_eigenvalues(self, lam: Any, values: Mapping[str, Any]) -> Any:
        """``lam`` with the damping and the drift terms of :meth:`_with_added_terms` (for :meth:`operators`)."""
        lam = lam - self._coefficient(values, "damping")
        drift = self._coefficient(values, "drift")
        if isinstance(drift, torch.Tensor) or drift != 0.0:  # complex eigenvalues only where there is a drift
            lam = lam - drift * self._symbol(self.drift_stencil, 1, values, real=False)
        return lam

    def check_stability(self) -> None:
        """Refuse coefficients for which the explicit solver step amplifies a mode of the linear part.

        The amplification factor of one step, ``R(dt lambda)`` (explicit Euler ``1 + z``, classic RK4 its
        4th-order Taylor polynomial), must not exceed ``max(1, |exp(z)|)`` (the exact factor, for modes the
        equation itself amplifies, like KS's longest waves) by more than 1e-6 on any Fourier mode.
        """
        z = self.dt * self.linear.symbol(self.n)
        factor = 1 + z if self.method == "euler" else 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24
        excess = np.abs(factor) / np.maximum(1.0, np.abs(np.exp(z)))
        worst = float(np.max(excess))
        if not worst <= 1 + 1e-6:  # (also catches NaN)
            raise ValueError(
                f"{self.name}: with these coefficients the {self.method} solver step is unstable (it amplifies "
                f"a mode {worst:.3g} times more than the equation, per step); give a smaller dt (and more substeps)"
            )

    # ------------------------------------------------------------------ equation
    def forcing(self, a: Array) -> Array:
        """Forcing field ``f = sum_i a_i g_i(x)`` of shape ``(..., n)`` from actions ``(..., action_dim)``."""
        return superpose(a, self.actuator_shapes)

    @abstractmethod
    def upwind(self, u: Array) -> Array:
        """Raw upwind difference of ``u^2`` (not divided by the grid spacing)."""

    def nonlinear(self, u: Array, f: Array) -> Array:
        """``N(u) + f = nonlinear_coef * U(u^2; u) + f``: everything but the linear stencil."""
        return self.nonlinear_coef * self.upwind(u) + f

    def rhs_forced(self, u: Array, f: Array) -> Array:
        """``du/dt`` for a given forcing field ``f`` (broadcast against ``u``)."""
        return self.linear.apply(u) + self.nonlinear(u, f)

    def rhs(self, u: Array, a: Array) -> Array:
        """``L u + N(u) + f`` with the forcing built from the actions ``a``."""
        return self.rhs_forced(u, self.forcing(a))

    def substep_forced(self, u: Array, f: Array) -> Array:
        """One solver step of length dt (classic RK4 or explicit Euler) with forcing field ``f``."""
        dt = self.dt
        if self.method == "euler":
            return u + dt * self.rhs_forced(u, f)
        k1 = self.rhs_forced(u, f)
        k2 = self.rhs_forced(u + 0.5 * dt * k1, f)
        k3 = self.rhs_forced(u + 0.5 * dt * k2, f)
        k4 = self.rhs_forced(u + dt * k3, f)
        return u + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

    def substep(self, u: Array, a: Array) -> Array:
        """One solver step with the forcing of ``a`` held fixed."""
        return self.substep_forced(u, self.forcing(a))

    def step(self, u: Array, a: Array, substeps: int | None = None) -> Array:
        """Like :meth:`Physics.step`, but builds the forcing field once for all the solver steps."""
        f = self.forcing(a)
        for _ in range(self.substeps if substeps is None else substeps):
            u = self.substep_forced(u, f)
        return u

    def etdrk4(self, steps_per_control: int) -> ETDRK4:
        """The coarse exponential integrator with ``steps_per_control`` steps per control step."""
        if steps_per_control < 1:
            raise ValueError(f"steps_per_control must be >= 1, got {steps_per_control}")
        linear = self.linear if isinstance(self.linear, Stencil) else self.linear.symbol(self.n)[: self.n // 2 + 1]
        return ETDRK4(linear, self.n, self.control_dt / steps_per_control)

    # ------------------------------------------------------------------ fast simulator
    @abstractmethod
    def kernel_spec(self) -> PDEKernelSpec:
        """Operators and integrator of the compiled kernel (exactly this object's stencils)."""

    def run_kernel(
        self, u: np.ndarray, a: np.ndarray, accumulate: bool, weights: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One control step of the compiled kernel for a batch: ``(u_next, terms, reward)``."""
        if self._kernel is None:
            self.check_stability()
            self._kernel = build_pde_kernel(self.kernel_spec())
        u = np.ascontiguousarray(u, dtype=np.float64)
        a = np.ascontiguousarray(a, dtype=np.float64)
        return self._kernel(u, a, self.actuator_shapes, self.dt, self.substeps, accumulate, weights)


def etd_coefficients(lam: Any, h: float, contour_points: int = 32) -> dict[str, Any]:
    """ETDRK4 coefficients ``E, E2, Q, f1, f2, f3`` of the linear eigenvalues ``lam`` and step ``h``.

    NumPy arrays in, complex NumPy arrays out; a torch tensor in (e.g. eigenvalues that depend on trainable
    coefficients), complex128 tensors out, differentiable in ``lam``. The phi-functions are contour means
    (Kassam & Trefethen 2005), free of the cancellation of the direct formulas for small ``h lam``: over the
    upper half circle for real eigenvalues (the real part of that mean is the whole circle's), over the whole
    circle for complex ones (a drift term).
    """
    # (a symmetric stencil's symbol is real up to round-off)
    complex_lam = lam.is_complex() if isinstance(lam, torch.Tensor) else not np.allclose(np.imag(lam), 0.0)
    if complex_lam:  # the whole circle around each h lam (twice the points)
        r = np.exp(2j * np.pi * (np.arange(1, 2 * contour_points + 1) - 0.5) / (2 * contour_points))
    else:  # real h lam: the upper half circle, whose mean has the whole circle's real part
        r = np.exp(1j * np.pi * (np.arange(1, contour_points + 1) - 0.5) / contour_points)
    if isinstance(lam, torch.Tensor):
        xp: Any = torch
        lr = h * lam.to(torch.complex128)[:, None] + torch.as_tensor(r, device=lam.device)[None, :]
        hl = h * lam.to(torch.complex128)
    else:
        xp = np
        lr = h * lam[:, None] + r[None, :]
        hl = h * lam
    ex = xp.exp(lr)
    return {
        "E": xp.exp(hl),
        "E2": xp.exp(hl / 2),
        "Q": h * ((xp.exp(lr / 2) - 1) / lr).mean(1),
        "f1": h * ((-4 - lr + ex * (4 - 3 * lr + lr**2)) / lr**3).mean(1),
        "f2": h * ((2 + lr + ex * (-2 + lr)) / lr**3).mean(1),
        "f3": h * ((-4 - 3 * lr - lr**2 + ex * (4 - lr)) / lr**3).mean(1),
    }


class ETDRK4:
    """Fourth-order exponential time differencing for ``du/dt = L u + M(u)`` with a circulant ``L``.

    Args:
        linear: the periodic linear stencil ``L`` (its Fourier symbol gives the exact eigenvalues), or the
            eigenvalues of ``L`` (real, or complex for a non-symmetric stencil) on the ``n // 2 + 1`` rfft
            modes directly: a NumPy array, or a torch tensor (then the step is differentiable in them, for
            coefficients that are being learned).
        n: number of grid points.
        h: step size.
        contour_points: points of the contour integrals for the phi-functions.
    """

    def __init__(self, linear: Stencil | np.ndarray | torch.Tensor, n: int, h: float, contour_points: int = 32) -> None:
        if h <= 0:
            raise ValueError(f"step size must be > 0, got {h}")
        self.n = int(n)
        self.h = float(h)
        self._cache: dict[tuple[torch.dtype, torch.device], dict[str, torch.Tensor]] = {}
        if isinstance(linear, torch.Tensor):
            coeffs = etd_coefficients(linear, self.h, contour_points)
            self._real = not linear.is_complex()  # real eigenvalues: symmetric stencils
            self._coeffs: dict[str, Any] = {k: v.real for k, v in coeffs.items()} if self._real else coeffs
            self._differentiable = True
            return
        self._differentiable = False
        lam = linear.symbol(self.n)[: self.n // 2 + 1] if isinstance(linear, Stencil) else np.asarray(linear)
        self._coeffs = etd_coefficients(lam, self.h, contour_points)
        self._real = bool(np.allclose(np.imag(lam), 0.0))  # symmetric stencils: real coefficients
        if self._real:
            self._coeffs = {k: v.real.copy() for k, v in self._coeffs.items()}

    def _torch_coeffs(self, u: torch.Tensor) -> dict[str, torch.Tensor]:
        if self._differentiable:
            dtype = u.dtype if self._real else (torch.complex128 if u.dtype == torch.float64 else torch.complex64)
            return {k: v.to(device=u.device, dtype=dtype) for k, v in self._coeffs.items()}
        key = (u.dtype, u.device)
        if key not in self._cache:
            dtype = u.dtype if self._real else (torch.complex128 if u.dtype == torch.float64 else torch.complex64)
            self._cache[key] = {k: torch.as_tensor(v).to(device=u.device, dtype=dtype) for k, v in self._coeffs.items()}
        return self._cache[key]

    def step(self, u: torch.Tensor, nonlinear: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
        """One step of size ``h`` from ``u`` (``(..., n)``, differentiable); ``nonlinear(v)`` is ``M(v)``."""
        c = self._torch_coeffs(u)
        fft = torch.fft.rfft

        def ifft(v: torch.Tensor) -> torch.Tensor:
            return torch.fft.irfft(v, n=self.n)

        uh = fft(u)
        nu = fft(nonlinear(u))
        a = c["E2"] * uh + c["Q"] * nu
        na = fft(nonlinear(ifft(a)))
        b = c["E2"] * uh + c["Q"] * na
        nb = fft(nonlinear(ifft(b)))
        cc = c["E2"] * a + c["Q"] * (2.0 * nb - nu)
        nc = fft(nonlinear(ifft(cc)))
        return ifft(c["E"] * uh + c["f1"] * nu + 2.0 * c["f2"] * (na + nb) + c["f3"] * nc)
