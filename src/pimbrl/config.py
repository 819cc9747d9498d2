"""Typed configuration helpers.

Dataclass fields with documented checks, validation, (de)serialisation and command-line flags generated
from the fields.

A field declared with :func:`param` carries its help text and a check; :func:`validate` runs every check
and raises :class:`ConfigError` naming the field, its allowed range and the bad value. Every float value
must also be finite (NaN and infinities are rejected for every field, checked or not, unless the field
is declared with ``param(..., finite=False)``), and the sizes and counts carry upper bounds
(:func:`at_most`), stated in their help texts.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import functools
import math
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any

__all__ = [
    "BROAD_SOURCES",
    "FEEDBACK_KINDS",
    "LOOP_SOURCES",
    "MAX_BATCH",
    "MAX_LR",
    "MAX_SEED",
    "MAX_STEPS",
    "MAX_TRANSITIONS",
    "MODEL_KINDS",
    "PHYSICS_MODEL_KINDS",
    "PHYSICS_SOURCES",
    "ConfigError",
    "add_arguments",
    "at_most",
    "check_env_id",
    "field_types",
    "flag_of",
    "load_yaml",
    "overrides_from_args",
    "param",
    "parse_learned",
    "parse_prior",
    "to_dict",
    "typed_value",
    "validate",
]

#: transition models with the prior's coarse scheme inside (pimbrl.models.hybrid), for any system
PHYSICS_MODEL_KINDS = ("physics", "hybrid")
#: every kind of transition model (pimbrl.models.make_model): the networks, then the physics-based ones
MODEL_KINDS = ("convlstm", "equivariant", "mlp", *PHYSICS_MODEL_KINDS)
#: the physics loss's sources (pimbrl.models.state_sources): those the training loop holds (real buffer,
#: imagined buffer), then those made from seed states and the physics; which a system offers depends on its kind
LOOP_SOURCES = ("policy", "imagined")
BROAD_SOURCES = ("symmetry", "scaled", "noise", "box")
PHYSICS_SOURCES = LOOP_SOURCES + BROAD_SOURCES
#: the feedback floors a system may declare (:mod:`pimbrl.control.feedback`)
FEEDBACK_KINDS = ("proportional", "lqr", "energy-lqr")

#: Upper bounds of the sizes and counts of the configurations (docs/training.md, section 'Bounds'): far
#: beyond any run this CPU library can make, low enough that a typo gives a message instead of an
#: ``OverflowError``, a hang or a failed allocation.
#: real environment steps, and every step count compared with them (a billion)
MAX_STEPS = 10**9
#: transitions a buffer holds or a collection gathers (a hundred million; memory is checked too)
MAX_TRANSITIONS = 10**8
#: minibatch sizes
MAX_BATCH = 100_000
#: learning rates (Adam moves each weight by about the learning rate per step)
MAX_LR = 1.0
#: seeds (numpy's classic seed range)
MAX_SEED = 2**32 - 1


def check_env_id(env: Any, registered: bool = False) -> str:
    """``env`` if it is an environment id a configuration file may name, else :class:`ConfigError` saying why.

    A non-empty string that is not Gymnasium's ``module:id`` form: read from a file (a run's ``config.json``,
    ``--config FILE``), that form would import the module it names, code that the person running the command
    did not name. With ``registered``, the id must also be registered with Gymnasium in this process.
    """
    if not isinstance(env, str) or not env:
        raise ConfigError(f"env must be an environment id (a non-empty string), got {env!r}")
    if ":" in env:
        module = env.split(":", 1)[0]
        raise ConfigError(
            f"env {env!r} is Gymnasium's module:id form, which would import the module {module!r}; a run or "
            "configuration file names a registered environment id only (pimbrl imports no module named in a file)"
        )
    if registered:
        import gymnasium as gym

        if env not in gym.registry:
            raise ConfigError(
                f"env {env!r} is not a registered environment here: install or import the package that registers it "
                "(a run names a registered id; pimbrl imports nothing named in a file)"
            )
    return env


class _Unset:
    """Default of generated flags: tells "not given" apart from an explicit ``none``."""

    def __repr__(self) -> str:
        return "<unset>"


UNSET = _Unset()


class ConfigError(ValueError):
    """A configuration value is invalid; the message names the field, the rule and the value."""


#: a check: a predicate and the rule it enforces, in words (``"must be > 0"``)
Check = tuple[Callable[[Any], bool], str]


def param(default: Any, help: str, check: Check | list[Check] | None = None, finite: bool = True, **kwargs: Any) -> Any:
    """A dataclass field with a help string and an optional check.

    ``check`` is a ``(predicate, rule)`` pair or a list of them, tried in order (:func:`validate` names
    the first rule that fails); the rules are appended to the help text, so that ``--help`` states every
    bound. ``finite=False`` lets a float field hold NaN or an infinity (no field does today).
    """
    checks = [] if check is None else list(check) if isinstance(check, list) else [check]
    if checks:
        help = f"{help} ({'; '.join(rule for _, rule in checks)})"
    metadata = {"help": help, "check": checks or None, "finite": finite}
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=metadata, **kwargs)
    return dataclasses.field(default=default, metadata=metadata, **kwargs)


def positive(kind: str = "") -> Check:
    """The check ``value > 0``."""
    return (lambda v: v > 0, f"must be > 0{kind}")


def non_negative() -> Check:
    """The check ``value >= 0``."""
    return (lambda v: v >= 0, "must be >= 0")


def _number(x: float) -> str:
    """``x`` for a message: whole numbers with thousands separators (``100,000,000``), others as written."""
    if isinstance(x, int) or (isinstance(x, float) and x.is_integer() and abs(x) < 1e15):
        return f"{int(x):,}"
    return repr(x)


def at_most(hi: float) -> Check:
    """The check ``value <= hi``: the documented upper bound of a size or a count."""
    return (lambda v: v <= hi, f"must be <= {_number(hi)}")


def in_range(lo: float, hi: float, lo_open: bool = False, hi_open: bool = False) -> Check:
    """The check ``lo <= value <= hi`` (``<`` at an open end)."""

    def ok(v: Any) -> bool:
        return (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)

    return ok, f"must be in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"


def one_of(*choices: Any) -> Check:
    """The check ``value in choices``."""
    return (lambda v: v in choices, f"must be one of {', '.join(map(repr, choices))}")


def _non_finite(value: Any) -> bool:
    """Whether ``value`` is a float NaN or infinity, or a list/tuple holding one."""
    if isinstance(value, (list, tuple)):
        return any(_non_finite(v) for v in value)
    return isinstance(value, float) and not math.isfinite(value)


def validate(cfg: Any, prefix: str = "") -> None:
    """Run every field's checks (recursively into nested dataclasses); the first failure is a :class:`ConfigError`.

    Before its own checks, every field (checked or not) must hold finite floats only, unless it was
    declared with ``param(..., finite=False)``: ``utd must be finite, got inf``.
    """
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        name = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            validate(value, prefix=f"{f.metadata.get('prefix', name)}.")
            continue
        if f.metadata.get("finite", True) and _non_finite(value):
            raise ConfigError(f"{name} must be finite, got {value!r}")
        checks = f.metadata.get("check")
        if checks is None or value is None:
            continue
        for predicate, rule in [checks] if isinstance(checks, tuple) else checks:
            try:
                good = bool(predicate(value))
            except TypeError:
                good = False
            if not good:
                raise ConfigError(f"{name} {rule}, got {value!r}")


def to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-ready dict (tuples become lists)."""
    return dataclasses.asdict(cfg)


@functools.cache
def field_types(cls: type) -> Mapping[str, Any]:
    """The resolved annotations of a config class (read-only), once per class: the parser is built on every command."""
    return types.MappingProxyType(typing.get_type_hints(cls))


def _base_type(tp: Any) -> Any:
    """``int`` for ``int | None``, ``tuple`` for ``tuple[int, ...]``, etc."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return _base_type(args[0]) if len(args) == 1 else str
    if origin is tuple:
        return tuple
    if origin is dict:
        return dict
    if origin is typing.Literal:
        return type(typing.get_args(tp)[0])
    return tp


def _parser_for(tp: Any, name: str) -> Callable[[str], Any]:
    base = _base_type(tp)
    optional = type(None) in typing.get_args(tp)

    def parse(text: str) -> Any:
        if optional and text.lower() in ("none", "null", ""):
            return None
        try:
            if base is bool:
                low = text.lower()
                if low in ("1", "true", "yes", "on"):
                    return True
                if low in ("0", "false", "no", "off"):
                    return False
                raise ValueError(text)
            if base is tuple:
                item = typing.get_args(_strip_optional(tp))[0]
                return tuple(item(x.strip()) for x in text.split(",") if x.strip())
            if base is int:
                return int(float(text)) if float(text).is_integer() else int(text)
            return base(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"--{name}: cannot read {text!r} as {getattr(base, '__name__', base)}") from None

    return parse


def _strip_optional(tp: Any) -> Any:
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    return args[0] if typing.get_origin(tp) in (typing.Union, types.UnionType) and len(args) == 1 else tp


def flag_of(path: str) -> str:
    """The command-line flag of a setting's path: ``imagine.rollout_length`` -> ``--imagine.rollout-length``."""
    return "--" + path.replace("_", "-")


def add_arguments(
    parser: argparse.ArgumentParser,
    cls: type,
    prefix: str = "",
    skip: tuple[str, ...] = (),
    default_note: str = "default {default!r}",
) -> None:
    """Add ``--<prefix><field>`` options (dashes for underscores) for every scalar field of ``cls``.

    ``default_note`` is the help's note on the default (``{default!r}`` is filled in). Defaults are
    :data:`UNSET` so that only the flags actually given override a preset; ``none`` given for an optional
    field sets it to ``None``.
    """
    hints = field_types(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if f.name in skip or dataclasses.is_dataclass(tp) or _base_type(tp) is dict:
            continue
        flag = flag_of(f"{prefix}{f.name}")
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            raise TypeError(f"{cls.__name__}.{f.name} has no default: a config field needs one to make an optional flag")
        parser.add_argument(
            flag,
            dest=f"{prefix}{f.name}",
            type=_parser_for(tp, f"{prefix}{f.name}"),
            default=UNSET,
            metavar=_base_type(tp).__name__.upper() if isinstance(_base_type(tp), type) else "VALUE",
            help=f"{f.metadata.get('help', '')} ({default_note.format(default=default)})",
        )


def overrides_from_args(args: argparse.Namespace, cls: type, prefix: str = "") -> dict[str, Any]:
    """The fields of ``cls`` given on the command line, as ``{name: value}``."""
    out = {}
    for f in dataclasses.fields(cls):
        value = getattr(args, f"{prefix}{f.name}", UNSET)
        if value is not UNSET:
            out[f.name] = value
    return out


def typed_value(tp: Any, value: Any, name: str) -> Any:
    """``value`` checked against the field type ``tp`` (no silent conversion).

    An ``int`` is accepted for a ``float`` field (and becomes a float), a list for a tuple field (and
    becomes a tuple); anything else of the wrong type is a :class:`ConfigError` naming ``name``: a float
    for an int field (``1.7`` is not truncated), a number or a string for a bool field, ...
    """
    optional = type(None) in typing.get_args(tp)
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{name} cannot be none")
    base = _base_type(tp)
    if base is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{name} must be true or false, got {value!r}")
    if base is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        hint = f" (write {int(value)})" if isinstance(value, float) and value.is_integer() else ""
        raise ConfigError(f"{name} must be an integer, got {value!r}{hint}")
    if base is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                return float(value)
            except OverflowError:  # an int beyond the float range
                raise ConfigError(f"{name} must be finite, got an integer of {len(str(abs(value)))} digits") from None
        raise ConfigError(f"{name} must be a number, got {value!r}")
    if base is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{name} must be a string, got {value!r}")
    if base is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{name} must be a list, got {value!r}")
        item = (typing.get_args(_strip_optional(tp)) or (Any,))[0]
        if item is Any:
            return tuple(value)
        return tuple(typed_value(item, v, f"{name}[{i}]") for i, v in enumerate(value))
    if base is dict:
        if isinstance(value, dict):
            return dict(value)
        raise ConfigError(f"{name} must be an object (a dict), got {value!r}")
    return value


# ------------------------------------------------------------------ YAML
#: a float as YAML 1.2 writes it: PyYAML's YAML 1.1 rule reads ``1e-3`` (no dot) as a string
_YAML_FLOAT = r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$"""


def load_yaml(text: str) -> Any:
    """YAML data (``yaml.safe_load``: no object is constructed) with YAML 1.2's floats (``1e-3`` is a number).

    A key given twice in one mapping is an error (``yaml.YAMLError``), not the last one silently kept. The
    data of a text read before is a fresh copy of what it gave then (every command reads the systems'
    preset files; parsing them again costs more than copying), so the caller may change what it gets.
    """
    return copy.deepcopy(_parsed_yaml(text))


@functools.lru_cache(maxsize=64)
def _parsed_yaml(text: str) -> Any:
    """The parse behind :func:`load_yaml`, kept per text (an error is raised again each time, not kept)."""
    import re

    import yaml

    class _Loader(yaml.SafeLoader):
        pass

    def mapping(loader: yaml.SafeLoader, node: yaml.MappingNode) -> dict[Any, Any]:
        loader.flatten_mapping(node)
        keys = set()
        for key_node, _ in node.value:
            key = loader.construct_object(key_node, deep=True)
            if key in keys:  # YAML keeps the last silently: a setting given twice is an error here
                raise yaml.constructor.ConstructorError(
                    None, None, f"the key {key!r} is given twice (line {key_node.start_mark.line + 1})", key_node.start_mark
                )
            keys.add(key)
        return loader.construct_mapping(node, deep=True)

    _Loader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(_YAML_FLOAT, re.X), list("-+0123456789."))
    _Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    return yaml.load(text, Loader=_Loader)


# ------------------------------------------------------------------ physical coefficients
def _coefficient_number(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ConfigError(f"{what}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise ConfigError(f"{what}: must be finite, got {text!r}")
    return value


def parse_prior(spec: str) -> dict[str, float]:
    """``"nu=0.007,damping=0"`` -> ``{"nu": 0.007, "damping": 0.0}`` (``""``: no change)."""
    out: dict[str, float] = {}
    for item in (part.strip() for part in spec.split(",")):
        if not item:
            continue
        name, eq, value = item.partition("=")
        if not eq or not name.strip():
            raise ConfigError(f"physics prior {spec!r}: each item is name=value (e.g. nu=0.007), got {item!r}")
        if name.strip() in out:
            raise ConfigError(f"physics prior {spec!r}: {name.strip()} is given twice")
        out[name.strip()] = _coefficient_number(value.strip(), f"physics prior {name.strip()}")
    return out


def parse_learned(spec: str) -> dict[str, tuple[float, float] | None]:
    """``"nu,damping:0:1"`` -> ``{"nu": None, "damping": (0.0, 1.0)}``: free or ranged coefficients."""
    out: dict[str, tuple[float, float] | None] = {}
    for item in (part.strip() for part in spec.split(",")):
        if not item:
            continue
        parts = [p.strip() for p in item.split(":")]
        if parts[0] in out:
            raise ConfigError(f"learned coefficients {spec!r}: {parts[0]} is given twice")
        if len(parts) == 1:
            out[parts[0]] = None
        elif len(parts) == 3:
            low = _coefficient_number(parts[1], f"learned coefficient {parts[0]} low")
            high = _coefficient_number(parts[2], f"learned coefficient {parts[0]} high")
            if not low < high:
                raise ConfigError(f"learned coefficient {parts[0]}: need low < high, got {low} and {high}")
            out[parts[0]] = (low, high)
        else:
            raise ConfigError(f"learned coefficients {spec!r}: each item is name or name:low:high, got {item!r}")
    return out
