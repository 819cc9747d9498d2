"""pimbrl: physics-informed model-based reinforcement learning for dynamic control.

Importing the package registers the Gymnasium environments ``pimbrl/KuramotoSivashinsky-v0``,
``pimbrl/Burgers-v0``, ``pimbrl/CartPole-v0`` and ``pimbrl/Pendulum-v0``.
"""

from .envs import ENV_IDS, register_envs

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "__version__", "register_envs"]

register_envs()
