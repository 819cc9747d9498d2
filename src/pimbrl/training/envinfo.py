"""What a configuration needs to know of an environment, read from its Gymnasium registration.

Its class (or its pimbrl task class), whether it is a PDE, the keyword arguments it takes and their
defaults. Nothing here steps a simulator: a pimbrl task's physics is built without simulating.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import inspect
from collections.abc import Iterable, Mapping
from typing import Any

from ..config import ConfigError

__all__ = [
    "changed_env_kwargs",
    "check_env_coefficients",
    "check_env_kwargs",
    "check_tensorboard",
    "default_physics",
    "did_you_mean",
    "entry_point",
    "is_pde_env",
    "physics_coefficient_names",
    "task_class",
]


def did_you_mean(word: str, candidates: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the candidate closest to ``word``, or ``""`` where none is close."""
    close = difflib.get_close_matches(word, list(candidates), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def entry_point(env: str) -> Any:
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


def task_class(env: str) -> Any:
    """The task class of a pimbrl environment id (``None`` for any other Gymnasium id)."""
    return getattr(entry_point(env), "task_class", None)


def default_physics(env: str) -> Any:
    """The physics of a pimbrl environment with its default coefficients (``None`` for any other Gymnasium id).

    Built once per task class and process, without simulating (a KS task reads its initial-state pools: about
    a second); a system declared again under the same id has a new task class, so its new physics.
    """
    cls = task_class(env)
    return None if cls is None else _physics_of(cls)


@functools.cache
def _physics_of(cls: type) -> Any:
    return cls().physics


def is_pde_env(env: str) -> bool:
    """Whether ``env`` is a pimbrl environment whose physics is a PDE.

    That is a system whose state is a field on a periodic grid (:attr:`pimbrl.physics.Physics.is_field`:
    Burgers, Kuramoto-Sivashinsky, a declared PDE); ``False`` for the ODE systems and any other Gymnasium id.
    """
    physics = default_physics(env)
    return physics is not None and bool(physics.is_field)


def physics_coefficient_names(env: str) -> tuple[str, ...]:
    """The physical coefficients of a pimbrl environment's physics (``()`` for any other Gymnasium id)."""
    physics = default_physics(env)
    return () if physics is None else tuple(physics.coefficients)


def check_env_coefficients(env: str, kwargs: Mapping[str, Any]) -> None:
    """Raise :class:`ConfigError` for a physical coefficient in ``kwargs`` outside its bounds (``nu: 1e300``).

    Checked when a configuration is resolved, so that a bad value stops a comparison or a sweep before any run
    starts, not inside one.
    """
    names = physics_coefficient_names(env) if kwargs else ()
    given = {k: v for k, v in kwargs.items() if k in names}
    if not given:
        return
    try:
        physics = default_physics(env).with_coefficients(**given)
        check = getattr(physics, "check_stability", None)
        if check is not None:  # an explicit solver step the coefficients make unstable (a PDE's)
            check()
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"env_kwargs: {exc}") from None


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
    entry = entry_point(env)
    if entry is None:
        return None
    try:
        cls = getattr(entry, "task_class", None)
        params = list(inspect.signature(cls or entry).parameters.values())
        coefficients: dict[str, float] = {}
        if cls is not None and any(p.kind is p.VAR_KEYWORD for p in params):
            coefficients = cls().physics.coefficient_values()  # a task's physics is built without simulating
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
