"""Training configuration: the run's budget, a typed method (:mod:`.methods`) and a typed agent; recipes; overrides.

``resolve_config(env, overrides, preset=None)`` starts from the types' defaults, applies the system's
recipe (:mod:`pimbrl.systems.presets`: ``default`` unless another is named, e.g. ``paper`` or ``best``), then
the overrides, and validates every field.

Overrides are setting paths with typed values: ``{"utd": 5.0, "agent.gamma": 0.98,
"imagine.rollout_length": 7, "physics.weight": 0.5}``. A path names a field of the run (``utd``), of the
agent (``agent.*``), of the method's own settings (``model.*``) or of one of its sections (``fit.*``,
``check.*``, ``imagine.*``, ``finetune.*``, ``physics.*``, ``learn.*``), or an experimental knob
(``experimental.*``). A path the chosen method or agent does not have is an error naming those that have it
(:func:`inapplicable_reason`); a recipe's settings that the method does not have are skipped.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..agents.config import AGENT_NAMES, AGENT_TYPES, AgentConfig, TD3Config
from ..config import (
    LOOP_SOURCES,
    MAX_SEED,
    MAX_STEPS,
    MAX_TRANSITIONS,
    ConfigError,
    at_most,
    check_env_id,
    field_types,
    in_range,
    load_yaml,
    non_negative,
    one_of,
    param,
    positive,
    typed_value,
    validate,
)
from ..config import flag_of as setting_flag
from .envinfo import (
    changed_env_kwargs,
    check_env_coefficients,
    check_env_kwargs,
    check_tensorboard,
    did_you_mean,
    is_pde_env,
    physics_coefficient_names,
    task_class,
)
from .legacy import is_legacy, new_from_legacy, renamed_message
from .methods import (
    CONTROL_METHODS,
    CONTROL_TYPES,
    METHOD_TYPES,
    METHODS,
    MFRL,
    SECTIONS,
    CoefficientFit,
    ControlMethod,
    DynaMethod,
    Feedback,
    Method,
    methods_with,
    pde_only,
)

__all__ = [
    "DEVICES",
    "EXTERNAL_PRESETS",
    "METHODS",
    "POLICIES",
    "Experimental",
    "TrainConfig",
    "applicable_overrides",
    "config_from_dict",
    "config_to_dict",
    "did_you_mean",
    "field_paths",
    "flag_of",
    "get_setting",
    "has_setting",
    "inapplicable_reason",
    "is_pde_env",
    "load_config_file",
    "preset_note",
    "recipe_of",
    "recipe_settings",
    "resolve_config",
    "return_scale_warnings",
    "run_names",
    "setting_type",
    "typed_overrides",
]

#: the policies of a run that can be evaluated: the checkpoint's latest, or the one policy selection kept
POLICIES = ("latest", "selected")
#: the draws the evaluations during training play (``eval_protocol``): the test pool, or the validation draws
#: (a tuning study, whose choices must read no test state)
EVAL_PROTOCOLS = ("test", "validation")
#: where the networks run (``auto``: CUDA where torch sees a GPU, else the CPU; the project never needs one)
DEVICES = ("cpu", "cuda", "auto")


@dataclass(frozen=True)
class Experimental:
    """Knobs kept for reproducing recorded runs, measured as no help (docs/journal/); off by default."""

    lr_decay_after: int | None = param(
        None,
        "real step after which the actor and critic learning rates fall linearly to lr_decay_to times their value at "
        "total_steps (none: constant, the paper's; on KS it changed nothing measurable)",
        [non_negative(), at_most(MAX_STEPS)],
    )
    lr_decay_to: float = param(0.1, "with lr_decay_after: the learning rates' final fraction", in_range(0.0, 1.0))
    critic_layer_norm: bool = param(
        False, "layer-normalise the critics' hidden layers before their ReLU (RLPD); on KS it learned slower"
    )
    reset_start_symmetry: bool = param(
        False,
        "reset starts of imagined rollouts from images of the initial states under the equation's symmetries "
        "(PDEs, with imagine.reset_start_fraction > 0); on KS it was slower",
    )


def _section_field(cls: type, help: str, prefix: str) -> Any:
    return dataclasses.field(default_factory=cls, metadata={"help": help, "prefix": prefix})


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (saved as ``config.json`` in the run directory)."""

    env: str = param("pimbrl/Pendulum-v0", "environment id (pimbrl/... or any Gymnasium id)")
    method: Method = _section_field(MFRL, "the method and its settings (model.*, fit.*, imagine.*, ...)", "model")
    agent: AgentConfig = _section_field(TD3Config, "the agent and its settings (agent.*)", "agent")
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
    eval_protocol: str = param(
        "test",
        "the draws the evaluations during training play: test (the test pool), or validation (a tuning study: "
        "its choices read no test state)",
        one_of(*EVAL_PROTOCOLS),
    )
    holdout_episodes: int = param(
        0,
        "episodes of the holdout pool (fresh draws no evaluation during training plays) the final policy plays "
        "once, at the end, into holdout.json (a confirmatory study's outcome; 0: none)",
        [non_negative(), at_most(10_000)],
    )
    threshold: float | None = param(None, "evaluation return that counts as solved (steps-to-threshold)")
    checkpoint_every: int = param(
        5_000, "real steps between checkpoints (taken at the next episode end)", [positive(), at_most(MAX_STEPS)]
    )
    checkpoint_minutes: float = param(
        10.0,
        "wall-clock minutes after which a checkpoint is also due (taken at the next episode end), so a kill "
        "loses at most about this much of a slow run; 0: by steps only",
        [non_negative(), at_most(10_000)],
    )
    log_every: int = param(1_000, "real steps between rows of metrics.csv", [positive(), at_most(MAX_STEPS)])
    threads: int = param(
        1,
        "threads for this run: torch's pool and the BLAS and OpenMP pools numpy and scipy load",
        in_range(1, 256),
    )
    device: str = param("cpu", "where the networks run: cpu, cuda or auto (cuda where torch sees a GPU)", one_of(*DEVICES))
    tensorboard: bool = param(False, "also write TensorBoard events (needs the tensorboard package)")
    env_kwargs: dict = dataclasses.field(
        default_factory=dict, metadata={"help": "keyword arguments for gymnasium.make", "check": None}
    )
    experimental: Experimental = _section_field(Experimental, "knobs measured as no help (experimental.*)", "experimental")

    @property
    def model_based(self) -> bool:
        """Whether the method is a Dyna method with a model (every RL method but MFRL)."""
        return not isinstance(self.method, (MFRL, *CONTROL_TYPES))

    @property
    def control(self) -> bool:
        """Whether the method is a controller of :mod:`pimbrl.control` (feedback, mpc, dpc): no agent is trained."""
        return isinstance(self.method, CONTROL_TYPES)

    @property
    def dyna(self) -> DynaMethod:
        """The method, which has a model (a :class:`ValueError` for MFRL and the controllers)."""
        if isinstance(self.method, (MFRL, *CONTROL_TYPES)):
            raise ValueError(f"a {self.method.name} run has no Dyna model")
        return self.method

    @property
    def controller(self) -> ControlMethod:
        """The control method (a :class:`ValueError` for the RL methods)."""
        if not isinstance(self.method, CONTROL_TYPES):
            raise ValueError(f"a {self.method.name} run is not a control method")
        return self.method


#: presets of Gymnasium environments that are not pimbrl systems (for model-free comparisons)
EXTERNAL_PRESETS: dict[str, dict[str, Any]] = {
    "Pendulum-v1": {"total_steps": 15_000, "warmup_steps": 1_000, "update_after": 1_000, "eval_every": 500, "threshold": -200.0},
}

_RUN_FIELDS = {f.name for f in dataclasses.fields(TrainConfig)} - {"method", "agent", "experimental", "env"}


# ----------------------------------------------------------------------------- recipes
def recipe_of(env: str, preset: str | None = None) -> Any:
    """The recipe ``preset`` of ``env``'s system (its default recipe for ``None``); ``None`` where it has none.

    Raises :class:`ConfigError` for a recipe the system does not have, naming those it has.
    """
    from ..systems import get_system
    from ..systems.presets import PresetError, Recipe

    system = get_system(env)
    if system is None:
        external = EXTERNAL_PRESETS.get(env)
        if preset not in (None, "default"):
            raise ConfigError(f"--preset {preset}: {env} has no recipes (only pimbrl systems declare them)")
        return None if external is None else Recipe("default", settings=external)
    try:
        default, recipes = system.recipes()
    except PresetError as exc:
        raise ConfigError(str(exc)) from None
    if not recipes:
        if preset is not None:
            raise ConfigError(f"--preset {preset}: {env} declares no preset (System.preset; docs/systems.md)")
        return None
    name = default if preset is None else preset
    if name not in recipes:
        raise ConfigError(f"--preset {name}: {env} has the recipes {', '.join(recipes)}{did_you_mean(name, recipes)}")
    return recipes[name]


def preset_note(env: str) -> str | None:
    """A line for a run on an environment without a preset (generic defaults apply), ``None`` where it has one."""
    if recipe_of(env) is not None:
        return None
    return (
        f"{env} has no preset: the generic defaults of every setting apply (see `pimbrl train {env} --print-config`); "
        "a system declares one with System.preset (docs/systems.md)"
    )


# ----------------------------------------------------------------------------- setting paths
def _fields(cls: type) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(cls)}


def _own_fields(cls: type) -> dict[str, dataclasses.Field]:
    """A method type's own settings (not its sections)."""
    return {n: f for n, f in _fields(cls).items() if not f.metadata.get("section")}


def _lookup(path: str) -> list[tuple[type, dataclasses.Field]]:
    """Every (type, field) the path can address, over all methods and agents (``[]``: none)."""
    head, _, rest = path.partition(".")
    if not rest:
        return [(TrainConfig, _fields(TrainConfig)[head])] if head in _RUN_FIELDS or head in ("method", "agent") else []
    if "." in rest:
        return []
    if head == "agent":
        return [(cls, _fields(cls)[rest]) for cls in AGENT_TYPES.values() if rest in _fields(cls)]
    if head == "experimental":
        return [(Experimental, _fields(Experimental)[rest])] if rest in _fields(Experimental) else []
    if head == "model":
        return [(cls, _own_fields(cls)[rest]) for cls in METHOD_TYPES.values() if rest in _own_fields(cls)]
    if head in SECTIONS:
        return [(SECTIONS[head], _fields(SECTIONS[head])[rest])] if rest in _fields(SECTIONS[head]) else []
    return []


def field_paths() -> list[str]:
    """Every setting path an override can name: ``utd``, ``agent.gamma``, ``imagine.rollout_length``, ..."""
    paths = ["method", "agent", *sorted(_RUN_FIELDS)]
    paths += sorted({f"agent.{n}" for cls in AGENT_TYPES.values() for n in _fields(cls)})
    paths += sorted({f"model.{n}" for cls in METHOD_TYPES.values() for n in _own_fields(cls)})
    paths += [f"{s}.{n}" for s, cls in SECTIONS.items() for n in _fields(cls)]
    paths += [f"experimental.{n}" for n in _fields(Experimental)]
    return paths


def setting_type(path: str) -> Any:
    """The declared type of the setting ``path``; :class:`ConfigError` (with the new name of an old one) if none."""
    found = _lookup(path)
    if not found:
        old = renamed_message(path)
        if old is not None:
            raise ConfigError(old)
        raise ConfigError(f"unknown setting {path!r}{did_you_mean(path, field_paths())}")
    if path in ("method", "agent"):
        return str
    cls, f = found[0]
    return field_types(cls)[f.name]


#: the run settings a control method (feedback, mpc, dpc) reads: it trains no agent and keeps no replay
CONTROL_RUN_FIELDS = frozenset(
    {"seed", "eval_episodes", "eval_seed", "eval_protocol", "holdout_episodes", "threshold", "threads", "env_kwargs"}
)


def has_setting(method: str, agent: str, path: str) -> bool:
    """Whether a run of ``method`` with ``agent`` has the setting ``path``."""
    head, _, rest = path.partition(".")
    if method in CONTROL_METHODS and (head in ("agent", "experimental") or not rest):
        return not rest and head in CONTROL_RUN_FIELDS
    if not rest or head == "experimental":
        return True
    if head == "agent":
        return rest in _fields(AGENT_TYPES[agent])
    return method in methods_with(path)


def get_setting(cfg: TrainConfig, path: str) -> Any:
    """The value of the setting ``path`` in ``cfg`` (``"method"`` and ``"agent"``: their names).

    Raises :class:`ConfigError` where the run does not have the setting.
    """
    head, _, rest = path.partition(".")
    if not rest:
        value = getattr(cfg, head)
        return value.name if head in ("method", "agent") else value
    holder = {"agent": cfg.agent, "experimental": cfg.experimental, "model": cfg.method}.get(head)
    if holder is None:
        holder = getattr(cfg.method, head, None)
    if holder is None or not hasattr(holder, rest):
        raise ConfigError(f"a {cfg.method.name} run with {cfg.agent.name} has no setting {path!r}")
    return getattr(holder, rest)


def flag_of(path: str) -> str:
    """The command-line flag of the setting ``path``, as a message names it (``total_steps``: its alias ``--steps``)."""
    return "--steps" if path == "total_steps" else setting_flag(path)


def inapplicable_reason(env: str, method: str, agent: str, path: str) -> str | None:
    """Why the setting ``path`` does nothing for a run of ``method`` with ``agent`` on ``env`` (``None``: it applies)."""
    head, _, rest = path.partition(".")
    flag = flag_of(path)
    if method in CONTROL_METHODS and not has_setting(method, agent, path) and (head in ("agent", "experimental") or not rest):
        return f"{flag} is a setting of the RL methods' training, not of --method {method} (it trains no agent)"
    if head == "agent" and rest and not has_setting(method, agent, path):
        agents = [name for name, cls in AGENT_TYPES.items() if rest in _fields(cls)]
        return f"{flag} is a setting of the agent {' and '.join(agents)}, not {agent}"
    if head not in ("agent", "experimental") and rest and not has_setting(method, agent, path):
        have = methods_with(path)
        return f"{flag} is a setting of --method {', '.join(have)}, not {method}"
    if path == "experimental.reset_start_symmetry" and method not in methods_with("imagine.reset_start_fraction"):
        return f"{flag} acts on imagined rollouts, which --method {method} does not have"
    found = _lookup(path)
    if found and rest and pde_only(found[0][1]) and not is_pde_env(env):
        return (
            f"{flag} applies to the PDE systems (Burgers, Kuramoto-Sivashinsky, a declared PDE), not {env}: an ODE "
            "system's model steps its solver, one state per solver step"
        )
    return None


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


#: the settings whose values are mappings, with an example (the command line reads them from a short text)
_MAPPINGS = {"model.prior": '{"nu": 0.01}', "learn.coefficients": '{"nu": null, "damping": [0, 1]}'}


def typed_overrides(overrides: Mapping[str, Any]) -> dict[str, Any]:
    """``overrides`` (setting paths -> values), each path checked to exist and each value against its type."""
    out = {}
    for path, value in overrides.items():
        if path == "env":
            raise ConfigError("env is not an override: it is given on its own (the first argument)")
        tp = setting_type(path)
        if path in _MAPPINGS and isinstance(value, str):
            raise ConfigError(f"{path} takes a mapping, e.g. {_MAPPINGS[path]} (on the command line: {flag_of(path)} {value})")
        value = typed_value(tp, value, path)
        if path == "method" and value not in METHODS:
            raise ConfigError(f"method must be one of {', '.join(METHODS)}, got {value!r}{did_you_mean(value, METHODS)}")
        if path == "agent" and value not in AGENT_NAMES:
            raise ConfigError(f"agent must be one of {', '.join(AGENT_NAMES)}, got {value!r}{did_you_mean(value, AGENT_NAMES)}")
        out[path] = value
    return out


# ----------------------------------------------------------------------------- building and resolving
def _build(env: str, method: str, agent: str, flat: Mapping[str, Any]) -> TrainConfig:
    """The configuration with the defaults of the types, ``flat`` (applicable, typed paths) set."""
    run: dict[str, Any] = {}
    agent_fields: dict[str, Any] = {}
    experimental: dict[str, Any] = {}
    own: dict[str, Any] = {}
    sections: dict[str, dict[str, Any]] = {}
    for path, value in flat.items():
        head, _, rest = path.partition(".")
        if not rest:
            run[head] = value
        elif head == "agent":
            agent_fields[rest] = value
        elif head == "experimental":
            experimental[rest] = value
        elif head == "model":
            own[rest] = value
        else:
            sections.setdefault(head, {})[rest] = value
    try:
        method_cfg = METHOD_TYPES[method](**own, **{name: SECTIONS[name](**f) for name, f in sections.items()})
        return TrainConfig(
            env=env,
            method=method_cfg,
            agent=AGENT_TYPES[agent](**agent_fields),
            experimental=Experimental(**experimental),
            **run,
        )
    except TypeError as exc:
        raise ConfigError(str(exc)) from None


def recipe_settings(recipe: Any, model_based: bool, method: str = "", agent: str = "") -> dict[str, Any]:
    """A recipe's settings for a method with or without a model, typed (the method and agent are its own keys).

    ``method`` and ``agent`` add the recipe's settings for them (its ``methods:`` and ``agents:``; ``agent``
    empty for a method that trains none). Each of those sections is checked whichever method runs, each a
    one-line :class:`ConfigError`: a name that is no method or agent, a value of the wrong type, a
    ``threshold`` (a study reads one per system: it belongs in ``settings:``), and a setting its own method
    (agent) does not have (it would never apply; ``agent.*`` settings of a method's section depend on the agent).
    """
    where = f"recipe {recipe.name!r}"
    for key, sections, known in (("methods", recipe.methods, METHODS), ("agents", recipe.agents, AGENT_NAMES)):
        for name, section in sections.items():
            if name not in known:
                raise ConfigError(
                    f"{where}: {key} names {name!r}{did_you_mean(name, known)}, which is not one of "
                    f"{', '.join(known)}; fix the system's preset file"
                )
            try:
                typed_overrides(section)
            except ConfigError as exc:
                raise ConfigError(f"{where}: {key}: {name}: {exc}") from None
            for path in section:
                if path in ("threshold", "method", "agent"):
                    raise ConfigError(
                        f"{where}: {key}: {name}: {path} belongs in the recipe's settings (or its own key), not here"
                    )
                if key == "methods":
                    lacks = not path.startswith("agent.") and not has_setting(name, "td3", path)
                else:
                    lacks = path.partition(".")[0] == "agent" and not has_setting("mfrl", name, path)
                if lacks:
                    raise ConfigError(
                        f"{where}: {key}: {name}: a {name} run has no setting {path!r}; fix the system's preset file"
                    )
    settings = recipe.for_method(model_based, method, agent)
    for key in ("method", "agent"):
        if key in settings:
            raise ConfigError(f"{where}: {key} is chosen by the recipe's own '{key}:' key, not among its settings")
    return typed_overrides(settings)


def _recipe_for_run(recipe: Any, method: str, agent: str) -> dict[str, Any]:
    """The recipe's typed settings for a run of ``method`` with ``agent`` (a control method: no agent's section)."""
    return recipe_settings(recipe, method != "mfrl", method, "" if method in CONTROL_METHODS else agent)


def run_names(env: str, overrides: Mapping[str, Any], preset: str | None = None) -> tuple[str, str]:
    """The method and the agent a run of ``env`` gets: the overrides', else the recipe's, else mfrl and td3."""
    recipe = recipe_of(env, preset)
    method = overrides.get("method") or (recipe.method if recipe is not None else "") or "mfrl"
    agent = overrides.get("agent") or (recipe.agent if recipe is not None else "") or "td3"
    return str(method), str(agent)


def resolve_config(env: str, overrides: Mapping[str, Any] | None = None, *, preset: str | None = None) -> TrainConfig:
    """The run's configuration: the types' defaults, then the system's recipe, then the overrides; validated.

    ``preset`` names the recipe (``None``: the system's default). ``overrides`` maps setting paths to
    values; ``"method"`` and ``"agent"`` choose the method and the agent (else the recipe's, else mfrl and
    td3). An override the run does not have is a :class:`ConfigError` with the reason
    (:func:`inapplicable_reason`); a recipe's setting the run does not have is skipped.
    """
    typed = typed_overrides(overrides or {})
    recipe = recipe_of(env, preset)
    method, agent = run_names(env, typed, preset)
    if method in CONTROL_METHODS and "agent" in typed:
        raise ConfigError(f"--agent does nothing with --method {method}: it trains no agent; drop --agent")
    typed.pop("method", None)
    typed.pop("agent", None)
    if method not in METHODS:
        raise ConfigError(f"the recipe's method {method!r} is not one of {', '.join(METHODS)}")
    if agent not in AGENT_NAMES:
        raise ConfigError(f"the recipe's agent {agent!r} is not one of {', '.join(AGENT_NAMES)}")
    for path in typed:
        reason = inapplicable_reason(env, method, agent, path)
        if reason is not None:
            raise ConfigError(reason)
    base = {} if recipe is None else _recipe_for_run(recipe, method, agent)
    base = {k: v for k, v in base.items() if has_setting(method, agent, k)}
    merged = {**base, **typed}
    if "env_kwargs" in base and "env_kwargs" in typed:  # the user's keyword arguments go on top of the recipe's
        merged["env_kwargs"] = {**base["env_kwargs"], **typed["env_kwargs"]}
    cfg = resolve_model(_build(env, method, agent, merged))
    validate(cfg)
    _check_runnable(cfg)
    return cfg


def resolve_model(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` with the model settings that follow from the system, so that config.json says what trains.

    ``model.network`` ``auto`` becomes the paper's network (ConvLSTM for a PDE, an MLP for an ODE or an env
    known by its data). An ODE system's model steps its solver: ``model.scheme`` becomes ``solver`` and
    ``model.n_intermediate`` the solver steps per control step. Other runs are returned unchanged.
    """
    m = cfg.method
    if isinstance(m, (MFRL, *CONTROL_TYPES)):
        return cfg
    changes: dict[str, Any] = {}
    pde = is_pde_env(cfg.env)
    if getattr(m, "network", None) == "auto":
        changes["network"] = "convlstm" if pde else "mlp"
    if not pde:
        cls = task_class(cfg.env)
        if cls is None:  # an env known by its data only: an MLP predicting the next observation
            changes["n_intermediate"] = 1
        else:
            try:
                changes["n_intermediate"] = int(cls(**cfg.env_kwargs).physics.substeps)
            except (TypeError, ValueError):  # bad keyword arguments: reported with their reason by _check_runnable
                return cfg
            if hasattr(m, "scheme"):
                changes["scheme"] = "solver"
    return dataclasses.replace(cfg, method=dataclasses.replace(m, **changes)) if changes else cfg


def _check_runnable(cfg: TrainConfig) -> None:
    """Check what validation of the fields cannot see.

    The environment's keyword arguments, the method's settings against the system (coefficients, sources,
    network), TensorBoard, the device.
    """
    check_env_kwargs(cfg.env, cfg.env_kwargs)
    check_env_coefficients(cfg.env, cfg.env_kwargs)
    check_lr_decay(cfg)
    check_device(cfg.device)
    if cfg.tensorboard:
        check_tensorboard()
    m = cfg.method
    if isinstance(m, MFRL):
        return
    if isinstance(m, CONTROL_TYPES):
        check_control(cfg)
        return
    if task_class(cfg.env) is None:  # an env outside pimbrl: its data only
        if m.name != "mbrl":
            raise ConfigError(
                f"--method {m.name} needs the system's equation, and {cfg.env} declares none: use --method mbrl "
                "(data-only: the observation as the state, the reward learned), or declare the system (docs/systems.md)"
            )
        check_observed(cfg)
    physics = getattr(m, "physics", None)
    if physics is not None:
        check_physics_sources(cfg.env, physics.sources)
    check_coefficients(cfg)
    check_network(cfg)
    check_rollout_starts(cfg)


def check_control(cfg: TrainConfig) -> None:
    """What a control method needs of the system: its equation, a differentiable reward, coefficients it has.

    One-line :class:`ConfigError` naming the problem and the fix.
    """
    m = cfg.controller
    cls = task_class(cfg.env)
    if cls is None:
        raise ConfigError(
            f"--method {m.name} needs the system's equation, and {cfg.env} declares none: declare the system "
            "(docs/systems.md), or use an RL method"
        )
    physics = cls(**cfg.env_kwargs).physics
    if not isinstance(m, Feedback):
        if not getattr(physics, "differentiable_reward", True):
            raise ConfigError(
                f"--method {m.name} optimises the reward by gradient, and {physics.name}'s reward has none "
                "(+1 per step until the episode ends): use --method feedback (an LQR), or an RL method"
            )
        if m.learn.correction:
            raise ConfigError(f"--method {m.name} identifies coefficients only: drop --learn.correction")
        check_coefficients(cfg)
    episodes = getattr(m, "validation_episodes", None)
    if episodes is not None:
        try:
            cls(**cfg.env_kwargs).validation_initial_states(episodes)
        except ValueError as exc:
            raise ConfigError(f"--model.validation-episodes {episodes}: {exc}") from None
    if isinstance(m, Feedback):
        from ..control.feedback import check_feedback  # builds the controller once: a kind that cannot work fails here

        try:
            check_feedback(cfg.env, cls(**cfg.env_kwargs), m.kind, m.gains)
        except ValueError as exc:
            raise ConfigError(f"--method feedback: {exc}") from None


def check_device(device: str) -> None:
    """A clear :class:`ConfigError` for ``--device cuda`` where torch sees no GPU."""
    if device != "cuda":
        return
    import torch

    if not torch.cuda.is_available():
        raise ConfigError("--device cuda: torch sees no CUDA GPU here; use --device cpu (or auto: a GPU where there is one)")


def check_observed(cfg: TrainConfig) -> None:
    """A clear :class:`ConfigError` for a data-only run on an env outside pimbrl that cannot be one.

    Such an env is known by its data only (:mod:`pimbrl.systems.observed`): Box spaces, no initial states to
    draw (no policy selection in the model), its own network (an MLP).
    """
    import gymnasium as gym

    from ..systems.observed import ObservedTask

    try:
        ObservedTask(gym.make(cfg.env, **cfg.env_kwargs))
    except ValueError as exc:
        raise ConfigError(f"{cfg.env}: {exc}") from None
    if cfg.dyna.imagine.select_episodes:
        raise ConfigError(f"--imagine.select-episodes needs initial states to draw, and {cfg.env} draws its own at reset")


def check_lr_decay(cfg: TrainConfig) -> None:
    """A clear :class:`ConfigError` for a learning-rate decay that cannot happen as asked."""
    x = cfg.experimental
    if x.lr_decay_after is None:
        if x.lr_decay_to != Experimental().lr_decay_to:
            raise ConfigError("--experimental.lr-decay-to sets where the decay ends; give --experimental.lr-decay-after STEP too")
        return
    if x.lr_decay_to == 1.0:
        raise ConfigError("--experimental.lr-decay-to 1 keeps the learning rates constant; give a fraction below 1")
    if x.lr_decay_after >= cfg.total_steps:
        raise ConfigError(
            f"--experimental.lr-decay-after {x.lr_decay_after:,} is not before --total-steps {cfg.total_steps:,}: the "
            "rates would never fall; give a step below total_steps, or drop it"
        )


def check_network(cfg: TrainConfig) -> None:
    """A clear :class:`ConfigError` for a network the system cannot have."""
    network = getattr(cfg.method, "network", None)
    pde = is_pde_env(cfg.env)
    if network == "mlp" and pde:
        raise ConfigError(
            f"--model.network mlp is the ODE systems' network, not for the PDE {cfg.env}: use convlstm (the paper's) "
            "or equivariant"
        )
    if network in ("convlstm", "equivariant") and not pde:
        raise ConfigError(
            f"--model.network {network} is a network on a PDE's grid, not for {cfg.env}: an ODE system's network is an MLP (auto)"
        )


def check_rollout_starts(cfg: TrainConfig) -> None:
    """A clear :class:`ConfigError` for rollout starts that cannot be made."""
    imagine = cfg.dyna.imagine
    if cfg.experimental.reset_start_symmetry:
        if imagine.reset_start_fraction == 0:
            raise ConfigError(
                "--experimental.reset-start-symmetry acts on reset starts, and --imagine.reset-start-fraction is 0: "
                "give a fraction (e.g. 0.5) or drop it"
            )
        if not is_pde_env(cfg.env):
            raise ConfigError(
                f"--experimental.reset-start-symmetry needs a PDE on a periodic grid (shifts, reflection); {cfg.env} has none"
            )
    if imagine.imagined_start_fraction + imagine.reset_start_fraction > 1.0:
        raise ConfigError(
            f"--imagine.imagined-start-fraction {imagine.imagined_start_fraction} and --imagine.reset-start-fraction "
            f"{imagine.reset_start_fraction} add up to more than 1: they are shares of the same rollout starts; lower one"
        )


def check_coefficients(cfg: TrainConfig) -> None:
    """A clear :class:`ConfigError` for a physics prior or learned coefficients that cannot work.

    Checked before anything runs: names, values (the prior is built), learned coefficients whose starting
    value would be the environment's true one (given in ``env_kwargs`` but not in the prior), an
    identified scheme with nothing to identify, the learning settings without anything learned.
    """
    m: Any = cfg.method  # a Dyna method, or MPC/DPC (the same prior and learned coefficients)
    prior = dict(m.prior)
    learn: CoefficientFit | None = getattr(m, "learn", None)
    learned = learn.ranges() if learn is not None else {}
    identify = getattr(m, "identify", None)
    if identify is not None and not learned and identify != type(identify)():
        raise ConfigError("--identify.* does nothing without --learn.coefficients (the coefficients to identify)")
    if m.name == "identified-scheme" and not learned:
        raise ConfigError(
            "--method identified-scheme fits coefficients of the prior's scheme: name them with --learn.coefficients "
            "(e.g. nu), or use --method known-scheme"
        )
    if learn is not None and not learned:
        for name in ("lr", "correction_penalty"):
            if getattr(learn, name) != getattr(type(learn)(), name):
                raise ConfigError(f"--learn.{name.replace('_', '-')} does nothing without --learn.coefficients")
    if learn is not None and not learn.correction and learn.correction_penalty != type(learn)().correction_penalty:
        raise ConfigError("--learn.correction-penalty does nothing without --learn.correction true")
    if not prior and not learned:
        return
    names = physics_coefficient_names(cfg.env)
    for flag, given in (
        ("--model.prior", prior),
        ("--learn.coefficients", {k: v for k, v in learned.items() if k != "correction"}),
    ):
        bad = [name for name in given if name not in names]
        if bad:
            raise ConfigError(
                f"{flag}: {cfg.env} has no coefficient {bad[0]!r}{did_you_mean(bad[0], names)}; "
                f"its coefficients are: {', '.join(names) or 'none'}"
            )
    if learned and is_pde_env(cfg.env) and getattr(m, "scheme", "etd") != "etd":
        raise ConfigError("--learn.coefficients needs the etd scheme (--model.scheme etd), not the solver's")
    leaked = [name for name in learned if name in cfg.env_kwargs and name not in prior]
    if leaked:
        raise ConfigError(
            f"--learn.coefficients: {leaked[0]} would start from the environment's true value (given in --env-kwargs); "
            f"give the value the run believes with --model.prior {leaked[0]}=..."
        )
    from ..models.coefficients import LearnedCoefficients  # builds the prior: values checked as the run will

    try:
        physics = task_class(cfg.env)(**cfg.env_kwargs).physics.with_coefficients(**prior)
        if learn is not None and learned:
            LearnedCoefficients(physics, learned, penalty=learn.correction_penalty)
    except ValueError as exc:
        raise ConfigError(f"physics prior: {exc}") from None


#: physics-loss sources by kind of system (what :func:`pimbrl.models.state_sources.available_sources`
#: gives for the PDEs and for the ODEs, without building the physics)
PDE_SOURCES = (*LOOP_SOURCES, "symmetry", "scaled", "noise")
ODE_SOURCES = (*LOOP_SOURCES, "box")


def check_physics_sources(env: str, sources: tuple[str, ...]) -> None:
    """A clear :class:`ConfigError` for physics-loss sources the environment does not offer (empty: all it offers)."""
    have = PDE_SOURCES if is_pde_env(env) else ODE_SOURCES
    bad = [name for name in sources if name not in have]
    if bad:
        raise ConfigError(
            f"--physics.sources: {', '.join(bad)} not available for {env}; choose from {', '.join(have)} (auto: all)"
        )


def return_scale_warnings(cfg: TrainConfig, preset: str | None = None) -> list[str]:
    """Recipe settings measured in test returns, kept for an environment the run changes.

    A recipe's ``threshold`` (steps-to-threshold; KS: -55) and ``finetune.at_return`` (the switch to
    model-free fine-tuning; KS: -55) were set on the return scale of the environment as registered.
    ``env_kwargs`` that change it (other coefficients, an actuator width, another reward) may change that
    scale, so the switch can fire at once or never. One line per such setting the run keeps, with the flag
    to set; nothing when the keyword arguments only repeat the registered defaults.
    """
    try:
        recipe = recipe_of(cfg.env, preset)
    except ConfigError:
        return []
    if recipe is None:
        return []
    try:
        settings = _recipe_for_run(recipe, cfg.method.name, cfg.agent.name)
    except ConfigError:
        return []
    kept = []  # (name, value, what it does, how to fix it)
    if settings.get("threshold") is not None and cfg.threshold == settings["threshold"]:
        kept.append(
            ("threshold", cfg.threshold, "counts a run as solved (steps to threshold)", "give --threshold for this system")
        )
    finetune = settings.get("finetune.at_return")
    if finetune is not None and cfg.model_based and cfg.dyna.finetune.at_return == finetune:
        fix = "give --finetune.at-return for this system, or --finetune.at-return none never to switch"
        kept.append(("finetune.at_return", finetune, "switches to model-free fine-tuning", fix))
    own = settings.get("env_kwargs") or {}  # the recipe's own keyword arguments set the scale its values were read on
    given = {k: v for k, v in cfg.env_kwargs.items() if k not in own or own[k] != v}
    changed = changed_env_kwargs(cfg.env, given) if kept else []
    if not changed:
        return []
    return [
        f"{name} = {value:g} (the recipe's) {role} at that test return, a value set for {cfg.env} as registered; "
        f"--env-kwargs change {', '.join(changed)}, which may change the scale of the returns: {fix}"
        for name, value, role, fix in kept
    ]


# ----------------------------------------------------------------------------- reading and writing
def config_to_dict(cfg: TrainConfig) -> dict[str, Any]:
    """A JSON-ready dict of ``cfg``: the method and the agent carry their ``name`` (tuples become lists).

    A control method's (feedback, mpc, dpc) has no agent and only the run settings it reads
    (:data:`CONTROL_RUN_FIELDS`): what is written is what ran.
    """
    data = dataclasses.asdict(cfg)
    data["method"] = {"name": cfg.method.name, **data["method"]}
    data["agent"] = {"name": cfg.agent.name, **data["agent"]}
    if cfg.control:
        data = {k: v for k, v in data.items() if k in ("env", "method") or k in CONTROL_RUN_FIELDS}
    return data


def _flatten(data: Mapping[str, Any]) -> dict[str, Any]:
    """A whole configuration as :func:`config_to_dict` writes it -> setting paths (with method and agent)."""
    flat: dict[str, Any] = {}
    for key, value in data.items():
        if key in ("method", "agent", "experimental"):
            if not isinstance(value, Mapping):
                raise ConfigError(f"{key} must be an object, got {value!r}")
            value = dict(value)
            if key != "experimental":
                flat[key] = value.pop("name", "mfrl" if key == "method" else "td3")
            for name, inner in value.items():
                if key == "method" and name in SECTIONS:
                    if not isinstance(inner, Mapping):
                        raise ConfigError(f"method.{name} must be an object, got {inner!r}")
                    flat.update({f"{name}.{k}": v for k, v in inner.items()})
                else:
                    flat[f"{'model' if key == 'method' else key}.{name}"] = inner
        else:
            flat[key] = value
    return flat


def config_from_dict(data: Mapping[str, Any]) -> TrainConfig:
    """A :class:`TrainConfig` from a whole configuration: ``config.json``'s ``config``, ``--print-config``'s output.

    Every value is type-checked and the result validated; missing fields take the types' defaults (not the
    recipes). A configuration written before the typed methods (flat ``dyna`` and ``agent_config``) is read
    into the types that run the same (:mod:`.legacy`).
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"a configuration must be a JSON object, got {type(data).__name__}")
    env = check_env_id(data.get("env", TrainConfig.env), registered=True)  # never imports a module named here
    if is_legacy(data):
        flat = new_from_legacy(data, lambda method, path: method in methods_with(path))
        if flat.get("model.network") == "convlstm":  # the old default, for ODE systems too: the paper's network
            flat["model.network"] = "auto"
    else:
        flat = _flatten({k: v for k, v in data.items() if k != "env"})
    legacy = is_legacy(data)
    flat = typed_overrides(flat)
    method = flat.pop("method", "mfrl")
    agent = flat.pop("agent", "td3")
    if legacy:  # the old form wrote every agent's fields for every agent: those of others were inert
        flat = {k: v for k, v in flat.items() if not k.startswith("agent.") or has_setting(method, agent, k)}
    for path in flat:
        if not has_setting(method, agent, path):
            raise ConfigError(inapplicable_reason(env, method, agent, path) or f"{path} does not apply")
    cfg = resolve_model(_build(env, method, agent, flat))
    validate(cfg)
    _check_runnable(cfg)
    return cfg


def load_config_file(path: str | Path) -> TrainConfig:
    """:func:`config_from_dict` of the JSON or YAML file ``path``; errors name the file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"configuration file {path} does not exist")
    text = path.read_text()
    try:
        data = load_yaml(text) if path.suffix in (".yaml", ".yml") else json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc})") from None
    except Exception as exc:  # yaml.YAMLError: imported lazily
        raise ConfigError(f"{path}: not valid YAML ({type(exc).__name__})") from None
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
