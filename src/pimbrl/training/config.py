"""Training configuration: one typed dataclass, per-environment presets from the paper, overrides.

``resolve_config(env, overrides)`` starts from the defaults, applies the environment's preset
(docs/methods.md, section 'Presets', and the paper's Table 2), then the user's overrides, and validates
every field.

Overrides are typed: ``{"utd": 5.0, "agent.gamma": 0.98, "dyna.rollout_length": 7}``, each value checked
against its field's type (a float for an int field is an error, not truncated). An override that does
nothing for the chosen method, agent or environment (``dyna.*`` with mfrl, SAC's temperature with TD3,
...) is an error that says why; :func:`inapplicable_reason` is that rule.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import importlib
import inspect
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..agents.config import AGENT_NAMES, AgentConfig
from ..config import (
    MAX_BATCH,
    MAX_LR,
    MAX_SEED,
    MAX_STEPS,
    MAX_TRANSITIONS,
    MODEL_KINDS,
    PHYSICS_MODEL_KINDS,
    ConfigError,
    at_most,
    check_env_id,
    field_type,
    from_dict,
    in_range,
    non_negative,
    one_of,
    param,
    parse_learned,
    parse_prior,
    positive,
    typed_value,
    validate,
)

__all__ = [
    "EXTERNAL_PRESETS",
    "METHODS",
    "POLICIES",
    "DynaConfig",
    "TrainConfig",
    "changed_env_kwargs",
    "check_env_kwargs",
    "check_tensorboard",
    "config_from_dict",
    "did_you_mean",
    "field_paths",
    "inapplicable_reason",
    "is_pde_env",
    "load_config_file",
    "preset_of",
    "resolve_config",
    "return_scale_warnings",
    "typed_overrides",
]

METHODS = ("mfrl", "mbrl", "pimbrl")
MODEL_BASED = ("mbrl", "pimbrl")


#: the policies of a run that can be evaluated: the checkpoint's latest, or the one policy selection kept
POLICIES = ("latest", "selected")


@dataclass(frozen=True)
class DynaConfig:
    """Settings of the model-based methods (mbrl, pimbrl): the model, its training and its use.

    Defaults follow the paper's Table 2 where the paper gives a value (lambda, l_M, n_sM, n_sR); presets
    per environment override them (see preset_of and docs/methods.md for every change and why).
    """

    threshold: float = param(1e-2, "lambda: held-out next-state MSE below which the model generates imagined data", positive())
    rollout_length: int = param(3, "l_M: chained model steps per imagined rollout", [positive(), at_most(10_000)])
    start_model_after: int = param(
        6_000, "n_sM: real transitions before the model is first trained", [non_negative(), at_most(MAX_STEPS)]
    )
    start_physics_after: int = param(
        12_000, "n_sR: real + imagined transitions before the physics loss joins (pimbrl)", [non_negative(), at_most(MAX_STEPS)]
    )
    model_steps: int = param(50, "model gradient steps per update phase", [non_negative(), at_most(1_000_000)])
    model_batch_size: int = param(256, "batch size of the data loss and of the physics loss", [positive(), at_most(MAX_BATCH)])
    model_lr: float = param(1e-3, "model learning rate (Adam)", [positive(), at_most(MAX_LR)])
    n_intermediate: int = param(5, "PDE models: intermediate states per control step (N)", [positive(), at_most(1_000)])
    residual: str = param("etd", "physics residual scheme for PDEs: etd or solver", one_of("etd", "solver"))
    physics_weight: float = param(1.0, "w_E: weight of the physics loss", [non_negative(), at_most(1e6)])
    rollouts: int = param(200, "imagined rollouts started per update phase (n_bf)", [non_negative(), at_most(1_000_000)])
    imagined_buffer_size: int = param(
        100_000, "capacity of the imagined buffer; older imagined data is refreshed", [positive(), at_most(MAX_TRANSITIONS)]
    )
    imagined_start_fraction: float = param(
        0.0, "fraction of rollout start states drawn from the imagined buffer", in_range(0.0, 1.0)
    )
    reset_start_fraction: float = param(
        0.0,
        "fraction of rollout start states drawn as the environment's resets draw them (its initial-state "
        "distribution; KS: the training pool), at episode step 0: imagined episodes from starts the real "
        "buffer may not hold (with imagined_start_fraction at most 1 in all)",
        in_range(0.0, 1.0),
    )
    reset_start_symmetry: bool = param(
        False,
        "reset starts from images of the sampled initial states under the equation's symmetries (a random "
        "circular shift and, half of the time, the reflection u(x) -> -u(-x)): many more distinct starts than "
        "the pool holds, for initial-state distributions that share the symmetries (KS: snapshots of its "
        "chaotic attractor); PDEs only, with reset_start_fraction > 0",
    )
    select_episodes: int = param(
        0,
        "policy selection in the model: at every evaluation, run the deterministic policy for this many whole "
        "episodes in the model from validation initial states and keep the policy with the best imagined return "
        "(selection.csv; `pimbrl eval --policy selected`; 0: off)",
        [non_negative(), at_most(10_000)],
    )
    real_ratio: float = param(0.5, "fraction of real transitions in agent batches while the model is in use", in_range(0.0, 1.0))
    holdout_fraction: float = param(
        0.1, "fraction of real transitions held out to measure the model's accuracy", in_range(0.0, 0.5, lo_open=True)
    )
    validation_size: int = param(
        2_000, "most recent held-out transitions used for the accuracy check", [positive(), at_most(MAX_TRANSITIONS)]
    )
    finetune_return: float | None = param(
        None,
        "switch to model-free fine-tuning once the mean return on the validation draws reaches this (the test states "
        "decide nothing)",
    )
    finetune_episodes: int = param(
        20,
        "validation episodes the fine-tuning switch evaluates at each evaluation while it waits (KS: at most the "
        "validation pool's 50)",
        [positive(), at_most(MAX_BATCH)],
    )
    finetune_after: int | None = param(
        None, "switch to model-free fine-tuning after this many real steps", [non_negative(), at_most(MAX_STEPS)]
    )
    accuracy: str = param(
        "absolute",
        "accuracy check: absolute (held-out MSE < threshold, the paper's lambda) or relative (held-out MSE < "
        "relative_threshold x the MSE of predicting no change on the same transitions)",
        one_of("absolute", "relative"),
    )
    relative_threshold: float = param(
        0.1, "accuracy=relative: the model is used below this fraction of the no-change error", in_range(0.0, 1.0, lo_open=True)
    )
    model: str = param(
        "convlstm",
        "the model: convlstm (the paper's, PDEs) or equivariant (fully convolutional, PDEs) -- the ODEs' is an "
        "MLP, recorded as mlp -- or, for any system, the prior's coarse scheme itself: physics (no network) or hybrid "
        "(the scheme plus a correction network that starts at zero; pimbrl.models.hybrid)",
        one_of(*MODEL_KINDS),
    )
    correction_scale: float = param(
        0.01,
        "model=hybrid: the correction network's scale, relative to the increments' standard deviation",
        [positive(), at_most(1e3)],
    )
    physics_sources: str = param(
        "auto",
        "pimbrl: state-action pairs of the physics loss, comma-separated: policy, imagined (the loop's), "
        "symmetry, scaled, noise (PDEs), box (ODEs); auto: all the physics offers (pimbrl.models.state_sources)",
    )
    residual_units: str = param(
        "step",
        "pimbrl: units of the physics loss: substep (per sub-step increment) or step (x N^2)",
        one_of("substep", "step"),
    )
    physics_start: int | None = param(
        None,
        "pimbrl: real steps after which the model trains on the physics loss alone (before start_model_after; "
        "normalisation from the equation), so it can be checked and used before it has labels",
        [non_negative(), at_most(MAX_STEPS)],
    )
    physics_prior: str = param(
        "",
        "mbrl and pimbrl: physical coefficients of the model's physics that differ from the environment's, "
        "name=value comma-separated (e.g. nu=0.007): a prior that is wrong (docs/partial-physics.md); empty: "
        "the environment's own",
    )
    learn_coefficients: str = param(
        "",
        "pimbrl: coefficients of the physics loss fitted to the labelled transitions, comma-separated, "
        "each name or name:low:high (e.g. nu or damping:0:1), starting from the prior's values; 'correction' (PDEs) "
        "adds a learned linear correction for what no coefficient expresses",
    )
    correction_penalty: float = param(
        1e-6,
        "pimbrl: weight of the learned correction's size (sum of its squared scaled coefficients)",
        [non_negative(), at_most(1e6)],
    )
    coefficient_lr: float = param(1e-2, "pimbrl: Adam learning rate of the learned coefficients", [positive(), at_most(MAX_LR)])
    reward_quadrature: str = param(
        "path",
        "PDEs: imagined rewards from the model's intermediate states (path) or from the step's two endpoints "
        "(endpoints: the same rule whether the intermediate states were trained or not)",
        one_of("path", "endpoints"),
    )


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (saved as ``config.json`` in the run directory)."""

    env: str = param("pimbrl/Pendulum-v0", "environment id (pimbrl/... or any Gymnasium id)")
    method: str = param("mfrl", "mfrl (model-free), mbrl (data-only model), pimbrl (physics-informed model)", one_of(*METHODS))
    agent: str = param("td3", "off-policy agent", one_of(*AGENT_NAMES))
    seed: int = param(0, "seeds networks, exploration, replay sampling and the environment", [non_negative(), at_most(MAX_SEED)])
    total_steps: int = param(15_000, "real environment steps", [positive(), at_most(MAX_STEPS)])
    warmup_steps: int = param(1_000, "initial steps with uniformly random actions", [non_negative(), at_most(MAX_STEPS)])
    update_after: int = param(1_000, "real steps collected before the first agent update", [non_negative(), at_most(MAX_STEPS)])
    update_every: int = param(50, "real steps between update phases (the paper's update_every)", [positive(), at_most(MAX_STEPS)])
    utd: float = param(
        1.0, "agent updates per real step (update-to-data ratio); the paper: 50 per 50 steps", [positive(), at_most(1_000)]
    )
    buffer_size: int = param(
        1_000_000, "capacity of the real replay buffer (its memory is checked too)", [positive(), at_most(MAX_TRANSITIONS)]
    )
    eval_every: int = param(1_000, "real steps between evaluations", [positive(), at_most(MAX_STEPS)])
    eval_episodes: int = param(100, "test episodes per evaluation (the paper: 100; 200 for KS)", [positive(), at_most(10_000)])
    eval_seed: int = param(
        2021, "seed of the held-out test initial states (KS uses its test pool)", [non_negative(), at_most(MAX_SEED)]
    )
    threshold: float | None = param(None, "evaluation return that counts as solved (steps-to-threshold)")
    checkpoint_every: int = param(
        5_000, "real steps between checkpoints (taken at the next episode end)", [positive(), at_most(MAX_STEPS)]
    )
    log_every: int = param(1_000, "real steps between rows of metrics.csv", [positive(), at_most(MAX_STEPS)])
    lr_decay_after: int | None = param(
        None,
        "real step after which the actor and critic learning rates fall linearly, to lr_decay_to times their "
        "value at total_steps (none: constant, the paper's; a resume that changes total_steps changes the slope)",
        [non_negative(), at_most(MAX_STEPS)],
    )
    lr_decay_to: float = param(0.1, "with lr_decay_after: the learning rates' final fraction of their value", in_range(0.0, 1.0))
    threads: int = param(1, "torch threads for this run", in_range(1, 256))
    tensorboard: bool = param(False, "also write TensorBoard events (needs the tensorboard package)")
    env_kwargs: dict = dataclasses.field(
        default_factory=dict, metadata={"help": "keyword arguments for gymnasium.make", "check": None}
    )
    agent_config: AgentConfig = dataclasses.field(
        default_factory=AgentConfig, metadata={"help": "agent hyperparameters (flags --agent.<name>)", "prefix": "agent"}
    )
    dyna: DynaConfig = dataclasses.field(
        default_factory=DynaConfig, metadata={"help": "model-based settings (flags --dyna.<name>)", "prefix": "dyna"}
    )


#: presets of Gymnasium environments that are not pimbrl systems (for model-free comparisons)
EXTERNAL_PRESETS: dict[str, dict[str, Any]] = {
    "Pendulum-v1": {"total_steps": 15_000, "warmup_steps": 1_000, "update_after": 1_000, "eval_every": 500, "threshold": -200.0},
}


def preset_of(env: str) -> dict[str, Any]:
    """The training preset of ``env``: its system's (:attr:`pimbrl.systems.System.preset`), else ``{}``.

    The model-free part applies to every method; its ``model_based`` section on top for mbrl and pimbrl.
    A system declares it once (the built-in ones: the paper's TD3 table and Table 2, with the changes
    listed in docs/methods.md). All methods of one environment share budget and warm-up.
    """
    from ..systems import get_system

    system = get_system(env)
    if system is not None:
        return copy.deepcopy(dict(system.preset))
    return copy.deepcopy(EXTERNAL_PRESETS.get(env, {}))


#: agent fields that only some agents read (checked against agents/td3.py and agents/sac.py)
SAC_ONLY = ("init_alpha", "autotune_alpha", "alpha_lr", "target_entropy")
TD3_ONLY = ("policy_delay", "target_smoothing", "target_noise", "noise_clip")  # DDPG: no delay, no smoothing
NOISE_EXPLORATION = ("exploration_noise", "preactivation_penalty")  # TD3, DDPG; SAC samples its stochastic policy
#: dyna fields that only the physics loss reads (pimbrl) and only the PDE models read. start_physics_after
#: is read by pimbrl only too, but the shared smoke settings of the tests give it to mbrl runs: not checked
PIMBRL_ONLY = (
    "physics_weight",
    "residual",
    "start_physics_after",
    "physics_sources",
    "residual_units",
    "physics_start",
    "learn_coefficients",
    "coefficient_lr",
    "correction_penalty",
)
PDE_ONLY = (
    "n_intermediate",
    "residual",
    "reward_quadrature",
    "correction_penalty",
)


def _flag(path: str) -> str:
    head, _, name = path.rpartition(".")
    return f"--{head + '.' if head else ''}{name.replace('_', '-')}"


def _entry_point(env: str) -> Any:
    """The class (or factory) a Gymnasium id makes, imported (``None`` if the id or its module is unknown)."""
    import gymnasium as gym

    try:
        entry = gym.spec(env).entry_point
    except gym.error.Error:
        return None
    if isinstance(entry, str):
        module, _, name = entry.partition(":")
        try:
            entry = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError):
            return None
    return entry


def _task_class(env: str) -> Any:
    """The task class of a pimbrl environment id (``None`` for any other Gymnasium id)."""
    return getattr(_entry_point(env), "task_class", None)


@functools.cache
def is_pde_env(env: str) -> bool:
    """Whether ``env`` is a pimbrl environment whose physics is a PDE.

    That is a system whose state is a field on a periodic grid (:attr:`pimbrl.physics.Physics.is_field`:
    Burgers, Kuramoto-Sivashinsky, a declared PDE); ``False`` for the ODE systems and any other Gymnasium id.
    """
    task_class = _task_class(env)
    return task_class is not None and bool(task_class().physics.is_field)  # built without simulating


def inapplicable_reason(env: str, method: str, agent: str, path: str) -> str | None:
    """Why the field ``path`` does nothing for a run of ``method`` with ``agent`` on ``env``.

    ``path`` is a dotted field path (``"dyna.rollout_length"``, ``"agent.init_alpha"``, ...). Returns
    ``None`` where the field applies.
    """
    section, _, name = path.rpartition(".")
    flag = _flag(path)
    if section == "dyna":
        if method not in MODEL_BASED:
            return f"{flag} applies to the model-based methods mbrl and pimbrl, not {method}"
        if name in PIMBRL_ONLY and method != "pimbrl":
            return f"{flag} applies to pimbrl (it sets the physics loss, which mbrl does not have), not {method}"
        if name in PDE_ONLY and not is_pde_env(env):
            return (
                f"{flag} applies to the PDE systems (Burgers, Kuramoto-Sivashinsky, a declared PDE), not {env}: "
                "an ODE system's model is an MLP that predicts one state per solver step"
            )
    elif section == "agent":
        if name in SAC_ONLY and agent != "sac":
            return f"{flag} applies to the agent sac (its entropy temperature), not {agent}"
        if name in TD3_ONLY and agent != "td3":
            return f"{flag} applies to the agent td3 (delayed policy updates, target smoothing), not {agent}"
        if name in NOISE_EXPLORATION and agent == "sac":
            return f"{flag} applies to the agents td3 and ddpg; sac explores by sampling its stochastic policy"
    return None


def did_you_mean(word: str, candidates: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the candidate closest to ``word``, or ``""`` where none is close."""
    close = difflib.get_close_matches(word, list(candidates), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def field_paths() -> list[str]:
    """Every field path an override can set: ``utd``, ``agent.gamma``, ``dyna.rollout_length``, ..."""
    paths = [f.name for f in dataclasses.fields(TrainConfig) if f.name not in ("agent_config", "dyna")]
    paths += [f"agent.{f.name}" for f in dataclasses.fields(AgentConfig)]
    paths += [f"dyna.{f.name}" for f in dataclasses.fields(DynaConfig)]
    return paths


def check_tensorboard() -> None:
    """Raise :class:`ConfigError` where TensorBoard events cannot be written (no tensorboard package).

    Checked when a configuration with ``tensorboard = true`` is resolved, before a run directory exists.
    """
    try:
        import torch.utils.tensorboard  # noqa: F401
    except ImportError:
        raise ConfigError(
            "tensorboard = true needs the tensorboard package: pip install 'pimbrl[tensorboard]' "
            "(or pip install tensorboard), or leave --tensorboard out"
        ) from None


def _env_keywords(env: str) -> tuple[list[inspect.Parameter], dict[str, float]] | None:
    """What the environment ``env`` takes as keyword arguments, ``None`` where that cannot be read.

    The parameters of its class (of its task, for pimbrl environments) and, for a task taking
    ``**coefficients``, its physics' coefficients with their values (the defaults).
    """
    entry = _entry_point(env)
    if entry is None:
        return None
    try:
        task_class = getattr(entry, "task_class", None)
        params = list(inspect.signature(task_class or entry).parameters.values())
        coefficients: dict[str, float] = {}
        if task_class is not None and any(p.kind is p.VAR_KEYWORD for p in params):
            coefficients = task_class().physics.coefficient_values()  # a task's physics is built without simulating
    except (AttributeError, TypeError, ValueError):
        return None
    return params, coefficients


def check_env_kwargs(env: str, kwargs: Mapping[str, Any]) -> None:
    """Raise :class:`ConfigError` for a keyword argument that the environment ``env`` does not take.

    The names are read from the signature of the environment's class (of its task, for pimbrl
    environments); a pimbrl task's ``**coefficients`` stand for the names of its physics'
    :attr:`~pimbrl.physics.Physics.coefficients`. Any other environment that takes ``**kwargs``, or one that
    cannot be inspected, is not checked.
    """
    found = _env_keywords(env) if kwargs else None
    if found is None:
        return
    params, coefficients = found
    if not coefficients and any(p.kind is p.VAR_KEYWORD for p in params):
        return
    names = [p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name != "self"]
    names += [name for name in coefficients if name not in names]
    for key in kwargs:
        if key not in names:
            takes = ", ".join(names) if names else "none"
            raise ConfigError(f"env_kwargs: {env} takes no keyword argument {key!r}{did_you_mean(key, names)}; it takes: {takes}")


def changed_env_kwargs(env: str, kwargs: Mapping[str, Any]) -> list[str]:
    """The names in ``kwargs`` whose value differs from the environment's registered default.

    Defaults are read from the environment's class (of its task, for pimbrl environments, whose physical
    coefficients default to its physics' :meth:`~pimbrl.physics.Physics.coefficient_values`); a name whose
    default cannot be read counts as changed.
    """
    found = _env_keywords(env) if kwargs else None
    defaults: dict[str, Any] = {}
    if found is not None:
        params, coefficients = found
        defaults = {p.name: p.default for p in params if p.default is not inspect.Parameter.empty}
        defaults.update(coefficients)
    return [name for name, value in kwargs.items() if name not in defaults or defaults[name] != value]


def return_scale_warnings(cfg: TrainConfig) -> list[str]:
    """Preset settings measured in test returns, kept for an environment the run changes.

    A preset's ``threshold`` (steps-to-threshold; KS: -55) and, for the model-based methods, its
    ``dyna.finetune_return`` (the switch to model-free fine-tuning; KS: -55) were set on the return scale
    of the environment as registered. ``env_kwargs`` that change it (other coefficients such as
    ``convection``, an actuator width, another reward or initial-state pool) may change that scale, so the
    switch can fire at once or never, and steps to the threshold measure something else. One line per such
    setting, with the flag to set, when the run keeps the preset's value (a value given equal to the
    preset's cannot be told apart, and is warned about too); nothing when the keyword arguments only
    repeat the registered defaults.
    """
    preset = preset_of(cfg.env)
    kept = []  # (name, value, what it does, how to fix it)
    if preset.get("threshold") is not None and cfg.threshold == preset["threshold"]:
        role = "counts a run as solved (steps to threshold)"
        kept.append(("threshold", cfg.threshold, role, "give --threshold for this system"))
    finetune = preset.get("model_based", {}).get("dyna", {}).get("finetune_return")
    if cfg.method in MODEL_BASED and finetune is not None and cfg.dyna.finetune_return == finetune:
        fix = (
            "give --dyna.finetune-return for this system, or --dyna.finetune-return none never to switch (the model stays in use)"
        )
        kept.append(("dyna.finetune_return", finetune, "switches to model-free fine-tuning", fix))
    changed = changed_env_kwargs(cfg.env, cfg.env_kwargs) if kept else []
    if not changed:
        return []
    return [
        f"{name} = {value:g} (the preset's) {role} at that test return, a value set for {cfg.env} as registered; "
        f"--env-kwargs change {', '.join(changed)}, which may change the scale of the returns: {fix}"
        for name, value, role, fix in kept
    ]


def _check_choice(name: str, value: Any, choices: Sequence[str]) -> None:
    if isinstance(value, str) and value not in choices:
        raise ConfigError(f"{name} must be one of {', '.join(map(repr, choices))}, got {value!r}{did_you_mean(value, choices)}")


def applicable_overrides(
    env: str, method: str, agent: str, overrides: Mapping[str, Any], reasons: dict[str, str] | None = None
) -> dict[str, Any]:
    """The ``overrides`` that apply to a run of ``method`` with ``agent`` on ``env``.

    For each one left out, the reason is recorded in ``reasons`` (first reason per field), so that a
    caller applying shared overrides to several runs can report those that apply to none.
    """
    kept: dict[str, Any] = {}
    for key, value in overrides.items():
        reason = inapplicable_reason(env, method, agent, key)
        if reason is None:
            kept[key] = value
        elif reasons is not None:
            reasons.setdefault(key, reason)
    return kept


def typed_overrides(overrides: Mapping[str, Any]) -> dict[str, Any]:
    """``overrides`` (dotted field paths -> values), checked and typed.

    Every path is checked to be a field of :class:`TrainConfig` and every value against that field's
    type (:func:`pimbrl.config.typed_value`).
    """
    out = {}
    for path, value in overrides.items():
        if path == "env":
            raise ConfigError("env is not an override: it is given on its own (the first argument)")
        if path.startswith("agent_config."):
            path = "agent." + path[len("agent_config.") :]
        try:
            tp = field_type(TrainConfig, path)
        except ConfigError as exc:
            raise ConfigError(f"{exc}{did_you_mean(path, field_paths())}") from None
        out[path] = typed_value(tp, value, path)
    return out


def resolve_config(
    env: str,
    overrides: Mapping[str, Any] | None = None,
    agent_overrides: Mapping[str, Any] | None = None,
    dyna_overrides: Mapping[str, Any] | None = None,
) -> TrainConfig:
    """The run's configuration: defaults, then the preset of ``env``, then the overrides; validated.

    The preset contributes its model-free part, plus its model-based part for mbrl and pimbrl.

    ``overrides`` maps field paths to values: ``"utd"``, ``"agent.gamma"``, ``"dyna.rollout_length"``
    (``agent_overrides`` and ``dyna_overrides``, by field name, are the same as ``agent.``/``dyna.``
    paths). Values must have their field's type. An override that does not apply to the method, agent or
    environment of the run is a :class:`ConfigError` with the reason (:func:`inapplicable_reason`); the
    presets are not checked this way.
    """
    flat = dict(overrides or {})
    flat.update({f"agent.{k}": v for k, v in (agent_overrides or {}).items()})
    flat.update({f"dyna.{k}": v for k, v in (dyna_overrides or {}).items()})
    flat = typed_overrides(flat)
    method = flat.get("method", TrainConfig.method)
    agent = flat.get("agent", TrainConfig.agent)
    _check_choice("method", method, METHODS)
    _check_choice("agent", agent, AGENT_NAMES)
    if method in METHODS and agent in AGENT_NAMES:  # otherwise validation names the bad method or agent below
        for path in flat:
            reason = inapplicable_reason(env, method, agent, path)
            if reason is not None:
                raise ConfigError(reason)
    preset = preset_of(env)
    model_based = dict(preset.pop("model_based", {}))
    if method in MODEL_BASED:
        preset.update({k: v for k, v in model_based.items() if k not in ("agent_config", "dyna")})
        for key in ("agent_config", "dyna"):
            preset[key] = {**preset.get(key, {}), **model_based.get(key, {})}
    agent_fields = {**preset.pop("agent_config", {}), **{k[6:]: v for k, v in flat.items() if k.startswith("agent.")}}
    dyna_fields = {**preset.pop("dyna", {}), **{k[5:]: v for k, v in flat.items() if k.startswith("dyna.")}}
    fields = {**preset, **{k: v for k, v in flat.items() if "." not in k}, "env": env}
    try:
        agent_cfg = from_dict(AgentConfig, agent_fields)
        dyna_cfg = from_dict(DynaConfig, dyna_fields)
        cfg = from_dict(TrainConfig, fields)
    except TypeError as exc:
        raise ConfigError(str(exc)) from None
    cfg = record_ode_model(dataclasses.replace(cfg, agent_config=agent_cfg, dyna=dyna_cfg))
    validate(cfg)
    _check_runnable(cfg)
    return cfg


def record_ode_model(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` with the model fields of an ODE system's run set to what trains, so that config.json says so.

    A model-based run on a system whose state is not a field trains an MLP that emits one state per solver
    step (:func:`pimbrl.models.make_model`) checked by the solver's own step: ``dyna.model`` becomes
    ``mlp`` (``physics`` and ``hybrid`` stay), ``dyna.residual`` ``solver`` and ``dyna.n_intermediate`` the
    solver steps per control step. Other runs are returned unchanged.
    """
    if cfg.method not in MODEL_BASED or is_pde_env(cfg.env):
        return cfg
    task_class = _task_class(cfg.env)
    if task_class is None:  # an env known by its data only: an MLP predicting the next observation
        model = "mlp" if cfg.dyna.model == "convlstm" else cfg.dyna.model
        return dataclasses.replace(cfg, dyna=dataclasses.replace(cfg.dyna, model=model, n_intermediate=1))
    try:
        substeps = int(task_class(**cfg.env_kwargs).physics.substeps)
    except (TypeError, ValueError):  # bad keyword arguments: reported with their reason by _check_runnable
        return cfg
    model = "mlp" if cfg.dyna.model == "convlstm" else cfg.dyna.model
    return dataclasses.replace(cfg, dyna=dataclasses.replace(cfg.dyna, model=model, residual="solver", n_intermediate=substeps))


def preset_note(env: str) -> str | None:
    """A line for a run on an environment without a preset (generic defaults apply), ``None`` where it has one."""
    if preset_of(env):
        return None
    return (
        f"{env} has no preset: the generic defaults of every setting apply (see `pimbrl train {env} --print-config`); "
        "a system declares one with System.preset (docs/systems.md)"
    )


def _check_runnable(cfg: TrainConfig) -> None:
    """Check what validation of the fields cannot see.

    The environment's keyword arguments, TensorBoard, the physics-loss sources the environment offers.
    """
    check_env_kwargs(cfg.env, cfg.env_kwargs)
    check_lr_decay(cfg)
    if cfg.tensorboard:
        check_tensorboard()
    if cfg.method in MODEL_BASED and _task_class(cfg.env) is None:  # an env outside pimbrl: its data only
        if cfg.method == "pimbrl":
            raise ConfigError(
                f"pimbrl needs the system's equation, and {cfg.env} declares none: use --method mbrl (data-only: the "
                "observation as the state, the reward learned), or declare the system (docs/systems.md)"
            )
        check_observed(cfg)
    if cfg.method == "pimbrl":
        check_physics_sources(cfg.env, cfg.dyna.physics_sources)
    if cfg.method in MODEL_BASED:
        check_coefficients(cfg)
        check_model_kind(cfg)
        check_rollout_starts(cfg)


def check_observed(cfg: TrainConfig) -> None:
    """A clear :class:`ConfigError` for a data-only run on an env outside pimbrl that cannot be one.

    Such an env is known by its data only (:mod:`pimbrl.systems.observed`): Box spaces, no initial states to
    draw (no policy selection in the model), its own network (an MLP; no physics model).
    """
    import gymnasium as gym

    from ..systems.observed import ObservedTask

    try:
        ObservedTask(gym.make(cfg.env, **cfg.env_kwargs))
    except ValueError as exc:
        raise ConfigError(f"{cfg.env}: {exc}") from None
    if cfg.dyna.select_episodes:
        raise ConfigError(f"--dyna.select-episodes needs initial states to draw, and {cfg.env} draws its own at reset")
    if cfg.dyna.model in PHYSICS_MODEL_KINDS:
        raise ConfigError(f"--dyna.model {cfg.dyna.model} needs the system's equation, and {cfg.env} declares none")


def check_lr_decay(cfg: TrainConfig) -> None:
    """A clear :class:`ConfigError` for a learning-rate decay that cannot happen as asked."""
    if cfg.lr_decay_after is None:
        if cfg.lr_decay_to != TrainConfig().lr_decay_to:
            raise ConfigError("--lr-decay-to sets where the decay ends; give --lr-decay-after STEP too (the step it starts)")
        return
    if cfg.lr_decay_to == 1.0:
        raise ConfigError("--lr-decay-to 1 keeps the learning rates constant; give a fraction below 1, or drop --lr-decay-after")
    if cfg.lr_decay_after >= cfg.total_steps:
        raise ConfigError(
            f"--lr-decay-after {cfg.lr_decay_after:,} is not before --total-steps {cfg.total_steps:,}: the rates would "
            "never fall; give a step below total_steps, or drop --lr-decay-after"
        )


def check_model_kind(cfg: TrainConfig) -> None:
    """A clear :class:`ConfigError` for a model kind the system cannot have, or a setting it ignores."""
    d = cfg.dyna
    if d.model == "mlp" and is_pde_env(cfg.env):
        raise ConfigError(
            f"--dyna.model mlp is the ODE systems' network, not for the PDE {cfg.env}: use convlstm (the paper's), "
            "equivariant, physics or hybrid"
        )
    if d.model == "equivariant" and not is_pde_env(cfg.env):
        raise ConfigError(
            f"--dyna.model equivariant is a network on a PDE's grid, not for {cfg.env}: an ODE system's network "
            "is an MLP (the default), or use --dyna.model physics or hybrid"
        )
    if d.model != "hybrid" and d.correction_scale != DynaConfig().correction_scale:
        raise ConfigError(f"--dyna.correction-scale sets the hybrid model's correction; give --dyna.model hybrid (now {d.model})")


def check_rollout_starts(cfg: TrainConfig) -> None:
    """A clear :class:`ConfigError` for rollout starts that cannot be made.

    That is shares of the start states that exceed the whole, or symmetric reset starts without reset
    starts or on an ODE system.
    """
    d = cfg.dyna
    if d.reset_start_symmetry and d.reset_start_fraction == 0:
        raise ConfigError(
            "--dyna.reset-start-symmetry true acts on reset starts, and --dyna.reset-start-fraction is 0: "
            "give a fraction (e.g. 0.5) or drop the flag"
        )
    if d.reset_start_symmetry and not is_pde_env(cfg.env):
        raise ConfigError(f"--dyna.reset-start-symmetry needs a PDE on a periodic grid (shifts, reflection); {cfg.env} has none")
    if d.imagined_start_fraction + d.reset_start_fraction > 1.0:
        raise ConfigError(
            f"--dyna.imagined-start-fraction {d.imagined_start_fraction} and --dyna.reset-start-fraction "
            f"{d.reset_start_fraction} add up to more than 1: they are shares of the same rollout starts; lower one"
        )


def physics_coefficient_names(env: str) -> tuple[str, ...]:
    """The physical coefficients of a pimbrl environment's physics (``()`` for any other Gymnasium id)."""
    task_class = _task_class(env)
    return () if task_class is None else tuple(task_class().physics.coefficients)


def check_coefficients(cfg: TrainConfig) -> None:
    """A clear :class:`ConfigError` for a physics prior or learned coefficients that cannot work.

    Checked before anything runs: names, values (the prior is built), learned coefficients whose starting
    value would be the environment's true one (given in ``env_kwargs`` but not in the prior), the learning
    settings without anything learned, the residual scheme.
    """
    d = cfg.dyna
    prior = parse_prior(d.physics_prior)
    learned = parse_learned(d.learn_coefficients) if cfg.method == "pimbrl" else {}
    if cfg.method == "pimbrl" and not learned:
        defaults = DynaConfig()
        for name in ("coefficient_lr", "correction_penalty"):
            if getattr(d, name) != getattr(defaults, name):
                raise ConfigError(f"{_flag('dyna.' + name)} does nothing without --dyna.learn-coefficients")
    if learned and "correction" not in learned and d.correction_penalty != DynaConfig().correction_penalty:
        raise ConfigError("--dyna.correction-penalty does nothing without 'correction' in --dyna.learn-coefficients")
    if not prior and not learned:
        return
    names = physics_coefficient_names(cfg.env)
    if "correction" in learned and not is_pde_env(cfg.env):
        raise ConfigError(
            f"dyna.learn_coefficients: the learned correction is a linear operator on a PDE's grid (Burgers, "
            f"Kuramoto-Sivashinsky), not for {cfg.env}; name the coefficients to learn (its coefficients are: {', '.join(names)})"
        )
    for field, given in (("dyna.physics_prior", prior), ("dyna.learn_coefficients", learned)):
        allowed = (*names, "correction") if field == "dyna.learn_coefficients" else names
        bad = [name for name in given if name not in allowed]
        if bad:
            raise ConfigError(
                f"{field}: {cfg.env} has no coefficient {bad[0]!r}{did_you_mean(bad[0], names)}; "
                f"its coefficients are: {', '.join(names) or 'none'}"
            )
    if learned and is_pde_env(cfg.env) and d.residual != "etd":
        raise ConfigError("dyna.learn_coefficients needs the etd residual (--dyna.residual etd), not the solver's")
    leaked = [name for name in learned if name in cfg.env_kwargs and name not in prior]
    if leaked:
        raise ConfigError(
            f"dyna.learn_coefficients: {leaked[0]} would start from the environment's true value (given in "
            f"--env-kwargs); give the value the run believes with --dyna.physics-prior {leaked[0]}=..."
        )
    from ..models.coefficients import LearnedCoefficients  # builds the prior: values checked as the run will

    try:
        physics = _task_class(cfg.env)(**cfg.env_kwargs).physics.with_coefficients(**prior)
        if learned:
            LearnedCoefficients(physics, learned, penalty=d.correction_penalty)
    except ValueError as exc:
        raise ConfigError(f"physics prior: {exc}") from None


#: physics-loss sources by kind of system (what :func:`pimbrl.models.state_sources.available_sources`
#: gives for the PDEs and for the ODEs, without building the physics)
PDE_SOURCES = ("policy", "imagined", "symmetry", "scaled", "noise")
ODE_SOURCES = ("policy", "imagined", "box")


def check_physics_sources(env: str, text: str) -> None:
    """A clear :class:`ConfigError` for a ``dyna.physics_sources`` the environment does not offer."""
    if text == "auto":
        return
    have = PDE_SOURCES if is_pde_env(env) else ODE_SOURCES
    names = [name.strip() for name in text.split(",") if name.strip()]
    bad = [name for name in names if name not in have]
    if bad or not names:
        raise ConfigError(
            f"dyna.physics_sources: {', '.join(bad) or '(none)'} not available for {env}; choose from {', '.join(have)} or auto"
        )


def config_from_dict(data: Mapping[str, Any]) -> TrainConfig:
    """A :class:`TrainConfig` from a whole configuration as :func:`pimbrl.config.to_dict` writes it.

    That is the ``config`` of a run's ``config.json``, or the output of ``pimbrl train --print-config``.
    Every value is type-checked and the result validated. Missing fields take their defaults (not the
    presets).
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"a configuration must be a JSON object, got {type(data).__name__}")
    flat: dict[str, Any] = {}
    for key, value in data.items():
        nested = {"agent_config": "agent", "dyna": "dyna"}.get(key)
        if nested is None:
            flat[key] = value
        elif not isinstance(value, Mapping):
            raise ConfigError(f"{key} must be an object, got {value!r}")
        else:
            flat.update({f"{nested}.{k}": v for k, v in value.items()})
    env = check_env_id(flat.pop("env", TrainConfig.env), registered=True)  # never imports a module named here
    flat = {"env": env, **typed_overrides(flat)}
    top = {k: v for k, v in flat.items() if "." not in k}
    agent = {k[6:]: v for k, v in flat.items() if k.startswith("agent.")}
    dyna = {k[5:]: v for k, v in flat.items() if k.startswith("dyna.")}
    cfg = dataclasses.replace(
        from_dict(TrainConfig, top), agent_config=from_dict(AgentConfig, agent), dyna=from_dict(DynaConfig, dyna)
    )
    validate(cfg)
    _check_runnable(cfg)
    return cfg


def load_config_file(path: str | Path) -> TrainConfig:
    """:func:`config_from_dict` of the JSON file ``path``; errors name the file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"configuration file {path} does not exist")
    try:
        return config_from_dict(json.loads(path.read_text()))
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc})") from None
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
