"""`pimbrl sweep`: a grid of runs (environments x methods x seeds x parameter values) on Ray.

A sweep file (JSON, or TOML on Python >= 3.11) describes the grid::

    {
      "name": "ks-rollout-length",
      "envs": ["ks"],
      "methods": ["pimbrl"],
      "seeds": [0, 1],
      "grid": {"imagine.rollout_length": [3, 8, 40, 120]},
      "overrides": {"total_steps": 60000},
      "threshold": -55,
      "preset": "default"
    }

``grid`` keys are configuration fields (``utd``, ``agent.gamma``, ``check.threshold``, ...); every
combination of their values is one setting. ``overrides`` sets fields for every trial (field paths ->
values, like the grid). Values are type-checked against their fields when the file is read: a float for an
int field (``"imagine.rollout_length": [1.7]``) or a number for a bool field is an error, as is an unknown
field. ``train_args``, a list of `pimbrl train` flags (``["--steps", "60000"]``), is still accepted and
read into overrides once, when the file is loaded. ``preset`` names the systems' recipe every trial starts
from (default: each system's default recipe).

A grid key must apply to every method and environment of the sweep (``imagine.*`` with mfrl is an error,
since every setting would be the same run); an override applies to the trials it fits (``fit.*`` to the
trials of methods with a model, an agent field of SAC to SAC trials) and is an error only where it fits none.

Every (env, method, setting, seed) is one trial: its resolved :class:`~pimbrl.training.TrainConfig`
and a resumable run directory ``DIR/<env>/<method>/<setting>/seed<k>``. Every trial's configuration is
resolved and checked before any trial runs. Finished trials are skipped (a finished sweep re-runs in no
time), interrupted ones resume from their checkpoint, and a failed trial is reported without stopping the
others.

A sweep is a study (:func:`sweep_study`, run by :mod:`pimbrl.experiments.engine`, which also writes its
record, ``DIR/record.json``, and ``DIR/study.yaml``: `pimbrl study report DIR/study.yaml` reports it).
Trials run as Ray tasks (one CPU each) on a local Ray instance started for the sweep (its helper processes
end with the driver, also a killed one), or on an existing cluster with ``--address`` (the workers need
pimbrl installed and the run directory on a shared file system). Without Ray, or with ``--no-ray``, they
run as local processes, one per core: the outputs are the same, since a trial's result depends only on
its configuration and seed. The results are aggregated
into ``DIR/results.csv`` (one row per trial), ``DIR/summary.json`` and ``DIR/curves.png``.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config import ConfigError, typed_value
from ..fileio import atomic_write_bytes
from ..training import METHODS, RunDirectory, TrainConfig
from ..training.cli_args import parse_train_args
from ..training.config import did_you_mean, typed_overrides
from .engine import plan_study, ray_available, run_study
from .spec import StudySpec, parse_spec, spec_to_yaml

__all__ = ["SweepSpec", "Trial", "load_sweep", "plan_trials", "ray_available", "run_sweep", "sweep_study"]

#: fields a sweep sets from its own keys (envs, methods, seeds), not from the grid or overrides
_OWN = {"env": "envs", "method": "methods", "seed": "seeds"}


@dataclass(frozen=True)
class SweepSpec:
    """A sweep: environments, methods and seeds crossed with a grid of settings.

    ``grid`` maps field paths to the values to try, ``overrides`` fields to set in every trial (both
    typed: see :func:`~pimbrl.training.config.typed_overrides`).
    """

    name: str
    envs: tuple[str, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    grid: dict[str, tuple[Any, ...]] = field(default_factory=dict)
    overrides: dict[str, Any] = field(default_factory=dict)
    threshold: float | None = None
    #: the systems' recipe every trial starts from (``None``: each system's default)
    preset: str | None = None


@dataclass(frozen=True)
class Trial:
    """One run of a sweep: an environment, a method, a seed and one setting of the grid."""

    env: str
    method: str
    seed: int
    params: tuple[tuple[str, Any], ...]  # the grid values of its setting, as written in the sweep file
    path: str
    config: TrainConfig
    #: the ``--import`` arguments (systems of the user's own) a worker loads before it runs the trial
    imports: tuple[str, ...] = ()

    @property
    def setting(self) -> str:
        """The setting's grid values as ``"key=value,..."`` (``"default"`` for an empty grid)."""
        return ",".join(f"{k}={v}" for k, v in self.params) or "default"

    @property
    def label(self) -> str:
        """A short name for logs: environment, method and setting."""
        return f"{self.env.split('/')[-1]} {self.method} {self.setting}"


_KEYS = {"name", "envs", "methods", "seeds", "grid", "overrides", "train_args", "threshold", "preset"}


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and check a sweep file; errors name the file and the offending key."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"sweep file {path} does not exist")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a text file ({exc}); a sweep file is JSON or TOML") from None
    if path.suffix == ".toml":
        if sys.version_info >= (3, 11):
            import tomllib

            try:
                data = tomllib.loads(text)
            except tomllib.TOMLDecodeError as exc:
                raise ConfigError(f"{path}: not valid TOML ({exc})") from None
        else:  # pragma: no cover - Python 3.10 has no tomllib
            raise ConfigError(f"{path}: TOML sweep files need Python >= 3.11; use JSON")
    else:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a sweep file is an object (a table) of keys, got {type(data).__name__}")
    unknown = set(data) - _KEYS
    if unknown:
        names = sorted(unknown)
        raise ConfigError(
            f"{path}: unknown key(s) {', '.join(names)}{did_you_mean(names[0], _KEYS)}; allowed: {', '.join(sorted(_KEYS))}"
        )
    for key in ("envs", "methods", "seeds"):
        if key not in data:
            raise ConfigError(f"{path}: '{key}' is missing: it must be a non-empty list")
        if not isinstance(data[key], list) or not data[key]:
            raise ConfigError(f"{path}: '{key}' must be a non-empty list, got {data[key]!r}")
    if any(not isinstance(e, str) for e in data["envs"]):
        raise ConfigError(f"{path}: 'envs' must be a list of environment names, got {data['envs']!r}")
    _check_envs(path, data["envs"])
    if any(not isinstance(m, str) for m in data["methods"]):
        raise ConfigError(f"{path}: 'methods' must be a list of method names, got {data['methods']!r}")
    bad = [m for m in data["methods"] if m not in METHODS]
    if bad:
        raise ConfigError(
            f"{path}: unknown method(s) {', '.join(map(repr, bad))} in 'methods'{did_you_mean(bad[0], METHODS)}: "
            f"choose from {', '.join(METHODS)}"
        )
    if not isinstance(data.get("name", ""), str):
        raise ConfigError(f"{path}: 'name' must be a string, got {data['name']!r}")
    for seed in data["seeds"]:
        if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
            raise ConfigError(f"{path}: 'seeds' must be a list of integers >= 0, got {seed!r}")
    grid = data.get("grid", {})
    if not isinstance(grid, dict) or any(not isinstance(v, list) or not v for v in grid.values()):
        raise ConfigError(f"{path}: 'grid' must map configuration fields to non-empty lists of values")
    try:
        for key, values in grid.items():
            if key in _OWN:
                raise ConfigError(f"'{key}' cannot be a grid key: the sweep's '{_OWN[key]}' sets it")
            for v in values:  # every value, for an error that names it
                try:
                    typed_overrides({key: v})
                except ConfigError as exc:
                    raise ConfigError(f"grid: {exc}") from None
        overrides = data.get("overrides", {})
        if not isinstance(overrides, dict):
            raise ConfigError(f"'overrides' must map configuration fields to values, got {overrides!r}")
        overrides = typed_overrides(overrides)
        train_args = data.get("train_args", [])
        if not isinstance(train_args, list) or any(not isinstance(a, str) for a in train_args):
            raise ConfigError(f"'train_args' must be a list of `pimbrl train` flags (strings), got {train_args!r}")
        from_args = parse_train_args(train_args)
        for key in from_args.keys() & overrides.keys():
            raise ConfigError(f"{key} is set both in 'train_args' and in 'overrides'")
        overrides.update(from_args)
        for key in overrides:
            if key in _OWN:
                raise ConfigError(f"{key} cannot be overridden: the sweep's '{_OWN[key]}' sets it")
            if key in grid:
                raise ConfigError(f"{key} is both a grid key and an override")
        threshold = data.get("threshold")
        if threshold is not None:
            threshold = typed_value(float, threshold, "'threshold'")
            if "threshold" in overrides:
                raise ConfigError("threshold is set both as 'threshold' and as an override")
        preset = data.get("preset")
        if preset is not None and not isinstance(preset, str):
            raise ConfigError(f"'preset' must be the name of a recipe (e.g. paper), got {preset!r}")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return SweepSpec(
        name=str(data.get("name", path.stem)),
        envs=tuple(data["envs"]),
        methods=tuple(data["methods"]),
        seeds=tuple(data["seeds"]),
        grid={k: tuple(v) for k, v in grid.items()},
        overrides=overrides,
        threshold=threshold,
        preset=preset,
    )


def _check_envs(path: Path, envs: Sequence[str]) -> None:
    """Every name of a sweep's 'envs' must be an environment; the error names the file and the key."""
    from ..simulate import resolve_env_id

    for env in envs:
        try:
            resolve_env_id(env)
        except ValueError as exc:
            raise ConfigError(f"{path}: 'envs': {exc}") from None


def sweep_study(spec: SweepSpec, imports: Sequence[str] = ()) -> StudySpec:
    """The study spec a sweep is: its environments, methods (as arms), seeds, grid and overrides.

    Runs live at ``DIR/<env>/<method>/<setting>/seed<k>`` (the full layout, as sweeps always had).
    """
    data: dict[str, Any] = {
        "name": spec.name,
        "systems": list(spec.envs),
        "methods": list(spec.methods),
        "seeds": list(spec.seeds),
        "layout": "full",
    }
    if spec.grid:
        data["grid"] = {k: list(v) for k, v in spec.grid.items()}
    overrides = dict(spec.overrides)
    if spec.threshold is not None:
        overrides["threshold"] = float(spec.threshold)
        data["thresholds"] = [float(spec.threshold)]
    if overrides:
        data["overrides"] = json.loads(json.dumps(overrides))
    if spec.preset is not None:
        data["preset"] = spec.preset
    if imports:
        data["imports"] = list(imports)
    try:
        return parse_spec(data, where=f"sweep {spec.name}", text=spec_to_yaml(data))
    except ConfigError as exc:
        raise ConfigError(str(exc)) from None


def plan_trials(spec: SweepSpec, root: str | Path) -> list[Trial]:
    """Every trial of ``spec`` with its resolved configuration.

    Raises :class:`ConfigError` for any trial that is invalid, before anything runs.
    """
    runs = plan_study(sweep_study(spec), Path(root).resolve())
    return [Trial(r.system, r.arm, r.seed, r.setting, str(r.path), r.config) for r in runs]


def run_sweep(
    spec: SweepSpec,
    root: str | Path,
    use_ray: bool | None = None,
    address: str | None = None,
    num_cpus: int | None = None,
    log: Callable[[str], None] = print,
    imports: Sequence[str] = (),
    replicas: bool = True,
) -> dict[str, Any]:
    """Run the unfinished trials of ``spec`` (a study, :func:`sweep_study`) and aggregate all of them into ``root``.

    ``replicas``: as :func:`~.engine.run_study`'s (a seed-free controller trains two seeds and copies the first
    where they agree).

    ``imports``: the ``--import`` arguments every trial's process loads first (files as absolute paths, so
    that a Ray worker in another directory finds them). Without Ray (or ``use_ray=False``) the trials run as
    local processes, ``num_cpus`` at a time (default: every core); the results are the same.
    """
    root = Path(root)
    absolute = tuple(str(Path(s).resolve()) if s.endswith(".py") or "/" in s else s for s in imports)
    study = sweep_study(spec, absolute)
    trials = plan_trials(spec, root)  # every configuration checked before anything runs
    if use_ray is None:
        use_ray = ray_available()
    if use_ray and not ray_available():
        raise RuntimeError("Ray is not installed: pip install 'pimbrl[ray]', or run the sweep with --no-ray")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    jobs = num_cpus or cores
    before = sum(1 for t in trials if RunDirectory(t.path).status == "finished")
    backend = "ray" if use_ray else "local"
    record = run_study(study, root, jobs=jobs, backend=backend, address=address, replicas=replicas, status=False, log=log)
    result = aggregate(spec, trials)
    for line in result["unreadable"]:
        log(f"UNREADABLE {line}")
    result["failed"] = [str(root.resolve() / f) for f in record["failed"]]
    after = sum(1 for t in trials if RunDirectory(t.path).status == "finished")
    result["executed"] = after - before
    write_sweep_outputs(result, root, spec.name)
    return result


def aggregate(spec: SweepSpec, trials: Sequence[Trial]) -> dict[str, Any]:
    """One row per trial that has evaluations, and the curves of every setting (for means over seeds).

    A trial whose run directory cannot be read (damaged, or holding links or FIFOs) is left out and named,
    with the reason, in ``unreadable``.
    """
    rows: list[dict[str, Any]] = []
    curves: dict[tuple[str, str, str], list[dict[str, list[float]]]] = {}
    unreadable: list[str] = []
    for t in trials:
        try:
            result = RunDirectory(t.path).result(spec.threshold)
        except (ValueError, OSError) as exc:  # a damaged run directory: reported, the others aggregated
            unreadable.append(f"{t.path}: {exc}")
            continue
        if result is None:
            continue
        curve = result.pop("curve")
        rows.append({"env": t.env, "method": t.method, "setting": t.setting, "seed": t.seed, **result})
        curves.setdefault((t.env, t.method, t.setting), []).append(curve)
    return {"name": spec.name, "threshold": spec.threshold, "rows": rows, "curves": curves, "unreadable": unreadable}


def write_sweep_outputs(result: dict[str, Any], root: Path, title: str) -> None:
    from ..plotting import plot_learning_curves, seed_band

    cols = [
        "env",
        "method",
        "setting",
        "seed",
        "finished",
        "steps",
        "steps_to_threshold",
        "final_return",
        "wall_s",
        "updates",
    ]
    lines = [",".join(cols)]
    for r in sorted(result["rows"], key=lambda r: (r["env"], r["method"], r["setting"], r["seed"])):
        lines.append(",".join('"' + str(r[c]) + '"' if c == "setting" else ("" if r[c] is None else str(r[c])) for c in cols))
    atomic_write_bytes(root / "results.csv", ("\n".join(lines) + "\n").encode())
    summary = {k: v for k, v in result.items() if k != "curves"}
    atomic_write_bytes(root / "summary.json", (json.dumps(summary, indent=2, default=str, allow_nan=False) + "\n").encode())
    if not result["curves"]:
        return
    plotted = [
        seed_band(f"{env.split('/')[-1]} {method} {setting}", runs) for (env, method, setting), runs in result["curves"].items()
    ]
    plot_learning_curves(plotted, root / "curves.png", title=title, threshold=result["threshold"])
