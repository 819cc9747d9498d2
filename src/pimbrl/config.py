"""Typed configuration helpers.

Dataclass fields with documented checks, validation, (de)serialisation and command-line flags generated
from the fields.

A field declared with :func:`param` carries its help text and a check; :func:`validate` runs every check
and raises :class:`ConfigError` naming the field, its allowed range and the bad value.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

__all__ = ["ConfigError", "add_arguments", "from_dict", "overrides_from_args", "param", "replace_path", "to_dict", "validate"]

#: a dataclass instance (typeshed's protocol: anything with ``__dataclass_fields__``)
D = TypeVar("D", bound="DataclassInstance")


class _Unset:
    """Default of generated flags: tells "not given" apart from an explicit ``none``."""

    def __repr__(self) -> str:
        return "<unset>"


UNSET = _Unset()


class ConfigError(ValueError):
    """A configuration value is invalid; the message names the field, the rule and the value."""


def param(default: Any, help: str, check: tuple[Callable[[Any], bool], str] | None = None, **kwargs: Any) -> Any:
    """A dataclass field with a help string and an optional ``(predicate, description)`` check."""
    metadata = {"help": help, "check": check}
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=metadata, **kwargs)
    return dataclasses.field(default=default, metadata=metadata, **kwargs)


def positive(kind: str = "") -> tuple[Callable[[Any], bool], str]:
    return (lambda v: v > 0, f"must be > 0{kind}")


def non_negative() -> tuple[Callable[[Any], bool], str]:
    return (lambda v: v >= 0, "must be >= 0")


def in_range(lo: float, hi: float, lo_open: bool = False, hi_open: bool = False) -> tuple[Callable[[Any], bool], str]:
    def ok(v: Any) -> bool:
        return (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)

    return ok, f"must be in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"


def one_of(*choices: Any) -> tuple[Callable[[Any], bool], str]:
    return (lambda v: v in choices, f"must be one of {', '.join(map(repr, choices))}")


def validate(cfg: Any, prefix: str = "") -> None:
    """Run every field's check (recursively into nested dataclasses)."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        name = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            validate(value, prefix=f"{f.metadata.get('prefix', name)}.")
            continue
        check = f.metadata.get("check")
        if check is None or value is None:
            continue
        predicate, rule = check
        try:
            good = bool(predicate(value))
        except TypeError:
            good = False
        if not good:
            raise ConfigError(f"{name} {rule}, got {value!r}")


def to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-ready dict (tuples become lists)."""
    return dataclasses.asdict(cfg)


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def from_dict(cls: type[D], data: dict[str, Any]) -> D:
    """Rebuild a (nested) config dataclass from :func:`to_dict` output; unknown keys are an error."""
    hints = _field_types(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ConfigError(f"unknown {cls.__name__} field(s): {', '.join(sorted(unknown))}")
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        tp = hints[key]
        if isinstance(tp, type) and dataclasses.is_dataclass(tp) and isinstance(value, dict):
            kwargs[key] = from_dict(tp, value)
        elif _base_type(tp) is tuple and isinstance(value, list):
            kwargs[key] = tuple(value)
        else:
            kwargs[key] = value
    return cls(**kwargs)


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
                return tuple(item(x) for x in text.split(",") if x.strip())
            if base is int:
                return int(float(text)) if float(text).is_integer() else int(text)
            return base(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"--{name}: cannot read {text!r} as {getattr(base, '__name__', base)}") from None

    return parse


def _strip_optional(tp: Any) -> Any:
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    return args[0] if typing.get_origin(tp) in (typing.Union, types.UnionType) and len(args) == 1 else tp


def add_arguments(parser: argparse.ArgumentParser, cls: type, prefix: str = "", skip: tuple[str, ...] = ()) -> None:
    """Add ``--<prefix><field>`` options (dashes for underscores) for every scalar field of ``cls``.

    Defaults are :data:`UNSET` so that only the flags actually given override a preset; ``none`` given
    for an optional field sets it to ``None``.
    """
    hints = _field_types(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if f.name in skip or dataclasses.is_dataclass(tp) or _base_type(tp) is dict:
            continue
        flag = f"--{prefix}{f.name.replace('_', '-')}"
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
            help=f"{f.metadata.get('help', '')} (preset/default: {default!r})",
        )


def overrides_from_args(args: argparse.Namespace, cls: type, prefix: str = "") -> dict[str, Any]:
    """The fields of ``cls`` given on the command line, as ``{name: value}``."""
    out = {}
    for f in dataclasses.fields(cls):
        value = getattr(args, f"{prefix}{f.name}", UNSET)
        if value is not UNSET:
            out[f.name] = value
    return out


def replace_path(cfg: D, path: str, value: Any) -> D:
    """``dataclasses.replace`` through a dotted path, e.g. ``replace_path(cfg, "agent.gamma", 0.98)``."""
    head, _, rest = path.partition(".")
    if not any(f.name == head for f in dataclasses.fields(cfg)):
        raise ConfigError(f"unknown field {path!r} in {type(cfg).__name__}")
    if rest:
        return dataclasses.replace(cfg, **{head: replace_path(getattr(cfg, head), rest, value)})
    return dataclasses.replace(cfg, **{head: value})
