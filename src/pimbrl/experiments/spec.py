"""A study is a spec: a YAML file of systems x arms x seeds x settings, thresholds, statistics and hypotheses.

``pimbrl study run SPEC`` trains its runs (resumably) and writes its record; ``pimbrl study report SPEC``
writes its tables, figures and hypothesis verdicts from that record. A spec::

    name: burgers-main                  # default: the file's stem
    kind: exploratory                   # or confirmatory (see pimbrl.experiments.registration)
    question: Does PiMBRL need fewer real steps than MFRL on Burgers?
    systems: [burgers]
    preset: default                     # the systems' recipe every run starts from
    seeds: [0, 1, 2]                    # or a count: 3 means seeds 0, 1, 2
    methods: [mfrl, mbrl, pimbrl]       # arms; or a mapping of arm names to a method and its overrides:
    #   known-scheme: {method: known-scheme}
    #   mfrl-matched: {method: mfrl, match_updates: true}   # the model-based recipe's update-to-data ratio
    #   pimbrl-w0.1: {method: pimbrl, overrides: {physics.weight: 0.1}}
    #   mpc: {method: mpc, seeds: [0, 1, 2]}   # an arm's own seeds (default: the spec's)
    overrides: {total_steps: 3000}      # every run they apply to (an override applying to none is an error)
    grid: {imagine.rollout_length: [3, 8]}   # every combination is one setting of every arm
    thresholds: [-11]                   # returns the report counts steps to (default: each system's)
    outcome: final                      # a run's result: its last evaluation (final), its selected policy, or
    #                                     the final policy on the holdout pool (holdout: needs holdout_episodes)
    statistics: {confidence: 0.95, reps: 10000}
    comparisons: [[pimbrl, mbrl], [pimbrl, mfrl]]
    hypotheses:
      H1: {claim: PiMBRL reaches -11 in fewer real steps than MBRL, better: pimbrl, than: mbrl,
           metric: steps_to_threshold, threshold: -11}
    tuning: {pimbrl: [pimbrl-w0.01, pimbrl-w0.1], mbrl: [mbrl-l3, mbrl-l8]}   # a tuning study: each method's
    #   candidate arms (as many for every method: equal budgets), chosen by IQM on the validation draws
    #   (overrides: {eval_protocol: validation}); the report names each method's choice
    plan: 9 runs x 4 min / 2 cores = 18 min   # the compute plan, stated before the first run
    paper: PiMBRL reaches its target after 800 steps, MBRL 1,300   # docs/reproduce.md puts ours beside it

A study whose runs were made before the study engine existed names its record instead of running::

    record: {path: ../results/compare_burgers.json, format: compare,
             command: "pimbrl compare burgers --seeds 3 -- --steps 3000"}

Every key is checked when the file is read; an unknown key, arm, method or field is a one-line error
naming the file and the key. The spec's identity is the SHA-256 of its bytes (:attr:`StudySpec.sha256`).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config import MAX_SEED, ConfigError, load_yaml, typed_value
from ..training.config import did_you_mean, typed_overrides
from ..training.methods import METHODS

__all__ = [
    "KINDS",
    "MAX_RUNS",
    "MAX_SEEDS",
    "METRICS",
    "OUTCOMES",
    "RECORD_FORMATS",
    "Arm",
    "Hypothesis",
    "RecordSource",
    "StudySpec",
    "load_spec",
    "parse_spec",
    "safe_component",
    "setting_values",
    "spec_to_yaml",
    "system_id",
]

#: what a study is: confirmatory only through the registration mechanics, everything else exploratory
KINDS = ("exploratory", "confirmatory")
#: a run's result: the return of its last evaluation, or of the policy its model-based selection kept
OUTCOMES = ("final", "selected", "holdout")
#: what a hypothesis compares: the final (or selected) return, or the real steps to a threshold
METRICS = ("final_return", "steps_to_threshold")
#: the formats of records made before the study engine (pimbrl.experiments.legacy_records)
#: ("study": a record the study engine wrote, e.g. benchmarks/results/<name>.json, kept in the repository)
RECORD_FORMATS = ("study", "compare", "sweep", "partial", "steps_ratio", "selection", "protocols")
#: the most runs one study plans, and the most seeds it gives each (planning more would take minutes)
MAX_RUNS = 100_000
MAX_SEEDS = 10_000
#: the shorthand arm of MFRL with the model-based recipe's agent-update budget
MATCHED = "mfrl-matched"

_KEYS = {
    "name",
    "kind",
    "question",
    "systems",
    "preset",
    "seeds",
    "methods",
    "overrides",
    "grid",
    "thresholds",
    "outcome",
    "statistics",
    "comparisons",
    "hypotheses",
    "plan",
    "paper",
    "layout",
    "record",
    "imports",
    "tuning",
}
_ARM_KEYS = {"method", "overrides", "match_updates", "seeds"}
_HYPOTHESIS_KEYS = {"claim", "better", "than", "metric", "threshold", "system"}
_STAT_KEYS = {"confidence", "reps"}
_RECORD_KEYS = {"path", "format", "command", "relabel", "select", "note"}
#: fields a study sets from its own keys, never from overrides or the grid
_OWN = {"env": "systems", "method": "methods", "seed": "seeds"}


@dataclass(frozen=True)
class Arm:
    """One arm of a study: a method with its own overrides (on top of the study's)."""

    name: str
    method: str
    overrides: dict[str, Any] = field(default_factory=dict)
    #: MFRL with the update-to-data ratio of the model-based recipe (unless ``overrides`` set ``utd``)
    match_updates: bool = False
    #: the arm's own seeds (``()``: the spec's), e.g. fewer for a costly arm, or a deterministic controller
    seeds: tuple[int, ...] = ()


def _arm_seeds(arm: Arm, seeds: tuple[int, ...]) -> tuple[int, ...]:
    """The seeds ``arm`` runs: its own, else the spec's ``seeds`` (also while the spec is being read)."""
    return arm.seeds or seeds


@dataclass(frozen=True)
class Hypothesis:
    """A claim the report answers: ``better`` beats ``than`` on ``metric`` (on ``system``, or each system)."""

    id: str
    claim: str
    better: str
    than: str
    metric: str = "final_return"
    threshold: float | None = None
    system: str | None = None


@dataclass(frozen=True)
class RecordSource:
    """A record made before the study engine: where it is, its format and the command that made it."""

    path: Path
    format: str
    command: str = ""
    #: record labels -> arm names where the record's label does not say what ran
    relabel: dict[str, str] = field(default_factory=dict)
    #: which part of the record (for formats that hold several groups)
    select: dict[str, Any] = field(default_factory=dict)
    note: str = ""


@dataclass(frozen=True)
class StudySpec:
    """A parsed, checked study spec (see the module docstring for the file format)."""

    name: str
    systems: tuple[str, ...]
    arms: tuple[Arm, ...]
    seeds: tuple[int, ...]
    kind: str = "exploratory"
    question: str = ""
    preset: str | None = None
    overrides: dict[str, Any] = field(default_factory=dict)
    grid: dict[str, tuple[Any, ...]] = field(default_factory=dict)
    thresholds: tuple[float, ...] = ()
    outcome: str = "final"
    confidence: float = 0.95
    reps: int = 10_000
    comparisons: tuple[tuple[str, str], ...] = ()
    hypotheses: tuple[Hypothesis, ...] = ()
    plan: str = ""
    #: what the paper reports for the question this study answers (docs/reproduce.md puts ours beside it)
    paper: str = ""
    #: run directories: "compact" (ARM/seedK for one system without a grid) or "full" (SYSTEM/ARM/SETTING/seedK)
    layout: str = "auto"
    record: RecordSource | None = None
    #: modules or files declaring the user's systems (``--import``), relative to the spec's directory
    imports: tuple[str, ...] = ()
    #: a tuning study's candidates: each method family's arms, as many for every family (equal budgets)
    tuning: dict[str, tuple[str, ...]] = field(default_factory=dict)
    #: the file it was read from and the SHA-256 of its bytes (empty for a spec built in code)
    path: Path | None = None
    sha256: str = ""
    text: str = ""

    @property
    def arm_names(self) -> tuple[str, ...]:
        """The arms' names, in the spec's order."""
        return tuple(a.name for a in self.arms)

    def seeds_of(self, arm: str | Arm) -> tuple[int, ...]:
        """The seeds ``arm`` runs: its own, else the spec's."""
        return _arm_seeds(self.arm(arm) if isinstance(arm, str) else arm, self.seeds)

    def arm(self, name: str) -> Arm:
        """The arm called ``name``."""
        for a in self.arms:
            if a.name == name:
                return a
        raise KeyError(name)

    @property
    def tuning_budget(self) -> tuple[int, int]:
        """A tuning study's budget per method: its candidates and their seeds; ``(0, 0)`` where it tunes nothing.

        Every method has the same (checked when the spec is read).
        """
        if not self.tuning:
            return 0, 0
        first = next(iter(self.tuning.values()))
        return len(first), len(self.seeds_of(first[0]))

    @property
    def compact(self) -> bool:
        """Whether runs live at ``ROOT/ARM/seedK`` (one system, no grid) rather than the full layout."""
        if self.layout == "auto":
            return len(self.systems) == 1 and not self.grid
        return self.layout == "compact"


def _fail(where: str, message: str) -> ConfigError:
    return ConfigError(f"{where}: {message}")


def _known_keys(body: dict[Any, Any], allowed: set[str], where: str, what: str) -> None:
    """An unknown key of ``body`` (a part of the spec, named by ``what``) is an error naming it and the allowed ones."""
    unknown = sorted(map(str, set(body) - allowed))
    if unknown:
        raise _fail(
            where, f"{what}unknown key {unknown[0]!r}{did_you_mean(unknown[0], allowed)}; allowed: {', '.join(sorted(allowed))}"
        )


def _seeds(value: Any, where: str) -> tuple[int, ...]:
    if isinstance(value, int) and not isinstance(value, bool):
        if not 1 <= value <= MAX_SEEDS:
            raise _fail(where, f"'seeds' as a count must be in [1, {MAX_SEEDS:,}], got {value}")
        return tuple(range(value))
    if not isinstance(value, list) or not value:
        raise _fail(where, f"'seeds' must be a non-empty list of integers or a count, got {value!r}")
    if len(value) > MAX_SEEDS:
        raise _fail(where, f"{len(value):,} seeds are more than a study gives an arm ({MAX_SEEDS:,} at most); give fewer")
    seeds = []
    for s in value:
        if isinstance(s, bool) or not isinstance(s, int) or not 0 <= s <= MAX_SEED:
            raise _fail(where, f"'seeds' must hold integers in [0, {MAX_SEED:,}], got {s!r}")
        if s in seeds:
            raise _fail(where, f"seed {s} is given twice in 'seeds'; give each seed once")
        seeds.append(s)
    return tuple(seeds)


#: names an arm cannot take: the files a study keeps in its directory
_RESERVED = {"record.json", "study.json", "study.yaml", "compare.lock", "report.md", "summary.csv", "summary.json"}


def safe_component(name: Any) -> bool:
    """Whether ``name`` is one safe path component: no slash or backslash, no leading '.', printable, 1 to 100 bytes."""
    return (
        isinstance(name, str)
        and 0 < len(name.encode()) <= 100
        and "/" not in name
        and "\\" not in name
        and not name.startswith(".")
        and name.isprintable()
    )


def _arms(value: Any, where: str) -> tuple[Arm, ...]:
    if isinstance(value, list) and len(set(map(str, value))) != len(value):
        raise _fail(where, f"'methods' names an arm twice ({value!r}); give each once")
    if isinstance(value, list):
        value = {name: {} for name in value} if all(isinstance(n, str) for n in value) else value
    if not isinstance(value, dict) or not value:
        raise _fail(where, f"'methods' must be a non-empty list of methods or a mapping of arm names, got {value!r}")
    arms = []
    known = (*METHODS, MATCHED)
    for name, body in value.items():
        if not safe_component(name) or name in _RESERVED:
            raise _fail(
                where,
                f"arm name {name!r} must be a printable name of at most 100 bytes without '/' or a leading '.', "
                "and not a study file's name",
            )
        body = {} if body is None else body
        if not isinstance(body, dict):
            raise _fail(where, f"arm {name}: must be a mapping with 'method' (and 'overrides'), got {body!r}")
        _known_keys(body, _ARM_KEYS, where, f"arm {name}: ")
        method = body.get("method", name)
        if method not in known:
            raise _fail(
                where, f"arm {name}: unknown method {method!r}{did_you_mean(str(method), known)}; choose from {', '.join(known)}"
            )
        match = bool(body.get("match_updates", False)) or method == MATCHED
        if match and method not in ("mfrl", MATCHED):
            raise _fail(where, f"arm {name}: match_updates is for mfrl arms (MFRL with the model-based update budget)")
        try:
            overrides = typed_overrides(body.get("overrides") or {})
        except ConfigError as exc:
            raise _fail(where, f"arm {name}: {exc}") from None
        for key in overrides:
            if key in _OWN:
                raise _fail(where, f"arm {name}: {key} cannot be overridden: the spec's '{_OWN[key]}' sets it")
        seeds = _seeds(body["seeds"], f"{where}: arm {name}") if "seeds" in body else ()
        arms.append(Arm(name, "mfrl" if method == MATCHED else method, overrides, match, seeds))
    return tuple(arms)


def _pairs(value: Any, arms: Sequence[str], where: str) -> tuple[tuple[str, str], ...]:
    if not isinstance(value, list):
        raise _fail(where, f"'comparisons' must be a list of [arm, arm] pairs, got {value!r}")
    out = []
    for pair in value:
        if not isinstance(pair, list) or len(pair) != 2:
            raise _fail(where, f"'comparisons': each entry is a pair [arm, arm], got {pair!r}")
        for a in pair:
            if a not in arms:
                raise _fail(where, f"'comparisons': {a!r} is not an arm{did_you_mean(str(a), arms)}; arms: {', '.join(arms)}")
        out.append((pair[0], pair[1]))
    return tuple(out)


def setting_values(
    arm: Arm, overrides: Mapping[str, Any], grid: Mapping[str, Sequence[Any]], key: str, default: Any
) -> list[Any]:
    """The values ``key`` takes in the runs of ``arm``: its own override, else the grid's values, else the study's."""
    if key in arm.overrides:
        return [arm.overrides[key]]
    if key in grid:
        return list(grid[key])
    return [overrides.get(key, default)]


def _tuning(
    value: Any,
    arms: Sequence[Arm],
    overrides: Mapping[str, Any],
    grid: Mapping[str, Sequence[Any]],
    outcome: str,
    seeds: tuple[int, ...],
    where: str,
) -> dict[str, tuple[str, ...]]:
    """A tuning study's candidates per method family, checked.

    Known arms, each in one family, equal budgets, and every candidate evaluated on the validation draws
    (a choice must read no test state).
    """
    if not value:
        return {}
    if not isinstance(value, dict) or any(not isinstance(v, list) or not v for v in value.values()):
        raise _fail(where, f"'tuning' must map each method to a non-empty list of its candidate arms, got {value!r}")
    if outcome != "final":
        raise _fail(where, f"a tuning study chooses by each candidate's final validation return: 'outcome: {outcome}' is refused")
    by_name = {a.name: a for a in arms}
    seen: dict[str, str] = {}
    for family, candidates in value.items():
        for arm in candidates:
            if arm not in by_name:
                raise _fail(where, f"'tuning': {arm!r} is not an arm{did_you_mean(str(arm), list(by_name))}")
            if arm in seen:
                raise _fail(where, f"'tuning': arm {arm} is a candidate of both {seen[arm]} and {family}; give it to one")
            seen[arm] = str(family)
            protocols = set(setting_values(by_name[arm], overrides, grid, "eval_protocol", "test"))
            if protocols != {"validation"}:
                shown = ", ".join(sorted(str(p) for p in protocols - {"validation"}))
                raise _fail(
                    where,
                    f"'tuning': arm {arm} is evaluated on the {shown} draws; a tuning study chooses on the validation "
                    "draws alone: set eval_protocol: validation in the overrides",
                )
            if any(setting_values(by_name[arm], overrides, grid, "holdout_episodes", 0)):
                raise _fail(
                    where, f"'tuning': arm {arm} plays the holdout pool (holdout_episodes); a tuning study must not read it"
                )
    sizes = {family: len(candidates) for family, candidates in value.items()}
    if len(set(sizes.values())) > 1:
        listed = ", ".join(f"{f} {n}" for f, n in sizes.items())
        raise _fail(where, f"'tuning': the methods have unequal budgets ({listed} candidates); give each as many")
    counts = {len(_arm_seeds(by_name[arm], seeds)) for candidates in value.values() for arm in candidates}
    if len(counts) > 1:
        raise _fail(
            where,
            f"'tuning': the candidates run unequal numbers of seeds ({', '.join(map(str, sorted(counts)))}); "
            "give every candidate the same (drop the arms' own 'seeds')",
        )
    return {str(family): tuple(candidates) for family, candidates in value.items()}


def _hypotheses(value: Any, arms: Sequence[str], systems: Sequence[str], where: str) -> tuple[Hypothesis, ...]:
    if not isinstance(value, dict):
        raise _fail(where, f"'hypotheses' must map ids (H1, ...) to {{claim, better, than, metric}}, got {value!r}")
    out = []
    for hid, body in value.items():
        if not isinstance(body, dict):
            raise _fail(where, f"hypothesis {hid}: must be a mapping, got {body!r}")
        _known_keys(body, _HYPOTHESIS_KEYS, where, f"hypothesis {hid}: ")
        for key in ("claim", "better", "than"):
            if not isinstance(body.get(key), str) or not body[key]:
                raise _fail(where, f"hypothesis {hid}: '{key}' is missing (a claim and the two arms it compares)")
        for key in ("better", "than"):
            if body[key] not in arms:
                raise _fail(where, f"hypothesis {hid}: '{key}' {body[key]!r} is not an arm; arms: {', '.join(arms)}")
        metric = body.get("metric", "final_return")
        if metric not in METRICS:
            raise _fail(where, f"hypothesis {hid}: metric must be one of {', '.join(METRICS)}, got {metric!r}")
        threshold = body.get("threshold")
        if threshold is not None:
            threshold = typed_value(float, threshold, f"hypothesis {hid}: threshold")
            if not math.isfinite(threshold):
                raise _fail(where, f"hypothesis {hid}: threshold must be a finite number, got {threshold}")
        elif metric == "steps_to_threshold":
            raise _fail(where, f"hypothesis {hid}: steps_to_threshold needs a 'threshold'")
        system = body.get("system")
        if system is not None and system not in systems and system_id(system) not in {system_id(s) for s in systems}:
            raise _fail(where, f"hypothesis {hid}: system {system!r} is not one of the spec's systems")
        out.append(Hypothesis(str(hid), body["claim"], body["better"], body["than"], metric, threshold, system))
    return tuple(out)


def system_id(name: str) -> str:
    """The environment id of a system named in a spec (the name itself where it is not registered here)."""
    from ..simulate import resolve_env_id

    try:
        return resolve_env_id(name)
    except ValueError:
        return name


def _record(value: Any, base: Path, where: str) -> RecordSource:
    if not isinstance(value, dict) or "path" not in value or "format" not in value:
        raise _fail(where, f"'record' must be a mapping with 'path' and 'format', got {value!r}")
    _known_keys(value, _RECORD_KEYS, where, "'record': ")
    if value["format"] not in RECORD_FORMATS:
        raise _fail(where, f"'record': format must be one of {', '.join(RECORD_FORMATS)}, got {value['format']!r}")
    relabel = value.get("relabel") or {}
    select = value.get("select") or {}
    if not isinstance(relabel, dict) or not isinstance(select, dict):
        raise _fail(where, "'record': 'relabel' and 'select' must be mappings")
    return RecordSource(
        path=(base / str(value["path"])).resolve(),
        format=value["format"],
        command=str(value.get("command", "")),
        relabel={str(k): str(v) for k, v in relabel.items()},
        select=dict(select),
        note=str(value.get("note", "")),
    )


def parse_spec(data: Any, *, where: str = "spec", base: Path | None = None, text: str = "") -> StudySpec:
    """A :class:`StudySpec` from the spec's data (a mapping, as read from YAML); errors name ``where``."""
    from ..simulate import resolve_env_id

    if not isinstance(data, dict):
        raise _fail(where, f"a study spec is a mapping of keys, got {type(data).__name__}")
    _known_keys(data, _KEYS, where, "")
    for key in ("systems", "methods", "seeds"):
        if key not in data:
            raise _fail(where, f"'{key}' is missing")
    base = base or Path.cwd()
    systems = data["systems"]
    if isinstance(systems, str):
        systems = [systems]
    if not isinstance(systems, list) or not systems or any(not isinstance(s, str) for s in systems):
        raise _fail(where, f"'systems' must be a non-empty list of system names, got {systems!r}")
    record = _record(data["record"], base, where) if "record" in data else None
    imports = data.get("imports") or []
    if not isinstance(imports, list) or any(not isinstance(i, str) for i in imports):
        raise _fail(where, f"'imports' must be a list of modules or files, got {imports!r}")
    imports = [str((base / i).resolve()) if i.endswith(".py") else i for i in imports]
    if record is None:  # a record made elsewhere may name systems this installation lacks
        if imports:
            from ..systems import import_systems

            import_systems(imports)
        for s in systems:
            try:
                resolve_env_id(s)
            except ValueError as exc:
                raise _fail(where, f"'systems': {exc}") from None
    if len(set(systems)) != len(systems):
        raise _fail(where, "'systems' names a system twice; give each once")
    arms = _arms(data["methods"], where)
    names = [a.name for a in arms]
    seeds = _seeds(data["seeds"], where)
    kind = data.get("kind", "exploratory")
    if kind not in KINDS:
        raise _fail(where, f"'kind' must be one of {', '.join(KINDS)}, got {kind!r}")
    outcome = data.get("outcome", "final")
    if outcome not in OUTCOMES:
        raise _fail(where, f"'outcome' must be one of {', '.join(OUTCOMES)}, got {outcome!r}")
    preset = data.get("preset")
    if preset is not None and not isinstance(preset, str):
        raise _fail(where, f"'preset' must name a recipe (e.g. paper), got {preset!r}")
    try:
        overrides = typed_overrides(data.get("overrides") or {})
        grid_in = data.get("grid") or {}
        if not isinstance(grid_in, dict) or any(not isinstance(v, list) or not v for v in grid_in.values()):
            raise ConfigError("'grid' must map configuration fields to non-empty lists of values")
        grid: dict[str, tuple[Any, ...]] = {}
        for key, values in grid_in.items():
            if key in _OWN:
                raise ConfigError(f"'{key}' cannot be a grid key: the spec's '{_OWN[key]}' sets it")
            if key in overrides:
                raise ConfigError(f"{key} is both a grid key and an override")
            for v in values:
                try:
                    typed_overrides({key: v})
                except ConfigError as exc:
                    raise ConfigError(f"grid: {exc}") from None
            grid[key] = tuple(values)
        for key in overrides:
            if key in _OWN:
                raise ConfigError(f"{key} cannot be overridden: the spec's '{_OWN[key]}' sets it")
        thresholds = data.get("thresholds", [])
        if not isinstance(thresholds, list):
            thresholds = [thresholds]
        thresholds = tuple(typed_value(float, t, "'thresholds'") for t in thresholds)
        if not all(math.isfinite(t) for t in thresholds):
            raise ConfigError(f"'thresholds' must be finite numbers, got {list(thresholds)}")
        stats = data.get("statistics") or {}
        if not isinstance(stats, dict) or set(stats) - _STAT_KEYS:
            raise ConfigError(f"'statistics' takes {', '.join(sorted(_STAT_KEYS))}, got {stats!r}")
        confidence = typed_value(float, stats.get("confidence", 0.95), "statistics.confidence")
        reps = typed_value(int, stats.get("reps", 10_000), "statistics.reps")
        if not math.isfinite(confidence) or not 0.5 <= confidence < 1 or not 100 <= reps <= 1_000_000:
            raise ConfigError("statistics: confidence must be in [0.5, 1) and reps in [100, 1,000,000]")
    except ConfigError as exc:
        raise _fail(where, str(exc)) from None
    if outcome == "holdout" and record is None:
        unset = [a.name for a in arms if not all(setting_values(a, overrides, grid, "holdout_episodes", 0))]
        if unset:
            raise _fail(
                where,
                f"'outcome: holdout' needs holdout_episodes > 0 in the overrides (the holdout pool's episodes each run's "
                f"final policy plays); arm(s) {', '.join(unset)} have none in some run",
            )
    layout = data.get("layout", "auto")
    if layout not in ("auto", "compact", "full"):
        raise _fail(where, f"'layout' must be auto, compact or full, got {layout!r}")
    if layout == "compact" and (len(systems) > 1 or grid):
        raise _fail(where, "'layout: compact' is for one system without a grid")
    n_runs = len(systems) * sum(len(_arm_seeds(a, seeds)) for a in arms) * math.prod(len(v) for v in grid.values())
    if n_runs > MAX_RUNS:
        raise _fail(where, f"{n_runs:,} runs are more than a study plans ({MAX_RUNS:,} at most); give fewer")
    name = data.get("name", Path(where).stem if where.endswith((".yaml", ".yml")) else "study")
    if not safe_component(name):
        raise _fail(where, f"'name' must be a printable name of at most 100 bytes without '/' or a leading '.', got {name!r}")
    return StudySpec(
        name=name,
        systems=tuple(systems),
        arms=arms,
        seeds=seeds,
        kind=kind,
        question=str(data.get("question", "")),
        preset=preset,
        overrides=overrides,
        grid=grid,
        thresholds=thresholds,
        outcome=outcome,
        confidence=confidence,
        reps=reps,
        comparisons=_pairs(data.get("comparisons") or [], names, where),
        hypotheses=_hypotheses(data.get("hypotheses") or {}, names, systems, where),
        plan=str(data.get("plan", "")),
        paper=str(data.get("paper", "")),
        layout=layout,
        record=record,
        imports=tuple(imports),
        tuning=_tuning(data.get("tuning"), arms, overrides, grid, outcome, seeds, where),
        sha256=hashlib.sha256(text.encode()).hexdigest() if text else "",
        text=text,
    )


def load_spec(path: str | Path) -> StudySpec:
    """Read and check the spec at ``path`` (YAML or JSON); its :attr:`~StudySpec.sha256` is of the file's bytes."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise FileNotFoundError(f"study spec {path} does not exist") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file; a study spec is YAML") from None
    try:
        data = load_yaml(text)
    except Exception as exc:  # yaml.YAMLError: one line naming the file
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(f"{path}: not valid YAML ({first})") from None
    spec = parse_spec(data, where=str(path), base=path.resolve().parent, text=text)
    return _with_path(spec, path.resolve(), hashlib.sha256(raw).hexdigest())


def _with_path(spec: StudySpec, path: Path, sha: str) -> StudySpec:
    from dataclasses import replace

    return replace(spec, path=path, sha256=sha)


def spec_to_yaml(data: Mapping[str, Any]) -> str:
    """A spec's data as YAML text (for specs written by a program, e.g. `pimbrl compare`)."""
    import yaml

    return yaml.safe_dump(dict(data), sort_keys=False, default_flow_style=None, width=120)
