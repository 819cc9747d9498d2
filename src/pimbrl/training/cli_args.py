"""`pimbrl train` flags -> typed overrides, below the command line so that experiments can use it.

The flags are generated from the configuration dataclasses (``--utd``, ``--agent.gamma``,
``--dyna.rollout-length``, ...). :func:`parse_train_args` turns a list of such flags (a sweep file's
``train_args``, the arguments after ``--`` of ``pimbrl compare``) into the typed override dict that
:func:`~pimbrl.training.config.resolve_config` takes; :func:`config_from_argv` is ``pimbrl train``'s
whole configuration step (the environment, then flags).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
from collections.abc import Sequence
from typing import Any

from ..agents.config import AgentConfig
from ..config import ConfigError, add_arguments, overrides_from_args
from .config import DynaConfig, TrainConfig, resolve_config

__all__ = ["add_train_flags", "config_from_argv", "overrides_from_namespace", "parse_train_args"]


def add_train_flags(parser: argparse.ArgumentParser) -> None:
    """Add the configuration flags of ``pimbrl train`` to ``parser``.

    These are ``--steps``, ``--env-kwargs`` and one flag per field (defaults unset, so that only the
    flags given override a preset).
    """
    parser.add_argument("--steps", type=int, default=None, help="real environment steps (alias of --total-steps)")
    parser.add_argument(
        "--env-kwargs", dest="env_kwargs_json", default=None, help="JSON object of keyword arguments for gymnasium.make"
    )
    add_arguments(parser, TrainConfig, skip=("env", "env_kwargs", "agent_config", "dyna"))
    add_arguments(parser, AgentConfig, prefix="agent.")
    add_arguments(parser, DynaConfig, prefix="dyna.")


def overrides_from_namespace(args: argparse.Namespace) -> dict[str, Any]:
    """The configuration flags given in ``args`` (parsed with :func:`add_train_flags`) as overrides.

    For example ``{"total_steps": 200, "agent.gamma": 0.9, ...}``.
    """
    overrides = overrides_from_args(args, TrainConfig)
    overrides.pop("env", None)  # the positional environment, not a flag
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
    overrides.update({f"agent.{k}": v for k, v in overrides_from_args(args, AgentConfig, prefix="agent.").items()})
    overrides.update({f"dyna.{k}": v for k, v in overrides_from_args(args, DynaConfig, prefix="dyna.").items()})
    return overrides


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
        lines = err.getvalue().strip().splitlines() or ["unreadable arguments"]
        raise ConfigError(f"bad train arguments {' '.join(argv)!r}: {lines[-1].removeprefix('pimbrl train: error: ')}") from None


def parse_train_args(argv: Sequence[str]) -> dict[str, Any]:
    """Typed overrides from `pimbrl train` flags (no environment).

    For example ``["--steps", "200", "--agent.gamma", "0.9"]`` -> ``{"total_steps": 200, "agent.gamma": 0.9}``
    (``--quiet`` is accepted and ignored). Raises :class:`ConfigError` with the parser's message for
    arguments it cannot read.
    """
    return overrides_from_namespace(_parse(_parser(positional_env=False), argv))


def config_from_argv(argv: Sequence[str]) -> TrainConfig:
    """The :class:`TrainConfig` that ``pimbrl train <argv>`` runs (``argv[0]`` the environment or its alias)."""
    from ..simulate import resolve_env_id

    args = _parse(_parser(positional_env=True), argv)
    return resolve_config(resolve_env_id(args.env), overrides_from_namespace(args))
