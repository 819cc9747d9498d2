"""The ``pimbrl`` command line."""

from __future__ import annotations

import argparse
import contextlib
import difflib
import errno
import functools
import json
import os
import re
import select
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from .config import ConfigError, add_arguments, overrides_from_args
from .training.stopping import RunStopped, TimeLimitReached

__all__ = ["build_parser", "main"]


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors suggest the closest choice for a mistyped one."""

    def error(self, message: str) -> Any:
        """Print ``message`` (with a suggestion where one is close) in one line, and exit with status 2.

        No usage block: the line says what is wrong and where the options are listed.
        """
        choice = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if choice:
            options = re.findall(r"'([^']*)'", choice.group(2))
            message += _suggestion(choice.group(1), options)
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def fail_unknown(self, unknown: list[str]) -> None:
        """Exit with the error for the unrecognised arguments ``unknown``, suggesting the closest flag."""
        from .training.legacy import old_flag_message

        flags = [o for a in self._actions for o in a.option_strings]
        first = next((u.split("=")[0] for u in unknown if u.startswith("-")), None)
        old = old_flag_message(first) if first else None
        if old is not None:  # a flag of the previous release: its new name
            self.error(old)
        hint = _suggestion(first, flags, quote=False) if first else ""
        self.error(f"unrecognized arguments: {' '.join(unknown)}{hint}")


def _suggestion(word: str, options: Sequence[str], quote: bool = True) -> str:
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    if not close:
        return ""
    return f" (did you mean {close[0]!r}?)" if quote else f" (did you mean {close[0]}?)"


def _cmd_simulate(args: argparse.Namespace) -> int:
    import gymnasium as gym
    import numpy as np

    from . import plotting
    from .envs import PhysicsEnv
    from .simulate import make_simple_policy, resolve_env_id, run_episode

    env_id = resolve_env_id(args.env)
    kwargs = {}
    if args.initial_states is not None:
        kwargs["initial_states"] = args.initial_states
    try:
        env = gym.make(env_id, max_episode_steps=args.steps, **kwargs) if args.steps else gym.make(env_id, **kwargs)
    except TypeError as exc:
        if args.initial_states is None or "initial_states" not in str(exc):
            raise
        raise ValueError(f"--initial-states applies to systems with initial-state pools (KS), not {env_id}") from None
    value = None if args.value is None else [float(v) for v in args.value.split(",")]
    if args.policy == "feedback":
        policy = _feedback_policy(env_id, env, args.gain)
    else:
        policy = make_simple_policy(env.action_space, args.policy, np.random.default_rng(args.seed), value)
    record = run_episode(env, policy, seed=args.seed)
    out = Path(args.out) if args.out else Path("out") / f"{env_id.split('/')[-1]}_{args.policy}_seed{args.seed}.png"
    base = env.unwrapped
    x = getattr(base.physics, "x", None) if isinstance(base, PhysicsEnv) and base.physics.state_dim > 4 else None
    plotting.plot_episode(record, out, x=x)
    what = f"{args.policy} (gain {args.gain:g})" if args.policy == "feedback" else args.policy
    print(f"{env_id}  policy={what}  seed={args.seed}  steps={record.length}  return={record.total_return:.4f}")
    print(f"figure: {out}")
    return 0


def _feedback_policy(env_id: str, env: Any, gain: float) -> Any:
    """The system's feedback floor at ``gain`` as a policy of one env (it reads the physical state)."""
    import numpy as np

    from .control.base import env_actions, task_of
    from .control.feedback import declared_feedback, make_feedback

    task = task_of(env_id, {})
    kind, options, _ = declared_feedback(env_id, task.physics)
    controller = make_feedback(task, kind, gain, options)
    base = env.unwrapped
    return lambda obs: env_actions(task, controller(base.state[None], np.array([base.elapsed_steps])))[0]


def _default_run_dir(env_id: str, method: str, agent: str | None, seed: int) -> str:
    short = env_id.split("/")[-1].split("-v")[0].lower()
    return str(Path("runs") / short / (f"{method}-{agent}-seed{seed}" if agent else f"{method}-seed{seed}"))


def _train_config_from_args(args: argparse.Namespace):
    from .simulate import resolve_env_id
    from .training.cli_args import overrides_from_namespace
    from .training.config import flag_of, load_config_file, resolve_config

    overrides = overrides_from_namespace(args)
    if args.config is not None:  # a whole configuration: nothing else may change it
        given = [flag_of(k) for k in overrides] + ([f"the environment {args.env!r}"] if args.env is not None else [])
        given += ["--preset"] if args.preset is not None else []
        if given:
            raise ValueError(
                f"--config {args.config} is a whole configuration; it cannot be combined with {', '.join(given)} "
                "(edit the file instead; only --run-dir, --quiet and --print-config go with --config)"
            )
        return load_config_file(args.config)
    if args.env is None:
        raise ValueError(
            "`pimbrl train` needs an environment (ks, burgers, cartpole, pendulum, or a Gymnasium id) or --config FILE"
        )
    return resolve_config(resolve_env_id(args.env), overrides, preset=args.preset)


def _config_warnings(cfg: Any, preset: str | None = None) -> list[str]:
    from .training.advice import config_warnings

    return config_warnings(cfg, preset)


def _check_run_dir(path: str | Path, flag: str = "--run-dir") -> None:
    """Refuse a run directory that cannot be created or written, before anything is made.

    The nearest existing ancestor must be a directory and writable (e.g. not under a regular file).
    """
    path = Path(path).absolute()
    for existing in (path, *path.parents):
        if not existing.exists():
            continue
        if not existing.is_dir():
            raise ValueError(f"{existing} is a file, not a directory: {flag} {path} cannot be made; choose another {flag}")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise ValueError(f"{existing} is not writable (permission denied or a read-only disk); choose another {flag}")
        return


def _train(args: argparse.Namespace, run: Any) -> Any:
    """Train ``run`` to its end; ``args.active_run`` and ``args.checkpoint_step`` say what a failure leaves."""
    from .training import train

    args.active_run = run
    args.checkpoint_step = run.t if run.run_dir.checkpoint_path.exists() else None

    def on_event(name: str, r: Any) -> None:
        if name == "checkpoint":  # called once the checkpoint is written
            args.checkpoint_step = r.t

    return train(run, on_event=on_event, stop_on_signal=True)  # SIGTERM, SIGINT: checkpointed at the episode end


def _cmd_train(args: argparse.Namespace) -> int:
    if args.help_all:
        from .training.cli_args import full_help

        print(full_help())
        return 0
    cfg = _train_config_from_args(args)
    for line in _config_warnings(cfg, args.preset):
        print(f"pimbrl train: warning: {line}", file=sys.stderr)
    if args.preset is not None and args.config is None:
        from .training.config import recipe_of

        recipe = recipe_of(cfg.env, args.preset)
        chosen = f"; chosen by {recipe.chosen_by}" if recipe.chosen_by else ""
        print(f"pimbrl train: recipe {recipe.name} of {cfg.env}: {recipe.about}{chosen}", file=sys.stderr)
    if args.print_config:  # the resolved configuration (defaults, recipe, overrides); nothing is trained
        from .training.config import config_to_dict

        print(json.dumps(config_to_dict(cfg), indent=2))
        return 0
    run_dir = args.run_dir or _default_run_dir(cfg.env, cfg.method.name, None if cfg.control else cfg.agent.name, cfg.seed)
    _check_run_dir(run_dir)
    from .training import create_run

    print(f"run directory: {run_dir}", file=sys.stderr)
    run = create_run(cfg, run_dir, progress=not args.quiet, command=" ".join(sys.argv))
    _print_summary(run_dir, _train(args, run), run.cfg.eval_protocol)
    return 0


def _print_summary(run_dir: str, summary, protocol: str) -> None:
    """The run's one-line summary; its evaluations' draws named (``test``, or a tuning run's ``validation``)."""
    final = "-" if summary.final_return_mean is None else f"{summary.final_return_mean:.3f}"
    reached = "not reached" if summary.steps_to_threshold is None else f"{summary.steps_to_threshold:,d} steps"
    print(
        f"{run_dir}: {summary.steps:,d} steps, {summary.updates:,d} updates, final {protocol} return {final}, "
        f"threshold {reached}, {summary.wall_s:.1f} s"
    )


def _cmd_resume(args: argparse.Namespace) -> int:
    from .training import open_run, train
    from .training.runs import extend_run

    if args.total_steps is not None:
        extend_run(args.run_dir, args.total_steps)
        print(f"{args.run_dir}: total_steps raised to {args.total_steps:,d}", file=sys.stderr)
    run = open_run(args.run_dir, progress=not args.quiet)
    _print_kernel_note(run)
    if run.finished:
        train(run)  # repairs a "running" status left by a kill after the final checkpoint
        print(f"{args.run_dir} has already finished ({run.t:,d} steps); nothing to do")
        return 0
    print(f"resuming {args.run_dir} at step {run.t:,d}", file=sys.stderr)
    _print_summary(args.run_dir, _train(args, run), run.cfg.eval_protocol)
    return 0


def _print_kernel_note(run: Any) -> None:
    """Say so on stderr where a PDE run was made with another simulator kernel than this pimbrl's."""
    from .training.config import is_pde_env
    from .training.rundir import kernel_note

    note = kernel_note(run.run_dir.read_config().get("versions", {})) if is_pde_env(run.cfg.env) else None
    if note:
        print(f"note: {note}", file=sys.stderr)


def _cmd_eval(args: argparse.Namespace) -> int:
    import dataclasses

    from .training import load_run, steps_to_threshold

    run = load_run(args.run_dir, require_checkpoint=True)
    _print_kernel_note(run)
    cfg = run.cfg
    label, policy_step = f"step {run.t:,d}", run.t
    if args.policy == "selected":
        policy_step = run.use_selected_policy()
        label = f"selected at step {policy_step:,d} of {run.t:,d}"
    evaluator = run.evaluator_for(args.protocol, args.episodes or None)
    result = evaluator.run(lambda o: run.agent.act(o, deterministic=True))
    s = {**result.summary(), **result.quartiles()}
    print(
        f"{args.run_dir} ({label}, {evaluator.episodes} {args.protocol}-protocol episodes): return mean "
        f"{s['return_mean']:.3f}, quartiles {s['return_q25']:.3f} / {s['return_median']:.3f} / {s['return_q75']:.3f}, "
        f"min {s['return_min']:.3f}, max {s['return_max']:.3f}, std {s['return_std']:.3f}"
    )
    rows = run.run_dir.evaluations.read()
    if cfg.threshold is not None:
        reached = steps_to_threshold(rows, cfg.threshold)
        print(f"steps to threshold {cfg.threshold:g}: {'not reached' if reached is None else f'{reached:,d}'}")
    if args.json:
        payload = {
            "step": run.t,
            "policy": args.policy,
            "policy_step": policy_step,
            "protocol": args.protocol,
            **s,
            "returns": result.returns.tolist(),
        }
        print(json.dumps({**payload, "config": dataclasses.asdict(cfg)}, default=str))
    return 0


def _cmd_plot(args: argparse.Namespace) -> int:
    import numpy as np

    from . import plotting
    from .training import RunDirectory
    from .training.legacy import method_and_agent

    if args.labels and len(args.labels) != len(args.run_dirs):
        raise ValueError(f"--labels gives {len(args.labels)} labels for {len(args.run_dirs)} run directories; give one each")
    runs = []
    for path in args.run_dirs:
        run = RunDirectory(path)
        run.check_entries()
        cfg = run.recorded_config()
        rows = run.evaluations.read()
        if not rows:
            raise ValueError(f"{path} has no evaluations yet")
        runs.append((path, cfg, rows))
    envs = sorted({cfg["env"] for _, cfg, _ in runs})
    if len(envs) > 1:
        print(
            f"pimbrl plot: warning: the runs are on {len(envs)} systems ({', '.join(envs)}), whose returns are on "
            "different scales; each curve's label names its system",
            file=sys.stderr,
        )
    names = []
    for _path, cfg, _ in runs:
        method, agent = method_and_agent(cfg)
        system = f"{cfg['env'].split('/')[-1]} " if len(envs) > 1 else ""
        names.append(f"{system}{method}/{agent} seed {cfg.get('seed')}")
    for i, name in enumerate(names):  # two runs with the same description: the directory tells them apart
        if names.count(name) > 1:
            names[i] = f"{name} ({runs[i][0]})"
    curves = []
    thresholds = set()
    for i, (_, cfg, rows) in enumerate(runs):
        label = args.labels[i] if args.labels else names[i]
        cols = {name: np.array([float(r[name]) for r in rows]) for name in ("step", "return_mean", "return_min", "return_max")}
        curves.append((label, cols["step"], cols["return_mean"], cols["return_min"], cols["return_max"]))
        if cfg.get("threshold") is not None:
            thresholds.add(float(cfg["threshold"]))
    out = Path(args.out)
    plotting.plot_learning_curves(
        curves,
        out,
        title=", ".join(envs),
        threshold=thresholds.pop() if len(thresholds) == 1 else None,
        band="band: the lowest to the highest return of the test episodes at each evaluation",
    )
    print(f"figure: {out}")
    return 0


def _cmd_model_eval(args: argparse.Namespace) -> int:
    import dataclasses

    from .config import parse_learned, parse_prior
    from .experiments import ModelEvalConfig, model_eval_defaults, run_model_eval
    from .simulate import resolve_env_id
    from .training.methods import PhysicsLoss

    env_id = resolve_env_id(args.env)
    fields = {**model_eval_defaults(env_id), **overrides_from_args(args, ModelEvalConfig)}
    for flag, parse in (("env_coefficients", parse_prior), ("physics_prior", parse_prior), ("learn_coefficients", parse_learned)):
        text = getattr(args, f"{flag}_text")
        if text is not None:  # the short text of the command line, read once into the setting's mapping
            value = parse(text)
            fields[flag] = {k: list(v) if isinstance(v, tuple) else v for k, v in value.items()}
    physics = overrides_from_args(args, PhysicsLoss, prefix="physics.")
    if "sources" in physics:
        from .training.cli_args import read_sources

        physics["sources"] = read_sources(physics["sources"])
    cfg = dataclasses.replace(ModelEvalConfig(), **fields)
    cfg = dataclasses.replace(cfg, physics=dataclasses.replace(cfg.physics, **physics))
    if cfg.labels:  # the study: errors against the number of labelled transitions
        from .experiments.model_study import run_model_study

        run_model_study(env_id, args.run_dir, cfg, log=lambda m: print(m, flush=True))
        print(f"wrote {Path(args.run_dir) / 'study.csv'}, study.json and study.png")
        return 0
    run_model_eval(env_id, args.run_dir, cfg, log=lambda m: print(m, flush=True))
    print(f"wrote {Path(args.run_dir) / 'model_errors.csv'}, summary.json and model_errors.png")
    return 0


def _seed_list(text: str) -> list[int]:
    """``"3"`` means seeds 0, 1, 2; ``"0,4,7"`` those seeds; ``"5,"`` seed 5 alone."""
    from .experiments.compare import MAX_SEEDS

    try:
        count = None if "," in text else int(text)
    except ValueError:
        count = 0
    if count is not None and count > MAX_SEEDS:
        raise ValueError(f"--seeds {count:,} is more than a comparison runs ({MAX_SEEDS:,} seeds at most); give fewer")
    try:
        seeds = [int(s) for s in text.split(",") if s.strip()] if count is None else list(range(count))
    except ValueError:
        seeds = []
    if not seeds:
        raise ValueError(
            f"--seeds must be a count >= 1 (e.g. 3 for seeds 0,1,2) or a list (e.g. 0,1,2, or 5, for seed 5 alone), got {text!r}"
        )
    seen: set[int] = set()
    for s in seeds:  # one run directory per seed: a repeated seed would be one run counted twice
        if s in seen:
            raise ValueError(f"seed {s} is given twice in --seeds {text}; give each seed once")
        seen.add(s)
    return seeds


def _cmd_compare(args: argparse.Namespace, extra: list[str]) -> int:
    from .experiments.compare import compare, plan_runs, ratio_lines
    from .simulate import resolve_env_id
    from .training.cli_args import parse_train_args

    env_id = resolve_env_id(args.env)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    overrides = parse_train_args(extra)  # typed once; each run gets those that apply to its method
    for flag, key, value in (("--steps", "total_steps", args.steps), ("--threshold", "threshold", args.threshold)):
        if value is not None:
            if key in overrides:
                raise ValueError(f"give {flag} once: as a compare option or after --, not both")
            overrides[key] = value
    seeds = _seed_list(args.seeds)
    if not args.no_run:
        _check_run_dir(args.run_dir)
        warned = set()
        for spec in plan_runs(env_id, methods, seeds[:1], Path(args.run_dir), overrides, args.preset):
            for line in _config_warnings(spec.config, args.preset):
                if (spec.label, line) not in warned:
                    warned.add((spec.label, line))
                    print(f"pimbrl compare: warning: {spec.label}: {line}", file=sys.stderr)
    result = compare(
        env_id,
        methods,
        seeds,
        args.run_dir,
        overrides,
        jobs=args.jobs,
        threshold=args.threshold,
        run=not args.no_run,
        rerun=args.rerun,
        imports=args.imports,
        preset=args.preset,
        replicas=not args.no_replicas,
    )
    thr = result["threshold"]
    print(f"{env_id}: threshold {thr}")
    for label, m in result["methods"].items():
        s2t = "not reached on every seed" if m["steps_to_threshold_mean"] is None else f"{m['steps_to_threshold_mean']:,.0f}"
        print(
            f"  {label:13s} seeds {m['seeds']}  reached {m['reached']}/{m['seeds']}  steps to threshold {s2t} "
            f"{m['steps_to_threshold']}  final {m['final_return_mean']:.3f}  updates/step {m['update_to_data']:.2f}  "
            f"wall {m['wall_s_mean']:.0f} s"
        )
    for line in ratio_lines(result["ratios"]):
        print(f"  steps ratio {line}")
    if result["failed"]:
        print(f"failed runs: {', '.join(result['failed'])}", file=sys.stderr)
        return 1
    if not result["runs"]:
        print(
            f"error: no run under {args.run_dir} has an evaluation yet (looked for {args.run_dir}/<method>/seed<k> "
            f"for methods {args.methods} and seeds {args.seeds}); check --run-dir, --methods and --seeds, or drop "
            "--no-run to start the runs",
            file=sys.stderr,
        )
        return 2
    print(f"wrote {Path(args.run_dir) / 'curves.png'}, summary.csv and summary.json")
    if not args.no_run:
        spec_file = Path(args.run_dir) / "study.yaml"
        print(f"tables with intervals: pimbrl study report {spec_file} (the comparison's spec; its record: record.json)")
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from .experiments.sweep import load_sweep, run_sweep

    spec = load_sweep(args.config)  # run_sweep resolves every trial's configuration before anything runs
    _check_run_dir(args.run_dir)
    use_ray = False if args.no_ray else (True if args.address else None)
    result = run_sweep(
        spec,
        args.run_dir,
        use_ray=use_ray,
        address=args.address,
        num_cpus=args.cpus,
        log=lambda m: print(m, flush=True),
        imports=args.imports,
        replicas=not args.no_replicas,
    )
    print(
        f"{len(result['rows'])} trials with results, {result['executed']} run now; "
        f"wrote {Path(args.run_dir) / 'results.csv'}, summary.json, curves.png"
    )
    if result["failed"]:
        print(f"failed trials: {', '.join(result['failed'])}", file=sys.stderr)
        return 1
    return 0


def _study_run_dir(spec_path: str, spec_name: str, given: str | None) -> Path:
    """A study's directory: ``--run-dir``, else the spec's own directory, else ``runs/<study name>``.

    The spec's own directory where it holds the study's record or registration (a spec written by `pimbrl
    compare` or `pimbrl sweep` beside its runs).
    """
    from .experiments.engine import RECORD_FILE
    from .experiments.registration import REGISTRATION_FILE

    if given is not None:
        return Path(given)
    here = Path(spec_path).resolve().parent
    if (here / RECORD_FILE).exists() or (here / REGISTRATION_FILE).exists():
        return here
    return Path("runs") / spec_name


def _study_status(spec: Any, root: Path, jobs: int, archive: Path | None, totals: Any = None) -> None:
    """One study's progress table and estimate (added to ``totals``, a ``QueueTotals``, when given)."""
    from .experiments.archive import plan_restore
    from .experiments.engine import plan_study
    from .experiments.progress import progress_lines, study_progress

    notes = []
    runs = plan_study(spec, root)  # planned once: the archive's restore and the progress table read the same runs
    if archive is not None and archive.is_dir():
        plan = plan_restore(spec, root, archive, runs)
        if plan.refusal is not None:
            notes.append(f"the archive {archive} is not restored here: {plan.refusal}")
        elif plan.runs or plan.carried or plan.passed:
            notes.append(
                f"{len(plan.runs)} finished run(s) wait in the archive {archive} for `pimbrl study run` to copy them back"
                + (f", and {len(plan.carried)} interrupted run(s) with their checkpoints, to resume" if plan.carried else "")
                + (f"; {len(plan.passed)} left out there ({plan.passed[0]})" if plan.passed else "")
            )
    if not root.is_dir() and spec.record is not None and spec.record.path.is_file():
        print(
            f"study {spec.name}: no run directory {root} here; its record {os.path.relpath(spec.record.path)} is kept "
            "(`pimbrl study report` reads it)"
        )
    elif not root.is_dir():
        print(f"study {spec.name}: no run directory {root} yet (start it with `pimbrl study run`; or give --run-dir)")
        if totals is not None:
            totals.untimed.append(f"{spec.name} (no run directory yet)")
    else:
        print("\n".join(progress_lines(spec, study_progress(spec, root, runs), jobs=jobs, totals=totals)))
    for line in notes:
        print(line)


def _study_archive(args: argparse.Namespace, spec: Any, root: Path) -> Path | None:
    """The archive a `pimbrl study` action reads or writes (``None``: none), after checking the flags."""
    archive = _archive_flag(args, spec)
    if archive is not None and (args.action == "archive" or args.keep_archive):
        inner, outer = archive.resolve(), root.resolve()
        if inner.is_relative_to(outer) or outer.is_relative_to(inner):
            raise ValueError(
                f"the archive {archive} and the run directory {root} lie one inside the other (the run directory need not "
                "outlive the machine, the archive must): give --archive DIR apart from it"
            )
    return archive


def _archive_flag(args: argparse.Namespace, spec: Any) -> Path | None:
    from .experiments.archive import default_archive

    if args.archive is not None and args.no_archive:
        raise ValueError("give --archive DIR or --no-archive, not both")
    if args.time_limit is not None and args.action != "run":
        raise ValueError(f"--time-limit applies to study run, not {args.action}")
    if args.keep_archive and args.action != "run":
        raise ValueError(f"--keep-archive applies to study run, not {args.action}")
    if args.checkpoints and args.action != "archive":
        raise ValueError(f"--checkpoints applies to study archive, not {args.action}")
    if args.action not in ("run", "status", "archive"):
        if args.archive is not None or args.no_archive:
            raise ValueError(f"--archive and --no-archive apply to study run, status and archive, not {args.action}")
        return None
    if args.keep_archive and args.no_archive:
        raise ValueError("give --keep-archive or --no-archive, not both")
    if args.no_archive:
        if args.action == "archive":
            raise ValueError("`pimbrl study archive` writes an archive: drop --no-archive")
        return None
    if args.archive is None:
        found = default_archive(spec)
        near = os.path.relpath(found)  # shorter in messages, where it lies below the working directory
        archive = found if near.startswith("..") else Path(near)
        if archive.exists() and not archive.is_dir():
            raise ValueError(f"{archive}, the archive beside the spec, is not a folder: move it away, or give --archive DIR")
        return archive
    archive = Path(args.archive)
    if archive.exists() and not archive.is_dir():
        raise ValueError(f"--archive {archive} is not a folder: give the archive's folder")
    if args.action != "archive" and not archive.is_dir() and not args.keep_archive:
        raise ValueError(
            f"no archive {archive}: check --archive, or drop it to use {default_archive(spec)} (the one beside the spec)"
        )
    return archive


def _threshold_arg(text: str) -> float | str:
    """`study draft --threshold`: a number, or ``rule``."""
    if text == "rule":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"give a number or 'rule', got {text!r}") from None


def _study_draft(args: argparse.Namespace, spec: Any, root: Path) -> int:
    """`pimbrl study draft TUNING [AMENDMENT...]`: the confirmatory spec the records give, to --out or stdout.

    Never over a file; each amendment's methods replace the first study's (``draft_confirmatory``).
    """
    from .experiments.draft import draft_confirmatory
    from .experiments.report import load_record
    from .experiments.spec import load_spec
    from .fileio import create_file

    out = Path(args.out) if args.out else None
    if out is not None and out.exists():  # checked again, atomically, when it is written
        raise FileExistsError(
            f"{out} exists: a registered spec is never rewritten (give another --out, or remove an unregistered draft)"
        )
    if len(args.specs) > 1 and args.run_dir is not None:
        raise ValueError("`pimbrl study draft` with amendments reads each study's own record: drop --run-dir")
    record = load_record(spec, root if spec.record is None or spec.record.format == "study" else None)
    amendments = []
    for path in args.specs[1:]:
        amending = load_spec(path)
        amending_root = _study_run_dir(path, amending.name, None)
        amendments.append((amending, load_record(amending, amending_root)))
    text = draft_confirmatory(
        spec, record, out, seeds=args.seeds, other_seeds=args.other_seeds, total_steps=args.total_steps,
        holdout_episodes=args.holdout_episodes, threshold=args.threshold, amendments=amendments,
    )  # fmt: skip
    if out is None:
        print(text, end="")
        return 0
    try:
        create_file(out, text.encode())
    except FileExistsError:
        raise FileExistsError(f"{out} appeared while the draft was made: nothing was written (give another --out)") from None
    print(f"wrote {out}: review it, then commit it alone before its first run (`pimbrl study run {out}`)")
    return 0


def _study_queue(args: argparse.Namespace, log: Callable[[str], None]) -> int:
    """`pimbrl study run A B ...`: a queue, each study in its own directory with its own archive (``run_studies``)."""
    from .experiments.engine import QueuedStudy, run_studies
    from .experiments.spec import load_spec

    if args.run_dir is not None or args.archive is not None:
        raise ValueError(
            "`pimbrl study run` with several specs runs each in its own directory with its own archive: drop --run-dir, --archive"
        )
    queue = []
    for path in args.specs:
        spec = load_spec(path)
        root = _study_run_dir(path, spec.name, None)
        _check_run_dir(str(root))
        archive = _study_archive(args, spec, root)
        keep = args.keep_archive
        queue.append(QueuedStudy(spec, root, rerun=args.rerun, replicas=not args.no_replicas, archive=archive, keep_archive=keep))
    run_studies(queue, jobs=args.jobs, backend=args.backend, address=args.address, log=log, time_limit=args.time_limit)
    failed = False
    for q in queue:  # each study's "runs recorded" line was logged as it ended
        record = q.record or {"failed": []}
        if record["failed"]:
            print(f"study {q.spec.name}: failed runs: {', '.join(record['failed'])}", file=sys.stderr)
            failed = True
    return 1 if failed else 0


def _cmd_study(args: argparse.Namespace) -> int:
    from .experiments.engine import plan_study, run_study
    from .experiments.report import load_record, study_report, write_pages
    from .experiments.spec import load_spec

    log = lambda m: print(m, flush=True)
    if args.action == "report" and args.pages:
        if args.archive is not None or args.no_archive or args.keep_archive or args.checkpoints:
            raise ValueError(
                "--archive, --no-archive, --keep-archive and --checkpoints apply to study run, status and archive, not report"
            )
        specs = [load_spec(p) for p in args.specs]
        folders = dict.fromkeys(Path(p).resolve().parent for p in args.specs)  # the first holding the hand-written part
        header = next((f / "_reproduce.md" for f in folders if (f / "_reproduce.md").is_file()), None)
        preamble = header.read_text(encoding="utf-8") if header is not None else ""
        for path in write_pages(specs, args.pages, preamble=preamble):
            print(f"wrote {path}")
        return 0
    if args.action == "status" and len(args.specs) > 1:
        if args.run_dir is not None or args.archive is not None:
            raise ValueError(
                "`pimbrl study status` with several specs reads each one's own directory and archive: drop --run-dir, --archive"
            )
        from .experiments.progress import QueueTotals

        totals = QueueTotals()
        for i, path in enumerate(args.specs):
            if i:
                print()
            each = load_spec(path)
            each_root = _study_run_dir(path, each.name, None)
            _study_status(each, each_root, args.jobs, _study_archive(args, each, each_root), totals)
        print()
        print(totals.line(len(args.specs), args.jobs))
        return 0
    if args.action == "run" and len(args.specs) > 1:
        return _study_queue(args, log)
    if len(args.specs) != 1 and args.action != "draft":
        raise ValueError(
            f"`pimbrl study {args.action}` takes one spec (several only with run, status, draft or report --pages), got "
            f"{len(args.specs)}"
        )
    spec = load_spec(args.specs[0])
    root = _study_run_dir(args.specs[0], spec.name, args.run_dir)
    archive = _study_archive(args, spec, root)
    if args.action == "plan":
        runs = plan_study(spec, root)
        for r in runs:
            print(f"{r.path}  {r.system} {r.arm} {r.setting_text} seed {r.seed}")
        print(f"{len(runs)} runs of study {spec.name} ({spec.kind}); plan: {spec.plan or 'not stated in the spec'}")
        return 0
    if args.action == "status":
        _study_status(spec, root, args.jobs, archive)
        return 0
    if args.action == "draft":
        return _study_draft(args, spec, root)
    if args.action == "archive":
        from .experiments.archive import archive_study

        assert archive is not None
        result = archive_study(
            spec, root, archive, plan_study(spec, root), checkpoints=args.checkpoints, drop_unplanned=args.checkpoints
        )
        print(result.line("archived", archive) + f" (commit it to keep it: git add {archive})")
        return 0
    if args.action == "run":
        _check_run_dir(str(root))
        record = run_study(
            spec, root, jobs=args.jobs, backend=args.backend, address=args.address, rerun=args.rerun,
            replicas=not args.no_replicas, archive=archive, keep_archive=args.keep_archive, log=log,
            time_limit=args.time_limit,
        )  # fmt: skip
        if record["failed"]:
            print(f"failed runs: {', '.join(record['failed'])}", file=sys.stderr)
            return 1
        return 0
    record = load_record(spec, root if spec.record is None or spec.record.format == "study" else None)
    out = Path(args.out) if args.out else root
    report = study_report(spec, record, figures_dir=out, link_base=out)
    from .fileio import atomic_write_bytes

    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / "report.md", report.markdown.encode())
    print(report.markdown)
    print(f"wrote {out / 'report.md'}" + "".join(f", {f}" for f in report.figures))
    return 0


FIGURES = ("ks-contours", "burgers", "model-errors", "rollouts", "curves")
#: each figure's default file in the run directory (model-eval writes model_errors.png: a histogram figure has its own)
FIGURE_FILES = {
    "ks-contours": "ks_contours.png",
    "burgers": "burgers_episodes.png",
    "model-errors": "model_error_histograms.png",
    "rollouts": "rollouts.png",
    "curves": "curves.png",
}


def _cmd_figure(args: argparse.Namespace) -> int:
    from .experiments import figures

    out = Path(args.out) if args.out else Path(args.dirs[0]) / FIGURE_FILES[args.kind]
    if args.kind != "curves" and len(args.dirs) != 1:
        raise ValueError(f"`pimbrl figure {args.kind}` takes one directory, got {len(args.dirs)}")
    if args.kind in ("ks-contours", "burgers", "rollouts"):
        figures.check_fits(args.kind, args.dirs[0])  # before the run is loaded
    if args.kind == "ks-contours":
        figures.ks_contours(args.dirs[0], out)
    elif args.kind == "burgers":
        figures.burgers_episodes(args.dirs[0], out)
    elif args.kind == "model-errors":
        figures.model_error_histograms(args.dirs[0], out)
    elif args.kind == "rollouts":
        figures.rollout_snapshots(args.dirs[0], out, lengths=[int(v) for v in args.lengths.split(",")])
    else:
        return _cmd_plot(argparse.Namespace(run_dirs=args.dirs, out=str(out), labels=None))
    print(f"figure: {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``pimbrl`` argument parser with one subcommand per command; each sets ``func`` to its handler."""
    from .training.config import POLICIES

    parser = _Parser(prog="pimbrl", description="Physics-informed model-based RL for dynamic control.")
    parser.add_argument("--version", action="version", version=f"pimbrl {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("simulate", help="run one episode with a simple policy, print the return and plot it")
    sim.add_argument(
        "env", help="ks | burgers | cartpole | pendulum, a system's alias or id (see --import), or a registered Gymnasium id"
    )
    sim.add_argument("--policy", choices=["zero", "random", "constant", "feedback"], default="zero")
    sim.add_argument("--value", help="for --policy constant: one number, or comma-separated per action component")
    sim.add_argument(
        "--gain",
        type=float,
        default=1.0,
        help="for --policy feedback: the gain of the system's feedback floor (PDEs: a_i = -gain x the observation "
        "averaged under actuator i; an LQR: its action cost; the pendulum: its energy pumping)",
    )
    sim.add_argument("--seed", type=int, default=0, help="seeds the initial state and the random policy")
    sim.add_argument("--steps", type=int, default=None, help="episode length (default: the env's time limit)")
    sim.add_argument(
        "--initial-states", choices=["train", "test"], default=None, help="systems with initial-state pools (KS): which pool"
    )
    sim.add_argument("--out", help="PNG path (default: out/<env>_<policy>_seed<seed>.png)")
    _add_import(sim)
    sim.set_defaults(func=_cmd_simulate)

    from .training.cli_args import add_train_flags

    tr = sub.add_parser(
        "train",
        help="train an agent (a recipe per system; every setting can be overridden)",
        description="Train an agent with a method on a system. The system's recipe (--preset: default, paper, best) "
        "sets the budget; every setting can be overridden: the common ones are below, all of them with "
        "--help-all (--imagine.rollout-length, --physics.weight, --agent.gamma, ...). A setting the chosen method "
        "or agent does not have is an error naming those that have it.",
    )
    tr.add_argument(
        "env",
        nargs="?",
        default=None,
        help="ks | burgers | cartpole | pendulum, a system's alias or id (see --import), or any Gymnasium id (e.g. Pendulum-v1)",
    )
    tr.add_argument(
        "--config",
        default=None,
        metavar="FILE",
        help="train the whole configuration in this JSON or YAML file (as --print-config writes it) instead of a "
        "recipe with flags; no other configuration flags may be given with it",
    )
    tr.add_argument("--run-dir", default=None, help="run directory (default: runs/<env>/<method>-<agent>-seed<seed>)")
    tr.add_argument("--quiet", action="store_true", help="no progress bar or log lines")
    tr.add_argument("--print-config", action="store_true", help="print the resolved configuration as JSON and exit")
    tr.add_argument("--help-all", action="store_true", help="list every setting's flag, with the methods that have it")
    add_train_flags(tr)
    _add_import(tr)
    tr.set_defaults(func=_cmd_train)

    rs = sub.add_parser("resume", help="continue a run from its last checkpoint")
    rs.add_argument("run_dir")
    rs.add_argument("--quiet", action="store_true")
    rs.add_argument(
        "--total-steps",
        type=int,
        default=None,
        help="first raise the run's budget to this many real steps (continue a finished run, e.g. to a threshold)",
    )
    _add_import(rs)
    rs.set_defaults(func=_cmd_resume)

    ev = sub.add_parser("eval", help="evaluate a run's latest checkpoint on its test episodes")
    ev.add_argument("run_dir")
    ev.add_argument("--episodes", type=int, default=None, help="number of test episodes (default: the run's)")
    ev.add_argument(
        "--protocol",
        choices=("test", "validation", "authors"),
        default="test",
        help="initial states: the run's held-out test states (default), the validation draws, or KS 'authors': the "
        "5 training-pool rows 0, 49, 99, 149, 199 on which the paper reports its mean return (the holdout pool is "
        "played only by a run's final evaluation: --holdout-episodes)",
    )
    ev.add_argument(
        "--policy",
        choices=POLICIES,
        default="latest",
        help="the checkpoint's latest policy (default), or the one model-based policy selection kept "
        "(runs trained with --dyna.select-episodes)",
    )
    ev.add_argument("--json", action="store_true", help="also print a JSON line")
    _add_import(ev)
    ev.set_defaults(func=_cmd_eval)

    pl = sub.add_parser("plot", help="learning curves (mean test return with the min-max band) of run directories")
    pl.add_argument("run_dirs", nargs="+")
    pl.add_argument("--out", default="curves.png")
    pl.add_argument("--labels", nargs="*", default=None, help="one label per run directory")
    _add_import(pl)
    pl.set_defaults(func=_cmd_plot)

    from .experiments import ModelEvalConfig
    from .training.methods import PhysicsLoss

    me = sub.add_parser(
        "model-eval",
        help="train a data-only and a physics-informed model on the same random-policy data; compare their errors",
    )
    me.add_argument("env", help="ks | burgers | cartpole | pendulum, or a system of yours that declares an out-of-sample set")
    me.add_argument("--run-dir", required=True, help="output directory (model_errors.csv, summary.json, model_errors.png)")
    add_arguments(me, ModelEvalConfig, default_note="default {default!r} where the system's model-eval settings set none")
    add_arguments(me, PhysicsLoss, prefix="physics.", skip=("start_after", "alone_from"))
    me.add_argument(
        "--env-coefficients",
        dest="env_coefficients_text",
        default=None,
        metavar="NAME=VALUE,...",
        help="study: the environment's coefficients where they differ from the paper's, e.g. nu=0.013",
    )
    me.add_argument(
        "--physics-prior",
        dest="physics_prior_text",
        default=None,
        metavar="NAME=VALUE,...",
        help="study: the physics loss's prior where it differs from the environment, e.g. nu=0.01 (adds the model physics-true)",
    )
    me.add_argument(
        "--learn-coefficients",
        dest="learn_coefficients_text",
        default=None,
        metavar="NAME[:LOW:HIGH],...",
        help="study: coefficients fitted to the labels from the prior, e.g. nu (adds the model physics-learned)",
    )
    _add_import(me)
    me.set_defaults(func=_cmd_model_eval)

    cp = sub.add_parser(
        "compare",
        help="run several methods x seeds on one environment (resumable) and write curves.png and summary.csv",
        description="Run every method and seed (finished runs are skipped, interrupted ones resumed), then "
        "write DIR/curves.png, DIR/summary.csv and DIR/summary.json. Arguments after -- are `pimbrl train` "
        "flags; each goes to the runs it applies to (e.g. --fit.* to the methods with a model, not mfrl), and one "
        "that applies to none of the compared methods is an error.",
    )
    cp.add_argument("env")
    cp.add_argument(
        "--methods",
        default="mfrl,mbrl,pimbrl",
        help="comma-separated: mfrl, mbrl, pimbrl, known-scheme, identified-scheme, hybrid, pihybrid, and mfrl-matched "
        "(mfrl with the model-based runs' updates per real step)",
    )
    cp.add_argument(
        "--preset", default=None, metavar="RECIPE", help="the system's recipe every run starts from (default: its default)"
    )
    cp.add_argument("--seeds", default="3", help="a count (3 -> seeds 0,1,2) or a list (0,1,2)")
    cp.add_argument("--run-dir", required=True)
    cp.add_argument("--jobs", type=int, default=1, help="runs in parallel (each one thread)")
    cp.add_argument("--steps", type=int, default=None, help="real steps of every run")
    cp.add_argument("--threshold", type=float, default=None, help="return that counts as solved (default: the recipe's)")
    cp.add_argument("--no-run", action="store_true", help="start nothing: summarise the runs as they are (finished or not)")
    cp.add_argument(
        "--rerun",
        action="store_true",
        help="a run directory that holds a run of another configuration (e.g. another --steps) is moved aside "
        "(to seed<k>.replaced-<time>) and trained again; without it, that is an error",
    )
    _add_no_replicas(cp)
    _add_import(cp)
    cp.set_defaults(func=_cmd_compare, takes_extra=True)

    sw = sub.add_parser(
        "sweep",
        help="run a grid of trials (envs x methods x seeds x parameters) on Ray, resumable, with one table and figure",
        description="Run the trials of a sweep file (JSON or TOML), a study of the study engine, on a local Ray instance "
        "(default when Ray is installed), on a cluster (--address), or as local processes (--no-ray).",
    )
    sw.add_argument("config", help="sweep file (see pimbrl.experiments.sweep)")
    sw.add_argument("--run-dir", required=True)
    sw.add_argument("--address", default=None, help="address of an existing Ray cluster (e.g. ray://host:10001 or auto)")
    sw.add_argument("--no-ray", action="store_true", help="run the trials as local processes, --cpus at a time")
    sw.add_argument("--cpus", type=int, default=None, help="trials at a time: Ray's local CPUs or local processes (default: all)")
    _add_no_replicas(sw)
    _add_import(sw)
    sw.set_defaults(func=_cmd_sweep)

    st = sub.add_parser(
        "study",
        help="run a study spec (systems x methods x seeds x settings), resumable; report its tables and hypotheses",
        description="plan SPEC: list its runs. run SPEC: train what is missing (local processes or Ray) and write its "
        "record; run A B ...: a queue, in order, each study in its own directory (a process one study leaves free at its "
        "end starts the next one's runs; each record is written as its study ends). status SPEC: which runs have "
        "finished, run or wait, and the compute left (no returns). "
        "report SPEC: tables with intervals, comparisons, hypothesis verdicts and figures from its record; "
        "report --pages DOCS SPEC...: docs/results.md and docs/reproduce.md from many specs. draft TUNING "
        "[AMENDMENT...]: the confirmatory spec a finished tuning study (and its amendments) gives by the rules of "
        "docs/confirmatory.md (arms, seeds, hypotheses, plan), to review and register. archive SPEC: copy the "
        "finished runs' files (no checkpoints) and the registration to the study's archive, to commit; `run` copies "
        "them back on a fresh machine. Format: pimbrl.experiments.spec.",
    )
    st.add_argument("action", choices=("plan", "run", "status", "report", "draft", "archive"))
    st.add_argument("specs", nargs="+", metavar="SPEC", help="study spec (YAML)")
    st.add_argument("--run-dir", default=None, help="the study's directory (default: runs/<study name>)")
    st.add_argument(
        "--jobs", type=int, default=1, help="run: runs at a time (one process each, one thread each); status: for the estimate"
    )
    st.add_argument("--backend", choices=("local", "ray"), default="local", help="run: local processes or Ray tasks")
    st.add_argument("--address", default=None, help="run: address of an existing Ray cluster")
    st.add_argument("--rerun", action="store_true", help="run: move runs of another configuration aside and train them again")
    st.add_argument(
        "--time-limit",
        type=float,
        default=None,
        metavar="MINUTES",
        help="run: after this many minutes start no run and stop the running ones at a checkpoint (an RL run at its "
        "next episode end); exit status 124, the same command again continues: for a batch job's allocation",
    )
    _add_no_replicas(st, "run: ")
    st.add_argument(
        "--archive",
        default=None,
        metavar="DIR",
        help="archive: where the finished runs' files go; run: where they come back from (default: archive/<study name> "
        "beside the spec)",
    )
    st.add_argument("--no-archive", action="store_true", help="run, status: leave the archive out")
    st.add_argument(
        "--keep-archive",
        action="store_true",
        help="run: copy each run into the archive as it finishes (then commit the archive to keep it)",
    )
    st.add_argument(
        "--checkpoints",
        action="store_true",
        help="archive: also carry each interrupted run with its checkpoint (xz-compressed), so that `study run` on "
        "another machine resumes it where it stopped; carried copies of runs the spec no longer plans are removed",
    )
    st.add_argument(
        "--out",
        default=None,
        help="report: directory of report.md and figures (default: the run directory); draft: the spec file (default: stdout)",
    )
    st.add_argument("--seeds", type=int, default=10, help="draft: seeds per arm, from 100 (with --other-seeds: the main arms')")
    st.add_argument(
        "--other-seeds", type=int, default=None, help="draft: seeds of the arms besides the protocol's main ones (KS: 3)"
    )
    st.add_argument("--total-steps", type=int, default=None, help="draft: real steps per run, where not the tuning runs' (KS)")
    st.add_argument("--holdout-episodes", type=int, default=100, help="draft: holdout states each run's final policy plays")
    st.add_argument(
        "--threshold",
        type=_threshold_arg,
        default=None,
        help="draft: the return H1a and H3 count steps to, where the recipe sets none; 'rule': derived from the tuning "
        "record by docs/confirmatory.md's rule",
    )
    st.add_argument("--pages", default=None, metavar="DOCS", help="report: write DOCS/results.md and DOCS/reproduce.md")
    _add_import(st)
    st.set_defaults(func=_cmd_study)

    fg = sub.add_parser(
        "figure",
        help="the paper's figures from run directories",
        description="ks-contours RUN: KS space-time contours, one uncontrolled and three controlled test episodes; "
        "burgers RUN: Burgers state surfaces with random and learned control, with actions and rewards; "
        "model-errors DIR: histograms of a `pimbrl model-eval` directory; rollouts RUN: model-predicted KS "
        "states after l_M model steps against the true environment (mbrl/pimbrl runs); curves RUN...: learning curves.",
    )
    fg.add_argument("kind", choices=FIGURES)
    fg.add_argument("dirs", nargs="+", help="run directory (several for curves)")
    fg.add_argument(
        "--out",
        default=None,
        help="PNG path (default: in the first directory, " + ", ".join(f"{k}: {v}" for k, v in FIGURE_FILES.items()) + ")",
    )
    fg.add_argument("--lengths", default="3,8,40,120", help="rollouts: rollout lengths to show")
    _add_import(fg)
    fg.set_defaults(func=_cmd_figure)
    return parser


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("pimbrl")
    except PackageNotFoundError:  # run from a source tree that is not installed
        return "unknown (not installed)"


def _add_no_replicas(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    parser.add_argument(
        "--no-replicas",
        action="store_true",
        help=f"{prefix}train every seed of a seed-free controller (feedback, MPC without identification) instead of "
        "copying its first seed where its first two agree on every episode",
    )


def _add_import(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--import",
        dest="imports",
        action="append",
        default=[],
        metavar="MODULE_OR_FILE",
        help="import a module (from the working directory) or a .py file that declares systems of your own "
        "(repeatable; docs/systems.md); installed packages' systems (entry points pimbrl.systems) load by themselves",
    )


def _load_systems(args: argparse.Namespace) -> None:
    """Register the systems of installed packages and of ``--import`` (a one-line error for a bad one)."""
    from .systems import import_systems, load_entry_points

    load_entry_points()
    import_systems(args.imports)


def _subparser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and command in action.choices:
            return action.choices[command]
    return parser


#: what to do about an operating-system error, by errno
_OS_FIXES = {
    errno.ENOSPC: "free some disk space or choose a --run-dir on another disk",
    errno.EDQUOT: "free some space within your disk quota or choose a --run-dir on another disk",
    errno.EROFS: "the disk is read-only: choose a --run-dir on a writable disk",
    errno.EFBIG: "a file-size limit was reached (ulimit -f, or the file system's largest file): raise the limit, or "
    "choose a --run-dir on another disk",
    errno.EACCES: "check the permissions of that path, or choose a --run-dir where you can write",
    errno.EPERM: "check the permissions of that path, or choose a --run-dir where you can write",
    errno.ENOTDIR: "a part of that path is a file, not a directory: choose another path",
    errno.EISDIR: "that path is a directory, not a file",
}


def _is_environment_error(exc: OSError) -> bool:
    """An error of the disk or the file system (reported as a message), not of the program (a traceback)."""
    return exc.filename is not None or exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG)


def _os_message(exc: OSError) -> str:
    what = exc.strerror or str(exc)
    where = f": {exc.filename}" if exc.filename is not None else ""
    fix = _OS_FIXES.get(exc.errno or 0, "check that path and the disk")
    return f"{what}{where}; {fix}"


def _checkpoint_note(args: argparse.Namespace) -> str:
    """What a failed or interrupted run leaves: whether it has a checkpoint, at which step, and how to go on."""
    run = getattr(args, "active_run", None)
    if run is None:
        if args.command in ("compare", "sweep"):
            return "; the same command again continues: finished runs are kept, interrupted ones resume"
        return ""
    path = run.run_dir.path
    step = getattr(args, "checkpoint_step", None)
    if step is not None and run.run_dir.checkpoint_path.exists():
        return f"; the last checkpoint (step {step:,d}) is intact: `pimbrl resume {path}` continues from it"
    return (
        f"; no checkpoint was written yet (the first is due at step {run.cfg.checkpoint_every:,d}"
        f"{_minutes_clause(run.cfg.checkpoint_minutes)}): "
        f"`pimbrl resume {path}` starts the run over"
    )


def _minutes_clause(minutes: float) -> str:
    """`` or after N minutes`` for a wall-clock checkpoint cadence (none for 0)."""
    return f" or after {minutes:g} minutes, whichever comes first" if minutes > 0 else ""


def _stdout_closed() -> bool:
    """Whether standard output is a pipe whose reader has gone (the kernel reports an error condition on it)."""
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & select.POLLERR for _, events in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # no file descriptor behind sys.stdout, or no poll()
        return False


def _silence_stdout() -> None:
    """Point standard output at the null device, so that what is still buffered for a closed pipe is dropped at exit."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no file descriptor behind sys.stdout (a test's capture)
        pass


@functools.lru_cache(maxsize=1)
def _shared_parser() -> argparse.ArgumentParser:
    """The parser :func:`main` uses, built once per process (about 20 ms and 212 arguments a build).

    Parsing reads the parser and writes only the namespace it returns, so one instance serves every call. Each
    command's handler is bound when the parser is built: a caller who replaces a handler, or changes a parser,
    builds its own with :func:`build_parser`.
    """
    return build_parser()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``pimbrl`` command line on ``argv`` (default: ``sys.argv[1:]``) and return the exit status.

    A bad input, a disk or file-system error (with the path) and a diverging run end with one line,
    ``pimbrl <command>: error: <problem>; <fix>``, and exit status 2. A closed standard output (the reader of a
    pipe went away) ends the command quietly with status 141, with a line on how to go on where a run was stopped.
    """
    parser = _shared_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:  # everything after -- is passed through (compare -> train)
        cut = argv.index("--")
        argv, extra = argv[:cut], argv[cut + 1 :]
    args, unknown = parser.parse_known_args(argv)
    for name, value in vars(args).items():  # a list default (--import's) is the shared parser's: hand out a copy
        if isinstance(value, list):
            setattr(args, name, list(value))
    if unknown:
        sub = _subparser(parser, args.command)
        if isinstance(sub, _Parser):
            sub.fail_unknown(unknown)
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    if extra and not getattr(args, "takes_extra", False):
        parser.error(f"`pimbrl {args.command}` takes no arguments after --")
    steps = getattr(args, "steps", None)
    if isinstance(steps, int) and steps < 1:  # config-driven commands default to an UNSET sentinel
        parser.error("--steps must be >= 1")
    prefix = f"pimbrl {args.command}: error:"
    try:
        _load_systems(args)
        status = int(args.func(args, extra) if getattr(args, "takes_extra", False) else args.func(args))
        sys.stdout.flush()  # a reader that went away surfaces here, not as a second error at exit
        return status
    except BrokenPipeError:
        if not _stdout_closed():  # another pipe broke (a child process's): not the reader of our output
            raise
        _silence_stdout()  # `pimbrl study status SPEC | head -1`: the reader has what it wanted
        if note := _checkpoint_note(args):  # a run stopped by it can go on
            with contextlib.suppress(OSError):  # standard error may have gone with it (`2>&1 | head`)
                print(f"pimbrl {args.command}: stopped: its standard output was closed{note}", file=sys.stderr)
        return 141  # 128 + SIGPIPE, as a shell reports a command its pipe ended
    except (ConfigError, ValueError) as exc:
        print(f"{prefix} {exc}", file=sys.stderr)
        return 2
    except FloatingPointError as exc:  # a diverging run
        print(f"{prefix} {exc}{_checkpoint_note(args)}", file=sys.stderr)
        return 2
    except OSError as exc:
        if _is_environment_error(exc):
            print(f"{prefix} {_os_message(exc)}{_checkpoint_note(args)}", file=sys.stderr)
        elif isinstance(exc, (FileNotFoundError, FileExistsError)):  # raised by pimbrl with a message
            print(f"{prefix} {exc}", file=sys.stderr)
        else:
            raise
        return 2
    except RunStopped as stopped:  # SIGTERM or SIGINT while training: checkpointed at the next episode end
        print(f"pimbrl {args.command}: {stopped}{_checkpoint_note(args)}", file=sys.stderr)
        return stopped.exit_status
    except TimeLimitReached as reached:  # study run --time-limit: the runs checkpointed, the driver stopped
        print(f"pimbrl {args.command}: {reached}", file=sys.stderr)
        return 124
    except KeyboardInterrupt:
        print(f"pimbrl {args.command}: interrupted{_checkpoint_note(args)}", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
