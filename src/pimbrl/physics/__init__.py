"""What is derived from any equation: the :class:`Physics` interface, stencils, integrators, kernels.

The systems themselves (Cart-Pole, Pendulum, Burgers, Kuramoto-Sivashinsky, a user's own) are declared in
:mod:`pimbrl.systems`, one module each.
"""

from .base import Physics
from .stencil import Stencil

__all__ = ["Physics", "Stencil"]
