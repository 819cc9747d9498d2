"""Someone else's simulator with your equation as the prior: the adapter for external Gymnasium envs.

The simulator is an external Gymnasium env whose physical state can be read and set, through one small
contract: ``reset(seed=s)`` draws an initial state, ``reset(options={"state": u})`` starts from ``u``, and
the ``info`` of ``reset`` and ``step`` carries the physical state in ``info["state"]``. A step's
``terminated`` ends the episode (its ``truncated`` is ignored: the system's episode length is the time
limit). Each control step starts from a reset to the state, so the simulator's dynamics and reward must
not depend on its own step counter. The equation is a
declared system (:class:`~pimbrl.systems.ODESystem` or :class:`~pimbrl.systems.PeriodicPDESystem`): what
the user believes the simulator integrates. It serves as the physics prior of PiMBRL (the residual, the
scheme as the model, the hybrid model) and gives the imagined rewards; the real transitions and rewards
come from the external simulator alone. The prior may be wrong (a coefficient, a missing term): learned
coefficients and the hybrid correction then fit it to the simulator's data, as with the built-in systems
(``--dyna.physics-prior``, ``--dyna.learn-coefficients``).

:func:`declare_external` builds the task and the environments and registers the system. The declared
reward must be the simulator's: it is checked on a few steps when the system is declared, since a
model-based method scores imagined transitions with it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from ..envs.task import StepOutcome
from .declared import DeclaredTask, ODESystem, PeriodicPDESystem, register_task
from .registry import System, SystemSpecError

__all__ = ["ExternalTask", "declare_external"]


class ExternalTask(DeclaredTask):
    """A declared system's task whose transitions come from an external simulator.

    The prior (:attr:`physics`) gives the observation, the action bounds, the episode, the reward of imagined
    steps and the physics loss; :meth:`advance` and :meth:`sample_initial_states` run the external env.
    """

    make_simulator: ClassVar[Callable[[], gym.Env]]

    def __init__(self, divergence_penalty: float = -100.0, **coefficients: float) -> None:
        self.simulator = type(self).make_simulator()
        super().__init__(divergence_penalty, **coefficients)

    def _reset(self, **kwargs: Any) -> np.ndarray:
        _, info = self.simulator.reset(**kwargs)
        if not isinstance(info, dict) or "state" not in info:
            raise SystemSpecError("the external env's reset() must return the physical state in info['state']")
        return np.asarray(info["state"], dtype=np.float64).reshape(self.state_dim)

    def sample_initial_states(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` initial states of the external simulator, each from ``reset(seed=s)`` with ``s`` drawn from ``rng``."""
        seeds = rng.integers(0, 2**31 - 1, size=n)
        return np.stack([self._reset(seed=int(s)) for s in seeds]) if n else np.zeros((0, self.state_dim))

    def advance(self, u: np.ndarray, physical_action: np.ndarray, k: np.ndarray) -> StepOutcome:
        """One control step of the external simulator from each state of the batch (reset to it, then step)."""
        u = np.asarray(u, dtype=np.float64)
        u_next = np.empty_like(u)
        reward = np.empty(len(u))
        ended = np.zeros(len(u), dtype=bool)
        for i in range(len(u)):
            self._reset(options={"state": u[i].copy()})
            _, r, terminated, _, info = self.simulator.step(np.asarray(physical_action[i], dtype=np.float64))
            if not isinstance(info, dict) or "state" not in info:
                raise SystemSpecError("the external env's step() must return the physical state in info['state']")
            u_next[i] = np.asarray(info["state"], dtype=np.float64).reshape(self.state_dim)
            reward[i] = float(r)
            ended[i] = bool(terminated)  # the simulator's own end of an episode (its time limit is truncation)
        out = self.outcome(u, u_next, reward)
        return StepOutcome(out.state, out.reward, out.terminated | ended, out.diverged)


def _check_reward(task: ExternalTask, steps: int = 3) -> None:
    """A :class:`SystemSpecError` where the prior's reward is not the simulator's on a few random steps."""
    rng = np.random.default_rng(0)
    u = task.sample_initial_states(rng, steps)
    a = rng.uniform(task.physics.action_low, task.physics.action_high, size=(steps, task.physics.action_dim))
    out = task.advance(u, a, np.zeros(steps, dtype=np.int64))
    declared = np.asarray(task.physics.reward(u, a, out.state, np.zeros(steps, dtype=np.int64)), dtype=np.float64)
    scale = max(1.0, float(np.abs(out.reward).max()))
    worst = float(np.abs(declared - out.reward).max())
    if not worst <= 1e-6 * scale:
        raise SystemSpecError(
            f"{task.physics.name}: the declared reward differs from the external simulator's by {worst:.3g} on a test step; "
            "declare the simulator's reward (imagined transitions are scored with it)"
        )


def declare_external(
    prior_class: type[Any],
    make_simulator: Callable[[], gym.Env],
    id: str,
    *,
    aliases: tuple[str, ...] = (),
    preset: Mapping[str, Any] | str | Path | None = None,
    out_of_sample: Callable[..., np.ndarray] | None = None,
    check_reward: bool = True,
) -> System:
    """Register an external simulator with a declared system as its prior; returns the :class:`System`.

    Args:
        prior_class: a subclass of :class:`ODESystem` or :class:`PeriodicPDESystem`: the equation believed,
            with the simulator's reward, observation, action bounds, episode length and divergence bound.
        make_simulator: builds the external Gymnasium env (the contract is in the module docstring).
        id: the Gymnasium id of the adapted system, ``namespace/Name-v0``.
        aliases: short names for the command line.
        preset: its training settings (as for :func:`pimbrl.systems.declare`).
        out_of_sample: initial states outside the training distribution for ``pimbrl model-eval``.
        check_reward: compare the declared reward with the simulator's on a few steps (a one-line error).
    """
    if not (isinstance(prior_class, type) and issubclass(prior_class, (ODESystem, PeriodicPDESystem))):
        raise SystemSpecError(f"declare_external() takes a subclass of ODESystem or PeriodicPDESystem, got {prior_class!r}")
    if not callable(make_simulator):
        raise SystemSpecError("make_simulator must be a function that builds the external env")
    stem = prior_class.__name__
    namespace = {
        "physics_class": prior_class,
        "make_simulator": staticmethod(make_simulator),
        "__module__": prior_class.__module__,
    }
    task = type(f"{stem}ExternalTask", (ExternalTask,), namespace)
    probe = task()
    if not math.isfinite(prior_class.divergence_bound):
        raise SystemSpecError(f"{stem}: an external system needs a finite divergence_bound (blow-ups end episodes)")
    if check_reward:
        _check_reward(probe)
    return register_task(task, id, aliases=aliases, preset=preset, out_of_sample=out_of_sample)
