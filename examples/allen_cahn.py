"""Allen-Cahn on a periodic line, held at its unstable uniform state u = 0: a user's PDE in one file.

    u_t = eps u_xx + u - u^3 + sum_i a_i g_i(x),   x in [0, 2 pi), four Gaussian actuators.

Train it from the command line (nothing in pimbrl is edited):

    pimbrl train allen-cahn --import examples/allen_cahn.py --method pimbrl --steps 3000
"""

from pathlib import Path

import numpy as np

from pimbrl.physics import Stencil
from pimbrl.systems import Coefficient, PeriodicPDESystem, declare, gaussian_actuators

#: 2nd-order central second difference (raw: divide by dx^2)
D2 = Stencil.centered((1.0, -2.0, 1.0), "D2")


class AllenCahn(PeriodicPDESystem):
    """Allen-Cahn with 64 grid points and 4 actuators in ``[-1, 1]``; reward: stay near ``u = 0``."""

    name = "allen-cahn"
    n, length = 64, 2 * np.pi
    dt, substeps, method = 0.02, 5, "rk4"  # a control step is 0.1 time units
    action_low, action_high = [-1.0] * 4, [1.0] * 4
    episode_steps = 100
    divergence_bound = 10.0
    reflection_symmetric = True  # u(x) -> -u(-x) maps solutions to solutions (odd reaction, even diffusion)
    coefficients = {
        "eps": Coefficient(0.05, low=1e-4, high=1.0, doc="diffusion"),
        "growth": Coefficient(1.0, low=0.0, high=10.0, doc="linear growth rate of u = 0"),
        "width": Coefficient(0.4, low=0.05, high=3.0, doc="actuator half-width"),
    }

    def linear_operator(self):
        """``eps u_xx + growth u``: a stencil (already divided by dx^2)."""
        return D2.scaled(self.eps / self.dx**2) + Stencil((0,), (self.growth,), "growth")

    def nonlinearity(self, u):
        """``-u^3`` (NumPy or torch)."""
        return -(u**3)

    def actuators(self):
        """Four periodic Gaussians, evenly spaced."""
        return gaussian_actuators(self.x, np.arange(4) * self.length / 4 + self.length / 8, self.width, self.length)

    def reward(self, u, a, u_next, k, path=None):
        """``-mean(u^2)`` after the step, minus a small actuation cost."""
        return -(u_next**2).mean(-1) - 0.01 * (a**2).mean(-1)

    def initial_states(self, rng, n):
        """Smooth random fields: Fourier modes 1-3 with amplitudes ~ N(0, 0.3^2 / m)."""
        m = np.arange(1, 4)
        amp = rng.normal(0.0, 0.3 / np.sqrt(m), size=(n, 2, 3))
        phase = m[None, :, None] * self.x[None, None, :]
        return (amp[:, 0, :, None] * np.cos(phase) + amp[:, 1, :, None] * np.sin(phase)).sum(1)


SYSTEM = declare(
    AllenCahn,
    "example/AllenCahn-v0",
    aliases=("allen-cahn",),
    preset=Path(__file__).with_suffix(".yaml"),  # its recipes, in allen_cahn.yaml beside this file
    out_of_sample=lambda task, rng, n: 3.0 * task.sample_initial_states(rng, n),
)
