"""Partially-known physics: the system's coefficients differ from the physics prior the model is held to.

For one environment whose true coefficients differ from the prior's (``--true nu=0.013 --prior nu=0.01``),
runs, over the seeds, with the same budget and the same evaluation states:

* ``mbrl``: the data-only model (the prior judges imagined steps, but no physics loss);
* ``pimbrl-wrong``: the physics loss of the wrong prior, fixed;
* ``pimbrl-learned``: the physics loss with the ``--learn`` coefficients fitted to the labels, from the prior;
* ``pimbrl-learned-correction`` (PDEs, ask for it with ``--variants``): the same plus the learned linear
  correction for what no coefficient expresses, kept small by its penalty;
* ``pimbrl-true``: the physics loss of the true system (the upper reference).

Each run is a separate process (one thread), ``--jobs`` at a time; finished runs are skipped, interrupted
ones resumed. Prints and records (``--name``: ``benchmarks/results/<name>.json``) the steps to each
threshold, the final and best returns and, for ``pimbrl-learned``, the identified coefficients after each
model phase and the first real step at which they are within 5 % of the truth.

Usage, e.g.::

    python benchmarks/run_partial_physics.py burgers --true nu=0.013 --prior nu=0.01 --learn nu \\
        --steps 900 --thresholds -11,-10.2 --out-dir runs/partial/burgers_nu+30 --name partial_burgers_nu+30
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
from pathlib import Path

import _common

from pimbrl.cli import config_warnings
from pimbrl.config import parse_prior
from pimbrl.experiments.compare import RunSpec, run_all
from pimbrl.models.coefficients import CORRECTION_OF
from pimbrl.training import RunDirectory
from pimbrl.training.cli_args import config_from_argv
from pimbrl.training.rundir import steps_to_threshold

VARIANTS = ("mbrl", "pimbrl-wrong", "pimbrl-learned", "pimbrl-true")
OPTIONAL_VARIANTS = ("pimbrl-learned-correction",)


def variant_args(variant: str, true: str, prior: str, learn: str) -> list[str]:
    """`pimbrl train` flags of one variant (the environment always gets the true coefficients)."""
    env_kwargs = ["--env-kwargs", json.dumps(parse_prior(true))]
    if variant == "mbrl":
        return ["--method", "mbrl", *env_kwargs, "--dyna.physics-prior", prior]
    if variant == "pimbrl-wrong":
        return ["--method", "pimbrl", *env_kwargs, "--dyna.physics-prior", prior]
    if variant == "pimbrl-learned":
        return ["--method", "pimbrl", *env_kwargs, "--dyna.physics-prior", prior, "--dyna.learn-coefficients", learn]
    if variant == "pimbrl-learned-correction":
        return [
            "--method",
            "pimbrl",
            *env_kwargs,
            "--dyna.physics-prior",
            prior,
            "--dyna.learn-coefficients",
            f"{learn},correction",
        ]
    if variant == "pimbrl-true":
        return ["--method", "pimbrl", *env_kwargs]
    raise ValueError(f"unknown variant {variant!r}; choose from {', '.join(VARIANTS + OPTIONAL_VARIANTS)}")


def identified_within(history: list[dict], truth: dict[str, float], tolerance: float = 0.05) -> int | None:
    """First real step from which every learned coefficient stays within ``tolerance`` of the truth.

    A true term learned through the correction is compared with the correction's coefficient of the same
    form (a drift ``c`` with ``-correction_u_x``). ``None`` where nothing learned can be compared.
    """
    pairs = []
    for name, value in truth.items():
        if history and name in history[0]:
            pairs.append((name, value))
        elif history and name in CORRECTION_OF and CORRECTION_OF[name][0] in history[0]:
            column, sign = CORRECTION_OF[name]
            pairs.append((column, sign * value))
    if not pairs:
        return None
    first = None
    for row in history:
        ok = all(abs(row[name] - value) <= tolerance * abs(value) for name, value in pairs)
        if ok and first is None:
            first = int(row["step"])
        elif not ok:
            first = None
    return first


def mean_after(evaluations: list[dict], warmup_steps: int) -> float | None:
    """Mean test return of the evaluations made after ``warmup_steps`` (``None`` if there are none)."""
    returns = [float(r["return_mean"]) for r in evaluations if int(r["step"]) > warmup_steps]
    return statistics.mean(returns) if returns else None


def draw(specs: list[RunSpec], variants: list[str], rows: list[dict], path: Path, title: str) -> None:
    """Two panels per study: the test return and the model's held-out MSE against real steps.

    Per variant, the mean over seeds as a line and the seeds' range as a band (the spread of the seeds'
    means, not of the test episodes, so that variants stay apart); evaluations within the warm-up, where
    every agent acts at random, are left out.
    """
    import matplotlib.pyplot as plt
    import numpy as np

    from pimbrl.plotting import save_figure

    fig, (ax_return, ax_model) = plt.subplots(1, 2, figsize=(12, 4.5))
    for variant in variants:
        mine = [s for s in specs if s.label == variant]
        runs = [[r for r in RunDirectory(s.path).evaluations.read() if int(r["step"]) > s.config.warmup_steps] for s in mine]
        runs = [r for r in runs if r]
        if not runs:
            continue
        n = min(len(r) for r in runs)
        means = np.array([[float(row["return_mean"]) for row in r[:n]] for r in runs])
        steps = np.array([int(row["step"]) for row in runs[0][:n]])
        label = f"{variant} ({len(runs)} seed{'s' if len(runs) > 1 else ''})"
        (line,) = ax_return.plot(steps, means.mean(axis=0), label=label, lw=1.6)
        ax_return.fill_between(steps, means.min(axis=0), means.max(axis=0), color=line.get_color(), alpha=0.18, lw=0)
        mses = [r["model_val_mse"] for r in rows if r["variant"] == variant]
        common = sorted(set.intersection(*(set(m) for m in mses))) if mses else []
        if common:
            values = np.array([[m[step] for step in common] for m in mses])
            ax_model.plot(common, values.mean(axis=0), color=line.get_color(), lw=1.6, label=label)
            ax_model.fill_between(common, values.min(axis=0), values.max(axis=0), color=line.get_color(), alpha=0.18, lw=0)
    ax_return.set_ylabel("test return (mean over the evaluation states)")
    ax_model.set_ylabel("model held-out next-state MSE")
    ax_model.set_yscale("log")
    for ax in (ax_return, ax_model):
        ax.set_xlabel("real environment steps")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path)
    print(f"figure: {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("env")
    parser.add_argument("--true", required=True, help="the environment's coefficients, name=value,...")
    parser.add_argument("--prior", required=True, help="the prior's coefficients, name=value,...")
    parser.add_argument("--learn", required=True, help="coefficients pimbrl-learned fits, name[:low:high],...")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--steps", type=int, required=True)
    parser.add_argument("--thresholds", required=True, help="comma-separated returns")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--out-dir", required=True)
    parser.add_argument("--jobs", type=int, default=1, help="runs in parallel (one thread each)")
    parser.add_argument(
        "--pimbrl-args",
        default="",
        help="`pimbrl train` flags for the pimbrl variants only, e.g. '--dyna.physics-start 0' (flags after the "
        "options go to every variant)",
    )
    parser.add_argument("--name", default=None, help="record as benchmarks/results/<name>.json")
    parser.add_argument("--no-run", action="store_true", help="summarise the runs as they are")
    parser.add_argument(
        "--figure", default=None, help="draw the learning curves here: per variant, the seeds' mean and their range"
    )
    args, extra = parser.parse_known_args()
    extra = [a for a in extra if a != "--"]
    truth = parse_prior(args.true)
    missing = [name for name in truth if name not in parse_prior(args.prior)]
    if missing:  # the prior would inherit the environment's true value of these
        raise SystemExit(f"--prior must give a value for every coefficient of --true; missing: {', '.join(missing)}")

    out = Path(args.out_dir)
    seeds = [int(s) for s in args.seeds.split(",")]
    thresholds = [float(t) for t in args.thresholds.split(",")]
    variants = args.variants.split(",")
    specs = []
    for seed in seeds:  # seed by seed, so that runs cut short leave every variant on the first seeds
        for variant in variants:
            flags = variant_args(variant, args.true, args.prior, args.learn)
            if variant.startswith("pimbrl"):
                flags += shlex.split(args.pimbrl_args)
            argv = [args.env, "--seed", str(seed), "--threads", "1", "--steps", str(args.steps), *flags, *extra]
            specs.append(RunSpec(variant, seed, out / variant / f"seed{seed}", config_from_argv(argv)))
    for line in sorted({line for spec in specs for line in config_warnings(spec.config)}):
        print(f"warning: {line}")
    if not args.no_run:
        run_all(specs, jobs=args.jobs)
    truth = parse_prior(args.true)
    rows = []
    for spec in specs:
        run = RunDirectory(spec.path)
        if not (spec.path / "evaluations.csv").exists():
            continue
        evaluations = run.evaluations.read()
        returns = [float(r["return_mean"]) for r in evaluations]
        row = {
            "variant": spec.label,
            "seed": spec.seed,
            "steps": int(evaluations[-1]["step"]) if evaluations else 0,
            "finished": run.status == "finished",
            **{f"steps_to_{t:g}": steps_to_threshold(evaluations, t) for t in thresholds},
            "final_return": returns[-1] if returns else None,
            "best_return": max(returns) if returns else None,
            # the mean over the evaluations after the warm-up (the area under the learning curve per
            # evaluation): a sample-efficiency figure that one lucky or unlucky evaluation moves less
            "mean_return_after_warmup": mean_after(evaluations, spec.config.warmup_steps),
            # the model's held-out next-state MSE as the loop measured it at each evaluation step
            "model_val_mse": {
                int(m["step"]): float(m["model/val_mse"])
                for m in run.metrics([]).read()
                if m.get("model/val_mse") and int(m["step"]) in {int(r["step"]) for r in evaluations}
            },
        }
        report = spec.path / "coefficients.json"
        if report.exists():
            coefficients = json.loads(report.read_text())
            row["identified"] = coefficients["current"]
            current = coefficients["current"]
            row["relative_error"] = {k: abs(v - truth[k]) / abs(truth[k]) for k, v in current.items() if k in truth}
            row["within_5pct_from_step"] = identified_within(coefficients["history"], truth)
        rows.append(row)
    summary = {}
    for variant in variants:
        mine = [r for r in rows if r["variant"] == variant]
        entry: dict = {"seeds": len(mine)}
        for t in thresholds:
            steps = [r[f"steps_to_{t:g}"] for r in mine]
            reached = [s for s in steps if s is not None]
            entry[f"steps_to_{t:g}"] = steps
            entry[f"mean_steps_to_{t:g}"] = statistics.mean(reached) if len(reached) == len(steps) and steps else None
        entry["final_return"] = [r["final_return"] for r in mine]
        entry["mean_return_after_warmup"] = [r["mean_return_after_warmup"] for r in mine]
        summary[variant] = entry
        line = "  ".join(f"to {t:g}: {entry[f'steps_to_{t:g}']}" for t in thresholds)
        final = [round(x, 2) for x in entry["final_return"] if x is not None]
        area = [round(x, 2) for x in entry["mean_return_after_warmup"] if x is not None]
        print(f"{variant:>15}  {line}  final {final}  mean after warm-up {area}")
    steps = sorted({step for r in rows for step in r["model_val_mse"]})
    if steps:
        print("model held-out MSE (mean over seeds) at steps " + ", ".join(f"{s:,d}" for s in steps))
        for variant in variants:
            mine = [r["model_val_mse"] for r in rows if r["variant"] == variant]
            means = [statistics.mean(m[s] for m in mine if s in m) if any(s in m for m in mine) else None for s in steps]
            summary[variant]["model_val_mse_mean"] = dict(zip(steps, means, strict=True))
            print(f"{variant:>15}  " + " ".join("-" if v is None else f"{v:.1e}" for v in means))
    for r in rows:
        if "identified" in r:
            within = r["within_5pct_from_step"]
            print(f"  {r['variant']} seed {r['seed']}: identified {r['identified']}, within 5 % from step {within}")
    if args.figure:
        draw(specs, variants, rows, Path(args.figure), f"{args.env}: true {args.true}, prior {args.prior}")
    payload = {
        "env": args.env,
        "true": args.true,
        "prior": args.prior,
        "learn": args.learn,
        "steps": args.steps,
        "thresholds": thresholds,
        "extra_flags": extra,
        "pimbrl_flags": shlex.split(args.pimbrl_args),
        "runs": rows,
        "summary": summary,
    }
    if args.name:
        _common.record(args.name, payload)


if __name__ == "__main__":
    main()
