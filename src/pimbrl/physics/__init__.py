"""Governing equations, discretisations, rewards and residuals: one object per system."""

from .base import Physics
from .burgers import Burgers
from .cartpole import CartPole
from .ks import KuramotoSivashinsky
from .pendulum import Pendulum, wrap_angle
from .stencil import Stencil

__all__ = ["Burgers", "CartPole", "KuramotoSivashinsky", "Pendulum", "Physics", "Stencil", "wrap_angle"]
