"""Presets: a system's named training recipes, read from a YAML file next to its definition.

A preset file holds recipes by name and says which one a run gets without ``--preset``::

    default: default           # the recipe of a run that names none
    recipes:
      default:
        about: what this recipe is, in one line
        settings:              # every method
          total_steps: 3000
          agent.gamma: 0.977
        model_based:           # on top, for the methods with a model
          utd: 5.0
          imagine.rollout_length: 1
      best:
        about: ...
        chosen_by: the study that chose it, and on which draws
        method: known-scheme   # a recipe may choose the method (and the agent)
        settings: {...}
        methods:               # on top, for one method each (e.g. each method's tuned settings)
          pimbrl: {physics.weight: 0.01}
        agents:                # on top of those, for one agent each
          crossq: {agent.actor_lr: 0.001}
      paper:
        about: ...
        extends: default       # the default recipe's sections, with this recipe's entries on top
        model_based: {utd: 1.0}

A recipe that ``extends`` another starts from that recipe's ``settings``, ``model_based``, ``methods`` and
``agents`` (section by section, its own entries winning one setting at a time within a section) and its
``method`` and ``agent`` unless it names its own; ``about`` and ``chosen_by`` are the recipe's own. The order
of the sections still holds across the two recipes: a setting in the parent's ``model_based`` (or
``methods``/``agents``) section wins over the same setting in the child's ``settings``; put the child's
entry in the same section to change it. An inherited entry cannot be removed, only given another value.
Chains are followed; a cycle or a missing parent is an error.

Settings are the paths of the training configuration (``utd``, ``agent.gamma``, ``fit.steps``, ...). A
recipe's setting that the chosen method does not have is skipped (a recipe serves every method); the
configuration checks every value. The built-in systems' files are ``pimbrl/systems/<module>.yaml``; a
user's system names its file (or gives the same structure as a mapping) in ``System.preset``.
YAML is read with ``yaml.safe_load``: data only, nothing in the file is executed.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["PresetError", "Recipe", "load_presets"]

_RECIPE_KEYS = {"about", "chosen_by", "extends", "method", "agent", "settings", "model_based", "methods", "agents"}


class PresetError(ValueError):
    """A preset file or mapping that cannot be read (a one-line message naming the file and the fix)."""


@dataclass(frozen=True)
class Recipe:
    """One named recipe of a system's presets.

    Attributes:
        name: its name (``default``, ``paper``, ``best``, ...).
        about: what it is, in one line.
        chosen_by: the study that chose it and on which draws (``best``), else ``""``.
        method: the method it chooses (``""``: the command line's, else mfrl).
        agent: the agent it chooses (``""``: the command line's, else td3).
        settings: configuration paths -> values, for every method.
        model_based: configuration paths -> values, on top for the methods with a model.
        methods: method name -> (configuration paths -> values), on top for that method.
        agents: agent name -> (configuration paths -> values), on top (last) for that agent.
        extends: the recipe it was built on (its sections already merged in here), else ``""``.
    """

    name: str
    about: str = ""
    chosen_by: str = ""
    method: str = ""
    agent: str = ""
    settings: Mapping[str, Any] = field(default_factory=dict)
    model_based: Mapping[str, Any] = field(default_factory=dict)
    methods: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    agents: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    extends: str = ""

    def for_method(self, model_based: bool, method: str = "", agent: str = "") -> dict[str, Any]:
        """The recipe's settings for a method with (``True``) or without a model; ``method``'s and ``agent``'s own on top."""
        return {
            **self.settings,
            **(self.model_based if model_based else {}),
            **self.methods.get(method, {}),
            **self.agents.get(agent, {}),
        }


def _read(source: str | Path | Mapping[str, Any], where: str) -> Mapping[str, Any]:
    if isinstance(source, Mapping):
        return source
    import yaml

    from ..config import load_yaml

    path = Path(source)
    try:
        data = load_yaml(path.read_text())
    except OSError as exc:
        raise PresetError(f"{where}: cannot read the preset file {path} ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark is not None else ""
        raise PresetError(f"{where}: the preset file {path} is not valid YAML{at}") from None
    if not isinstance(data, Mapping):
        raise PresetError(f"{where}: the preset file {path} must hold a mapping with 'recipes', got {type(data).__name__}")
    return data


def _recipe(name: str, body: Any, where: str) -> Recipe:
    if not isinstance(body, Mapping):
        raise PresetError(f"{where}: recipe {name!r} must be a mapping (about, settings, model_based, ...)")
    unknown = set(body) - _RECIPE_KEYS
    if unknown:
        raise PresetError(
            f"{where}: recipe {name!r} has unknown key(s) {', '.join(sorted(map(str, unknown)))}; "
            f"a recipe has {', '.join(sorted(_RECIPE_KEYS))}"
        )
    for key in ("settings", "model_based"):
        value = body.get(key) or {}
        if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
            raise PresetError(f"{where}: recipe {name!r}: {key} must map setting paths (e.g. agent.gamma) to values")
    for key in ("methods", "agents"):
        value = body.get(key) or {}
        if not isinstance(value, Mapping) or not all(
            isinstance(k, str) and isinstance(v, Mapping) and all(isinstance(p, str) for p in v) for k, v in value.items()
        ):
            example = "pimbrl: {physics.weight: 0.01}" if key == "methods" else "crossq: {agent.actor_lr: 0.001}"
            raise PresetError(f"{where}: recipe {name!r}: {key} must map {key[:-1]} names to settings (e.g. {example})")
    for key in ("about", "chosen_by", "extends", "method", "agent"):
        if not isinstance(body.get(key, ""), str):
            raise PresetError(f"{where}: recipe {name!r}: {key} must be a string")
    return Recipe(
        name=name,
        about=body.get("about", ""),
        chosen_by=body.get("chosen_by", ""),
        method=body.get("method", ""),
        agent=body.get("agent", ""),
        settings=dict(body.get("settings") or {}),
        model_based=dict(body.get("model_based") or {}),
        methods={str(k): dict(v) for k, v in (body.get("methods") or {}).items()},
        agents={str(k): dict(v) for k, v in (body.get("agents") or {}).items()},
        extends=body.get("extends", ""),
    )


def _merged(child: Recipe, parent: Recipe) -> Recipe:
    """``child`` on top of ``parent``: each section merged one setting at a time, the child's entries winning."""

    def nested(mine: Mapping[str, Mapping[str, Any]], theirs: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
        return {k: {**theirs.get(k, {}), **mine.get(k, {})} for k in {**theirs, **mine}}

    return Recipe(
        name=child.name,
        about=child.about,
        chosen_by=child.chosen_by,
        method=child.method or parent.method,
        agent=child.agent or parent.agent,
        settings={**parent.settings, **child.settings},
        model_based={**parent.model_based, **child.model_based},
        methods=nested(child.methods, parent.methods),
        agents=nested(child.agents, parent.agents),
        extends=child.extends,
    )


def _resolve_extends(recipes: dict[str, Recipe], where: str) -> dict[str, Recipe]:
    """Every recipe with the recipes it extends merged in (chains followed; a cycle or a missing parent is an error)."""
    done: dict[str, Recipe] = {}

    def resolve(name: str, chain: tuple[str, ...]) -> Recipe:
        if name in done:
            return done[name]
        recipe = recipes[name]
        if recipe.extends:
            if recipe.extends not in recipes:
                import difflib

                close = difflib.get_close_matches(recipe.extends, list(recipes), n=1, cutoff=0.6)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise PresetError(
                    f"{where}: recipe {name!r} extends {recipe.extends!r}, which is not among the recipes "
                    f"({', '.join(recipes)}){hint}"
                )
            if recipe.extends in (*chain, name):
                path = (*chain, name, recipe.extends)
                cycle = " -> ".join(path[path.index(recipe.extends) :])
                raise PresetError(f"{where}: recipes extend each other in a cycle ({cycle}); one of them must extend nothing")
            recipe = _merged(recipe, resolve(recipe.extends, (*chain, name)))
        done[name] = recipe
        return recipe

    return {name: resolve(name, ()) for name in recipes}


def load_presets(source: str | Path | Mapping[str, Any] | None, where: str = "preset") -> tuple[str, dict[str, Recipe]]:
    """The default recipe's name and every recipe of a preset file (or mapping); ``("", {})`` for ``None``.

    Raises :class:`PresetError` (one line, naming ``where``) for a file that cannot be read or a recipe
    that is not a recipe.
    """
    if source is None or (isinstance(source, Mapping) and not source):
        return "", {}
    data = _read(source, where)
    recipes = data.get("recipes")
    if not isinstance(recipes, Mapping) or not recipes:
        raise PresetError(f"{where}: a preset needs 'recipes', a mapping of named recipes (default, paper, best, ...)")
    out = _resolve_extends({str(name): _recipe(str(name), body, where) for name, body in recipes.items()}, where)
    default = data.get("default", "default")
    if default not in out:
        raise PresetError(f"{where}: the default recipe {default!r} is not among the recipes ({', '.join(out)})")
    extra = set(data) - {"default", "recipes"}
    if extra:
        raise PresetError(
            f"{where}: unknown top-level key(s) {', '.join(sorted(map(str, extra)))}; a preset has default and recipes"
        )
    return str(default), out
