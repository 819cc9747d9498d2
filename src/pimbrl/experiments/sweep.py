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

Trials run as Ray tasks (one CPU each) on a local Ray instance started for the sweep, or on an existing
cluster with ``--address`` (the workers need pimbrl installed and the run directory on a shared file
system). Without Ray, or with ``--no-ray``, they run one after another in this process: the outputs are
the same, since a trial's result depends only on its configuration and seed. The results are aggregated
into ``DIR/results.csv`` (one row per trial), ``DIR/summary.json`` and ``DIR/curves.png``.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import sys
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config import ConfigError, typed_value
from ..fileio import atomic_write_bytes, check_below
from ..training import METHODS, RunDirectory, TrainConfig
from ..training.cli_args import parse_train_args
from ..training.config import applicable_overrides, config_to_dict, did_you_mean, resolve_config, run_names, typed_overrides

__all__ = ["SweepSpec", "Trial", "execute_trial", "load_sweep", "plan_trials", "ray_available", "run_sweep"]

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


#: the longest setting directory name kept as written (file systems allow 255 bytes)
_MAX_NAME = 100


def _directory_name(setting: str) -> str:
    """A setting's directory name: one path component inside the run root, whatever its values hold.

    The setting as written where that is a safe component (no ``/``, no leading ``.``, printable, at most
    100 characters: the names of earlier sweeps); otherwise characters other than letters, digits and
    ``_ . , = + -`` become ``_``, the name is cut to 80 characters, and the first 8 hex digits of the
    setting's SHA-256 are appended (two settings never share a directory). The trial's ``params`` keep the
    values as written.
    """
    import hashlib

    safe = "/" not in setting and "\\" not in setting and not setting.startswith(".") and setting.isprintable()
    if safe and 0 < len(setting.encode()) <= _MAX_NAME:
        return setting
    name = "".join(c if c.isalnum() or c in "_.,=+-" else "_" for c in setting)[:80].lstrip(".")
    return f"{name or 'setting'}-{hashlib.sha256(setting.encode()).hexdigest()[:8]}"


def _env_directory(env_id: str) -> str:
    """An environment's directory name: the id's name for pimbrl's systems, ``namespace__Name-vN`` for others."""
    namespace, _, name = env_id.rpartition("/")
    return name if namespace in ("", "pimbrl") else f"{namespace}__{name}"


def _same_run_key(env_id: str, method: str, cfg: TrainConfig) -> str:
    """What makes two trials the same run: the environment, the method and the whole resolved configuration.

    Numbers are compared as numbers (``9`` and ``9.0``), mappings whatever their order.
    """
    data = json.loads(json.dumps(config_to_dict(cfg), default=str), parse_int=float)
    return json.dumps([env_id, method, data], sort_keys=True)


def plan_trials(spec: SweepSpec, root: str | Path) -> list[Trial]:
    """Every trial of ``spec`` with its resolved configuration.

    Raises :class:`ConfigError` for any trial that is invalid, before anything runs.
    """
    from ..simulate import resolve_env_id

    root = Path(root).resolve()
    keys = list(spec.grid)
    fixed = typed_overrides(spec.overrides)
    if spec.threshold is not None:
        fixed["threshold"] = float(spec.threshold)
    used: set[str] = set()
    reasons: dict[str, str] = {}
    trials = []
    seen: dict[str, str] = {}  # each distinct run once: by its environment, method and resolved configuration
    for env, method in itertools.product(spec.envs, spec.methods):
        env_id = resolve_env_id(env)
        for values in itertools.product(*(spec.grid[k] for k in keys)) if keys else [()]:
            params = tuple(zip(keys, values))
            setting = ",".join(f"{k}={v}" for k, v in params) or "default"
            swept = typed_overrides(dict(params))
            agent = run_names(env_id, {**fixed, **swept}, spec.preset)[1]
            fields = dict(swept)
            applied = applicable_overrides(env_id, method, agent, fixed, reasons)
            fields.update(applied)
            used.update(applied)
            for seed in spec.seeds:
                label = f"{env} {method} {setting} seed {seed}"
                try:
                    cfg = resolve_config(env_id, {**fields, "method": method, "seed": seed}, preset=spec.preset)
                except ConfigError as exc:
                    raise ConfigError(f"sweep {spec.name}, trial {env_id} {method} {setting} seed {seed}: {exc}") from None
                key = _same_run_key(env_id, method, cfg)
                if key in seen:
                    raise ConfigError(
                        f"sweep {spec.name}: {label} is the same run as {seen[key]} (a value, seed or environment given "
                        "twice); give each once"
                    )
                seen[key] = label
                path = root / _env_directory(env_id) / method / _directory_name(setting) / f"seed{seed}"
                trials.append(Trial(env_id, method, seed, params, str(path), cfg))
    unused = [reasons[k] for k in fixed if k not in used]
    if unused:
        raise ConfigError(f"sweep {spec.name}: {'; '.join(unused)} (methods {', '.join(spec.methods)})")
    return trials


def execute_trial(trial: Trial) -> dict[str, Any]:
    """Train (or resume) one trial in this process; never raises (a failure is returned)."""
    from ..systems import import_systems, load_entry_points
    from ..training import RunDirectory, resume_training, run_training

    try:
        load_entry_points()  # a Ray worker is a fresh process: the user's systems are registered there too
        import_systems(trial.imports)
        status = RunDirectory(trial.path).status
        if status == "finished":
            return {"path": trial.path, "ok": True, "skipped": True}
        if status is None:
            run_training(trial.config, trial.path, progress=False)
        else:
            resume_training(trial.path, progress=False)
        return {"path": trial.path, "ok": True, "skipped": False}
    except Exception as exc:  # reported, the other trials go on
        return {"path": trial.path, "ok": False, "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}


def ray_available() -> bool:
    """Whether Ray can be imported; a sweep runs its trials on Ray by default when it can."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def run_sweep(
    spec: SweepSpec,
    root: str | Path,
    use_ray: bool | None = None,
    address: str | None = None,
    num_cpus: int | None = None,
    log: Callable[[str], None] = print,
    imports: Sequence[str] = (),
) -> dict[str, Any]:
    """Run the unfinished trials of ``spec`` and aggregate all of them into ``root``.

    ``imports``: the ``--import`` arguments every trial's process loads first (files as absolute paths, so
    that a Ray worker in another directory finds them).
    """
    root = Path(root)
    trials = plan_trials(spec, root)  # every configuration checked before anything runs
    absolute = tuple(str(Path(s).resolve()) if s.endswith(".py") or "/" in s else s for s in imports)
    trials = [dataclasses.replace(t, imports=absolute) for t in trials]
    base = root.resolve()
    for trial in trials:  # DIR/<env>/<method>/<setting>/seed<k>: no link on the way below DIR
        check_below(base, Path(trial.path).relative_to(base), "directory")
    root.mkdir(parents=True, exist_ok=True)
    todo = [t for t in trials if RunDirectory(t.path).status != "finished"]
    if use_ray is None:
        use_ray = ray_available()
    if use_ray and not ray_available():
        raise RuntimeError("Ray is not installed: pip install 'pimbrl[ray]', or run the sweep with --no-ray")
    log(
        f"sweep {spec.name}: {len(trials)} trials, {len(trials) - len(todo)} already finished, {len(todo)} to run"
        + (" on Ray" if use_ray and todo else "")
    )
    outcomes: list[dict[str, Any]] = []
    if todo and use_ray:
        outcomes = _run_on_ray(todo, address, num_cpus, log)
    else:
        for trial in todo:
            log(f"trial {trial.label} seed {trial.seed}")
            outcomes.append(execute_trial(trial))
    failed = [o for o in outcomes if not o["ok"]]
    for o in failed:
        log(f"FAILED {o['path']}: {o['error']}")
    result = aggregate(spec, trials)
    for line in result["unreadable"]:
        log(f"UNREADABLE {line}")
    result["failed"] = [o["path"] for o in failed]
    result["executed"] = sum(1 for o in outcomes if o["ok"] and not o.get("skipped"))
    write_sweep_outputs(result, root, spec.name)
    return result


def _run_on_ray(
    trials: Sequence[Trial], address: str | None, num_cpus: int | None, log: Callable[[str], None]
) -> list[dict[str, Any]]:
    import ray

    started_here = not ray.is_initialized()
    if started_here:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(execute_trial)
        refs = {remote.remote(t): t for t in trials}
        outcomes = []
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                trial = refs[ref]
                try:
                    outcome = ray.get(ref)
                except Exception as exc:  # a worker that died
                    outcome = {"path": trial.path, "ok": False, "error": f"{type(exc).__name__}: {exc}"}
                log(f"{'done' if outcome['ok'] else 'failed'}: {trial.label} seed {trial.seed}")
                outcomes.append(outcome)
        return outcomes
    finally:
        if started_here:
            ray.shutdown()


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
        "best_return",
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
