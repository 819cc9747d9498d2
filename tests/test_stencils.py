"""Stencils: convergence order on smooth periodic functions, symbols, and NumPy == torch application."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pimbrl.physics.stencil import Stencil
from pimbrl.systems.burgers import BURGERS_D2, BURGERS_UPWIND
from pimbrl.systems.ks import KS_D1, KS_D2, KS_D4, KS_UPWIND_BACKWARD, KS_UPWIND_FORWARD


def _f(x):
    return np.exp(np.sin(x))


def _derivatives(x):
    s, c = np.sin(x), np.cos(x)
    e = np.exp(s)
    d1 = c * e
    d2 = (c * c - s) * e
    # d/dx of (c^2 - s) e = (-2cs - c) e + (c^2 - s) c e
    d3 = (-2 * c * s - c + c**3 - s * c) * e
    # d4 = d/dx[(c^3 - 3cs - c) e]
    g = c**3 - 3 * c * s - c
    dg = -3 * c * c * s - 3 * (c * c - s * s) + s
    d4 = (dg + g * c) * e
    return {1: d1, 2: d2, 3: d3, 4: d4}


@pytest.mark.parametrize(
    ("stencil", "order", "derivative"),
    [
        (KS_D2, 6, 2),
        (KS_D4, 6, 4),
        (KS_D1, 6, 1),
        (KS_UPWIND_BACKWARD, 4, 1),
        (KS_UPWIND_FORWARD, 4, 1),
        (BURGERS_D2, 4, 2),
        (BURGERS_UPWIND, 2, 1),
    ],
)
def test_convergence_order(stencil: Stencil, order: int, derivative: int) -> None:
    errors = []
    sizes = [32, 64, 128]
    for n in sizes:
        x = 2 * np.pi * np.arange(n) / n
        dx = 2 * np.pi / n
        approx = stencil.apply(_f(x)) / dx**derivative
        errors.append(np.max(np.abs(approx - _derivatives(x)[derivative])))
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert rates[-1] == pytest.approx(order, abs=0.35), f"{stencil.name}: errors {errors}, rates {rates}"


def test_forward_upwind_is_minus_mirror_of_backward() -> None:
    # forward = -(25/12 w_j - 4 w_{j+1} + 3 w_{j+2} - 4/3 w_{j+3} + 1/4 w_{j+4})
    # (docs/environments.md, section "Kuramoto-Sivashinsky")
    for o_b, c_b in zip(KS_UPWIND_BACKWARD.offsets, KS_UPWIND_BACKWARD.coeffs):
        i = KS_UPWIND_FORWARD.offsets.index(-o_b)
        assert KS_UPWIND_FORWARD.coeffs[i] == -c_b


def test_symbol_matches_matrix_eigenvalues() -> None:
    n = 16
    mat = KS_D4.matrix(n)
    modes = np.exp(2j * np.pi * np.outer(np.arange(n), np.arange(n)) / n)  # column m is mode m
    np.testing.assert_allclose(mat @ modes, modes * KS_D4.symbol(n)[None, :], atol=1e-12)


def test_numpy_and_torch_application_agree() -> None:
    rng = np.random.default_rng(0)
    u = rng.standard_normal((3, 5, 64))
    for st in (KS_D2, KS_D4, KS_UPWIND_BACKWARD, BURGERS_UPWIND):
        out_t = st.apply(torch.tensor(u)).numpy()
        np.testing.assert_allclose(out_t, st.apply(u), atol=1e-12)
        np.testing.assert_allclose(st.matrix(64) @ u[0, 0], st.apply(u[0, 0]), atol=1e-12)


def test_invalid_stencils_are_rejected() -> None:
    with pytest.raises(ValueError, match="strictly increasing"):
        Stencil((1, 0), (1.0, 2.0))
    with pytest.raises(ValueError, match="odd number"):
        Stencil.centered((1.0, 2.0))
