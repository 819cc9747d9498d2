"""Controlled systems: each declared once, in one module of this folder or in a user's own file.

The public API of a system of your own (docs/systems.md):

* :class:`ODESystem` and :class:`PeriodicPDESystem`: subclass one, write the equation, reward and initial
  draws; :class:`Coefficient` declares a named coefficient with its physical bounds;
* :func:`declare`: build the environments and register the system under a Gymnasium id and aliases;
* :class:`System` and :func:`register`: the declaration itself, for a system whose environment you wrote
  yourself;
* :func:`declare_external`: someone else's simulator (a Gymnasium env whose state can be read and set),
  with a declared system as its physics prior (:mod:`pimbrl.systems.external`);
* :func:`import_systems` (``--import``) and :func:`load_entry_points` (group ``pimbrl.systems``).

The built-in systems, one module each: :mod:`~pimbrl.systems.cartpole`, :mod:`~pimbrl.systems.pendulum`,
:mod:`~pimbrl.systems.burgers`, :mod:`~pimbrl.systems.ks`. Their classes are importable from here
(``from pimbrl.systems import Burgers, BurgersTask``); they, and the declaration API, are imported on first
use so that ``import pimbrl`` stays light (no torch).
"""

from __future__ import annotations

import importlib
from typing import Any

from .registry import (
    BUILTIN,
    ENTRY_POINT_GROUP,
    System,
    SystemSpecError,
    aliases,
    get_system,
    import_systems,
    load_entry_points,
    register,
    register_builtin,
    resolve_env_id,
    system_ids,
    system_origin,
)

#: name -> module (below this package) of what is imported on first use
_LAZY = {
    **dict.fromkeys(
        (
            "Coefficient",
            "DeclaredTask",
            "FourierOperator",
            "ODESystem",
            "PeriodicPDESystem",
            "declare",
            "gaussian_actuators",
            "xp_of",
        ),
        "declared",
    ),
    **dict.fromkeys(("ExternalTask", "declare_external"), "external"),
    **dict.fromkeys(("CartPole", "CartPoleEnv", "CartPoleTask", "CartPoleVectorEnv"), "cartpole"),
    **dict.fromkeys(("Pendulum", "PendulumEnv", "PendulumTask", "PendulumVectorEnv", "wrap_angle"), "pendulum"),
    **dict.fromkeys(("Burgers", "BurgersEnv", "BurgersTask", "BurgersVectorEnv"), "burgers"),
    **dict.fromkeys(
        (
            "KuramotoSivashinsky",
            "KuramotoSivashinskyEnv",
            "KuramotoSivashinskyVectorEnv",
            "KSTask",
            "KSPool",
            "KSPoolConfig",
            "ks_initial_state_pool",
        ),
        "ks",
    ),
}

__all__ = [
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "System",
    "SystemSpecError",
    "aliases",
    "get_system",
    "import_systems",
    "load_entry_points",
    "register",
    "register_builtin",
    "resolve_env_id",
    "system_ids",
    "system_origin",
    *sorted(_LAZY),
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
