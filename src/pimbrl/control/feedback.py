"""Feedback floors: a controller per system that needs no learning, with one gain tuned on validation draws.

* :class:`ProportionalFeedback` (PDEs with localised actuators): ``a_i = -gain x`` the observation averaged
  under actuator ``i``'s shape (Burgers: the local tracking error; KS: the local ``u``), clipped.
* :class:`LQR`: the linear-quadratic regulator of the control step linearised at a target state and action
  (the Jacobians of the system's own step, by automatic differentiation), from the discrete Riccati equation;
  ``gain`` weighs the action cost. Cart-Pole: around the upright pole, its force applied as a push to the
  force's side. A declared ODE: around the origin.
* :class:`EnergySwingUp` (the pendulum): pump the energy towards the upright's, ``T = -gain E theta_dot``
  (``E`` the energy relative to the upright, per unit inertia), and hand over to the LQR of the reward's own
  weights near the top.

A system declares its floor by name (:attr:`pimbrl.systems.System.feedback`, with its gains to try); a
system without a declaration gets proportional feedback if it is a PDE with actuator shapes and an LQR
around the origin if it is an ODE. :func:`make_feedback` builds it; :func:`tune_gain` picks the gain on the
validation draws.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from ..config import FEEDBACK_KINDS
from ..envs import Task
from ..physics import Physics
from ..systems import get_system
from .base import Controller, play

__all__ = [
    "FEEDBACK_KINDS",
    "FEEDBACK_OPTIONS",
    "LQR",
    "EnergySwingUp",
    "ProportionalFeedback",
    "RiccatiError",
    "check_feedback",
    "declared_feedback",
    "default_feedback",
    "feedback_gains",
    "make_feedback",
    "tune_gain",
]

#: the gains tried on the validation draws where a system declares none, by kind
DEFAULT_GAINS: dict[str, tuple[float, ...]] = {
    "proportional": (0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 10.0, 20.0),
    "lqr": (0.001, 0.01, 0.1, 1.0, 10.0, 100.0),
    "energy-lqr": (0.05, 0.1, 0.2, 0.5, 1.0, 2.0),
}


class ProportionalFeedback(Controller):
    """``a_i = -gain * <obs>_i``: the observation averaged under actuator ``i`` (weights ``shape_i / sum shape_i``)."""

    def __init__(self, task: Task, gain: float) -> None:
        if not math.isfinite(gain):
            raise ValueError(f"the feedback gain must be a finite number, got {gain}")
        shapes = getattr(task.physics, "actuator_shapes", None)
        if shapes is None:
            raise ValueError(
                f"proportional feedback is for PDE systems with localised actuators; {task.physics.name} has none "
                "(declare feedback='lqr' for an ODE system)"
            )
        weights = np.asarray(shapes, dtype=np.float64)
        self.weights = weights / weights.sum(axis=1, keepdims=True)
        self.task = task
        self.gain = float(gain)
        self.low, self.high = task.physics.action_low, task.physics.action_high

    def __call__(self, states: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Proportional actions, clipped to the actuators' bounds."""
        obs = np.asarray(self.task.observe(states, k), dtype=np.float64).reshape(len(states), -1)
        if obs.shape[1] != self.weights.shape[1]:
            raise ValueError(
                f"proportional feedback averages the observation under each actuator: the actuators cover "
                f"{self.weights.shape[1]} points, the observation has {obs.shape[1]}"
            )
        return np.clip(-self.gain * obs @ self.weights.T, self.low, self.high)


def linearise(physics: Physics, state: np.ndarray, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(A, B)``: the Jacobians of one control step ``u' = F(u, a)`` at ``(state, action)`` (float64)."""
    u = torch.as_tensor(state, dtype=torch.float64)
    a = torch.as_tensor(action, dtype=torch.float64)
    jac_u, jac_a = torch.autograd.functional.jacobian(lambda x, y: physics.step(x[None], y[None])[0], (u, a))
    return jac_u.numpy(), jac_a.numpy()


class RiccatiError(ValueError):
    """The LQR's Riccati iteration did not settle: the linearised system is not stabilisable at that target."""


#: the options each kind of floor takes (:attr:`pimbrl.systems.System.feedback_options`)
FEEDBACK_OPTIONS: dict[str, tuple[str, ...]] = {
    "proportional": (),
    "lqr": ("state", "action", "q"),
    "energy-lqr": ("switch", "speed"),
}


def riccati_gain(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray, iterations: int = 10_000) -> np.ndarray:
    """The LQR gain ``K`` (``a = -K u``) of the discrete Riccati equation, by fixed-point iteration.

    Raises ``ValueError`` where the iteration does not settle (an unstabilisable linearisation).
    """
    p = q.copy()
    with np.errstate(over="ignore", invalid="ignore"):  # a diverging iteration is detected below
        return _riccati(a, b, q, r, p, iterations)


def _riccati(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray, p: np.ndarray, iterations: int) -> np.ndarray:
    for _ in range(iterations):
        k = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
        p_next = q + a.T @ p @ (a - b @ k)
        if not np.all(np.isfinite(p_next)):
            break
        if np.max(np.abs(p_next - p)) <= 1e-10 * max(1.0, float(np.max(np.abs(p)))):
            return np.linalg.solve(r + b.T @ p_next @ b, b.T @ p_next @ a)
        p = p_next
    raise RiccatiError(
        "the LQR's Riccati iteration did not settle: the linearised system is not stabilisable at its target; "
        "give the floor another target (feedback_options state/action) or another kind (--model.kind)"
    )


class LQR(Controller):
    """``a = a* - K (u - u*)``, clipped; ``K`` from the linearised control step with costs ``Q`` and ``R``."""

    def __init__(
        self, physics: Physics, q: np.ndarray, r: np.ndarray, state: np.ndarray | None = None, action: np.ndarray | None = None
    ) -> None:
        self.physics = physics
        self.state = np.zeros(physics.state_dim) if state is None else np.asarray(state, dtype=np.float64)
        self.action = np.zeros(physics.action_dim) if action is None else np.asarray(action, dtype=np.float64)
        a, b = linearise(physics, self.state, self.action)
        self.k = riccati_gain(a, b, np.asarray(q, dtype=np.float64), np.asarray(r, dtype=np.float64))

    def __call__(self, states: np.ndarray, k: np.ndarray) -> np.ndarray:
        """The LQR's actions, clipped to the action bounds."""
        du = self.physics.state_difference(np.asarray(states, dtype=np.float64), self.state[None])
        return self.physics.clip_action(self.action - du @ self.k.T)


class EnergySwingUp(Controller):
    """The pendulum: energy pumping ``T = -gain E theta_dot`` far from the top, the reward's LQR near it.

    ``E = theta_dot^2 / 2 - (3 g / 2 l)(1 - cos theta)`` is zero at the upright pendulum at rest and
    ``dE/dt = (3 / m l^2) theta_dot T``, so the pumping drives ``E`` to zero from below. The LQR takes over where
    ``cos theta > cos(switch)`` and ``|theta_dot| < speed``.
    """

    def __init__(self, physics: Physics, gain: float, switch: float = 0.5, speed: float = 2.0) -> None:
        if physics.name != "pendulum":
            raise ValueError(f"energy-lqr is the pendulum's floor (its energy), not {physics.name}'s; use lqr or proportional")
        self.physics = physics
        self.gain = float(gain)
        self.cos_switch = math.cos(switch)
        self.speed = float(speed)
        # the reward's own weights: -(theta^2 + 0.1 theta_dot^2 + 0.001 T^2)
        self.lqr = LQR(physics, np.diag([1.0, 0.1]), np.array([[0.001]]))
        self.omega2 = 3.0 * float(physics.g) / (2.0 * float(physics.l))  # type: ignore[attr-defined]

    def __call__(self, states: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Pumping far from the top, the LQR near it."""
        theta, speed = states[:, 0], states[:, 1]
        energy = 0.5 * speed**2 - self.omega2 * (1.0 - np.cos(theta))
        pump = self.physics.clip_action((-self.gain * energy * speed)[:, None])
        near = (np.cos(theta) > self.cos_switch) & (np.abs(speed) < self.speed)
        return np.where(near[:, None], self.lqr(states, k), pump)


def default_feedback(physics: Physics) -> str:
    """The floor of a system that declares none: proportional for a PDE with actuator shapes, else an LQR."""
    return "proportional" if getattr(physics, "actuator_shapes", None) is not None else "lqr"


def check_feedback(env_id: str, task: Task, kind: str, gains: Sequence[float]) -> None:
    """Build the floor ``kind`` of ``env_id`` once (at its first gain): a kind that cannot work fails here, in one line."""
    chosen, options, declared = declared_feedback(env_id, task.physics, kind)
    try:
        controller = make_feedback(task, chosen, float((tuple(gains) or declared)[0]), options)
    except RiccatiError:
        return  # another gain may settle: the tuning scores each
    controller(task.validation_initial_states(1), np.zeros(1, dtype=np.int64))  # shapes: observation, actuators


def declared_feedback(env_id: str, physics: Physics, kind: str = "auto") -> tuple[str, dict[str, Any], tuple[float, ...]]:
    """The floor of ``env_id``: its kind (``auto``: the declared one, else :func:`default_feedback`), options, gains.

    The options and gains are the system's declared ones where ``kind`` is the declared kind, else none and
    the kind's default grid (:data:`DEFAULT_GAINS`).
    """
    system = get_system(env_id)
    declared = None if system is None else system.feedback
    chosen = kind if kind != "auto" else (declared or default_feedback(physics))
    if kind not in ("auto", *FEEDBACK_KINDS):
        raise ValueError(f"unknown feedback {kind!r}: choose one of auto, {', '.join(FEEDBACK_KINDS)}")
    if system is not None and chosen == declared:
        return chosen, dict(system.feedback_options), feedback_gains(chosen, system.feedback_gains)
    return chosen, {}, feedback_gains(chosen)


def make_feedback(task: Task, kind: str, gain: float, options: dict[str, Any] | None = None) -> Controller:
    """The feedback controller ``kind`` (one of :data:`FEEDBACK_KINDS`) of ``task`` at ``gain``.

    ``options`` of an LQR: ``state`` and ``action`` (the target; default the origin and zero), ``q`` (the state
    cost's diagonal; default ones); its action cost is ``gain`` times the identity.
    """
    physics = task.physics
    options = dict(options or {})
    if kind in FEEDBACK_OPTIONS:
        unknown = sorted(set(options) - set(FEEDBACK_OPTIONS[kind]))
        if unknown:
            allowed = ", ".join(FEEDBACK_OPTIONS[kind]) or "none"
            raise ValueError(f"{kind} feedback has no option {unknown[0]!r}; its options are: {allowed}")
    if kind == "proportional":
        return ProportionalFeedback(task, gain)
    if kind == "lqr":
        q = np.diag(np.asarray(options.get("q", np.ones(physics.state_dim)), dtype=np.float64))
        return LQR(physics, q, gain * np.eye(physics.action_dim), options.get("state"), options.get("action"))
    if kind == "energy-lqr":
        return EnergySwingUp(physics, gain, **options)
    raise ValueError(f"unknown feedback {kind!r}: choose one of {', '.join(FEEDBACK_KINDS)}")


def feedback_gains(kind: str, declared: Sequence[float] = ()) -> tuple[float, ...]:
    """The gains tuned over: the system's declared ones, else :data:`DEFAULT_GAINS` of ``kind``."""
    return tuple(float(g) for g in declared) or DEFAULT_GAINS[kind]


def tune_gain(
    env_id: str,
    env_kwargs: dict[str, Any],
    task: Task,
    kind: str,
    gains: Sequence[float],
    validation_states: np.ndarray,
    options: dict[str, Any] | None = None,
) -> tuple[float, list[tuple[float, float]], int]:
    """The gain with the best mean return on ``validation_states``; every gain's return; the steps played.

    The test states are never read here. A gain whose LQR cannot be built (its Riccati iteration does not
    settle) scores minus infinity; if none can be, that error is raised.
    """
    scores: list[tuple[float, float]] = []
    steps = 0
    first_error: RiccatiError | None = None
    for gain in gains:
        try:
            controller = make_feedback(task, kind, gain, options)
        except RiccatiError as exc:
            first_error = first_error or exc
            scores.append((float(gain), -math.inf))
            continue
        result = play(env_id, env_kwargs, controller, validation_states)
        steps += result.control_steps
        scores.append((float(gain), result.mean))
    if all(math.isinf(r) for _, r in scores):
        assert first_error is not None
        raise first_error
    best = max(scores, key=lambda s: s[1])[0]
    return best, scores, steps
