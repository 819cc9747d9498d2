"""Kuramoto-Sivashinsky equation with four Gaussian actuators (Liu & Wang 2021, section 3.3).

    u_t + u_xx + u_xxxx + u u_x = f(x, t),   x in [0, L) periodic,

discretised exactly as the authors' code computes it (docs/environments.md, section "Kuramoto-Sivashinsky"):

    du/dt = -D4 u / dx^4 - D2 u / dx^2 - Dup(u^2; u) / (2 dx) + f

with 6th-order central D2, D4, a sign-switched 4th-order one-sided upwind difference ``Dup`` of
``w = u^2``, and classic RK4 (dt = 0.001, 250 steps per control step, forcing frozen).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
import torch

from .base import Array, check_coefficient, records_arguments, xp_of
from .kernels import PDEKernel, PDEKernelSpec
from .pde import SemilinearPDE
from .stencil import Stencil, apply_upwind

__all__ = ["KS_D1", "KS_D2", "KS_D4", "KS_UPWIND_BACKWARD", "KS_UPWIND_FORWARD", "KuramotoSivashinsky"]

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
        hyper_diffusion = check_coefficient(self.name, "hyper_diffusion", hyper_diffusion, positive=True)
        actuator_width = check_coefficient(self.name, "actuator_width", actuator_width, positive=True)
        for name, value in (
            ("anti_diffusion", anti_diffusion),
            ("convection", convection),
            ("damping", damping),
            ("drift", drift),
        ):
            check_coefficient(self.name, name, value)
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
