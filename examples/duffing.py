"""A damped Duffing oscillator kept at its unstable equilibrium: a user's ODE system in one file.

    x'' + delta x' + alpha x + beta x^3 = a,   alpha = -1, beta = 1: a double well, x = 0 unstable.

Train it from the command line (nothing in pimbrl is edited):

    pimbrl train duffing --import examples/duffing.py --method pimbrl --steps 3000
"""

from pathlib import Path

import numpy as np

from pimbrl.systems import Coefficient, ODESystem, declare, xp_of


class Duffing(ODESystem):
    """Damped Duffing oscillator, state ``(x, v)``, one force ``a`` in ``[-2, 2]``; reward: stay at ``x = 0``."""

    name = "duffing"
    state_dim = 2
    action_low, action_high = [-2.0], [2.0]
    dt, substeps = 0.05, 2  # RK4, two solver steps per control step (0.1 time units)
    episode_steps = 200
    divergence_bound = 50.0
    coefficients = {
        "delta": Coefficient(0.3, low=0.0, high=10.0, doc="damping"),
        "alpha": Coefficient(-1.0, low=-10.0, high=10.0, doc="linear stiffness"),
        "beta": Coefficient(1.0, low=0.0, high=10.0, doc="cubic stiffness"),
    }

    def rhs(self, u, a):
        """``(v, a - delta v - alpha x - beta x^3)``: written once, for NumPy and torch alike."""
        xp = xp_of(u)  # numpy or torch
        x, v = u[..., 0], u[..., 1]
        return xp.stack([v, a[..., 0] - self.delta * v - self.alpha * x - self.beta * x**3], -1)

    def reward(self, u, a, u_next, k, path=None):
        """``-(x^2 + 0.1 v^2 + 0.01 a^2)`` after the step."""
        return -(u_next[..., 0] ** 2 + 0.1 * u_next[..., 1] ** 2 + 0.01 * a[..., 0] ** 2)

    def initial_states(self, rng, n):
        """Positions and speeds uniform in ``[-1.5, 1.5]``."""
        return rng.uniform(-1.5, 1.5, size=(n, 2))

    def admissible_box(self):
        """States the task visits: label-free states for the physics loss (the ``box`` source)."""
        return np.array([-2.5, -4.0]), np.array([2.5, 4.0])


SYSTEM = declare(
    Duffing,
    "example/Duffing-v0",
    aliases=("duffing",),
    preset=Path(__file__).with_suffix(".yaml"),  # its recipes, in duffing.yaml beside this file
    out_of_sample=lambda task, rng, n: rng.uniform(-2.5, 2.5, size=(n, 2)),
)
