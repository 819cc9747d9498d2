"""The training methods as typed configurations: one type per method, built from the model phase's parts.

A method's configuration is the constructor arguments of what it runs, and nothing else:

* :class:`MFRL` - model-free: no model (its agent and the run's budget are set elsewhere);
* :class:`MBRL` - Dyna with a network trained on the data loss alone (the paper's MBRL);
* :class:`PiMBRL` - the same network trained on the data loss and the physics loss (the paper's method);
* :class:`KnownScheme` - Dyna with the prior's coarse scheme itself as the model: no network, no training
  (with the exact equation, the known physics; under a wrong prior, as wrong as the prior);
* :class:`IdentifiedScheme` - that scheme with some of its coefficients fitted to the labels;
* :class:`Hybrid` - the scheme plus a correction network that starts at zero, trained on the data loss;
  :class:`PiHybrid` adds the physics loss (the correction's own defect) and learned coefficients.

Each is made of the parts of the model phase it uses: :class:`ModelFit` (gradient steps of the model),
:class:`AccuracyCheck` (when the model is trusted), :class:`Imagination` (rollouts and the agent's batch
mix), :class:`Finetune` (the switch to model-free fine-tuning), :class:`PhysicsLoss` and
:class:`CoefficientFit`. A setting that a method does not use is not a field of its type, so it cannot be
written: ``MBRL(physics=...)`` is a ``TypeError``, and ``--physics.weight`` with ``--method mbrl`` is an
error naming the methods that have it.

On the command line and in configuration files a setting is addressed by ``section.field``: ``fit.steps``,
``check.threshold``, ``imagine.rollout_length``, ``physics.weight``, ``learn.coefficients``; the method's own
fields (``network``, ``prior``, ``start_after``, ...) by ``model.field``. Plain data: importable without torch.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar

from ..config import (
    FEEDBACK_KINDS,
    MAX_BATCH,
    MAX_LR,
    MAX_STEPS,
    MAX_TRANSITIONS,
    PHYSICS_SOURCES,
    at_most,
    in_range,
    non_negative,
    one_of,
    param,
    positive,
)

__all__ = [
    "CONTROL_METHODS",
    "CONTROL_TYPES",
    "DPC",
    "MBRL",
    "METHODS",
    "METHOD_TYPES",
    "MFRL",
    "MPC",
    "NETWORKS",
    "SECTIONS",
    "AccuracyCheck",
    "CoefficientFit",
    "ControlMethod",
    "DynaMethod",
    "Feedback",
    "Finetune",
    "Hybrid",
    "Identification",
    "IdentifiedScheme",
    "Imagination",
    "KnownScheme",
    "Method",
    "ModelFit",
    "PhysicsLoss",
    "PiHybrid",
    "PiMBRL",
    "methods_with",
    "pde_only",
]

#: the networks a model-based method may train (``auto``: ConvLSTM for a PDE, an MLP for an ODE)
NETWORKS = ("auto", "convlstm", "equivariant", "mlp")
#: physics-loss sources (:mod:`pimbrl.models.state_sources`); which a system offers depends on its kind
SOURCES = PHYSICS_SOURCES


def pde_only(field: dataclasses.Field) -> bool:
    """Whether a field applies to the PDE systems only (its metadata says so)."""
    return bool(field.metadata.get("pde_only"))


def _pde_param(default: Any, help: str, check: Any = None) -> Any:
    """A :func:`~pimbrl.config.param` that applies to PDE systems only (an ODE system's run refuses it)."""
    f = param(default, f"PDEs: {help}", check)
    f.metadata = {**f.metadata, "pde_only": True}
    return f


# ----------------------------------------------------------------------------- the model phase's parts
@dataclass(frozen=True)
class ModelFit:
    """Gradient steps of the model at each model phase (the data loss, plus the physics loss where there is one)."""

    steps: int = param(50, "model gradient steps per model phase", [non_negative(), at_most(1_000_000)])
    batch_size: int = param(256, "batch size of the data loss and of the physics loss", [positive(), at_most(MAX_BATCH)])
    lr: float = param(1e-3, "model learning rate (Adam)", [positive(), at_most(MAX_LR)])


@dataclass(frozen=True)
class AccuracyCheck:
    """When the model is trusted: its error on held-out real transitions, after every fit."""

    threshold: float = param(1e-2, "lambda: held-out next-state MSE below which the model generates imagined data", positive())
    accuracy: str = param(
        "absolute",
        "absolute (held-out MSE < threshold, the paper's lambda) or relative (held-out MSE <= relative_threshold x "
        "the MSE of predicting no change on the same transitions)",
        one_of("absolute", "relative"),
    )
    relative_threshold: float = param(
        0.1, "accuracy=relative: the model is used below this fraction of the no-change error", in_range(0.0, 1.0, lo_open=True)
    )
    holdout_fraction: float = param(
        0.1, "fraction of real transitions held out to measure the model's accuracy", in_range(0.0, 0.5, lo_open=True)
    )
    validation_size: int = param(2_000, "most recent held-out transitions the check uses", [positive(), at_most(MAX_TRANSITIONS)])


@dataclass(frozen=True)
class Imagination:
    """Imagined rollouts while the model is trusted, and the agent's batches."""

    rollout_length: int = param(3, "l_M: chained model steps per imagined rollout", [positive(), at_most(10_000)])
    rollouts: int = param(200, "imagined rollouts started per model phase (n_bf)", [non_negative(), at_most(1_000_000)])
    buffer_size: int = param(
        100_000,
        "capacity of the imagined buffer D^f; the oldest imagined data is replaced",
        [positive(), at_most(MAX_TRANSITIONS)],
    )
    real_ratio: float = param(0.5, "fraction of real transitions in agent batches while the model is in use", in_range(0.0, 1.0))
    imagined_start_fraction: float = param(
        0.0, "fraction of rollout starts drawn from live imagined rollouts (continuing them)", in_range(0.0, 1.0)
    )
    reset_start_fraction: float = param(
        0.0,
        "fraction of rollout starts drawn as the environment's resets draw them (episode step 0; KS: its training pool)",
        in_range(0.0, 1.0),
    )
    reward_quadrature: str = _pde_param(
        "path",
        "imagined rewards from the model's intermediate states (path) or the step's two endpoints (endpoints)",
        one_of("path", "endpoints"),
    )
    select_episodes: int = param(
        0,
        "policy selection in the model: at every evaluation, play the deterministic policy for this many episodes "
        "in the model from validation initial states and keep the best (`pimbrl eval --policy selected`; 0: off)",
        [non_negative(), at_most(10_000)],
    )


@dataclass(frozen=True)
class Finetune:
    """The switch (once, for good) from Dyna to model-free fine-tuning."""

    at_return: float | None = param(
        None, "switch once the mean return on the validation draws reaches this (the test states decide nothing)"
    )
    episodes: int = param(
        20,
        "validation episodes the switch plays at each evaluation while it waits (KS: at most 50)",
        [positive(), at_most(MAX_BATCH)],
    )
    after: int | None = param(None, "switch after this many real steps", [non_negative(), at_most(MAX_STEPS)])


def _sources_ok(value: tuple[str, ...]) -> bool:
    return len(set(value)) == len(value) and all(s in SOURCES for s in value)


@dataclass(frozen=True)
class PhysicsLoss:
    """The physics loss L_E: the residual of the prior's equation on the model's states, on unlabelled pairs."""

    weight: float = param(1.0, "w_E: weight of the physics loss", [non_negative(), at_most(1e6)])
    units: str = param(
        "step", "units of the physics loss: substep (per sub-step increment) or step (x N^2)", one_of("substep", "step")
    )
    sources: tuple[str, ...] = param(
        (),
        "state-action pairs of the physics loss: policy, imagined, symmetry, scaled, noise (PDEs), box (ODEs); "
        "empty: all the system offers",
        (_sources_ok, f"must be distinct names among {', '.join(SOURCES)}"),
    )
    start_after: int = param(
        12_000, "n_sR: real + imagined transitions before the physics loss joins", [non_negative(), at_most(MAX_STEPS)]
    )
    alone_from: int | None = param(
        None,
        "real steps from which the model trains on the physics loss alone, before it has labels (normalisation "
        "from the equation); none: only with labels",
        [non_negative(), at_most(MAX_STEPS)],
    )


def _ranges_ok(value: dict) -> bool:
    for name, bounds in value.items():
        if not isinstance(name, str) or not name or name == "correction":
            return False
        if bounds is not None and not (
            isinstance(bounds, (list, tuple))
            and len(bounds) == 2
            and all(isinstance(b, (int, float)) and not isinstance(b, bool) and math.isfinite(b) for b in bounds)
            and bounds[0] < bounds[1]
        ):
            return False
    return True


@dataclass(frozen=True)
class CoefficientFit:
    """Physical coefficients of the prior fitted to the labelled transitions (and a learned linear correction)."""

    coefficients: dict[str, Any] = param(
        {},
        "coefficients fitted from the prior's values: name -> null (free) or [low, high]; on the command line nu,damping:0:1",
        (_ranges_ok, "must be a mapping of coefficient names to null or [low, high] with low < high"),
    )
    correction: bool = _pde_param(False, "also learn a linear correction for what no coefficient expresses")
    lr: float = param(1e-2, "Adam learning rate of the learned coefficients", [positive(), at_most(MAX_LR)])
    correction_penalty: float = _pde_param(1e-6, "weight of the learned correction's size", [non_negative(), at_most(1e6)])

    def ranges(self) -> dict[str, tuple[float, float] | None]:
        """``{name: (low, high) or None}``, with ``"correction": None`` where the correction is learned."""
        out: dict[str, tuple[float, float] | None] = {
            name: None if b is None else (float(b[0]), float(b[1])) for name, b in self.coefficients.items()
        }
        if self.correction:
            out["correction"] = None
        return out

    def __bool__(self) -> bool:
        return bool(self.coefficients) or self.correction


@dataclass(frozen=True)
class Identification:
    """Under partial physics, the coefficients of ``learn`` fitted to real transitions before control starts."""

    steps: int = param(
        2_000,
        "real transitions (uniformly random actions, from training resets) to fit the coefficients to",
        [positive(), at_most(MAX_STEPS)],
    )
    iterations: int = param(2_000, "Adam steps of the coefficient fit", [positive(), at_most(1_000_000)])
    batch_size: int = param(256, "transitions per Adam step", [positive(), at_most(MAX_BATCH)])


#: the sections a method may have, and the class of each
SECTIONS: dict[str, type] = {
    "fit": ModelFit,
    "check": AccuracyCheck,
    "imagine": Imagination,
    "finetune": Finetune,
    "physics": PhysicsLoss,
    "learn": CoefficientFit,
    "identify": Identification,
}


# ----------------------------------------------------------------------------- the methods
def _section(cls: type, help: str) -> Any:
    """A method's field holding one of :data:`SECTIONS` (addressed as ``section.field``)."""
    name = next(key for key, value in SECTIONS.items() if value is cls)
    return dataclasses.field(default_factory=cls, metadata={"help": help, "section": True, "prefix": name})


def _prior_ok(value: dict) -> bool:
    return all(
        isinstance(k, str) and k and isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
        for k, x in value.items()
    )


def _prior() -> Any:
    return param(
        {},
        "coefficients of the model's physics where the run believes other values than the environment's: "
        "name -> value (a wrong prior; on the command line nu=0.007); empty: the environment's own",
        (_prior_ok, "must be a mapping of coefficient names to finite numbers"),
    )


def _start_after() -> Any:
    return param(
        6_000, "n_sM: real transitions before the model is first fitted and checked", [non_negative(), at_most(MAX_STEPS)]
    )


def _n_intermediate() -> Any:
    return _pde_param(5, "intermediate states per control step (N)", [positive(), at_most(1_000)])


def _scheme() -> Any:
    return _pde_param(
        "etd", "the prior's coarse scheme: etd (the paper's residual) or solver (the simulator's)", one_of("etd", "solver")
    )


@dataclass(frozen=True)
class MFRL:
    """Model-free RL: the agent on real transitions only."""

    name: ClassVar[str] = "mfrl"
    model_kind: ClassVar[str | None] = None


@dataclass(frozen=True)
class MBRL:
    """Dyna with a network trained on the data loss alone (the paper's MBRL)."""

    name: ClassVar[str] = "mbrl"
    network: str = param(
        "auto",
        "the network: convlstm (the paper's) or equivariant for a PDE, mlp for an ODE; auto: the paper's",
        one_of(*NETWORKS),
    )
    n_intermediate: int = _n_intermediate()
    start_after: int = _start_after()
    prior: dict[str, float] = _prior()
    fit: ModelFit = _section(ModelFit, "the model's gradient steps")
    check: AccuracyCheck = _section(AccuracyCheck, "when the model is trusted")
    imagine: Imagination = _section(Imagination, "imagined rollouts and batches")
    finetune: Finetune = _section(Finetune, "the switch to model-free fine-tuning")

    @property
    def model_kind(self) -> str:
        """The kind of transition model (:func:`pimbrl.models.make_model`): the network."""
        return self.network


@dataclass(frozen=True)
class PiMBRL(MBRL):
    """The paper's method: the network trained on the data loss and the physics loss."""

    name: ClassVar[str] = "pimbrl"
    scheme: str = _scheme()
    physics: PhysicsLoss = _section(PhysicsLoss, "the physics loss")
    learn: CoefficientFit = _section(CoefficientFit, "coefficients fitted to the labels")


@dataclass(frozen=True)
class KnownScheme:
    """Dyna with the prior's coarse scheme as the model: no network, nothing trained."""

    name: ClassVar[str] = "known-scheme"
    model_kind: ClassVar[str] = "physics"
    n_intermediate: int = _n_intermediate()
    start_after: int = _start_after()
    prior: dict[str, float] = _prior()
    scheme: str = _scheme()
    check: AccuracyCheck = _section(AccuracyCheck, "when the model is trusted")
    imagine: Imagination = _section(Imagination, "imagined rollouts and batches")
    finetune: Finetune = _section(Finetune, "the switch to model-free fine-tuning")


@dataclass(frozen=True)
class IdentifiedScheme(KnownScheme):
    """The prior's coarse scheme with coefficients fitted to the labels (``learn``), as the model."""

    name: ClassVar[str] = "identified-scheme"
    fit: ModelFit = _section(ModelFit, "the coefficients' gradient steps")
    learn: CoefficientFit = _section(CoefficientFit, "coefficients fitted to the labels (at least one)")


@dataclass(frozen=True)
class Hybrid(KnownScheme):
    """The prior's coarse scheme plus a correction network that starts at zero, trained on the data loss."""

    name: ClassVar[str] = "hybrid"
    model_kind: ClassVar[str] = "hybrid"
    correction_scale: float = param(
        0.01, "the correction network's scale, relative to the increments' standard deviation", [positive(), at_most(1e3)]
    )
    fit: ModelFit = _section(ModelFit, "the correction's gradient steps")


@dataclass(frozen=True)
class PiHybrid(Hybrid):
    """:class:`Hybrid` with the physics loss (the correction's own defect) and learned coefficients."""

    name: ClassVar[str] = "pihybrid"
    physics: PhysicsLoss = _section(PhysicsLoss, "the physics loss")
    learn: CoefficientFit = _section(CoefficientFit, "coefficients fitted to the labels")


# ----------------------------------------------------------------------------- control that knows the physics
def _validation_episodes() -> Any:
    return param(
        20,
        "validation episodes that choose among settings (the test states decide nothing; KS: at most 50)",
        [positive(), at_most(MAX_BATCH)],
    )


def _gains_ok(value: tuple[float, ...]) -> bool:
    return all(isinstance(g, (int, float)) and not isinstance(g, bool) and math.isfinite(g) and g >= 0 for g in value)


@dataclass(frozen=True)
class Feedback:
    """A feedback floor (:mod:`pimbrl.control.feedback`): no learning, one gain chosen on the validation draws."""

    name: ClassVar[str] = "feedback"
    model_kind: ClassVar[str | None] = None
    kind: str = param(
        "auto",
        "the controller: proportional (PDEs), lqr, energy-lqr (the pendulum); auto: the one the system declares",
        one_of("auto", *FEEDBACK_KINDS),
    )
    gains: tuple[float, ...] = param(
        (),
        "gains tried on the validation draws; empty: the system's (or the kind's default grid)",
        (_gains_ok, "must be finite numbers >= 0"),
    )
    validation_episodes: int = _validation_episodes()


def _control_prior() -> Any:
    return param(
        {},
        "coefficients the controller believes where they differ from the environment's: name -> value (a wrong "
        "prior; on the command line convection=1.3); empty: the environment's own (known physics)",
        (_prior_ok, "must be a mapping of coefficient names to finite numbers"),
    )


@dataclass(frozen=True)
class MPC:
    """Model-predictive control by gradient through the prior's coarse scheme (:mod:`pimbrl.control.mpc`)."""

    name: ClassVar[str] = "mpc"
    model_kind: ClassVar[str | None] = None
    horizon: int = param(20, "control steps planned ahead", [positive(), at_most(10_000)])
    iterations: int = param(5, "Adam steps on the plan per control step (warm-started)", [positive(), at_most(100_000)])
    first_iterations: int = param(
        30, "Adam steps at an episode's first control step (from a zero plan)", [positive(), at_most(100_000)]
    )
    lr: float = param(0.1, "Adam learning rate on the plan (normalised action units)", [positive(), at_most(MAX_LR)])
    n_intermediate: int = _pde_param(
        5, "ETDRK4 steps of the coarse scheme per control step (KS: 1 suffices)", [positive(), at_most(1_000)]
    )
    batch: int = param(200, "test episodes planned at once (and per resumable chunk)", [positive(), at_most(MAX_BATCH)])
    prior: dict[str, float] = _control_prior()
    learn: CoefficientFit = _section(CoefficientFit, "coefficients identified from real transitions first")
    identify: Identification = _section(Identification, "the real transitions and the fit that identify them")


@dataclass(frozen=True)
class DPC:
    """Differentiable predictive control: a policy network trained through the coarse scheme (:mod:`pimbrl.control.dpc`)."""

    name: ClassVar[str] = "dpc"
    model_kind: ClassVar[str | None] = None
    horizon: int = param(20, "control steps back-propagated through per rollout", [positive(), at_most(10_000)])
    iterations: int = param(3_000, "gradient steps of the policy", [positive(), at_most(10_000_000)])
    batch_size: int = param(64, "rollouts per gradient step", [positive(), at_most(MAX_BATCH)])
    lr: float = param(1e-3, "Adam learning rate of the policy", [positive(), at_most(MAX_LR)])
    hidden: tuple[int, ...] = param(
        (256, 256),
        "hidden layer sizes of the policy",
        (lambda v: 0 < len(v) <= 16 and all(0 < h <= 4_096 for h in v), "must be 1 to 16 layer sizes in [1, 4,096]"),
    )
    continue_fraction: float = param(
        0.5, "fraction of rollouts continuing from states earlier rollouts reached (the rest: fresh resets)", in_range(0.0, 1.0)
    )
    validate_every: int = param(
        250, "gradient steps between validation episodes (the best policy is kept)", [positive(), at_most(10_000_000)]
    )
    validation_episodes: int = _validation_episodes()
    n_intermediate: int = _pde_param(
        5, "ETDRK4 steps of the coarse scheme per control step (KS: 1 suffices)", [positive(), at_most(1_000)]
    )
    prior: dict[str, float] = _control_prior()
    learn: CoefficientFit = _section(CoefficientFit, "coefficients identified from real transitions first")
    identify: Identification = _section(Identification, "the real transitions and the fit that identify them")


#: a control method's configuration (no agent, no replay: :mod:`pimbrl.control`)
ControlMethod = Feedback | MPC | DPC
CONTROL_TYPES = (Feedback, MPC, DPC)

#: a method's configuration
Method = MFRL | MBRL | PiMBRL | KnownScheme | IdentifiedScheme | Hybrid | PiHybrid | Feedback | MPC | DPC
#: the configuration of a method with a model (every one but MFRL)
DynaMethod = MBRL | PiMBRL | KnownScheme | IdentifiedScheme | Hybrid | PiHybrid
#: every method by name, in the order the help lists them
METHOD_TYPES: dict[str, type] = {
    cls.name: cls for cls in (MFRL, MBRL, PiMBRL, KnownScheme, IdentifiedScheme, Hybrid, PiHybrid, Feedback, MPC, DPC)
}
#: the methods of :mod:`pimbrl.control`: they train no agent
CONTROL_METHODS = tuple(cls.name for cls in CONTROL_TYPES)
METHODS = tuple(METHOD_TYPES)


def methods_with(path: str) -> list[str]:
    """The methods whose type has the setting ``path`` (``"physics.weight"``, ``"model.network"``)."""
    head, _, name = path.partition(".")
    out = []
    for method, cls in METHOD_TYPES.items():
        fields = {f.name: f for f in dataclasses.fields(cls)}
        own = head == "model" and name in fields and not fields[name].metadata.get("section")
        in_section = head in SECTIONS and head in fields and name in {f.name for f in dataclasses.fields(SECTIONS[head])}
        if own or in_section:
            out.append(method)
    return out
