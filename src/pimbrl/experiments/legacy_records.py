"""Records made before the study engine, read into the engine's record (nothing is re-run).

A spec in ``benchmarks/studies/`` names such a record with ``record: {path, format, ...}``;
:func:`import_record` reads it (JSON only, :func:`pimbrl.fileio.strict_json`) and returns a record in the
schema of :func:`pimbrl.experiments.engine.collect_record`, with one run per system, arm, setting and seed.
The formats, and the *label* of each run that ``record.relabel`` maps to an arm:

* ``compare``: ``pimbrl compare`` / ``benchmarks/collect_results.py`` (``compare_<env>*.json``): ``env``,
  ``threshold`` and ``runs``; label: the run's ``method``.
* ``sweep``: ``pimbrl sweep`` (``sweep_*.json``): ``threshold`` and ``rows`` with ``env``, ``method`` and
  ``setting`` (old setting names, e.g. ``dyna.rollout_length``, become their new paths); label: ``method``.
* ``partial``: ``benchmarks/run_partial_physics.py`` (``partial_*.json``, ``known_ks_physics_model.json``):
  ``env``, ``thresholds`` and ``runs`` with ``steps_to_<threshold>``; label: the run's ``variant``; the curve
  is the record's evaluations after the warm-up (``returns_after_warmup``).
* ``steps_ratio``: ``benchmarks/steps_ratio.py`` (``ks_steps_ratio*.json``): ``threshold`` and the run
  lists ``a`` and ``b``; label: the group, ``a`` or ``b``.
* ``selection``: ``benchmarks/selection_summary.py`` (``ks_selection*.json``): ``threshold`` and ``runs``
  (the seed read from ``run_dir``, ``.../seedK``), each with ``final_return`` (its latest policy) and
  ``selected_return`` (the policy its own model-based selection kept; ``outcome: selected`` in the spec
  reports that); label: the record file's stem.
* ``protocols``: ``benchmarks/eval_protocols.py`` (``ks_protocols*.json``): ``runs`` with ``label``,
  ``seed``, ``step`` and one evaluation per protocol; label: the run's ``label``. The run's return is that
  of ``select.protocol`` (``test``, the default: the held-out states; ``authors``: the paper's 5 states):
  its final return for the latest checkpoint, its selected return where the record evaluated the selected
  policy (``policy: selected``; its final return is then the training's, and unknown on ``authors``). Steps
  to the record's threshold (from the training's evaluations on the held-out states) on ``test`` only.

``record.select`` picks part of a record: ``labels: [..]`` keeps the runs of those labels only;
``protocol: test|authors`` (protocols); ``include: [FILE, ..]`` adds the runs of more records of the same
format (paths relative to the record's folder; e.g. seeds recorded in another file).

Checks, each a one-line :class:`~pimbrl.config.ConfigError` naming the file: every field read is there
and of its type; every run's arm (its label after ``relabel``) is an arm of the spec, whose method is the
method that ran, as the record says it or, where it cannot (the runs of the known equation's scheme as
the model were recorded as ``mbrl``, or without a method), as :data:`KNOWN_SCHEME` says from the journal;
every run's seed, system and setting are the spec's; no run is given twice; each of the spec's thresholds
has each run's recorded steps to it. A run's outcome is its final (or selected) return, never
``best_return`` (a maximum over test evaluations), which no record field here is read from.
"""

from __future__ import annotations

import itertools
import os
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from ..config import ConfigError
from ..fileio import strict_json
from .spec import StudySpec
from .stats import threshold_key

__all__ = ["FORMATS", "KNOWN_SCHEME", "PARTIAL_METHODS", "import_record"]

#: the formats this module reads (``spec.RECORD_FORMATS`` less the engine's own, ``study``)
FORMATS = ("compare", "sweep", "partial", "steps_ratio", "selection", "protocols")

_SCHEME_PROTOCOLS = {
    "ks_protocols_physics_model.json": "ks_physics_utd10",
    "ks_protocols_lm25.json": "ks_physics_lm25",
    "ks_protocols_lm25_gamma0.99.json": "ks_physics_lm25_gamma0.99",
    "ks_protocols_lm50_gamma0.99.json": "lm50_gamma0.99",
    "ks_protocols_lm25_reset0.5.json": "lm25_reset0.5",
    "ks_protocols_lm25_reset0.5_selected.json": "sel",
    "ks_protocols_lm25_reset0.5_selected_seeds6-7.json": "sel",
    "ks_protocols_lm25_reset0.5_selected_seeds8-9.json": "sel",
    "ks_protocols_lm25_reset0.5_lrdecay_selected.json": "lrd",
}
_SELECTIONS = ("", "_6seeds", "_8seeds", "_10seeds")
#: record file -> the labels of its runs that ran the known equation's coarse scheme as the model (no
#: network, no physics loss) although the record cannot say so (``method: mbrl`` or none); from the journal
#: (``--method mbrl --dyna.model physics``, now ``--method known-scheme``)
KNOWN_SCHEME: dict[str, tuple[str, ...]] = {
    **{f"ks_steps_ratio{s}.json": ("a",) for s in _SELECTIONS},
    **{f"ks_selection_lm25_reset0.5{s}.json": (f"ks_selection_lm25_reset0.5{s}",) for s in (*_SELECTIONS, "_lrdecay")},
    **{name: (label,) for name, label in _SCHEME_PROTOCOLS.items()},
}
#: run_partial_physics.py's variants -> the method each ran (its ``variant_args``)
PARTIAL_METHODS = {
    "mbrl": "mbrl",
    "pimbrl-wrong": "pimbrl",
    "pimbrl-learned": "pimbrl",
    "pimbrl-learned-correction": "pimbrl",
    "pimbrl-true": "pimbrl",
    "physics-wrong": "known-scheme",
    "physics-learned": "identified-scheme",
    "hybrid-learned": "pihybrid",
    "physics-true": "known-scheme",
}
_SELECT_KEYS = {"labels", "protocol", "include"}
_PROTOCOLS = ("test", "authors")

#: one run as a format reads it: (label, the method that ran, or None where the record does not say, run)
_Raw = tuple[str, "str | None", dict[str, Any]]


def _num(value: Any, name: str, *, optional: bool = False) -> Any:
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} is {value!r}, not a number")
    return value


def _run(
    r: Mapping[str, Any], *, seed: Any, steps: Any, final: Any, steps_to: Mapping[float, Any], **extra: Any
) -> dict[str, Any]:
    """The engine's fields of one run from what a record holds (``extra`` overrides the defaults)."""
    steps = int(_num(steps, "steps"))
    run = {
        "seed": int(_num(seed, "seed")),
        "finished": r.get("finished"),
        "steps": steps,
        "final_return": _num(final, "final_return", optional=True),
        "selected_return": None,
        "wall_s": _num(r.get("wall_s"), "wall_s", optional=True),
        "updates": _num(r.get("updates"), "updates", optional=True),
        "real_transitions": steps,
        "imagined_transitions": None,
        "scheme_transitions": None,
        "provenance": None,
        "curve": None,
        "steps_to": {threshold_key(t): _num(s, f"steps to {t:g}", optional=True) for t, s in steps_to.items()},
    }
    run.update(extra)
    return run


def _compare(data: Mapping[str, Any], select: Mapping[str, Any], name: str) -> tuple[list[_Raw], list[float]]:
    t = float(_num(data["threshold"], "threshold"))
    runs: list[_Raw] = []
    for r in data["runs"]:
        method = str(r["method"])
        run = _run(
            r,
            seed=r["seed"],
            steps=r["steps"],
            final=r["final_return"],
            steps_to={t: r["steps_to_threshold"]},
            system=data["env"],
        )
        runs.append((method, "mfrl" if method == "mfrl-matched" else method, run))
    return runs, [t]


def _sweep(data: Mapping[str, Any], select: Mapping[str, Any], name: str) -> tuple[list[_Raw], list[float]]:
    from ..training.legacy import RENAMED

    t = float(_num(data["threshold"], "threshold"))
    runs: list[_Raw] = []
    for r in data["rows"]:
        parts = []
        for item in str(r["setting"]).split(","):
            key, sep, value = item.partition("=")
            parts.append(f"{RENAMED.get(key) or key}{sep}{value}")
        setting = ",".join(parts)
        run = _run(
            r, seed=r["seed"], steps=r["steps"], final=r["final_return"], steps_to={t: r["steps_to_threshold"]}, system=r["env"]
        )
        runs.append((str(r["method"]), str(r["method"]), {**run, "setting": setting}))
    return runs, [t]


def _partial(data: Mapping[str, Any], select: Mapping[str, Any], name: str) -> tuple[list[_Raw], list[float]]:
    thresholds = [float(_num(t, "thresholds")) for t in data["thresholds"]]
    cpu = (data.get("machine") or {}).get("cpu")
    runs: list[_Raw] = []
    for r in data["runs"]:
        variant = str(r["variant"])
        if variant not in PARTIAL_METHODS:
            raise ValueError(f"unknown variant {variant!r}")
        after = r.get("returns_after_warmup")
        curve = None
        if after:
            steps = sorted(after, key=int)
            curve = {
                "step": [int(s) for s in steps],
                "return_mean": [float(_num(after[s], "returns_after_warmup")) for s in steps],
            }
        steps_to = {t: r[f"steps_to_{threshold_key(t)}"] for t in thresholds}
        run = _run(
            r, seed=r["seed"], steps=r["steps"], final=r["final_return"], steps_to=steps_to, system=data["env"], curve=curve
        )
        run["provenance"] = {"cpu": cpu} if cpu else None
        runs.append((variant, PARTIAL_METHODS[variant], run))
    return runs, thresholds


def _steps_ratio(data: Mapping[str, Any], select: Mapping[str, Any], name: str) -> tuple[list[_Raw], list[float]]:
    t = float(_num(data["threshold"], "threshold"))
    cpu = (data.get("machine") or {}).get("cpu")
    runs: list[_Raw] = []
    for group in ("a", "b"):
        for r in data[group]:
            run = _run(r, seed=r["seed"], steps=r["steps"], final=r["final_return"], steps_to={t: r["steps_to_threshold"]})
            run["provenance"] = {"cpu": cpu} if cpu else None
            runs.append((group, r.get("method"), run))
    return runs, [t]


def _seed_of(run_dir: Any) -> int:
    match = re.fullmatch(r"seed(\d+)", Path(str(run_dir)).name)
    if match is None:
        raise ValueError(f"run_dir {run_dir!r} does not end in seedK: its seed is unknown")
    return int(match.group(1))


def _selection(data: Mapping[str, Any], select: Mapping[str, Any], name: str) -> tuple[list[_Raw], list[float]]:
    t = float(_num(data["threshold"], "threshold"))
    cpu = (data.get("machine") or {}).get("cpu")
    label = Path(name).stem
    runs: list[_Raw] = []
    for r in data["runs"]:
        run = _run(
            r,
            seed=_seed_of(r["run_dir"]),
            steps=r["steps"],
            final=r["final_return"],
            steps_to={t: r["steps_to_threshold"]},
            selected_return=_num(r["selected_return"], "selected_return"),
            selected_step=_num(r.get("selected_step"), "selected_step", optional=True),
        )
        run["provenance"] = {"cpu": cpu} if cpu else None
        runs.append((label, None, run))
    return runs, [t]


def _protocols(data: Mapping[str, Any], select: Mapping[str, Any], name: str) -> tuple[list[_Raw], list[float]]:
    protocol = select.get("protocol", "test")
    if protocol not in _PROTOCOLS:
        raise ValueError(f"select.protocol must be one of {', '.join(_PROTOCOLS)}, got {protocol!r}")
    t = data.get("threshold")
    cpu = (data.get("machine") or {}).get("cpu")
    runs: list[_Raw] = []
    has_steps = True
    for r in data["runs"]:
        training = r.get("training") or {}
        value = _num(r[protocol]["return_mean"], f"{protocol}.return_mean")
        selected = r.get("policy") == "selected"
        final = (training["final_return"] if protocol == "test" else None) if selected else value
        steps_to = {}
        if t is not None and protocol == "test" and "steps_to_threshold" in training:
            steps_to = {float(_num(t, "threshold")): training["steps_to_threshold"]}
        else:
            has_steps = False
        run = _run({**training, "finished": None}, seed=r["seed"], steps=r["step"], final=final, steps_to=steps_to)
        run["selected_return"] = value if selected else None
        run["selected_step"] = r.get("policy_step") if selected else None
        run["provenance"] = {"cpu": cpu} if cpu else None
        label, method = str(r["label"]), str(r["method"])
        runs.append((label, "mfrl" if label == "mfrl-matched" else method, run))
    return runs, [float(t)] if t is not None and has_steps else []


_READERS: dict[str, Callable[[Mapping[str, Any], Mapping[str, Any], str], tuple[list[_Raw], list[float]]]] = {
    "compare": _compare,
    "sweep": _sweep,
    "partial": _partial,
    "steps_ratio": _steps_ratio,
    "selection": _selection,
    "protocols": _protocols,
}


def _read(path: Path, fmt: str, select: Mapping[str, Any]) -> tuple[dict[str, Any], list[_Raw], list[float]]:
    try:
        data = strict_json(path.read_bytes(), path)
    except FileNotFoundError:
        raise ConfigError(f"{path}: the record does not exist") from None
    except ValueError as exc:
        raise ConfigError(str(exc).splitlines()[0]) from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: not a {fmt} record (a JSON object was expected, got {type(data).__name__})")
    try:
        runs, thresholds = _READERS[fmt](data, select, path.name)
    except KeyError as exc:
        raise ConfigError(f"{path}: not a {fmt} record (missing field {exc})") from None
    except (TypeError, ValueError, AttributeError) as exc:
        raise ConfigError(
            f"{path}: not a {fmt} record ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
        ) from None
    return data, runs, thresholds


def import_record(spec: StudySpec) -> dict[str, Any]:
    """The record ``spec.record`` names, read into the study engine's schema (see the module docstring).

    Args:
        spec: a spec whose ``record`` has one of :data:`FORMATS`.

    Returns:
        The record: ``format``, ``study``, ``kind``, the spec's SHA-256 and text, ``provenance``, ``legacy``
        (the file and format read), ``thresholds`` per system, ``runs``, ``missing`` and ``unreadable``.

    Raises:
        ConfigError: a one-line message naming the file and what is wrong with it or with the spec.
    """
    from ..simulate import resolve_env_id

    source = spec.record
    if source is None or source.format not in FORMATS:
        raise ConfigError(f"study {spec.name}: no record made before the study engine to import (formats: {', '.join(FORMATS)})")
    path, fmt, select = source.path, source.format, source.select
    unknown = sorted(set(select) - _SELECT_KEYS)
    if unknown:
        raise ConfigError(
            f"{spec.path or spec.name}: record.select: unknown key {unknown[0]!r}; allowed: {', '.join(sorted(_SELECT_KEYS))}"
        )
    include = select.get("include") or []
    labels = select.get("labels")
    if not isinstance(include, list) or (labels is not None and not isinstance(labels, list)):
        raise ConfigError(f"{spec.path or spec.name}: record.select: 'include' and 'labels' must be lists")
    data, first, thresholds = _read(path, fmt, select)
    raw = [(path, r) for r in first]
    files = [path]
    for extra in include:
        more = (path.parent / str(extra)).resolve()
        raw += [(more, r) for r in _read(more, fmt, select)[1]]
        files.append(more)
    systems = {resolve_env_id(s): s for s in spec.systems}
    only = next(iter(systems)) if len(systems) == 1 else None
    grid = _settings(spec)
    runs: list[dict[str, Any]] = []
    seen: set[tuple[str, str, str, int]] = set()
    for file, (label, method, run) in raw:
        if labels is not None and label not in labels:
            continue
        where = f"{file}: the {label!r} run of seed {run['seed']}"
        arm_name = source.relabel.get(label, label)
        if arm_name not in spec.arm_names:
            raise ConfigError(f"{where}: {arm_name!r} is not an arm of the spec ({', '.join(spec.arm_names)}); relabel it")
        arm = spec.arm(arm_name)
        known = "known-scheme" if label in KNOWN_SCHEME.get(file.name, ()) else method
        if known is not None and arm.method != known:
            raise ConfigError(
                f"{where} ran {known}, but the spec's arm {arm_name!r} is {arm.method}; relabel it to an arm of {known}"
            )
        if label == "mfrl-matched" and not arm.match_updates:
            raise ConfigError(f"{where} is MFRL with the model-based update budget; its arm {arm_name!r} needs match_updates")
        system = run.pop("system", None) or only
        if system is None:
            raise ConfigError(f"{path}: the record does not name its system; give the spec one system")
        try:
            system = resolve_env_id(system)
        except ValueError as exc:
            raise ConfigError(f"{where}: {str(exc).splitlines()[0]}") from None
        if system not in systems:
            raise ConfigError(f"{where} is on {system}, not one of the spec's systems ({', '.join(spec.systems)})")
        setting = run.pop("setting", "default")
        if setting not in grid:
            raise ConfigError(f"{where} has the setting {setting!r}, not one of the spec's ({', '.join(sorted(grid))})")
        if run["seed"] not in spec.seeds_of(arm):
            whose = f"arm {arm.name}" if arm.seeds else "the spec"
            raise ConfigError(f"{where}: seed {run['seed']} is not one of {whose}'s seeds")
        ident = (system, arm_name, setting, run["seed"])
        if ident in seen:
            raise ConfigError(f"{where} is given twice (system, arm, setting and seed); select or relabel the runs apart")
        seen.add(ident)
        budget = {**spec.overrides, **arm.overrides}.get("total_steps")
        if run["finished"] is None and budget is not None:
            run["finished"] = run["steps"] >= int(budget)
        if run["final_return"] is None and spec.outcome == "final":
            raise ConfigError(f"{where} has no final return on this protocol (only its selected policy's); set outcome: selected")
        runs.append(
            {"system": system, "arm": arm_name, "label": label, "method": arm.method, "setting": setting, "budget": budget, **run}
        )
    _check_complete(spec, runs, path)
    wanted = [float(t) for t in spec.thresholds] or thresholds
    for r in runs:
        for t in wanted:
            if threshold_key(t) not in r["steps_to"]:
                recorded = _listed(thresholds)
                raise ConfigError(
                    f"{path}: threshold {t:g}: the record holds no steps to it for the {r['label']!r} runs; recorded: {recorded}"
                )
    machine: dict[str, Any] = data["machine"] if isinstance(data.get("machine"), dict) else {}
    base = spec.path.parent if spec.path is not None else Path.cwd()
    return {
        "format": "pimbrl-study-record/1",
        "study": spec.name,
        "kind": spec.kind,
        "spec_sha256": spec.sha256,
        "spec": spec.text,
        "registration": None,
        "provenance": {"cpu": machine.get("cpu"), "commit": None, "python": machine.get("python"), "torch": machine.get("torch")},
        "legacy": {"path": _relative(path, base), "format": fmt, "include": [_relative(f, base) for f in files[1:]]},
        "thresholds": {s: list(wanted) for s in systems},
        "runs": runs,
        "missing": [],
        "unreadable": [],
    }


def _settings(spec: StudySpec) -> set[str]:
    keys = list(spec.grid)
    if not keys:
        return {"default"}
    return {",".join(f"{k}={v}" for k, v in zip(keys, values)) for values in itertools.product(*(spec.grid[k] for k in keys))}


def _check_complete(spec: StudySpec, runs: list[dict[str, Any]], path: Path) -> None:
    """Every arm and seed the spec declares has a run in the record (the spec says what the record holds)."""
    arms = {r["arm"] for r in runs}
    pairs = {(r["arm"], r["seed"]) for r in runs}
    for arm in spec.arms:
        if arm.name not in arms:
            raise ConfigError(
                f"{path}: the spec's arm {arm.name!r} has no run in the record (relabel or select its runs, or drop the arm)"
            )
        for seed in arm.seeds:  # an arm's own seeds: each has its run
            if (arm.name, seed) not in pairs:
                raise ConfigError(f"{path}: arm {arm.name!r}'s seed {seed} has no run in the record")
    seeds = {seed for _, seed in pairs}
    for seed in spec.seeds:  # the spec's: each has a run of some arm (an old record may give an arm fewer)
        if seed not in seeds:
            raise ConfigError(f"{path}: the spec's seed {seed} has no run in the record")


def _listed(thresholds: list[float]) -> str:
    return ", ".join(f"{t:g}" for t in thresholds) or "none"


def _relative(path: Path, base: Path) -> str:
    try:
        return os.path.relpath(path, base)
    except ValueError:  # another drive (Windows)
        return str(path)
