"""The registry of systems: one :class:`System` declaration per controlled system, found by id or alias.

A system is registered once (:func:`register`): its Gymnasium id is registered with its single and vector
environments, its aliases become names every command accepts, and its preset, out-of-sample set and
model-study settings are read from the declaration by whoever needs them (the training configuration,
``pimbrl model-eval``). The four built-in systems are declared the same way, each in its own module of
:mod:`pimbrl.systems`; user systems come from ``--import MODULE_OR_FILE`` (:func:`import_systems`) or from
installed packages' entry points in the group ``pimbrl.systems`` (:func:`load_entry_points`).

This module imports neither torch nor the environments: ``import pimbrl`` registers the built-in systems
by entry point only.
"""

from __future__ import annotations

import contextlib
import difflib
import hashlib
import importlib
import importlib.metadata
import importlib.util
import math
import re
import sys
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import gymnasium as gym

from ..config import FEEDBACK_KINDS

__all__ = [
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "System",
    "SystemSpecError",
    "get_system",
    "import_systems",
    "load_entry_points",
    "register",
    "register_builtin",
    "resolve_env_id",
    "system_ids",
    "system_origin",
]

#: entry-point group in which installed packages declare systems (each entry: a :class:`System`, or a
#: function that registers systems when called)
ENTRY_POINT_GROUP = "pimbrl.systems"

#: the built-in systems: id -> (module under :mod:`pimbrl.systems`, aliases, episode length). Each module's
#: ``SYSTEM`` declares the same (tested), with the envs ``<Name>Env`` and ``<Name>VectorEnv`` (``<Name>``: the
#: id's name); this index lets ``import pimbrl`` register them without importing torch or the environments.
BUILTIN: Mapping[str, tuple[str, tuple[str, ...], int]] = MappingProxyType(
    {
        "pimbrl/KuramotoSivashinsky-v0": ("ks", ("ks", "kuramoto-sivashinsky"), 400),
        "pimbrl/Burgers-v0": ("burgers", ("burgers",), 60),
        "pimbrl/CartPole-v0": ("cartpole", ("cartpole",), 200),
        "pimbrl/Pendulum-v0": ("pendulum", ("pendulum",), 200),
    }
)

_ID = re.compile(r"^[A-Za-z0-9_.-]+/[A-Za-z0-9_.-]+-v\d+$")
_ALIAS = re.compile(r"^[a-z0-9][a-z0-9_.-]*$")


class SystemSpecError(ValueError):
    """A system declaration, registration or import that cannot be used (a one-line message)."""


@dataclass(frozen=True)
class System:
    """Everything the library needs to know about one controlled system, declared once.

    Attributes:
        id: the Gymnasium id, ``namespace/Name-vN`` (e.g. ``example/Duffing-v0``).
        env: the single environment's class (a :class:`~pimbrl.envs.PhysicsEnv` subclass, whose task the
            model-based methods read), or any callable Gymnasium accepts as an entry point.
        vector_env: the native vector environment's class (``None``: Gymnasium's synchronous vectoriser).
        episode_steps: control steps of an episode (the time limit Gymnasium adds).
        aliases: short names every command accepts for :attr:`id` (lower case, e.g. ``duffing``).
        preset: this system's named training recipes (``default``, ``paper``, ``best``, ...): the path of a
            YAML preset file, or the same structure as a mapping (:mod:`pimbrl.systems.presets`); empty:
            none, and a run says so when it starts.
        out_of_sample: ``f(task, rng, n) -> (n, state_dim)`` initial states outside the training
            distribution, for the model study (``pimbrl model-eval``); ``None``: the study is not offered.
        model_eval: settings of ``pimbrl model-eval`` for this system (fields of ``ModelEvalConfig``).
        label: a short name for progress lines (default: the id's name without namespace and version).
        origin: where the declaration came from (``pimbrl``, ``--import FILE``, ``entry point NAME``).
        feedback: its feedback floor (``pimbrl train --method feedback``): ``proportional``, ``lqr`` or
            ``energy-lqr`` (:mod:`pimbrl.control.feedback`); ``None``: proportional for a PDE with actuator
            shapes, an LQR around the origin otherwise.
        feedback_gains: the gains tried on the validation draws (empty: the kind's default grid).
        feedback_options: the controller's further arguments (an LQR's target ``state``, ``action`` and ``q``).
    """

    id: str
    env: Any
    episode_steps: int
    vector_env: Any = None
    aliases: tuple[str, ...] = ()
    preset: Mapping[str, Any] | str | Path = field(default_factory=dict)
    out_of_sample: Callable[..., Any] | None = None
    model_eval: Mapping[str, Any] = field(default_factory=dict)
    label: str | None = None
    origin: str = "pimbrl"
    feedback: str | None = None
    feedback_gains: tuple[float, ...] = ()
    feedback_options: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not _ID.match(self.id):
            raise SystemSpecError(f"system id {self.id!r} must look like 'namespace/Name-v0' (letters, digits, _ . -)")
        if isinstance(self.episode_steps, bool) or not isinstance(self.episode_steps, int) or self.episode_steps < 1:
            raise SystemSpecError(f"{self.id}: episode_steps must be a positive int, got {self.episode_steps!r}")
        if isinstance(self.aliases, str) or not all(isinstance(a, str) and _ALIAS.match(a) for a in self.aliases):
            raise SystemSpecError(
                f"{self.id}: aliases must be a tuple of lower-case names (a-z, 0-9, _ . -), got {self.aliases!r}"
            )
        if not isinstance(self.preset, (Mapping, str, Path)):
            raise SystemSpecError(f"{self.id}: preset must be the path of a preset file or a mapping of recipes")
        if not isinstance(self.model_eval, Mapping):
            raise SystemSpecError(f"{self.id}: model_eval must be a mapping of settings")
        if not callable(self.env):
            raise SystemSpecError(f"{self.id}: env must be an environment class (or a callable that makes the env)")
        if self.feedback is not None and self.feedback not in FEEDBACK_KINDS:
            raise SystemSpecError(f"{self.id}: feedback must be one of {', '.join(FEEDBACK_KINDS)}, got {self.feedback!r}")
        gains = self.feedback_gains
        if isinstance(gains, (str, bytes)) or not all(
            isinstance(g, (int, float)) and not isinstance(g, bool) and math.isfinite(g) and g >= 0 for g in gains
        ):
            raise SystemSpecError(f"{self.id}: feedback_gains must be a tuple of finite numbers >= 0, got {gains!r}")

    def recipes(self) -> tuple[str, dict[str, Any]]:
        """The default recipe's name and the recipes of :attr:`preset` (``("", {})`` without one)."""
        from .presets import load_presets

        return load_presets(self.preset or None, where=f"{self.id} preset")

    @property
    def name(self) -> str:
        """The short label of progress lines."""
        return self.label or self.id.split("/")[-1].rsplit("-v", 1)[0]


_SYSTEMS: dict[str, System] = {}
_ALIASES: dict[str, str] = {alias: env_id for env_id, (_, aliases, _) in BUILTIN.items() for alias in aliases}
#: the origin given to systems registered while :func:`import_systems` runs a user's module
_ORIGIN: list[str] = []
#: the file each declared id was declared in (its --import's file, else its environment's module's), and the
#: file an --import by path is loading: one file imported twice under two names (`import my_systems`, then
#: a study's `imports: [my_systems.py]`) declares the same system twice, not two systems
_DECLARED_IN: dict[str, str] = {}
_LOADING: list[str] = []
#: every registration, in order (what an import registered is read from it)
_REGISTERED: list[str] = []


def register_builtin() -> None:
    """Register the built-in systems with Gymnasium by entry point, importing nothing (idempotent)."""
    for env_id, (module, _, steps) in BUILTIN.items():
        if env_id not in gym.registry:
            path = f"pimbrl.systems.{module}:{env_id.split('/')[1].rsplit('-v', 1)[0]}"
            gym.register(id=env_id, entry_point=f"{path}Env", vector_entry_point=f"{path}VectorEnv", max_episode_steps=steps)


def register(system: System) -> System:
    """Register ``system``: its Gymnasium id (single and vector environments) and its aliases.

    Registering a system again under the same id replaces it (a module imported twice, or one file imported
    by module name and again by its path); a built-in id, an
    id that another library registered with Gymnasium, or an alias another system holds, is a
    :class:`SystemSpecError`. Returns ``system``, with :attr:`System.origin` set to the ``--import`` that is
    running (else to the module of its environment) where the declaration left the default.
    """
    if not isinstance(system, System):
        raise SystemSpecError(f"register() takes a pimbrl.systems.System, got {type(system).__name__}")
    if system.id in BUILTIN:
        raise SystemSpecError(f"{system.id} is a built-in system of pimbrl; give your system an id of its own")
    if system.origin == "pimbrl":  # where it comes from: the --import running, else the module of its env
        origin = _ORIGIN[-1] if _ORIGIN else f"module {getattr(system.env, '__module__', '?')}"
        system = System(**{**system.__dict__, "origin": origin})
    if system.id in gym.registry and system.id not in _SYSTEMS and system.id not in BUILTIN:
        raise SystemSpecError(f"{system.id} is already registered with Gymnasium by another library; choose another id")
    registered = {i.lower() for i in gym.registry}
    for alias in system.aliases:
        holder = _ALIASES.get(alias)
        if holder is not None and holder != system.id:
            raise SystemSpecError(f"{system.id}: the alias {alias!r} already names {holder}; choose another alias")
        if alias in registered and alias != system.id.lower():
            raise SystemSpecError(f"{system.id}: the alias {alias!r} is a registered Gymnasium id; choose another alias")
    old = _SYSTEMS.get(system.id)
    declared_in = _declaring_file(system)
    same_file = declared_in is not None and _DECLARED_IN.get(system.id) == declared_in
    if old is not None and old.origin != system.origin and not same_file:
        raise SystemSpecError(f"{system.id} is already declared by {old.origin}; two declarations cannot share an id")
    if old is not None:
        for alias in old.aliases:
            _ALIASES.pop(alias, None)
    if system.id in gym.registry:
        del gym.registry[system.id]
    gym.register(
        id=system.id,
        entry_point=system.env,
        vector_entry_point=system.vector_env,
        max_episode_steps=system.episode_steps,
    )
    _SYSTEMS[system.id] = system
    if declared_in is not None:
        _DECLARED_IN[system.id] = declared_in
    else:
        _DECLARED_IN.pop(system.id, None)
    for alias in system.aliases:
        _ALIASES[alias] = system.id
    _REGISTERED.append(system.id)
    return system


def get_system(env_id: str) -> System | None:
    """The declaration of a registered system (a built-in one is imported here), ``None`` for other ids."""
    if env_id in _SYSTEMS:
        return _SYSTEMS[env_id]
    if env_id in BUILTIN:
        module = importlib.import_module(f"pimbrl.systems.{BUILTIN[env_id][0]}")
        system = module.SYSTEM
        _SYSTEMS[env_id] = system
        return system
    return None


def system_origin(env_id: str) -> str:
    """Where the system ``env_id`` was declared (:attr:`System.origin`); ``gymnasium`` for another registered id."""
    system = get_system(env_id)
    return system.origin if system is not None else "gymnasium"


def system_ids() -> tuple[str, ...]:
    """The ids of the registered systems: the built-in ones first, then the user's in registration order."""
    return (*BUILTIN, *(i for i in _SYSTEMS if i not in BUILTIN))


def aliases() -> dict[str, str]:
    """Every alias and the id it names."""
    return dict(_ALIASES)


def resolve_env_id(name: str) -> str:
    """Map an alias (``ks``, ``burgers``, a user system's) or a registered Gymnasium id to the id.

    Raises:
        ValueError: a one-line message with the known names and the closest match.
    """
    env_id = name if name in gym.registry else _ALIASES.get(name.lower(), name)
    if env_id not in gym.registry:
        known = ", ".join(sorted(_ALIASES))
        close = difflib.get_close_matches(name, [*_ALIASES, *gym.registry], n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(
            f"unknown environment {name!r}{hint}: use one of {known}, a registered Gymnasium id, or pass "
            "--import MODULE_OR_FILE for a system of your own"
        )
    return env_id


@contextlib.contextmanager
def _origin(text: str) -> Iterator[None]:
    _ORIGIN.append(text)
    try:
        yield
    finally:
        _ORIGIN.pop()


def _declaring_file(system: System) -> str | None:
    """The file that declares ``system``: the file an --import by path is loading, else its env's module's."""
    if _LOADING:
        return _LOADING[-1]
    module = sys.modules.get(getattr(system.env, "__module__", None) or "")
    file = getattr(module, "__file__", None)
    return str(Path(file).resolve()) if file else None


def _module_from_file(path: Path) -> None:
    # one module per file: two files of the same name in different folders are two modules
    digest = hashlib.sha256(str(path).encode()).hexdigest()[:12]
    name = f"pimbrl_user_{re.sub(r'[^0-9A-Za-z_]', '_', path.stem)}_{digest}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise SystemSpecError(f"--import {path}: not a Python file Python can load")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    _LOADING.append(str(path))
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    finally:
        _LOADING.pop()


def import_systems(specs: Sequence[str]) -> list[str]:
    """Import user modules that declare systems (``--import``): a module name or a path to a ``.py`` file.

    A module name is imported with the working directory on the import path; a path (one that ends in
    ``.py`` or contains a path separator) is loaded as a file. Returns the ids registered by the imports.

    Raises:
        SystemSpecError: a one-line message for a missing file or module, or an error raised while importing.
    """
    start = len(_REGISTERED)
    for spec in specs:
        if not isinstance(spec, str) or not spec.strip():
            raise SystemSpecError(f"--import needs a module name or a path to a .py file, got {spec!r}")
        as_file = spec.endswith(".py") or "/" in spec or "\\" in spec
        try:
            with _origin(f"--import {spec}"):
                if as_file:
                    path = Path(spec)
                    if not path.is_file():
                        raise SystemSpecError(f"--import {spec}: no such file; give a path to a .py file or a module name")
                    _module_from_file(path.resolve())
                else:
                    cwd = str(Path.cwd())
                    added = cwd not in sys.path
                    if added:
                        sys.path.insert(0, cwd)
                    try:
                        importlib.import_module(spec)
                    finally:
                        if added:
                            sys.path.remove(cwd)
        except SystemSpecError as exc:
            raise SystemSpecError(f"--import {spec}: {exc}") from None
        except ModuleNotFoundError as exc:
            if exc.name and (exc.name == spec or spec.startswith(exc.name + ".")):
                raise SystemSpecError(
                    f"--import {spec}: no module named {exc.name!r} (run from the folder that holds it, "
                    "or give a path to the .py file)"
                ) from None
            raise SystemSpecError(f"--import {spec} failed: {type(exc).__name__}: {exc}") from None
        except Exception as exc:  # the user's module raised: report it in one line
            raise SystemSpecError(f"--import {spec} failed: {type(exc).__name__}: {exc}") from None
    return list(dict.fromkeys(_REGISTERED[start:]))


def load_entry_points() -> list[str]:
    """Register the systems of installed packages (entry-point group ``pimbrl.systems``); returns their ids.

    Each entry point loads a :class:`System` (registered here) or a function that registers its systems
    when called. An entry point that fails is skipped with a one-line warning naming it (one broken package
    does not stop every command); its systems are then unknown. Loaded once per process.
    """
    if _ENTRY_POINTS_LOADED:
        return []
    _ENTRY_POINTS_LOADED.append(True)
    start = len(_REGISTERED)
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            _load_entry_point(ep)
        except SystemSpecError as exc:
            warnings.warn(str(exc), RuntimeWarning, stacklevel=2)
    return list(dict.fromkeys(_REGISTERED[start:]))


_ENTRY_POINTS_LOADED: list[bool] = []


def _load_entry_point(ep: importlib.metadata.EntryPoint) -> None:
    """Load one entry point of the group (a :class:`SystemSpecError` naming it where it fails)."""
    try:
        with _origin(f"entry point {ep.name}"):
            target = ep.load()
            if isinstance(target, System):
                register(target)
            elif callable(target):
                target()
            else:
                raise SystemSpecError(f"entry point {ep.name} ({ep.value}) is neither a System nor a function")
    except SystemSpecError:
        raise
    except Exception as exc:
        raise SystemSpecError(
            f"entry point {ep.name} ({ep.value}) of group {ENTRY_POINT_GROUP} failed: {type(exc).__name__}: {exc}"
        ) from None
