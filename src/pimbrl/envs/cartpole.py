"""Cart-Pole balancing (Gymnasium's CartPole dynamics, the paper's CartPole-v0 settings)."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from ..physics import CartPole
from .base import PhysicsEnv, PhysicsVectorEnv
from .render import BLACK, BROWN, GREY, Canvas
from .task import Task

__all__ = ["CartPoleEnv", "CartPoleTask", "CartPoleVectorEnv"]


class CartPoleTask(Task):
    """Cart-Pole task: Discrete(2) actions (0: push left, 1: push right), 200 control steps.

    Args:
        **coefficients: physical coefficients of :class:`pimbrl.physics.CartPole` that differ from Gymnasium's
            (``gravity`` = 9.8, ``masscart`` = 1, ``masspole`` = 0.1, ``length`` = 0.5 (half the pole),
            ``cart_friction`` = 0, ``pole_friction`` = 0), e.g. ``masspole=0.15`` or ``pole_friction=0.002``:
            a system whose physics a prior may get wrong.
    """

    max_episode_steps = 200
    render_fps = 50  # a control step is 0.02 time units
    physics: CartPole

    def __init__(self, **coefficients: float) -> None:
        self.physics = CartPole().with_coefficients(**coefficients)
        p = self.physics
        high = np.array([p.x_threshold * 2, np.inf, p.theta_threshold_radians * 2, np.inf], dtype=np.float32)
        self.observation_space = spaces.Box(-high, high, dtype=np.float32)
        self.action_space = spaces.Discrete(2)

    def sample_initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """All four state variables uniform in ``[-0.05, 0.05]``, as in Gymnasium."""
        return rng.uniform(low=-0.05, high=0.05, size=(n, 4))

    def observe(self, u: np.ndarray, k: np.ndarray) -> np.ndarray:
        """The state itself, as float32."""
        return u.astype(np.float32)

    def physical_action(self, actions: Any, batch: int) -> np.ndarray:
        """Check that the actions are 0 or 1 and map them to forces ``-force_mag`` / ``+force_mag``."""
        arr = np.asarray(actions)
        if arr.ndim == 0 and batch == 1:
            arr = arr[None]
        if arr.shape != (batch,):
            what = "one discrete action" if batch == 1 else f"{batch} discrete actions"
            raise ValueError(f"Cart-Pole expects {what} in {{0, 1}}, got shape {arr.shape}")
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise ValueError("action contains NaN or inf; Cart-Pole expects integers 0 (left) or 1 (right)")
        if not np.all((arr == 0) | (arr == 1)):
            raise ValueError(f"Cart-Pole actions must be 0 (push left) or 1 (push right), got {arr.tolist()}")
        return np.where(arr == 1, self.physics.force_mag, -self.physics.force_mag)[:, None].astype(np.float64)

    def render(self, u: np.ndarray, k: int) -> np.ndarray:
        """A 300 x 600 sketch, as Gymnasium's: the track spans ``|x| <= 2.4``, cart (black) and pole (brown)."""
        height, width = 300, 600
        canvas = Canvas(height, width)
        p = self.physics
        scale = width / (2 * p.x_threshold)
        track_y = 0.7 * height
        canvas.segment((0, track_y), (width, track_y), GREY, 1.0)
        x, theta = float(u[0]), float(u[2])
        cart_x = width / 2 + x * scale
        canvas.rectangle(cart_x - 25, track_y - 15, cart_x + 25, track_y + 15, BLACK)
        pole = 2 * p.length * scale
        pivot = (cart_x, track_y - 10)
        canvas.segment(pivot, (pivot[0] + pole * np.sin(theta), pivot[1] - pole * np.cos(theta)), BROWN, 10.0)
        return canvas.image


_DOC = """Cart-Pole balancing (Barto, Sutton & Anderson 1983; the paper's CartPole-v0 settings).

    ## Description
    A pole is hinged on a cart that moves on a track (frictionless unless asked otherwise); pushing the
    cart left or right keeps the pole upright.

    ## Governing equation
    Gymnasium's cart-pole equations (g = 9.8, cart mass 1.0, pole mass 0.1, half-length 0.5):
    ``temp = (F + m_p l theta_dot^2 sin theta) / (m_c + m_p)``,
    ``theta_acc = (g sin theta - cos theta temp) / (l (4/3 - m_p cos^2 theta / (m_c + m_p)))``,
    ``x_acc = temp - m_p l theta_acc cos theta / (m_c + m_p)``. (The paper's equation (3.1) has typos.)
    With ``cart_friction = mu_c`` and ``pole_friction = mu_p`` (both 0 by default), Barto, Sutton &
    Anderson's (1983) frictional form: ``- mu_c sgn(x_dot)`` is added to the numerator of ``temp`` and
    ``- mu_p theta_dot / (m_p l)`` to that of ``theta_acc`` (see :mod:`pimbrl.physics.cartpole`).

    ## Discretisation
    Explicit Euler, ``tau = 0.02``, in Gymnasium's operation order: with the default coefficients,
    trajectories equal Gymnasium's ``CartPole`` bit for bit from the same state and actions.

    ## Action Space
    ``Discrete(2)``: 0 pushes the cart left (force -10), 1 pushes it right (+10).

    ## Observation Space
    ``Box(4,)``: ``(x, x_dot, theta, theta_dot)``, bounds as Gymnasium's.

    ## Rewards
    +1 for every step, the terminating one included.

    ## Starting State
    All four state variables ``~ U(-0.05, 0.05)``; ``reset(options={"initial_state": s})`` with
    ``s = (x, x_dot, theta, theta_dot)``.

    ## Episode End
    Termination when ``|x| > 2.4`` or ``|theta| > 12 degrees``; truncation after 200 steps.

    ## Rendering
    ``render_mode="rgb_array"``: a 300 x 600 sketch of cart and pole, 50 frames per second.

    ## Arguments
    The physical coefficients ``gravity`` (9.8), ``masscart`` (1.0), ``masspole`` (0.1), ``length`` (0.5, half
    the pole), ``cart_friction`` (0: a Coulomb friction force ``-mu_c sgn(x_dot)`` on the cart) and
    ``pole_friction`` (0: a friction torque ``-mu_p theta_dot`` at the pivot), e.g.
    ``gym.make("pimbrl/CartPole-v0", masspole=0.15)``. Masses and length must be > 0, frictions >= 0.

    ## Version History
    * v0: the paper's CartPole-v0 (200-step limit).
    """


class CartPoleEnv(PhysicsEnv):  # noqa: D101 - docstring set below, __doc__ = _DOC
    __doc__ = _DOC
    task_class = CartPoleTask
    metadata = {"render_modes": ["rgb_array"], "render_fps": CartPoleTask.render_fps}  # noqa: RUF012


class CartPoleVectorEnv(PhysicsVectorEnv):  # noqa: D101 - docstring set below, __doc__ = _DOC
    __doc__ = _DOC + "\n    Native vector version: all sub-environments advance in one NumPy call.\n"
    task_class = CartPoleTask
