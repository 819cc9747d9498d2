"""Kuramoto-Sivashinsky chaos suppression with four actuators."""

from __future__ import annotations

from typing import Any, Literal, cast

import numpy as np
from gymnasium import spaces

from ..physics import KuramotoSivashinsky
from .base import PhysicsEnv, PhysicsVectorEnv
from .ks_states import KSPoolConfig, Split, ks_initial_state_pool
from .task import Task, check_bool, check_finite_number

__all__ = ["KSTask", "KuramotoSivashinskyEnv", "KuramotoSivashinskyVectorEnv"]


class KSTask(Task):
    """KS task: observation ``u``, 4 actuator amplitudes in ``[-0.5, 0.5]``, 400 control steps.

    Args:
        reward: ``"code"`` (the authors' reward scale, default) or ``"physical"``.
        periodic_actuators: wrap the actuator Gaussians periodically (a bool; default False, as the authors).
        initial_states: ``"train"`` (default) or ``"test"`` pool, or an array ``(n, 64)`` of states.
        pool_config: generator settings of the pools (a :class:`KSPoolConfig` or a dict of its fields; see
            :mod:`pimbrl.envs.ks_states`).
        divergence_penalty: reward of a step that blows up, a finite number (default -100; a settled uncontrolled episode
            returns about -920, and with gamma = 0.977 the discounted cost of the rest of any episode
            is below 100).
        **coefficients: physical coefficients of :class:`pimbrl.physics.KuramotoSivashinsky` that differ from
            the paper's (``anti_diffusion``, ``hyper_diffusion``, ``convection``, ``damping``,
            ``actuator_width``, ``drift``), e.g. ``convection=1.3``. The initial-state pools are drawn from the paper's
            system whatever the coefficients.
    """

    max_episode_steps = 400
    render_fps = 4  # a control step is 0.25 time units
    render_scale = 4.0  # chaotic states stay within about |u| < 3
    physics: KuramotoSivashinsky
    action_space: spaces.Box

    def __init__(
        self,
        reward: Literal["code", "physical"] = "code",
        periodic_actuators: bool = False,
        initial_states: str | np.ndarray = "train",
        pool_config: KSPoolConfig | dict | None = None,
        divergence_penalty: float = -100.0,
        **coefficients: float,
    ) -> None:
        self.physics = KuramotoSivashinsky(
            reward=reward, periodic_actuators=check_bool(periodic_actuators, "periodic_actuators")
        ).with_coefficients(**coefficients)
        self.physics.check_stability()  # a one-line error now rather than at the first step
        self.divergence_penalty = check_finite_number(divergence_penalty, "divergence_penalty")
        if pool_config is not None and not isinstance(pool_config, (KSPoolConfig, dict)):
            raise TypeError(f"pool_config must be a KSPoolConfig or a dict of its fields, got {pool_config!r}")
        self.pool_config = KSPoolConfig(**pool_config) if isinstance(pool_config, dict) else pool_config
        if isinstance(initial_states, str):
            if initial_states not in ("train", "test"):
                raise ValueError(f"initial_states must be 'train', 'test' or an array of states, got {initial_states!r}")
            self._pool: np.ndarray | None = None
            self._pool_split = initial_states
        else:
            pool = np.asarray(initial_states, dtype=np.float64)
            if pool.ndim != 2 or pool.shape[1] != self.physics.n or len(pool) == 0 or not np.isfinite(pool).all():
                raise ValueError(f"initial_states must be a finite array of shape (n, {self.physics.n}), got shape {pool.shape}")
            self._pool = pool
            self._pool_split = "custom"
        bound = np.float32(self.physics.divergence_bound)
        self.observation_space = spaces.Box(-bound, bound, shape=(self.physics.n,), dtype=np.float32)
        self.action_space = spaces.Box(
            self.physics.action_low.astype(np.float32), self.physics.action_high.astype(np.float32), dtype=np.float32
        )

    @property
    def pool(self) -> np.ndarray:
        """The initial-state pool (generated and cached on first use)."""
        if self._pool is None:
            # a pool is given as an array exactly when the split is "custom": here it is "train" or "test"
            split = cast(Split, self._pool_split)
            self._pool = ks_initial_state_pool(split, self.pool_config).states
        return self._pool

    def sample_initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` states drawn with replacement from the initial-state pool."""
        return self.pool[rng.integers(len(self.pool), size=n)].copy()

    @property
    def test_pool_size(self) -> int:
        """Number of states in the test pool of :attr:`pool_config` (known without generating it)."""
        return (self.pool_config or KSPoolConfig()).n_test

    def test_initial_states(self, n: int, seed: int) -> np.ndarray:
        """The first ``n`` states of the test pool of :attr:`pool_config`, in pool order; ``seed`` is unused.

        The test pool comes from runs disjoint from the training pool's, whatever ``initial_states`` this
        task samples its training episodes from.
        """
        if not 0 <= n <= self.test_pool_size:
            raise ValueError(
                f"{n} KS test states requested, but the test pool holds {self.test_pool_size} "
                "(raise KSPoolConfig.n_test through pool_config, or ask for fewer test episodes)"
            )
        return ks_initial_state_pool("test", self.pool_config).states[:n].copy()

    #: rows of the training pool evaluated by the ``"authors"`` protocol, as the authors' code evaluates rows
    #: 0, 49, 99, 149 and 199 of its array of training initial states
    AUTHORS_EVAL_ROWS = (0, 49, 99, 149, 199)

    @property
    def eval_protocols(self) -> tuple[str, ...]:
        """``"test"`` (the held-out test pool), ``"validation"`` and ``"authors"`` (5 fixed training states)."""
        return ("test", "validation", "authors")

    def validation_initial_states(self, n: int) -> np.ndarray:
        """The first ``n`` states of the validation pool of :attr:`pool_config`, in pool order.

        The validation pool comes from runs disjoint from the training and test pools' (its own seed stream).
        """
        size = (self.pool_config or KSPoolConfig()).n_validation
        if not 0 <= n <= size:
            raise ValueError(
                f"{n} KS validation states requested, but the validation pool holds {size} "
                "(raise KSPoolConfig.n_validation through pool_config, or ask for fewer validation episodes)"
            )
        return ks_initial_state_pool("validation", self.pool_config).states[:n].copy()

    def protocol_initial_states(self, protocol: str, n: int | None, seed: int) -> np.ndarray:
        """``"test"``: the first ``n`` test-pool states; ``"authors"``: rows :data:`AUTHORS_EVAL_ROWS` of the training pool.

        The authors report the mean return over 5 states the agent trained on (rows 0, 49, 99, 149, 199 of
        their array of training states, snapshots of one trajectory); ``"authors"`` takes the same rows of
        this task's training pool (snapshots of several chaotic transients, so the 5 states come from
        different runs). ``n`` must then be 5 or ``None``.
        """
        if protocol != "authors":
            return super().protocol_initial_states(protocol, n, seed)
        rows = list(self.AUTHORS_EVAL_ROWS)
        if n is not None and n != len(rows):
            raise ValueError(f"the 'authors' KS protocol has {len(rows)} episodes, not {n}; leave the number of episodes unset")
        pool = ks_initial_state_pool("train", self.pool_config).states
        if len(pool) <= rows[-1]:
            raise ValueError(
                f"the 'authors' KS protocol evaluates training-pool row {rows[-1]}, but the pool holds {len(pool)} states "
                "(raise KSPoolConfig.n_train through pool_config)"
            )
        return pool[rows].copy()

    def observe(self, u: np.ndarray, k: np.ndarray) -> np.ndarray:
        """The field itself, as float32."""
        return u.astype(np.float32)

    def physical_action(self, actions: Any, batch: int) -> np.ndarray:
        """Check the actions' shape and finiteness and clip them to the actuator bounds."""
        return self._box_action(actions, batch, self.action_space, self.physics.action_low, self.physics.action_high)


_DOC = """Kuramoto-Sivashinsky chaos suppression with four actuators (Liu & Wang 2021, section 3.3).

    ## Description
    A periodic 1-D field ``u(x, t)`` on ``[0, 8 pi)`` obeys the Kuramoto-Sivashinsky equation and is,
    unforced, spatiotemporally chaotic for a long transient. Four Gaussian actuators at
    ``x in {0, L/4, L/2, 3L/4}`` inject forcing; the goal is to suppress the chaotic dynamics with
    little dissipation and input power.

    ## Governing equation
    ``u_t + u_xx + u_xxxx + u u_x = f(x, t)``, ``f = sum_i a_i exp(-(x - x_i)^2 / 2) / sqrt(2 pi)``
    (the Gaussians are not wrapped periodically unless ``periodic_actuators=True``).

    ## Discretisation
    64 points, ``dx = L/64``; ``du/dt = -D4 u/dx^4 - D2 u/dx^2 - Dup(u^2)/(2 dx) + f`` with 6th-order
    central D2 and D4 and a 4th-order one-sided upwind ``Dup`` switched point by point on the sign of
    ``u``; classic RK4 with ``dt = 0.001``, 250 steps per control step (0.25 time units), forcing frozen.
    The simulator is a compiled float64 kernel generated from the same stencil tables as the torch
    right-hand side (:class:`pimbrl.physics.KuramotoSivashinsky`).

    ## Action Space
    ``Box(-0.5, 0.5, (4,), float32)``: actuator amplitudes; values outside are clipped.

    ## Observation Space
    ``Box(-100, 100, (64,), float32)``: the field ``u`` on the grid.

    ## Rewards
    Default (``reward="code"``, the authors' scale, on which the paper's goal -55 is stated):
    ``r = -(1/250) sum_s [mean((D2 u_s)^2) + mean((Dup(u_s^2))^2) + mean(u_s f)]`` over the states
    ``u_s`` at the start of the 250 solver steps, with raw stencil sums. ``reward="physical"``:
    ``-(1/250) sum_s mean(u_xx^2 + u_x^2 + u f)`` with properly scaled derivatives.

    ## Starting State
    A state drawn from the seeded training pool of chaotic-transient snapshots
    (:mod:`pimbrl.envs.ks_states`); ``initial_states="test"`` draws from the disjoint test pool.
    ``reset(options={"initial_state": u})`` starts from a given field (shape ``(64,)``).

    ## Episode End
    Truncation after 400 control steps (100 time units). Termination only if the state blows up
    (non-finite or ``|u| > 100``): then the reward is ``divergence_penalty`` (-100),
    ``info["diverged"]`` is True and the last finite observation is returned.

    ## Rendering
    ``render_mode="rgb_array"``: the field over the grid (vertical axis ``[-4, 4]``, widened to fit),
    4 frames per second (one per control step).

    ## Arguments
    ``reward``, ``periodic_actuators`` (a bool), ``initial_states``, ``pool_config``, ``divergence_penalty``
    (see :class:`pimbrl.envs.ks.KSTask`); the physical coefficients ``anti_diffusion``, ``hyper_diffusion``,
    ``convection`` (1 each), ``damping`` (0: a term ``-mu u`` added to the right-hand side), ``actuator_width``
    (1) and ``drift`` (0: a term ``-c u_x``), e.g. ``gym.make("pimbrl/KuramotoSivashinsky-v0", convection=1.3)``.

    ## Version History
    * v0: initial version, numerics of the authors' code (docs/environments.md, section
      "Kuramoto-Sivashinsky", lists them in full).
    """


class KuramotoSivashinskyEnv(PhysicsEnv):  # noqa: D101 - docstring set below, __doc__ = _DOC
    __doc__ = _DOC
    task_class = KSTask
    metadata = {"render_modes": ["rgb_array"], "render_fps": KSTask.render_fps}  # noqa: RUF012


class KuramotoSivashinskyVectorEnv(PhysicsVectorEnv):  # noqa: D101 - docstring set below, __doc__ = _DOC
    __doc__ = _DOC + "\n    Native vector version: all sub-environments advance in one compiled call.\n"
    task_class = KSTask
