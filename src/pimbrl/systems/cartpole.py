"""Cart-Pole: Gymnasium's classic cart-pole dynamics (Barto, Sutton & Anderson 1983), optionally with friction.

The equations are written once here in array-agnostic form (NumPy or torch, batched), with the
operation order of Gymnasium's ``CartPoleEnv`` so that trajectories match it bit for bit. The paper's
equation (3.1) has typos; this is the form Gymnasium (and the authors' environment) integrate.

With friction (``mu_c = cart_friction``, ``mu_p = pole_friction``; both 0 by default, as Gymnasium) these
are Barto, Sutton & Anderson's (1983, appendix) frictional equations, in Gymnasium's sign convention
(``theta = 0`` upright, ``g > 0``; ``m = masspole``, ``M = masscart + masspole``, ``l`` the half-length)::

    temp      = (F + m l theta_dot^2 sin(theta) - mu_c sgn(x_dot)) / M
    theta_acc = (g sin(theta) - cos(theta) temp - mu_p theta_dot / (m l)) / (l (4/3 - m cos^2(theta) / M))
    x_acc     = temp - m l theta_acc cos(theta) / M

``mu_c sgn(x_dot)`` is a Coulomb friction force of constant magnitude ``mu_c`` (newtons) on the cart,
``mu_p theta_dot`` a viscous friction torque at the pivot. They follow from the Lagrangian of a uniform
pole (moment of inertia ``m l^2 / 3`` about its centre) on a cart with these two generalised friction
forces. Florian (2007, "Correct equations for the dynamics of the cart-pole system") points out that
physical Coulomb friction scales with the cart's normal force, which varies with the pole's motion; that
refinement is not modelled: ``mu_c`` is Barto et al.'s constant friction force. At ``x_dot = 0`` the
cart friction is 0 (no static friction). A friction term that is 0 is not computed at all, so the
defaults stay Gymnasium's bit for bit.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

from ..envs.base import PhysicsEnv, PhysicsVectorEnv
from ..envs.render import BLACK, BROWN, GREY, Canvas
from ..envs.task import Task
from ..physics.base import Array, Physics, active, check_coefficient, records_arguments, xp_of
from .registry import System

__all__ = ["SYSTEM", "CartPole", "CartPoleEnv", "CartPoleTask", "CartPoleVectorEnv"]


class CartPole(Physics):
    """Cart-pole with state ``(x, x_dot, theta, theta_dot)`` and a horizontal force on the cart.

    The physical action is the force (``[-force_mag, force_mag]``); the Gymnasium environment applies
    ``+force_mag`` for action 1 and ``-force_mag`` for action 0. Explicit Euler with ``tau = 0.02``.

    Args:
        gravity: gravitational acceleration (9.8), a finite number.
        masscart: mass of the cart (1.0), > 0.
        masspole: mass of the pole (0.1), > 0.
        length: half the pole's length (0.5), > 0.
        force_mag: magnitude of the force on the cart (10).
        tau: explicit Euler step (0.02).
        x_threshold: the episode ends beyond ``|x| > x_threshold`` (2.4).
        theta_threshold_radians: the episode ends beyond ``|theta| >`` this (12 degrees).
        cart_friction: magnitude ``mu_c`` of a Coulomb friction force ``-mu_c sgn(x_dot)`` on the cart
            (0: none, as Gymnasium), >= 0.
        pole_friction: coefficient ``mu_p`` of a viscous friction torque ``-mu_p theta_dot`` at the pivot
            (0: none, as Gymnasium), >= 0.

    The physical coefficients (:attr:`coefficients`) are ``gravity``, ``masscart``, ``masspole``,
    ``length``, ``cart_friction`` and ``pole_friction``. See the module docstring for the equations.

    Raises:
        ValueError: for a mass or length ``<= 0``, a friction ``< 0`` or a coefficient that is not finite.
    """

    name = "cartpole"
    coefficients = ("gravity", "masscart", "masspole", "length", "cart_friction", "pole_friction")
    tensor_coefficients = True
    differentiable_reward = False  # +1 per step until the episode ends: nothing for a gradient to climb

    @records_arguments
    def __init__(
        self,
        gravity: float = 9.8,
        masscart: float = 1.0,
        masspole: float = 0.1,
        length: float = 0.5,
        force_mag: float = 10.0,
        tau: float = 0.02,
        x_threshold: float = 2.4,
        theta_threshold_radians: float = 12 * 2 * math.pi / 360,
        cart_friction: float = 0.0,
        pole_friction: float = 0.0,
    ) -> None:
        self.gravity = check_coefficient("CartPole", "gravity", gravity, low=-100.0, high=100.0)
        self.masscart = check_coefficient("CartPole", "masscart", masscart, positive=True, high=1e3)
        self.masspole = check_coefficient("CartPole", "masspole", masspole, positive=True, high=1e3)
        self.length = check_coefficient("CartPole", "length", length, positive=True, high=100.0)  # half the pole's length
        self.cart_friction = check_coefficient("CartPole", "cart_friction", cart_friction, nonnegative=True, high=1e3)
        self.pole_friction = check_coefficient("CartPole", "pole_friction", pole_friction, nonnegative=True, high=1e3)
        self._derive_coefficients()
        self.force_mag = float(force_mag)
        self.dt = float(tau)
        self.substeps = 1
        self.x_threshold = float(x_threshold)
        self.theta_threshold_radians = float(theta_threshold_radians)
        self.state_dim = 4
        self.action_dim = 1
        self.action_low = np.array([-self.force_mag])
        self.action_high = np.array([self.force_mag])

    def _derive_coefficients(self) -> None:
        """The total mass and the pole's mass times half-length, as Gymnasium computes them."""
        self.total_mass = self.masspole + self.masscart
        self.polemass_length = self.masspole * self.length

    def rhs(self, u: Array, a: Array) -> Array:
        """Gymnasium's cart-pole equations of motion, with Barto et al.'s friction terms where nonzero.

        Returns ``(x_dot, x_acc, theta_dot, theta_acc)``.
        """
        xp = xp_of(u)
        x_dot, theta, theta_dot = u[..., 1], u[..., 2], u[..., 3]
        force = a[..., 0]
        costheta = xp.cos(theta)
        sintheta = xp.sin(theta)
        numerator = force + self.polemass_length * (theta_dot * theta_dot) * sintheta
        if active(self.cart_friction):  # each friction term is skipped at 0: the defaults stay Gymnasium's
            numerator = numerator - self.cart_friction * xp.sign(x_dot)
        temp = numerator / self.total_mass
        angular = self.gravity * sintheta - costheta * temp
        if active(self.pole_friction):
            angular = angular - self.pole_friction * theta_dot / self.polemass_length
        thetaacc = angular / (self.length * (4.0 / 3.0 - self.masspole * (costheta * costheta) / self.total_mass))
        xacc = temp - self.polemass_length * thetaacc * costheta / self.total_mass
        return xp.stack([x_dot, xacc, theta_dot, thetaacc], -1)

    def substep(self, u: Array, a: Array) -> Array:
        """One explicit Euler step of length :attr:`dt` (Gymnasium's ``euler`` integrator)."""
        return u + self.dt * self.rhs(u, a)

    def reward(self, u: Array, a: Array, u_next: Array, k: Array | int, path: Array | None = None) -> Array:
        """+1 for every step, the terminating one included (Gymnasium's reward)."""
        return 0.0 * u_next[..., 0] + 1.0

    #: speed bounds of :meth:`admissible_box` (cart m/s, pole rad/s): beyond what a balancing episode reaches
    speed_box = (3.0, 3.5)

    def admissible_box(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The termination box in position and angle; :attr:`speed_box` in the speeds."""
        high = np.array([self.x_threshold, self.speed_box[0], self.theta_threshold_radians, self.speed_box[1]])
        return -high, high

    def terminated(self, u: Array) -> Array:
        """The cart leaves ``|x| <= 2.4`` or the pole tilts beyond 12 degrees."""
        x, theta = u[..., 0], u[..., 2]
        return (
            (x < -self.x_threshold)
            | (x > self.x_threshold)
            | (theta < -self.theta_threshold_radians)
            | (theta > self.theta_threshold_radians)
        )

    def advance(self, u: np.ndarray, a: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One Euler step and the constant reward for a batch of states."""
        u = np.asarray(u, dtype=np.float64)
        a = np.asarray(a, dtype=np.float64)
        u_next = self.substep(u, a)
        return u_next, self.reward(u, a, u_next, k)


class CartPoleTask(Task):
    """Cart-Pole task: Discrete(2) actions (0: push left, 1: push right), 200 control steps.

    Args:
        **coefficients: physical coefficients of :class:`pimbrl.systems.CartPole` that differ from Gymnasium's
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
    ``- mu_p theta_dot / (m_p l)`` to that of ``theta_acc`` (see :mod:`pimbrl.systems.cartpole`).

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


#: half-widths of the Cart-Pole out-of-sample box ``(x, x_dot, theta, theta_dot)``: position and angle
#: stay inside the physics' termination bounds (``x_threshold``, ``theta_threshold_radians``; tested)
CARTPOLE_WIDE_BOX = np.array([2.0, 2.0, 0.18, 2.0])


def wide_states(task: Task, rng: np.random.Generator, n: int) -> np.ndarray:
    """Out of sample: Cart-Pole states far from upright rest (larger positions, speeds, angles; inside the bounds)."""
    return rng.uniform(-CARTPOLE_WIDE_BOX, CARTPOLE_WIDE_BOX, (n, 4))


#: the declaration: recipes in cartpole.yaml beside this file, out-of-sample set and model-study settings
SYSTEM = System(
    id="pimbrl/CartPole-v0",
    env=CartPoleEnv,
    vector_env=CartPoleVectorEnv,
    episode_steps=200,
    aliases=("cartpole",),
    preset=Path(__file__).with_suffix(".yaml"),  # default, paper (and best where one is recorded)
    out_of_sample=wide_states,
    model_eval={"transitions": 1_000, "steps": 3_000},
    feedback="lqr",  # around the upright pole, its force pushed to its side
    feedback_options={"q": (1.0, 1.0, 10.0, 1.0)},
)
