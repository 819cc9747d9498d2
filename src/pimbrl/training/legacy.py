"""Configurations written before the typed method configurations: read into the new types.

Runs recorded before this release wrote one flat configuration for every method (``config.json``'s
``method``, ``agent``, ``agent_config`` and ``dyna`` with 33 model-based fields, most of them inert for the
run). :func:`new_from_legacy` maps such a configuration to the typed one that runs the same (the method
named for what ran: ``--method mbrl --dyna.model physics`` was the known scheme as the model), and
:data:`RENAMED` says where each old setting went, so that an old flag or override gets a one-line
message naming its new path.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..config import ConfigError, flag_of, parse_learned, parse_prior

__all__ = [
    "RENAMED",
    "is_legacy",
    "legacy_method",
    "method_and_agent",
    "new_from_legacy",
    "old_flag_message",
    "renamed_message",
]

#: old path -> new path (``None``: the setting chose the method, see :func:`legacy_method`)
RENAMED: dict[str, str | None] = {
    "lr_decay_after": "experimental.lr_decay_after",
    "lr_decay_to": "experimental.lr_decay_to",
    "agent.critic_layer_norm": "experimental.critic_layer_norm",
    "dyna.threshold": "check.threshold",
    "dyna.accuracy": "check.accuracy",
    "dyna.relative_threshold": "check.relative_threshold",
    "dyna.holdout_fraction": "check.holdout_fraction",
    "dyna.validation_size": "check.validation_size",
    "dyna.rollout_length": "imagine.rollout_length",
    "dyna.rollouts": "imagine.rollouts",
    "dyna.imagined_buffer_size": "imagine.buffer_size",
    "dyna.real_ratio": "imagine.real_ratio",
    "dyna.imagined_start_fraction": "imagine.imagined_start_fraction",
    "dyna.reset_start_fraction": "imagine.reset_start_fraction",
    "dyna.reward_quadrature": "imagine.reward_quadrature",
    "dyna.select_episodes": "imagine.select_episodes",
    "dyna.reset_start_symmetry": "experimental.reset_start_symmetry",
    "dyna.start_model_after": "model.start_after",
    "dyna.n_intermediate": "model.n_intermediate",
    "dyna.residual": "model.scheme",
    "dyna.physics_prior": "model.prior",
    "dyna.correction_scale": "model.correction_scale",
    "dyna.model_steps": "fit.steps",
    "dyna.model_batch_size": "fit.batch_size",
    "dyna.model_lr": "fit.lr",
    "dyna.finetune_return": "finetune.at_return",
    "dyna.finetune_episodes": "finetune.episodes",
    "dyna.finetune_after": "finetune.after",
    "dyna.physics_weight": "physics.weight",
    "dyna.residual_units": "physics.units",
    "dyna.physics_sources": "physics.sources",
    "dyna.start_physics_after": "physics.start_after",
    "dyna.physics_start": "physics.alone_from",
    "dyna.learn_coefficients": "learn.coefficients",
    "dyna.correction_penalty": "learn.correction_penalty",
    "dyna.coefficient_lr": "learn.lr",
    "dyna.model": None,
}


def old_flag_message(flag: str) -> str | None:
    """A one-line message for a `pimbrl train` flag of the previous release (``None`` for any other flag)."""
    if not flag.startswith("--"):
        return None
    path = flag[2:].replace("-", "_")
    message = renamed_message(path)
    return None if message is None else message.replace(path, flag, 1)


def renamed_message(path: str) -> str | None:
    """A one-line message for an old setting's path (``None`` for any other path)."""
    key = path.replace("agent_config.", "agent.")
    if key not in RENAMED:
        return f"{path} is now {key} ({flag_of(key)})" if key != path else None
    new = RENAMED[key]
    if new is None:
        return (
            f"{path} is now the method itself: --method mbrl or pimbrl with --model.network convlstm, equivariant "
            "or mlp; --method known-scheme (was physics under mbrl), identified-scheme (physics under pimbrl with "
            "learned coefficients), hybrid or pihybrid (hybrid under mbrl or pimbrl)"
        )
    return f"{path} is now {new} ({flag_of(new)})"


def is_legacy(data: Mapping[str, Any]) -> bool:
    """Whether a whole configuration (``config.json``'s ``config``) is in the old flat form.

    The old form names its method with a string; the new one with an object (``{"name": "pimbrl", ...}``).
    """
    method = data.get("method")
    return isinstance(method, str) or (method is None and ("dyna" in data or "agent_config" in data))


def legacy_method(method: str, model: str, learn: str) -> str:
    """The method an old configuration ran: its ``method``, ``dyna.model`` and ``dyna.learn_coefficients``."""
    if method not in ("mbrl", "pimbrl"):
        return method
    if model == "physics":
        return "identified-scheme" if method == "pimbrl" and learn.strip() else "known-scheme"
    if model == "hybrid":
        return "pihybrid" if method == "pimbrl" else "hybrid"
    return method


def method_and_agent(config: Mapping[str, Any]) -> tuple[str, str]:
    """The names of the method and the agent a recorded configuration (old or new form) ran."""
    method, agent = config.get("method"), config.get("agent")
    if is_legacy(config):
        raw = config.get("dyna")
        dyna: Mapping[str, Any] = raw if isinstance(raw, Mapping) else {}
        name = legacy_method(str(method), str(dyna.get("model", "convlstm")), str(dyna.get("learn_coefficients", "")))
        return name, str(agent)
    method_name = method.get("name") if isinstance(method, Mapping) else None
    agent_name = agent.get("name") if isinstance(agent, Mapping) else None
    return str(method_name or "mfrl"), str(agent_name or "td3")


#: the old fields that were option strings (read into structured values)
_TEXTS = ("physics_prior", "physics_sources", "learn_coefficients", "model")


def _value(new_path: str, value: Any) -> Any:
    """An old field's value in its new form (the option strings become structured values)."""
    if new_path == "model.prior":
        return parse_prior(value)
    if new_path == "physics.sources":
        return [] if value == "auto" else [s.strip() for s in value.split(",") if s.strip()]
    return value


def _section(data: Mapping[str, Any], key: str) -> dict[str, Any]:
    value = data.get(key)
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ConfigError(f"{key} must be an object (the old form's {key} section), got {value!r}")
    for name in _TEXTS if key == "dyna" else ():
        if name in value and not isinstance(value[name], str):
            raise ConfigError(f"dyna.{name} must be a string (the old form's text), got {value[name]!r}")
    return dict(value)


def _check_scheme_runs(method: str, dyna: Mapping[str, Any]) -> None:
    """Refuse, in one line, the old scheme runs the typed methods cannot re-create exactly.

    The scheme as the model (nothing trained) was checked from ``physics_start`` on where that came before
    ``start_model_after``; and with ``model_steps`` 0 it was never checked, so never used.
    """
    if method not in ("known-scheme", "identified-scheme"):
        return
    start, labels = dyna.get("physics_start"), dyna.get("start_model_after", 6_000)
    if isinstance(start, int) and isinstance(labels, int) and start < labels:
        fix = f"model.start_after {start}" if method == "known-scheme" else "no equivalent"
        raise ConfigError(
            f"this old {method} run used the scheme from dyna.physics_start {start}, before dyna.start_model_after "
            f"{labels}; the typed method has {fix}: give it explicitly (docs/training.md)"
        )
    if dyna.get("model_steps") == 0:
        raise ConfigError(
            f"this old {method} run had dyna.model_steps 0, so its scheme was never checked nor used (an mfrl run in "
            "effect); re-create it as --method mfrl"
        )


def new_from_legacy(data: Mapping[str, Any], has: Any) -> dict[str, Any]:
    """The overrides (new paths -> values) and the method and agent that run what the old ``data`` ran.

    ``has(method, path)`` says whether the new method's type has a setting: the old configuration wrote every
    field for every method, and those the method ran without are left out. Returns the flat overrides,
    with ``"method"`` and ``"agent"`` set.
    """
    top = {k: v for k, v in data.items() if k not in ("dyna", "agent_config", "env")}
    dyna = _section(data, "dyna")
    agent = _section(data, "agent_config")
    method = legacy_method(
        str(top.get("method", "mfrl")), str(dyna.get("model", "convlstm")), str(dyna.get("learn_coefficients", ""))
    )
    _check_scheme_runs(method, dyna)
    out: dict[str, Any] = {"method": method, "agent": top.pop("agent", "td3")}
    top.pop("method", None)
    for key, value in top.items():
        out[RENAMED.get(key) or key] = value
    for key, value in agent.items():
        new = RENAMED.get(f"agent.{key}") or f"agent.{key}"
        out[new] = value
    for key, value in dyna.items():
        if key == "model":
            if value not in ("physics", "hybrid") and has(method, "model.network"):
                out["model.network"] = value
            continue
        if key == "learn_coefficients":
            learned = parse_learned(value)
            if learned and has(method, "learn.coefficients"):
                out["learn.correction"] = "correction" in learned
                out["learn.coefficients"] = {n: None if r is None else list(r) for n, r in learned.items() if n != "correction"}
            continue
        if f"dyna.{key}" not in RENAMED:
            raise ConfigError(f"unknown old configuration field 'dyna.{key}'")
        target = RENAMED[f"dyna.{key}"]
        if target is None:
            continue
        if target.startswith("experimental."):
            if value and has(method, "imagine.rollout_length"):
                out[target] = value
            continue
        if has(method, target):
            out[target] = _value(target, value)
    return out
