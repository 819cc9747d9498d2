"""`pimbrl train` flags -> typed overrides, below the command line so that experiments can use it.

The flags are generated from the configuration types: the run's fields (``--utd``), the agents' (``--agent.gamma``),
the methods' own (``--model.network``) and their sections' (``--imagine.rollout-length``, ``--physics.weight``), and
the experimental knobs. ``pimbrl train --help`` shows the few a run is usually given (:data:`MAIN_FLAGS`);
``--help-all`` shows every one, with the methods and agents that have it. :func:`parse_train_args` turns a list of
such flags (a sweep file's ``train_args``, the arguments after ``--`` of ``pimbrl compare``) into the typed
override dict that :func:`~pimbrl.training.config.resolve_config` takes; :func:`config_from_argv` is ``pimbrl
train``'s whole configuration step (the environment, then flags).

The two settings whose values are structures are read here, once: ``--model.prior nu=0.007,damping=0`` (a
mapping of coefficients) and ``--learn.coefficients nu,damping:0:1`` (free or ranged coefficients).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
from collections.abc import Sequence
from typing import Any

from ..agents.config import AGENT_NAMES, AGENT_TYPES
from ..config import UNSET, ConfigError, add_arguments, parse_learned, parse_prior
from .config import Experimental, TrainConfig, field_paths, resolve_config
from .legacy import old_flag_message
from .methods import METHOD_TYPES, METHODS, SECTIONS, methods_with

__all__ = [
    "MAIN_FLAGS",
    "add_train_flags",
    "config_from_argv",
    "full_help",
    "overrides_from_namespace",
    "parse_train_args",
    "read_sources",
]

#: the run settings ``pimbrl train --help`` shows (with --method, --agent, --preset, --steps, --env-kwargs)
MAIN_FLAGS = ("seed", "utd", "eval_every", "eval_episodes", "threshold", "threads", "device", "tensorboard")
_RUN_SKIP = ("env", "env_kwargs", "method", "agent", "experimental")
#: the help's note on a setting's default: a system's recipe may set another
RECIPE_NOTE = "default {default!r} where the recipe sets none; --print-config shows the run's"


def _own(cls: type) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if not f.metadata.get("section")]


def _hide(parser: argparse.ArgumentParser, before: int) -> None:
    for action in parser._actions[before:]:
        action.help = argparse.SUPPRESS


def add_train_flags(parser: argparse.ArgumentParser, show_all: bool = False) -> None:
    """Add the configuration flags of ``pimbrl train`` to ``parser``.

    Every setting has a flag (defaults unset, so that only the flags given override a recipe); unless
    ``show_all``, only :data:`MAIN_FLAGS` and the choices of method, agent and recipe appear in the help.
    """
    parser.add_argument(
        "--method",
        default=UNSET,
        metavar="{" + ",".join(METHODS) + "}",
        help="mfrl (model-free), mbrl (data-only model), "
        "pimbrl (physics-informed model, the paper's), known-scheme, identified-scheme, hybrid, pihybrid "
        "(default: the recipe's, else mfrl)",
    )
    parser.add_argument(
        "--agent", default=UNSET, metavar="{" + ",".join(AGENT_NAMES) + "}", help="off-policy agent (default: td3)"
    )
    parser.add_argument(
        "--preset",
        default=None,
        metavar="RECIPE",
        help="the system's recipe: default, paper (the paper's table) or best (the best recorded setting, "
        "naming its study); see docs/systems.md",
    )
    parser.add_argument("--steps", type=int, default=None, help="real environment steps (alias of --total-steps)")
    parser.add_argument(
        "--env-kwargs", dest="env_kwargs_json", default=None, help="JSON object of keyword arguments for gymnasium.make"
    )
    start = len(parser._actions)
    add_arguments(parser, TrainConfig, skip=_RUN_SKIP, default_note=RECIPE_NOTE)
    if not show_all:
        for action in parser._actions[start:]:
            if action.dest not in MAIN_FLAGS:
                action.help = argparse.SUPPRESS
    groups: list[tuple[str, str, list[type]]] = [("agent", "agent.", list(AGENT_TYPES.values()))]
    groups.append(("model", "model.", list(METHOD_TYPES.values())))
    groups += [(name, f"{name}.", [cls]) for name, cls in SECTIONS.items()]
    groups.append(("experimental", "experimental.", [Experimental]))
    seen: set[str] = set()
    for name, prefix, classes in groups:
        target = parser.add_argument_group(f"{name}.* settings") if show_all else parser
        for cls in classes:
            fields = _own(cls) if name == "model" else list(dataclasses.fields(cls))
            skip = tuple(f.name for f in dataclasses.fields(cls) if f.name in seen or f not in fields)
            before = len(parser._actions)
            add_arguments(target, cls, prefix=prefix, skip=skip, default_note=RECIPE_NOTE)  # type: ignore[arg-type]
            for action in parser._actions[before:]:
                path = action.dest
                seen.add(path.split(".", 1)[1])
                if show_all:
                    action.help = f"{action.help} [{_who(path)}]"
            if not show_all:
                _hide(parser, before)
        seen.clear()
    before = len(parser._actions)
    parser.add_argument(
        "--model.prior",
        dest="model.prior",
        default=UNSET,
        metavar="NAME=VALUE,...",
        help="coefficients the run believes where they differ from the environment's (a wrong prior), "
        f"e.g. nu=0.007 [{_who('model.prior')}]",
    )
    parser.add_argument(
        "--learn.coefficients",
        dest="learn.coefficients",
        default=UNSET,
        metavar="NAME[:LOW:HIGH],...",
        help="coefficients fitted to the labels from the prior's values, e.g. nu or damping:0:1; 'correction' "
        f"adds the learned linear correction (PDEs) [{_who('learn.coefficients')}]",
    )
    if not show_all:
        _hide(parser, before)


def _who(path: str) -> str:
    head, _, name = path.partition(".")
    if head == "agent":
        return "agent " + ", ".join(n for n, cls in AGENT_TYPES.items() if name in {f.name for f in dataclasses.fields(cls)})
    if head == "experimental":
        return "experimental"
    return "methods " + ", ".join(methods_with(path))


def overrides_from_namespace(args: argparse.Namespace) -> dict[str, Any]:
    """The configuration flags given in ``args`` (parsed with :func:`add_train_flags`) as overrides.

    For example ``{"total_steps": 200, "agent.gamma": 0.9, "imagine.rollout_length": 5, ...}``.
    """
    overrides = {key: value for key, value in vars(args).items() if value is not UNSET and _is_setting(key)}
    if getattr(args, "steps", None) is not None:
        if args.steps < 1:
            raise ConfigError(f"--steps must be >= 1, got {args.steps}")
        overrides["total_steps"] = args.steps
    if getattr(args, "env_kwargs_json", None):
        try:
            overrides["env_kwargs"] = json.loads(args.env_kwargs_json)
        except json.JSONDecodeError as exc:
            raise ValueError(f'--env-kwargs must be a JSON object, e.g. \'{{"reward": "physical"}}\': {exc}') from None
        if not isinstance(overrides["env_kwargs"], dict):
            raise ValueError(f"--env-kwargs must be a JSON object, got {args.env_kwargs_json}")
    if "physics.sources" in overrides:
        overrides["physics.sources"] = read_sources(overrides["physics.sources"])
    if "model.prior" in overrides:
        overrides["model.prior"] = parse_prior(overrides["model.prior"])
    if "learn.coefficients" in overrides:
        learned = parse_learned(overrides["learn.coefficients"])
        if "correction" in learned:
            if overrides.get("learn.correction") is False:
                raise ConfigError("--learn.coefficients names 'correction' and --learn.correction is false: give one of them")
            overrides["learn.correction"] = True
        overrides["learn.coefficients"] = {n: None if r is None else list(r) for n, r in learned.items() if n != "correction"}
    return overrides


#: what `--physics.sources` takes for every source the system offers
ALL_SOURCES = ("auto", "all", "none")


def read_sources(names: tuple[str, ...]) -> tuple[str, ...]:
    """``--physics.sources``: a list of names, or ``auto`` (also ``all``, ``none`` or nothing) for every source."""
    return () if len(names) <= 1 and (not names or names[0] in ALL_SOURCES) else names


#: the parser's destinations that are settings (the others: --steps, --env-kwargs, --preset, --quiet, ...)
_SETTINGS = frozenset(field_paths())


def _is_setting(dest: str) -> bool:
    return dest in _SETTINGS


def _parser(positional_env: bool) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pimbrl train", add_help=False)
    if positional_env:
        parser.add_argument("env")
    # `pimbrl train --quiet` changes no configuration: accepted in lists of train flags, and ignored
    # (runs started by compare and sweep are always quiet)
    parser.add_argument("--quiet", action="store_true")
    add_train_flags(parser)
    return parser


def _parse(parser: argparse.ArgumentParser, argv: Sequence[str]) -> argparse.Namespace:
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            return parser.parse_args(list(argv))
    except SystemExit:
        old = next((old_flag_message(a.split("=")[0]) for a in argv if old_flag_message(a.split("=")[0])), None)
        if old is not None:  # a flag of the previous release: its new name
            raise ConfigError(old) from None
        lines = err.getvalue().strip().splitlines() or ["unreadable arguments"]
        raise ConfigError(f"bad train arguments {' '.join(argv)!r}: {lines[-1].removeprefix('pimbrl train: error: ')}") from None


def parse_train_args(argv: Sequence[str]) -> dict[str, Any]:
    """Typed overrides from `pimbrl train` flags (no environment).

    For example ``["--steps", "200", "--agent.gamma", "0.9"]`` -> ``{"total_steps": 200, "agent.gamma": 0.9}``
    (``--quiet`` is accepted and ignored; ``--preset`` is not a setting and is refused here). Raises
    :class:`ConfigError` with the parser's message for arguments it cannot read.
    """
    args = _parse(_parser(positional_env=False), argv)
    if args.preset is not None:
        raise ConfigError("--preset chooses a recipe for a whole run; it is not an override (give it to the command)")
    return overrides_from_namespace(args)


def config_from_argv(argv: Sequence[str]) -> TrainConfig:
    """The :class:`TrainConfig` that ``pimbrl train <argv>`` runs (``argv[0]`` the environment or its alias)."""
    from ..simulate import resolve_env_id

    args = _parse(_parser(positional_env=True), argv)
    return resolve_config(resolve_env_id(args.env), overrides_from_namespace(args), preset=args.preset)


def full_help() -> str:
    """``pimbrl train --help-all``: every setting's flag by section, with the methods or agents that have it."""
    parser = argparse.ArgumentParser(
        prog="pimbrl train",
        add_help=False,
        usage="pimbrl train ENV [--method M] [--agent A] [--preset RECIPE] [SETTINGS ...]",
        description="Every setting of a run. A flag the chosen method or agent does not have is an error naming those "
        "that have it; the same settings go in a configuration file (--config FILE, as --print-config writes it).",
    )
    add_train_flags(parser, show_all=True)
    return parser.format_help()
