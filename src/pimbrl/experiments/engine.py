"""The study engine: plan a spec's runs, train them (local processes or Ray, the same results), collect the record.

:func:`plan_study` resolves every run's :class:`~pimbrl.training.TrainConfig` before anything runs (an
invalid override, an unstable coefficient, a run given twice are errors here). :func:`run_study` trains
what is missing: a finished run is skipped, an interrupted one resumed from its checkpoint, a failed one
reported without stopping the others. Runs live at ``ROOT/ARM/seedK`` (one system, no grid) or
``ROOT/SYSTEM/ARM/SETTING/seedK``. A study's directory is held by one driver at a time (``compare.lock``).

:func:`collect_record` reads every run back into the study's record (``ROOT/record.json``): the spec's
SHA-256 and text, its registration (:mod:`.registration`), the commit and CPU model of the collecting
process, and per run its configuration's provenance (CPU model, cores, commit), real, imagined, scheme and
validation transitions, agent updates, wall time and the per-evaluation curve.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import itertools
import json
import math
import os
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import ConfigError
from ..fileio import atomic_write_bytes, check_below
from ..training.config import TrainConfig, applicable_overrides, config_to_dict, resolve_config, run_names, typed_overrides
from ..training.rundir import RunDirectory, provenance
from .runner import RunSpec, check_reuse, lock_comparison, run_all, thread_variables
from .spec import StudySpec, safe_component

__all__ = [
    "RECORD_FILE",
    "RECORD_FORMAT",
    "SPEC_FILE",
    "QueuedStudy",
    "StudyRun",
    "collect_record",
    "directory_name",
    "env_directory",
    "execute_run",
    "plan_study",
    "run_studies",
    "run_study",
    "same_run_key",
    "study_thresholds",
]

#: the study's record in its directory
RECORD_FILE = "record.json"
#: the spec as run, in the study's directory
SPEC_FILE = "study.yaml"
#: the record's format tag (changes when its meaning does)
RECORD_FORMAT = "pimbrl-study-record/1"


@dataclass(frozen=True)
class StudyRun:
    """One run of a study: a system, an arm, a setting of the grid, a seed; its directory and configuration."""

    system: str  # the environment id
    arm: str
    seed: int
    setting: tuple[tuple[str, Any], ...]  # the grid values, as written in the spec
    path: Path
    config: TrainConfig

    @property
    def setting_text(self) -> str:
        """``"key=value,..."`` (``"default"`` for no grid)."""
        return ",".join(f"{k}={v}" for k, v in self.setting) or "default"

    def label(self, compact: bool) -> str:
        """The run's name in logs: its arm (compact studies), else system, arm and setting."""
        if compact:
            return self.arm
        return f"{self.system.split('/')[-1]} {self.arm} {self.setting_text}"


def directory_name(setting: str) -> str:
    """A setting's directory name: one path component inside the study's root, whatever its values hold.

    The setting as written where that is a safe component (:func:`~pimbrl.experiments.spec.safe_component`);
    otherwise characters other than letters, digits and ``_ . , = + -`` become ``_``, the
    name is cut to 80 characters, and the first 8 hex digits of the setting's SHA-256 are appended (two
    settings never share a directory).
    """
    if safe_component(setting):
        return setting
    name = "".join(c if c.isalnum() or c in "_.,=+-" else "_" for c in setting)[:80].lstrip(".")
    return f"{name or 'setting'}-{hashlib.sha256(setting.encode()).hexdigest()[:8]}"


def env_directory(env_id: str) -> str:
    """A system's directory name: the id's name for pimbrl's systems, ``namespace__Name-vN`` for others."""
    namespace, _, name = env_id.rpartition("/")
    return name if namespace in ("", "pimbrl") else f"{namespace}__{name}"


def same_run_key(env_id: str, method: str, cfg: TrainConfig) -> str:
    """What makes two runs the same: the system, the method and the whole resolved configuration.

    Numbers are compared as numbers (``9`` and ``9.0``), mappings whatever their order.
    """
    data = json.loads(json.dumps(config_to_dict(cfg), default=str), parse_int=float)
    return json.dumps([env_id, method, data], sort_keys=True)


def plan_study(spec: StudySpec, root: str | Path) -> list[StudyRun]:
    """Every run of ``spec`` with its resolved configuration, in the spec's order.

    The study's ``overrides`` go to every run they apply to (one applying to none is a :class:`ConfigError`
    with the reason); an arm's own overrides and the grid's values must apply to the arm. Two runs with the
    same system, method and resolved configuration are an error (a value, seed or alias given twice).
    """
    from ..simulate import resolve_env_id

    if spec.imports:
        from ..systems import import_systems

        import_systems(spec.imports)
    root = Path(root)
    keys = list(spec.grid)
    used: set[str] = set()
    reasons: dict[str, str] = {}
    seen: dict[str, str] = {}
    runs: list[StudyRun] = []
    for system in spec.systems:
        env_id = resolve_env_id(system)
        for arm in spec.arms:
            for values in itertools.product(*(spec.grid[k] for k in keys)) if keys else [()]:
                params = tuple(zip(keys, values))
                setting = ",".join(f"{k}={v}" for k, v in params) or "default"
                swept = typed_overrides(dict(params))
                for key in swept.keys() & arm.overrides.keys():
                    raise ConfigError(f"study {spec.name}: {key} is both a grid key and an override of arm {arm.name}")
                own = {**arm.overrides, **swept, "method": arm.method}
                agent = run_names(env_id, {**spec.overrides, **own}, spec.preset)[1]
                applied = applicable_overrides(env_id, arm.method, agent, spec.overrides, reasons)
                used.update(applied)
                fields = {**applied, **own}
                where = f"study {spec.name}, {env_id} {arm.name}" + ("" if not params else f" {setting}")
                try:
                    if arm.match_updates and "utd" not in fields:  # the user's utd wins
                        fields["utd"] = resolve_config(env_id, {"method": "pimbrl", "agent": agent}, preset=spec.preset).utd
                    first = resolve_config(env_id, {**fields, "seed": spec.seeds_of(arm)[0]}, preset=spec.preset)
                except ConfigError as exc:
                    raise ConfigError(f"{where}: {exc}") from None
                for seed in spec.seeds_of(arm):
                    cfg = dataclasses.replace(first, seed=seed)
                    key = same_run_key(env_id, arm.method, cfg)
                    label = f"{where} seed {seed}"
                    if key in seen:
                        raise ConfigError(
                            f"{label} is the same run as {seen[key]} (a value, seed, system or arm given twice); give each once"
                        )
                    seen[key] = label
                    if spec.compact:
                        path = root / arm.name / f"seed{seed}"
                    else:
                        path = root / env_directory(env_id) / arm.name / directory_name(setting) / f"seed{seed}"
                    runs.append(StudyRun(env_id, arm.name, seed, params, path, cfg))
    unused = [reasons[k] for k in spec.overrides if k not in used]
    if unused:
        raise ConfigError(f"study {spec.name}: {'; '.join(unused)} (arms: {', '.join(spec.arm_names)})")
    return runs


def study_thresholds(spec: StudySpec, system: str) -> list[float]:
    """The thresholds the report counts steps to on ``system``: the spec's, else the system's recipe's."""
    if spec.thresholds:
        return list(spec.thresholds)
    if spec.overrides.get("threshold") is not None:  # the runs' own threshold
        return [float(spec.overrides["threshold"])]
    try:
        threshold = resolve_config(system, {"method": "mfrl"}, preset=spec.preset).threshold
    except (ConfigError, ValueError):
        return []
    return [] if threshold is None else [threshold]


def execute_run(path: str, config: TrainConfig, imports: Sequence[str] = ()) -> dict[str, Any]:
    """Train (or resume) one run in this process (a Ray task); never raises (a failure is returned)."""
    from ..systems import import_systems, load_entry_points
    from ..training import resume_training, run_training

    try:
        load_entry_points()  # a Ray worker is a fresh process: the user's systems are registered there too
        import_systems(imports)
        status = RunDirectory(path).status
        if status == "finished":
            return {"path": path, "ok": True, "skipped": True}
        if status is None:
            run_training(config, path, progress=False)
        else:
            resume_training(path, progress=False)
        return {"path": path, "ok": True, "skipped": False}
    except Exception as exc:  # reported, the other runs go on
        return {"path": path, "ok": False, "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}


def run_study(
    spec: StudySpec,
    root: str | Path,
    *,
    jobs: int = 1,
    backend: str = "local",
    address: str | None = None,
    rerun: bool = False,
    status: bool = True,
    run: bool = True,
    replicas: bool = True,
    archive: str | Path | None = None,
    keep_archive: bool = False,
    log: Callable[[str], None] = print,
    time_limit: float | None = None,
) -> dict[str, Any]:
    """Train what is missing of ``spec`` in ``root`` and return (and write) its record.

    ``backend``: ``"local"`` (each run a child process, ``jobs`` at a time) or ``"ray"`` (each run a Ray task
    on a local instance started here, or on the cluster at ``address``; the helper processes of a local
    instance end with this process, also a killed one). ``run=False`` trains nothing and collects the runs as
    they stand. ``replicas``: a seed-free controller's arm runs two seeds and copies the first into the others
    where the two agree on every episode (:mod:`.replicas`). A confirmatory spec must be committed before its
    first run (:mod:`.registration`). ``archive``: a folder of the study's finished runs (:mod:`.archive`); each
    one whose directory does not exist here is copied back before the start, so that only the rest train. With
    ``keep_archive`` each run is copied into ``archive`` as it finishes, and every finished run at the end (a
    copy that cannot be made is logged; the study goes on). ``time_limit``: :func:`run_studies`'s.
    """
    if backend not in ("local", "ray"):
        raise ConfigError(f"backend must be local or ray, got {backend!r}")
    queued = QueuedStudy(spec, root, rerun=rerun, replicas=replicas, archive=archive, keep_archive=keep_archive)
    if not run:
        return _write_record(spec, queued.runs, queued.root, [], run=False)
    run_studies([queued], jobs=jobs, backend=backend, address=address, status=status, log=log, time_limit=time_limit)
    assert queued.record is not None  # a study that ended has its record; one that did not raised
    return queued.record


class QueuedStudy:
    """One study to train, alone or in a queue (:func:`run_studies`): its runs planned and checked.

    Nothing is touched until :meth:`open`; the arguments are :func:`run_study`'s.
    """

    def __init__(
        self,
        spec: StudySpec,
        root: str | Path,
        *,
        rerun: bool = False,
        replicas: bool = True,
        archive: str | Path | None = None,
        keep_archive: bool = False,
    ) -> None:
        if spec.record is not None and spec.record.format != "study":
            raise ConfigError(
                f"study {spec.name} reads the record {spec.record.path} made before the study engine; it has no runs to "
                "make (pimbrl study report shows it)"
            )
        self.spec = spec
        self.root = Path(root).resolve()  # absolute: a Ray worker elsewhere (or on another node) writes the same runs
        self.runs = plan_study(spec, self.root)  # every configuration checked before anything runs
        for r in self.runs:  # no link on the way below the root (it would lead the runs elsewhere): checked unresolved
            check_below(self.root, r.path.relative_to(self.root), "directory")
        self.rerun, self.replicas, self.keep_archive = rerun, replicas, keep_archive
        self.archive = None if archive is None else Path(archive)
        self.record: dict[str, Any] | None = None  # written when the last run has ended
        self.failed: list[str] = []
        self._lock: int | None = None
        self._by_path = {str(r.path): r for r in self.runs}
        self._copies: dict[Path, tuple[StudyRun, StudyRun]] = {}
        self._outstanding: set[str] = set()
        self._second: list[StudyRun] = []  # seed-free copies waiting for their two seeds (made, or trained)
        self._log: Callable[[str], None] = print
        self._plan: Any = None  # the archive's restore plan, made by check()
        self.broken = False  # an error while it was restored, archived or recorded: its runs end, nothing else
        self._trains = True  # whether this start found runs to train (a finished study's record is left as it was)

    def check(self, log: Callable[[str], None]) -> None:
        """Lock the directory and check what a start refuses, writing nothing (a queue checks every study first)."""
        from .archive import plan_restore
        from .registration import check_start

        self._log = log
        self.root.mkdir(parents=True, exist_ok=True)
        self._lock = lock_comparison(self.root)  # before any run is looked at: one driver in a directory at a time
        try:
            plan = plan_restore(self.spec, self.root, self.archive, self.runs) if self.archive is not None else None
            if plan is not None and plan.refusal is not None:  # refused before --rerun moves anything
                raise ConfigError(plan.refusal)
            self._plan = plan
            check_reuse([self._run_spec(r) for r in self.runs], rerun=self.rerun, log=log, move=False)
            registration = plan.registration if plan is not None else None  # the archive's, restored at the start
            # with --rerun the stale runs are moved aside before the start: the start checks what is left then
            check_start(self.spec, self.root, () if self.rerun else self.runs, registration=registration)
        except BaseException:
            self.close()
            raise

    def open(self, backend: str = "local") -> list[RunSpec]:
        """Restore the archive, register the start, log what is to run (after :meth:`check`).

        Returns the runs to train first (of a seed-free controller, the two seeds the others wait for), or
        ``[]`` when nothing is left to train (the record is written then).
        """
        from .archive import restore_study
        from .registration import REGISTRATION_FILE, start_study
        from .replicas import plan_replicas

        spec, root, log = self.spec, self.root, self._log
        assert self._lock is not None, "check() first"
        try:
            if self.rerun:  # runs of another configuration moved aside, to train again
                check_reuse([self._run_spec(r) for r in self.runs], rerun=True, log=log)
            if self.archive is not None:  # after --rerun moved runs aside their archived copies come back: planned again
                restored = restore_study(spec, root, self.archive, self.runs, None if self.rerun else self._plan)
                if restored.copied or restored.carried or restored.passed:
                    log(restored.line("restored", self.archive))
            todo = [r for r in self.runs if RunDirectory(r.path).status != "finished"]
            self._trains = bool(todo)
            if todo or not _seen_here(root / REGISTRATION_FILE, spec.sha256):  # a finished study run again starts nothing
                start_study(spec, root, self.runs)  # after the checks: a start refused there is no start
            if spec.text:  # the spec as run, beside its runs (pimbrl study report DIR/study.yaml)
                atomic_write_bytes(root / SPEC_FILE, spec.text.encode())
            on_ray = " on Ray" if todo and backend == "ray" else ""
            log(f"study {spec.name}: {len(self.runs)} runs, {len(self.runs) - len(todo)} finished, {len(todo)} to run{on_ray}")
            self._copies = plan_replicas(self.runs, todo) if self.replicas else {}
            first = [r for r in todo if r.path not in self._copies]
            self._second = [r for r in todo if r.path in self._copies]
            self._outstanding = {str(r.path) for r in first}
            return [self._run_spec(r) for r in first] if first else self._next()
        except BaseException:
            self.close()
            raise

    def ended(self, run: RunSpec, ok: bool) -> list[RunSpec]:
        """A run of this study ended (``ok``: finished well): archived where asked; the runs to make next.

        For a broken study (an error while it was restored, archived or recorded) nothing more is done: when
        its last running run has ended its directory is unlocked, and it gets no record.
        """
        path = str(run.path)
        self._outstanding.discard(path)
        if self.broken:
            if not self._outstanding:
                self.close()
            return []
        if ok and self.keep_archive and self.archive is not None:
            self._keep([self._by_path[path]])
        elif not ok:
            self.failed.append(str(Path(path).relative_to(self.root)))
        return [] if self._outstanding else self._next()

    def _next(self) -> list[RunSpec]:
        """After the first runs, the seed-free copies whose two seeds agree are made and the rest train.

        When nothing is left to train, the record is written.
        """
        from .replicas import replicate, same_episodes

        waiting, self._second = self._second, []
        rest = []
        for copy in waiting:
            first, second = self._copies[copy.path]
            if not same_episodes(first, second):
                rest.append(copy)
                continue
            try:
                replicate(first, copy, second, self.root)
            except (OSError, ValueError) as exc:  # that seed trains instead (shutil.Error is an OSError)
                self._log(f"no copy for {copy.label(self.spec.compact)} seed {copy.seed} ({exc}); training it")
                rest.append(copy)
                continue
            self._log(
                f"copy {copy.label(self.spec.compact)} seed {copy.seed}: seed-free, seeds {first.seed} and {second.seed} agree"
            )
        if rest:
            self._outstanding = {str(r.path) for r in rest}
            return [self._run_spec(r) for r in rest]
        self.finish()
        return []

    def finish(self) -> dict[str, Any]:
        """Archive every finished run (where asked), write the record, unlock the directory."""
        try:
            if self.keep_archive and self.archive is not None:
                self._keep(self.runs)  # the copies of seed-free runs, and any run the archive missed
            # under the lock; a study that trained nothing this time leaves a record of the same runs as it was
            self.record = _write_record(self.spec, self.runs, self.root, self.failed, run=True, keep_same=not self._trains)
            self._log(f"study {self.spec.name}: {len(self.record['runs'])} runs recorded in {self.root / RECORD_FILE}")
        finally:
            self.close()
        return self.record

    def break_off(self) -> None:
        """After an error in this study: no run of it starts, those running end, then its directory is unlocked."""
        self.broken = True
        if not self._outstanding:
            self.close()

    @property
    def is_open(self) -> bool:
        """Whether this driver holds the study's directory (between :meth:`check` and the record)."""
        return self._lock is not None

    def close(self) -> None:
        """Unlock the directory (once)."""
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None

    def _keep(self, which: Sequence[StudyRun]) -> None:  # into the archive; a failure there never stops the study
        from .archive import archive_study

        assert self.archive is not None
        try:
            result = archive_study(self.spec, self.root, self.archive, which)
        except (ConfigError, OSError, ValueError) as exc:
            self._log(f"archive: nothing copied to {self.archive} ({str(exc).splitlines()[0]}); the study goes on")
            return
        if result.copied:
            self._log(result.line("archived", self.archive))

    def planned(self, run: RunSpec) -> StudyRun:
        """The planned run of one of this study's run specs."""
        return self._by_path[str(run.path)]

    def _run_spec(self, r: StudyRun) -> RunSpec:
        return RunSpec(r.label(self.spec.compact), r.seed, r.path, r.config, tuple(self.spec.imports))


def run_studies(
    studies: Sequence[QueuedStudy],
    *,
    jobs: int = 1,
    backend: str = "local",
    address: str | None = None,
    status: bool = True,
    log: Callable[[str], None] = print,
    time_limit: float | None = None,
) -> list[dict[str, Any]]:
    """Train a queue of studies, in order, and return their records (each written as its study ends).

    Every study is first checked (its directory locked; its archive, its registration and its run directories
    checked) before anything is written, so a refusal anywhere stops the queue untouched. A study is then
    opened (archive restored, start registered) when the queue reaches it: with local processes, when a
    process is free and no run of the studies before it waits, so no core waits for a study's slowest run;
    the runs a study adds later (seed-free copies that must train) go before the next study's. On Ray the
    studies run one after another. An error while one study is opened or recorded is logged, the queue goes
    on, and the first such error is raised at the end. ``time_limit``: minutes after which the running runs are
    stopped with a checkpoint and :class:`~.runner.TimeLimitReached` is raised (local processes only).
    """
    if backend not in ("local", "ray"):
        raise ConfigError(f"backend must be local or ray, got {backend!r}")
    if time_limit is not None and backend != "local":
        raise ConfigError("a time limit applies to local processes, not to Ray: drop --time-limit or --backend ray")
    if time_limit is not None and not (math.isfinite(time_limit) and time_limit > 0):
        raise ConfigError(f"the time limit must be a positive number of minutes, got {time_limit!r}")
    for i, q in enumerate(studies):
        for other in studies[:i]:
            if q.root.is_relative_to(other.root) or other.root.is_relative_to(q.root):
                raise ConfigError(
                    f"studies {other.spec.name} and {q.spec.name} of the queue share a run directory ({other.root} and "
                    f"{q.root}): give each its own"
                )
    errors: list[BaseException] = []

    def guarded(q: QueuedStudy, step: Callable[[], list[RunSpec]]) -> list[RunSpec]:
        try:
            return step()
        except Exception as exc:  # one study's trouble: it breaks (its running runs end), the others go on
            if len(studies) > 1:
                log(f"study {q.spec.name}: {type(exc).__name__}: {exc}; its waiting runs are dropped, the queue goes on")
            errors.append(exc)
            q.break_off()
            return []

    try:
        for q in studies:
            q.check(log)
        owner = {str(r.path): q for q in studies for r in q.runs}
        waiting, opened = list(studies), []

        def next_study() -> list[RunSpec]:
            while waiting:
                q = waiting.pop(0)
                opened.append(q)
                batch = guarded(q, functools.partial(q.open, backend))
                if batch:
                    return batch
            return []

        def ended(s: RunSpec, ok: bool) -> list[RunSpec]:
            q = owner[str(s.path)]
            return guarded(q, lambda: q.ended(s, ok))

        if backend == "ray":
            for q in studies:
                opened.append(q)
                batch = guarded(q, functools.partial(q.open, backend))
                while batch:
                    bad = set(_run_on_ray([q.planned(s) for s in batch], q.spec.imports, address, jobs, log))
                    batch = [n for s in batch for n in ended(s, str(s.path) not in bad)]
        else:
            confirmatory = any(q.spec.kind == "confirmatory" for q in studies)  # then no line shows returns
            run_all(
                [], jobs=jobs, log=log, status=status, returns=not confirmatory, on_end=ended, more=next_study,
                drop=lambda s: owner[str(s.path)].broken, time_limit=time_limit,
            )  # fmt: skip
        for q in opened:  # every run ended, yet no record (not expected: a safety net): the record as the runs stand
            if q.record is None and q.is_open and not q.broken:
                log(f"study {q.spec.name}: its runs ended without its record (unexpected); recorded as they stand")
                guarded(q, functools.partial(_finished, q))
        if errors:
            raise errors[0]
        return [q.record for q in studies if q.record is not None]
    finally:
        for q in studies:
            q.close()


def _finished(q: QueuedStudy) -> list[RunSpec]:
    """:meth:`QueuedStudy.finish` as a step that adds no run."""
    q.finish()
    return []


def _seen_here(registration: Path, sha256: str) -> bool:
    """Whether the registration at ``registration`` exists and has seen the spec of ``sha256`` start already."""
    try:
        data = json.loads(registration.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and sha256 in (data.get("spec_sha256_seen") or [data.get("spec_sha256")])


#: what a record says of its collection, not of its runs: a record that differs only here is the same record
_COLLECTION_KEYS = ("collected_unix", "provenance")


def _same_record(path: Path, record: dict[str, Any]) -> bool:
    """Whether the record at ``path`` holds what ``record`` does, but for when and by which commit it was collected."""
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    if not isinstance(old, dict):
        return False
    drop = set(_COLLECTION_KEYS)
    new = json.loads(json.dumps({k: v for k, v in record.items() if k not in drop}))  # tuples as lists, as read back
    return {k: v for k, v in old.items() if k not in drop} == new


def _write_record(
    spec: StudySpec, runs: Sequence[StudyRun], root: Path, failed: list[str], run: bool, keep_same: bool = False
) -> dict[str, Any]:
    """Collect ``spec``'s record and write it to ``root`` (and, after a run, to the path the spec names).

    ``keep_same``: a file that already holds the same record (but for its collection's time and commit) is left
    as it is, so that a finished study run again does not rewrite its committed record with another commit.
    """
    record = collect_record(spec, runs, root)
    record["failed"] = failed
    if run or (root / RECORD_FILE).exists() or record["runs"]:
        root.mkdir(parents=True, exist_ok=True)
        text = (json.dumps(record, indent=1, allow_nan=False) + "\n").encode()
        targets = [root / RECORD_FILE]
        if spec.record is not None and run:  # the copy the spec names (kept in the repository)
            spec.record.path.parent.mkdir(parents=True, exist_ok=True)
            targets.append(spec.record.path)
        for target in targets:
            if not (keep_same and _same_record(target, record)):
                atomic_write_bytes(target, text)
    return record


def ray_available() -> bool:
    """Whether Ray can be imported."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def _run_on_ray(
    runs: Sequence[StudyRun], imports: Sequence[str], address: str | None, jobs: int, log: Callable[[str], None]
) -> list[str]:
    if not ray_available():
        raise ConfigError("Ray is not installed: pip install 'pimbrl[ray]', or run with --backend local")
    import ray

    from .watchdog import watch_descendants

    started_here = not ray.is_initialized()
    watchdog = None
    try:
        if started_here:
            if address:
                ray.init(address=address, log_to_driver=False)
            else:
                watchdog = watch_descendants()  # Ray's helpers end with this process, also a killed one
                ray.init(num_cpus=max(1, jobs), include_dashboard=False, log_to_driver=False)
        remote = ray.remote(num_cpus=1, max_retries=0)(execute_run)
        refs = {
            remote.options(runtime_env={"env_vars": thread_variables(r.config.threads)}).remote(
                str(r.path), r.config, tuple(imports)
            ): r
            for r in runs
        }
        failed = []
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                r = refs[ref]
                try:
                    outcome = ray.get(ref)
                except Exception as exc:  # a worker that died
                    outcome = {"path": str(r.path), "ok": False, "error": f"{type(exc).__name__}: {exc}"}
                if outcome["ok"]:
                    log(f"done {r.label(False)} seed {r.seed}")
                else:
                    log(f"FAILED {r.label(False)} seed {r.seed}: {outcome['error']}; the others go on")
                    failed.append(str(r.path))
        return failed
    finally:
        if started_here and ray.is_initialized():
            ray.shutdown()
        if watchdog is not None:
            watchdog.stop()


def _run_entry(run: StudyRun, root: Path, payload: dict[str, Any]) -> dict[str, Any] | None:
    """The record's entry of one run (``payload``: its config.json, read once); ``None`` before its first evaluation."""
    result = RunDirectory(run.path).result(None)
    if result is None:
        return None
    summary = payload.get("summary") or {}
    curve = result.pop("curve")
    try:
        relative = str(run.path.resolve().relative_to(root.resolve()))
    except ValueError:
        relative = str(run.path)
    return {
        "system": run.system,
        "arm": run.arm,
        "method": run.config.method.name,
        "agent": None if run.config.control else run.config.agent.name,
        "setting": run.setting_text,
        "seed": run.seed,
        "path": relative,
        "finished": result["finished"],
        "steps": result["steps"],
        # a controller's real steps are its identification's: it has no other budget
        "budget": result["steps"] if run.config.control else run.config.total_steps,
        "final_return": result["final_return"],
        "selected_step": summary.get("selected_step"),
        "selected_return": summary.get("selected_return_mean"),
        "holdout_return": summary.get("holdout_return_mean"),
        "wall_s": result["wall_s"],
        "updates": result["updates"],
        "real_transitions": summary.get("real_transitions", result["steps"] if not summary else None),
        "imagined_transitions": summary.get("imagined_transitions"),
        "scheme_transitions": summary.get("scheme_transitions"),
        "validation_transitions": summary.get("validation_transitions"),
        "inference_s_per_step": summary.get("inference_s_per_step"),
        "provenance": payload.get("provenance"),
        **({"resumed_on": payload["resumed_on"]} if payload.get("resumed_on") else {}),  # carried to other machines
        "replicate_of": _replica_source(payload),
        "feedback": _feedback_choice(run) if run.config.control else None,
        "curve": curve,
    }


def _feedback_choice(run: StudyRun) -> dict[str, Any] | None:
    """A feedback run's chosen gain with every candidate's validation return (its ``control.json``), else ``None``."""
    from ..training.control_run import read_stages

    stages = read_stages(RunDirectory(run.path)) or {}
    chosen = stages.get("feedback")
    if not isinstance(chosen, dict) or "gain" not in chosen:
        return None
    return {"kind": chosen.get("kind"), "gain": chosen["gain"], "validation": chosen.get("validation")}


def _replica_source(payload: dict[str, Any]) -> str | None:
    """The run a copied seed-free run was copied from, else ``None`` (``read_config`` checked its form)."""
    replica = payload.get("replicate_of")
    return None if replica is None else replica["source"]


def collect_record(spec: StudySpec, runs: Sequence[StudyRun], root: str | Path) -> dict[str, Any]:
    """The study's record from its run directories (runs not started yet are listed as missing)."""
    from .registration import read_registration
    from .runner import config_differences

    root = Path(root)
    entries, missing, unreadable, mismatched = [], [], [], []
    for run in runs:
        try:
            payload = RunDirectory(run.path).read_config() if (run.path / "config.json").exists() else None
            diffs = [] if payload is None else config_differences(payload.get("config"), run.config)
            if diffs:  # a run made with other settings is not this spec's run
                mismatched.append(f"{run.path}: {', '.join(diffs)}")
                continue
            entry = None if payload is None else _run_entry(run, root, payload)
        except (ValueError, OSError) as exc:  # a damaged run directory: named, the others collected
            unreadable.append(f"{run.path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}")
            continue
        if entry is None:
            missing.append(str(run.path))
        else:
            entries.append(entry)
    return {
        "format": RECORD_FORMAT,
        "study": spec.name,
        "kind": spec.kind,
        "spec_sha256": spec.sha256,
        "spec": spec.text,
        "registration": read_registration(root),
        "provenance": provenance(),
        "collected_unix": time.time(),
        "thresholds": {s: study_thresholds(spec, s) for s in dict.fromkeys(r.system for r in runs)},
        "runs": entries,
        "missing": missing,
        "unreadable": unreadable,
        "mismatched": mismatched,
    }
