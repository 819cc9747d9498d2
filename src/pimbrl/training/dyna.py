"""The model side of the Dyna loop (the paper's Algorithm 1): MBRL (data loss) and PiMBRL (data + physics).

:class:`DynaModel` owns the transition model, its trainer, the imagined environment and the imagined
buffer D^f. The training loop (:func:`pimbrl.training.loop.train`) calls :meth:`DynaModel.phase` every
``update_every`` real steps, before the agent's updates, and :meth:`DynaModel.agent_batch` for each update:

1. **fit** - once the real buffer D^r holds ``n_sM`` transitions: ``model_steps`` gradient steps of the
   data loss L_D on real transitions (the held-out ones excluded); for PiMBRL, once D^r and D^f together
   hold ``n_sR`` transitions (or from ``physics_start`` real steps on, if set), each step also carries the
   physics loss L_E on unlabelled state-action pairs from the configured sources (``physics_sources``:
   real training states with the current policy's actions, imagined pairs, and label-free states -
   symmetries, scalings, perturbations of observed fields, the admissible box; see
   :mod:`pimbrl.models.state_sources`). With ``physics_start`` below ``n_sM`` PiMBRL trains on the physics
   loss alone until labels are used, its normalisation fitted from the equation;
2. **check** - L_D on the most recent held-out real transitions; the model is *in use* while it is below
   lambda, or below ``relative_threshold`` times the no-change prediction's error (``accuracy``), and the
   run has not switched to model-free fine-tuning;
3. **imagine** - while in use: ``rollouts`` rollouts of ``l_M`` chained model steps from real start
   states, actions from the current policy with exploration noise, rewards and terminations from the
   physics; they go into D^f, whose oldest entries they replace;
4. the agent's batches then mix real and imagined transitions (``real_ratio`` real while the model is in
   use, else all real).

MBRL is this component with no physics residual; MFRL runs the same loop with no model at all. Every
draw comes from the run's streams for its purpose (:mod:`pimbrl.training.streams`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from ..agents import Agent
from ..buffers import Batch, ReplayBuffer, physics_extras
from ..envs import Task
from ..models import ModelEnv, ModelTrainer, PhysicsResidual, TransitionData, make_model
from ..models.residual import as_scheme
from ..models.reward import LearnedReward
from ..models.state_sources import PhysicsPairs, broad_actions, broad_states, choose_sources
from ..physics import Physics
from ..spaces import ActionAdapter
from .evaluation import Evaluator
from .methods import MFRL, CoefficientFit, DynaMethod, ModelFit, PhysicsLoss
from .selection import PolicySelector
from .streams import RandomStreams

__all__ = ["PHASES", "BufferView", "DynaModel", "agent_batch"]

#: Timed phases of a run (``time/<phase>_s`` in ``metrics.csv``; the model ones stay 0 for MFRL).
PHASES = ("env_step", "model_train", "model_check", "imagine", "agent_update", "evaluate", "select", "checkpoint")


def agent_batch(
    real: ReplayBuffer, imagined: ReplayBuffer | None, real_ratio: float, size: int, rng: np.random.Generator
) -> Batch:
    """The agent's training batch: all real, or ``real_ratio`` real and the rest imagined."""
    if imagined is None or len(imagined) == 0:
        return real.sample(size, rng)
    n_real = round(size * real_ratio)
    parts = [real.sample(n_real, rng)] if n_real else []
    if size - n_real:
        parts.append(imagined.sample(size - n_real, rng))
    return Batch.concat(parts)


class DynaModel:
    """Model, model trainer, imagination and imagined buffer of a model-based run.

    Args:
        method: the method's configuration (:mod:`pimbrl.training.methods`: MBRL, PiMBRL, KnownScheme, ...);
            its parts (``fit``, ``check``, ``imagine``, ``finetune``, ``physics``, ``learn``) set each phase.
        task: the real environment's task (physics, observations, action mapping).
        adapter: maps the agent's normalised actions to environment actions.
        obs_dim: flat observation size (the imagined buffer stores observations).
        streams: the run's random streams.
        validator: the validation episodes the fine-tuning switch reads (``None``: no switch by return).
        reset_start_symmetry: experimental: reset starts from images under the equation's symmetries.
    """

    def __init__(
        self,
        method: DynaMethod,
        task: Task,
        adapter: ActionAdapter,
        obs_dim: int,
        streams: RandomStreams,
        validator: Evaluator | None = None,
        reset_start_symmetry: bool = False,
    ) -> None:
        if isinstance(method, MFRL):
            raise ValueError("DynaModel serves a method with a model, not mfrl")
        self.method = m = method
        self.task = task
        self.fit: ModelFit | None = getattr(m, "fit", None)
        self.physics_loss: PhysicsLoss | None = getattr(m, "physics", None)
        learn: CoefficientFit | None = getattr(m, "learn", None)
        self.reset_start_symmetry = reset_start_symmetry
        # what the run knows of the system: the environment's physics, with the coefficients of the prior
        self.physics = task.physics.with_coefficients(**m.prior)
        self.adapter = adapter
        self.streams = streams
        scheme = as_scheme(getattr(m, "scheme", "etd"))
        n_states = PhysicsResidual.states_per_step(self.physics, m.n_intermediate)
        residual = (
            PhysicsResidual(
                self.physics,
                n_states,
                scheme,
                self.physics_loss.units if self.physics_loss is not None else "step",
                learned=learn.ranges(),
                correction_penalty=learn.correction_penalty,
            )
            if learn is not None
            else None
        )
        # a model with the physics inside steps the residual's scheme (and follows its learned coefficients)
        kind = m.model_kind
        inside = (residual or PhysicsResidual(self.physics, n_states, scheme)) if kind in ("physics", "hybrid") else None
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(streams.integer_seed("model_init"))
            self.model = make_model(
                self.physics,
                n_intermediate=m.n_intermediate,
                kind=kind,
                scheme=inside,
                correction_scale=getattr(m, "correction_scale", 0.01),
            )
        self.sources = choose_sources(self.physics_loss.sources, self.physics) if self.physics_loss is not None else ()
        lr = self.fit.lr if self.fit is not None else ModelFit().lr
        #: the learned reward of a system that declares none (an observed Gymnasium env: pimbrl.systems.observed)
        self.reward_model: LearnedReward | None = None
        if getattr(self.physics, "learned_reward", False):
            seed = streams.integer_seed("model_init") + 1  # its own generator: no stream of the run is drawn from
            self.reward_model = LearnedReward(self.physics.state_dim, self.physics.action_dim, lr=lr, seed=seed)
            self.physics.reward_fn = self.reward_model.predict  # type: ignore[attr-defined]
        self.trainer = ModelTrainer(
            self.model,
            residual,
            lr=lr,
            weight_physics=self.physics_loss.weight if self.physics_loss is not None else 1.0,
            coefficient_lr=learn.lr if learn is not None else CoefficientFit().lr,
        )
        #: (step, coefficient values, coefficient loss) after every model phase that fitted them
        self.coefficient_history: list[dict[str, float]] = []
        self.extras = physics_extras(self.physics.state_dim, self.physics.action_dim)
        self.imagined = ReplayBuffer(m.imagine.buffer_size, obs_dim, adapter.dim, extras=self.extras)
        self.model_env = ModelEnv(
            self.model,
            task,
            adapter,
            streams.imagination,
            use_path=m.imagine.reward_quadrature == "path",
            physics=self.physics,
        )
        self._model_steps_unknown = False
        self.in_use = False
        self.finetuning = False
        self.val_mse = float("inf")
        self.baseline_mse = float("inf")  # the no-change prediction's error on the same held-out transitions
        self.metrics: dict[str, float] = {}
        self.imagined_total = 0
        #: real-simulator steps of the fine-tuning switch's validation episodes (``None``: unknown, a run resumed
        #: from a checkpoint written before they were counted)
        self.validation_transitions: int | None = 0
        #: the validation episodes the fine-tuning switch reads (``finetune.at_return``), None when off: the
        #: switch never reads the test states, so a run trains the same whatever its test set
        self.validator = validator
        #: the mean return on the validation draws at the last evaluation (None before the first)
        self.last_validation: float | None = None
        #: model-based policy selection (``imagine.select_episodes``), None when off
        episodes = m.imagine.select_episodes
        self.selector = PolicySelector(self.model_env, episodes) if episodes else None

    # ------------------------------------------------------------------ real transitions
    def holdout_flag(self) -> float:
        """1.0 for a real transition to hold out of model training (drawn from the ``holdout`` stream)."""
        return float(self.streams.holdout.random() < self.method.check.holdout_fraction)

    # ------------------------------------------------------------------ the model phase
    def validate(self, agent: Agent) -> None:
        """At an evaluation: the deterministic policy on the validation draws, while the fine-tuning switch waits.

        Nothing is drawn from the run's random streams (fixed initial states, the deterministic policy), so
        this changes no step of the run; the switch reads the result at the next model phase.
        """
        if self.validator is not None and not self.finetuning:
            result = self.validator.run(lambda o: agent.act(o, deterministic=True))
            self.last_validation = result.mean
            if self.validation_transitions is not None:
                self.validation_transitions += int(result.lengths.sum())

    def phase(
        self,
        real: ReplayBuffer,
        agent: Agent,
        t: int,
        timed: Callable[[str], Any],
        message: Callable[[str], None],
    ) -> None:
        """Fit, check and imagine (each where due); ``timed(phase)`` is a context manager that times a phase."""
        if self._switch_to_finetuning(t, self.last_validation):
            message(f"step {t:>8,d}  switching to model-free fine-tuning")
        if self.finetuning:
            self.in_use = False
            return
        n_real = len(real)
        with_labels = n_real >= self.method.start_after
        physics_only = not with_labels and self._physics_started(n_real)
        train_idx, holdout_idx = split_indices(real)
        if (with_labels or physics_only) and (self.fit is None or self.fit.steps > 0) and len(train_idx) > 0:
            with timed("model_train"):
                self.fit_model(real, train_idx, agent, t, with_labels)
            with timed("model_check"):
                self.check_model(BufferView(real, holdout_idx[-self.method.check.validation_size :]).all())
        if self.in_use and self.method.imagine.rollouts > 0:
            with timed("imagine"):
                self.imagine(real, agent, self.method.imagine.rollouts)

    def fit_model(self, real: ReplayBuffer, train_idx: torch.Tensor, agent: Agent, t: int, with_labels: bool) -> None:
        """Fit: the data loss on the labelled training transitions, the physics loss on unlabelled pairs where due.

        Without labels (the physics loss alone, ``physics.alone_from``) the normalisation comes from the equation.
        A method without a fit (the known scheme) only has its normalisation set.
        """
        labelled = BufferView(real, train_idx) if with_labels else None
        unlabelled = None
        physics = self.physics_loss
        if physics is not None and (self._physics_started(len(real)) or len(real) + len(self.imagined) >= physics.start_after):
            unlabelled = self.physics_pairs(real, train_idx, agent)
        if labelled is not None:
            self.trainer.ensure_normalization(labelled.all())  # once: statistics of the first training data
        else:
            self._normalise_from_the_equation(real, train_idx)
        if self.fit is None:
            return
        self.metrics = self.trainer.fit(
            self.fit.steps,
            self.fit.batch_size,
            self.streams.model_batches,
            labelled,
            unlabelled,
            unlabelled_rng=self.streams.physics_states,
        )
        if self.reward_model is not None and labelled is not None:
            self.metrics["model/reward_mse"] = self._fit_reward(real, train_idx)
        coefficients = self.trainer.coefficients
        if coefficients is not None and labelled is not None:
            self.coefficient_history.append({"step": t, **coefficients.current(), "loss": self.metrics["model/coefficient_loss"]})
            self._follow_learned_coefficients()

    def physics_pairs(self, real: ReplayBuffer, train_idx: torch.Tensor, agent: Agent) -> PhysicsPairs:
        """The physics loss's unlabelled pairs (:class:`~pimbrl.models.state_sources.PhysicsPairs`).

        Real training states with the current policy's actions, the imagined buffer's pairs, the broad sources.
        The policy acts on the rows' observations, with its exploration noise; actions and the broad sources
        draw from the ``physics_states`` stream.
        """

        def actions(rows: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
            obs = real.obs.index_select(0, train_idx.index_select(0, rows)).numpy()
            env_actions = self.adapter.to_env(agent.act(obs, rng=rng), rng)
            return torch.as_tensor(self.task.physical_action(env_actions, len(rows)), dtype=torch.float32)

        return PhysicsPairs(
            self.physics,
            self.sources,
            lambda rows: real.extra("state", train_idx.index_select(0, rows)),
            len(train_idx),
            actions,
            lambda: len(self.imagined),
            lambda rows: (self.imagined.extra("state", rows), self.imagined.extra("physical_action", rows)),
            self.streams.physics_states,
        )

    def check_model(self, recent: TransitionData) -> None:
        """Check: the model's error on the most recent held-out real transitions decides whether it is in use."""
        check = self.method.check
        self.val_mse = self.trainer.validation_mse(recent)
        self.baseline_mse = no_change_mse(self.physics, recent)
        if check.accuracy == "relative":  # <=: an exact model of a system at rest is accurate too
            self.in_use = bool(np.isfinite(self.val_mse)) and self.val_mse <= check.relative_threshold * self.baseline_mse
        else:
            self.in_use = self.val_mse < check.threshold

    def _fit_reward(self, real: ReplayBuffer, train_idx: torch.Tensor) -> float:
        """Fit the learned reward on the model's training transitions (as many steps as the model); its last loss."""
        assert self.reward_model is not None
        assert self.fit is not None
        u, a = real.extra("state", train_idx), real.extra("physical_action", train_idx)
        nxt, reward = real.extra("next_state", train_idx), real.reward.index_select(0, train_idx)
        return self.reward_model.fit(u, a, nxt, reward, self.fit.steps, self.fit.batch_size)

    def _follow_learned_coefficients(self) -> None:
        """Judge imagined steps with the prior at the learned coefficients' current values (after a fit).

        The imagined rewards, terminations and divergence bound then use, e.g., the actuator shapes of the
        learned width (the KS reward's ``mean(u f)``); without learned coefficients this does nothing.
        """
        residual = self.trainer.residual
        if residual is not None and residual.coefficients is not None:
            self.model_env.physics = residual.current_physics()

    def _physics_started(self, n_real: int) -> bool:
        """PiMBRL with ``physics_start``: the physics loss from then on (alone before ``start_model_after``)."""
        start = None if self.physics_loss is None else self.physics_loss.alone_from
        return start is not None and n_real >= start

    def _normalise_from_the_equation(self, real: ReplayBuffer, train_idx: torch.Tensor) -> None:
        """Fit the normalisation once from the equation, before any label is used.

        State statistics from the observed states, the increment scale from one step of the physics' coarse
        scheme from them (random actions).
        """
        if bool(self.model.fitted) or self.trainer.residual is None:
            return
        states = real.extra("state", train_idx)
        actions = broad_actions(self.physics, len(states), self.streams.physics_states)
        with torch.no_grad():
            nxt = self.trainer.residual.rollout(states.double(), actions.double())[:, -1].float()
        self.model.fit_normalization(states, nxt)

    def _switch_to_finetuning(self, t: int, validation_return: float | None) -> bool:
        """Switch (once, for good) to model-free fine-tuning when the configured criterion is met.

        By return: the mean return on the validation draws at the last evaluation (:meth:`validate`).
        """
        f = self.method.finetune
        if self.finetuning:
            return False
        by_return = f.at_return is not None and validation_return is not None and validation_return >= f.at_return
        by_steps = f.after is not None and t >= f.after
        self.finetuning = by_return or by_steps
        return self.finetuning

    def imagine(self, real: ReplayBuffer, agent: Agent, n_rollouts: int) -> None:
        """Roll the model from sampled start states and store the imagined transitions in D^f."""
        d = self.method.imagine
        rng = self.streams.imagination
        n_img = round(n_rollouts * d.imagined_start_fraction) if len(self.imagined) else 0
        n_reset = min(round(n_rollouts * d.reset_start_fraction), n_rollouts - n_img)  # the shares' roundings fit
        starts = [real.sample_indices(n_rollouts - n_img - n_reset, rng)]
        states = [real.extra("state", starts[0])]
        ks = [real.extra("k", starts[0])]
        if n_reset:
            # imagined episodes from their first step, started as the environment's resets start them
            reset = torch.from_numpy(self.task.sample_initial_states(rng, n_reset))
            if self.reset_start_symmetry:  # an image of each under a random symmetry of the equation
                reset = broad_states(self.physics, "symmetry", reset, n_reset, rng)
            states.append(reset.to(states[0].dtype))
            ks.append(torch.zeros((n_reset, *ks[0].shape[1:]), dtype=ks[0].dtype))
        if n_img:
            # continue only imagined rollouts that had not ended (no termination, time left)
            n = len(self.imagined)
            live = (self.imagined.terminated[:n] < 0.5) & (self.imagined.truncated[:n] < 0.5)
            live_idx = torch.nonzero(live).reshape(-1)
            if len(live_idx):
                idx = live_idx[torch.from_numpy(rng.integers(0, len(live_idx), size=n_img))]
                states.append(self.imagined.extra("next_state", idx))
                ks.append(self.imagined.extra("k", idx) + 1)
            else:
                starts.append(real.sample_indices(n_img, rng))
                states.append(real.extra("state", starts[-1]))
                ks.append(real.extra("k", starts[-1]))
        u = torch.cat(states).double().numpy()
        k = torch.cat(ks).reshape(-1).long().numpy()
        batch = self.model_env.rollout(u, k, lambda obs: agent.act(obs, rng=rng), d.rollout_length)
        if len(batch):
            ones = np.ones((len(batch), 1), np.float32)
            self.imagined.add_transitions(batch, holdout=0 * ones, valid=ones)
            self.imagined_total += len(batch)

    @property
    def scheme_transitions(self) -> int | None:
        """Transitions a scheme of the known equation stepped (imagination and policy selection), else 0.

        ``None`` where unknown: a run resumed from a checkpoint written before they were counted.
        """
        if self.method.model_kind not in ("physics", "hybrid"):
            return 0
        return None if self._model_steps_unknown else self.model_env.transitions

    def agent_batch(self, real: ReplayBuffer, size: int, rng: np.random.Generator) -> Batch:
        """The agent's batch: mixed with imagined transitions while the model is in use."""
        return agent_batch(real, self.imagined if self.in_use else None, self.method.imagine.real_ratio, size, rng)

    # ------------------------------------------------------------------ logging and state
    def metric_names(self) -> list[str]:
        """Columns this component adds to ``metrics.csv``."""
        names = [
            "model/data_loss",
            "model/val_mse",
            "model/no_change_mse",
            "model/in_use",
            "model/finetuning",
            "imagined_buffer",
            "imagined_total",
        ]
        if self.validator is not None:
            names.append("model/validation_return")
        if self.trainer.residual is not None:
            names.append("model/physics_loss")
        if self.reward_model is not None:
            names.append("model/reward_mse")
        if self.trainer.coefficients is not None:
            names += ["model/coefficient_loss", *(f"coef/{name}" for name in self.trainer.coefficients.names)]
        return names

    def metric_row(self) -> dict[str, Any]:
        """This component's values of :meth:`metric_names`."""
        return {
            "model/data_loss": self.metrics.get("model/data_loss"),
            "model/physics_loss": self.metrics.get("model/physics_loss"),
            "model/reward_mse": self.metrics.get("model/reward_mse"),
            "model/val_mse": None if not np.isfinite(self.val_mse) else self.val_mse,
            "model/no_change_mse": None if not np.isfinite(self.baseline_mse) else self.baseline_mse,
            "model/in_use": int(self.in_use),
            "model/finetuning": int(self.finetuning),
            "model/validation_return": self.last_validation,
            "imagined_buffer": len(self.imagined),
            "imagined_total": self.imagined_total,
            "model/coefficient_loss": self.metrics.get("model/coefficient_loss"),
            **{f"coef/{k}": v for k, v in self.learned_coefficients().items()},
        }

    def learned_coefficients(self) -> dict[str, float]:
        """The learned coefficients' current values (empty where none is learned)."""
        return {} if self.trainer.coefficients is None else self.trainer.coefficients.current()

    def coefficients_report(self) -> dict[str, Any]:
        """The content of ``coefficients.json``: the prior, the current values and their history per phase."""
        learned = self.trainer.coefficients
        return {
            "environment": self.task.physics.coefficient_values(),
            "prior": self.physics.coefficient_values(),
            "learned": {} if learned is None else {n: list(r) if r else None for n, r in learned.ranges.items()},
            "correction": learned is not None and learned.correction is not None,
            "current": self.learned_coefficients(),
            "history": self.coefficient_history,
        }

    def state_dict(self) -> dict[str, Any]:
        """Model, optimiser, imagined buffer and flags."""
        return {
            "trainer": self.trainer.state_dict(),
            "imagined": self.imagined.state_dict(),
            "in_use": self.in_use,
            "finetuning": self.finetuning,
            "last_validation": self.last_validation,
            "val_mse": self.val_mse,
            "baseline_mse": self.baseline_mse,
            "metrics": dict(self.metrics),
            "imagined_total": self.imagined_total,
            "validation_transitions": self.validation_transitions,
            "model_transitions": None if self._model_steps_unknown else self.model_env.transitions,
            "coefficient_history": list(self.coefficient_history),
            "selection": None if self.selector is None else self.selector.state_dict(),
            "reward_model": None if self.reward_model is None else self.reward_model.state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.trainer.load_state_dict(state["trainer"])
        self.imagined.load_state_dict(state["imagined"])
        self.in_use = bool(state["in_use"])
        self.finetuning = bool(state["finetuning"])
        last = state.get("last_validation")  # absent from checkpoints before the validation draws
        self.last_validation = None if last is None else float(last)
        self.val_mse = float(state["val_mse"])
        self.baseline_mse = float(state["baseline_mse"])
        self.metrics = dict(state["metrics"])
        self.imagined_total = int(state["imagined_total"])
        # absent from checkpoints written before they were counted: unknown from then on
        counted = state.get("validation_transitions")
        self.validation_transitions = None if counted is None else int(counted)
        stepped = state.get("model_transitions")
        self._model_steps_unknown = stepped is None
        self.model_env.transitions = 0 if stepped is None else int(stepped)
        self.coefficient_history = list(state.get("coefficient_history", []))
        if self.reward_model is not None and state.get("reward_model") is not None:
            self.reward_model.load_state(state["reward_model"])
        if self.selector is not None and state.get("selection") is not None:
            self.selector.load_state_dict(state["selection"])
        if self.coefficient_history:  # imagined steps at the restored values; the prior until the first fit
            self._follow_learned_coefficients()


def no_change_mse(physics: Physics, data: TransitionData) -> float:
    """The error of predicting ``u_{t+1} = u_t``: the scale against which ``accuracy=relative`` judges a model."""
    if len(data) == 0 or data.next_state is None:
        return float("inf")
    return float(physics.state_difference(data.next_state, data.state).double().pow(2).mean())


def split_indices(buf: ReplayBuffer) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices of the model's training and held-out real transitions, oldest first.

    Steps that blew up (whose stored next state is the pre-step state) are in neither.
    """
    n = len(buf)
    age = (torch.arange(n) - buf.pos) % buf.capacity if n == buf.capacity else torch.arange(n)
    order = torch.argsort(age)
    hold = buf.extras["holdout"][order, 0] > 0.5
    valid = buf.extras["valid"][order, 0] > 0.5
    return order[~hold & valid], order[hold & valid]


class BufferView:
    """Physical transitions ``idx`` of a replay buffer, gathered batch by batch (never copied whole)."""

    def __init__(self, buf: ReplayBuffer, idx: torch.Tensor) -> None:
        self.buf = buf
        self.idx = idx

    def __len__(self) -> int:
        return len(self.idx)

    def take(self, rows: torch.Tensor) -> TransitionData:
        """The transitions at positions ``rows`` of the view."""
        sel = self.idx.index_select(0, rows)
        return TransitionData(
            self.buf.extra("state", sel), self.buf.extra("physical_action", sel), self.buf.extra("next_state", sel)
        )

    def sample(self, batch: int, rng: np.random.Generator) -> TransitionData:
        """``batch`` transitions drawn uniformly with replacement."""
        return self.take(torch.from_numpy(rng.integers(0, len(self.idx), size=batch)))

    def all(self) -> TransitionData:
        """Every transition of the view."""
        return self.take(torch.arange(len(self.idx)))
