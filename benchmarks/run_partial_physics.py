"""Partially-known physics: the system's coefficients differ from the physics prior the model is held to.

For one environment whose true coefficients differ from the prior's (``--true nu=0.013 --prior nu=0.01``),
runs, over the seeds, with the same budget and the same evaluation states:

* ``mbrl``: the data-only model (the prior judges imagined steps, but no physics loss);
* ``pimbrl-wrong``: the physics loss of the wrong prior, fixed;
* ``pimbrl-learned``: the physics loss with the ``--learn`` coefficients fitted to the labels, from the prior;
* ``pimbrl-learned-correction`` (PDEs, ask for it with ``--variants``): the same plus the learned linear
  correction for what no coefficient expresses, kept small by its penalty;
* ``pimbrl-true``: the physics loss of the true system (the upper reference).

Optional variants with the physics inside the model (:mod:`pimbrl.models.hybrid`; ask with ``--variants``):

* ``physics-wrong``: the prior's coarse scheme as the model, fixed (the physics-only model; no network);
* ``physics-learned``: that scheme with the ``--learn`` coefficients fitted to the labels (pimbrl);
* ``hybrid-learned``: the scheme with the learned coefficients plus a correction network that starts at zero
  (pimbrl: the physics loss keeps the correction small);
* ``physics-true``: the true system's coarse scheme as the model (the upper reference of these).

Flags after the options go to every variant; ``--pimbrl-args`` to the pimbrl variants only (e.g.
``--pimbrl-args=--physics.alone-from=0``). Each run is a separate process (one thread), ``--jobs`` at a
time; finished runs are skipped, interrupted ones resumed, and a run directory that holds a run of another
configuration is refused (``--rerun`` moves it aside). Prints and records (``--name``:
``benchmarks/results/<name>.json``) per run the steps to each threshold, the final and best returns, the
mean return over the evaluations after the warm-up, the model's held-out error at each evaluation and, for
the variants that learn coefficients, the identified values and the first real step from which they stay
within 5 % of the truth. ``--figure`` draws the returns and the model errors per variant (mean over seeds,
band: the seeds' range). Per variant and threshold the summary gives the mean steps (where every seed reached
it) and the median over the seeds, censored where some did not (see
:func:`pimbrl.experiments.compare.median_steps_to_threshold`).

``--include RECORD`` adds the runs of an earlier record of the same study (same system, prior, budget and
flags; its run directories may be gone) to the summary, for the variants asked: a study extended with more
seeds. Where a variant and seed were both recorded and run here, the fresh run is kept and the two are
compared evaluation by evaluation (a reproduction check of the current code against the record's).

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

from pimbrl.config import parse_prior
from pimbrl.experiments.compare import RunSpec, check_reuse, median_steps_to_threshold, run_all, steps_text
from pimbrl.models.coefficients import CORRECTION_OF
from pimbrl.training import RunDirectory
from pimbrl.training.advice import config_warnings
from pimbrl.training.cli_args import config_from_argv
from pimbrl.training.rundir import steps_to_threshold

VARIANTS = ("mbrl", "pimbrl-wrong", "pimbrl-learned", "pimbrl-true")
OPTIONAL_VARIANTS = ("pimbrl-learned-correction", "physics-wrong", "physics-learned", "hybrid-learned", "physics-true")


def uses_pimbrl(variant: str) -> bool:
    """Whether ``variant`` runs a method with the physics loss, pimbrl or pihybrid (and takes ``--pimbrl-args``)."""
    flags = variant_args(variant, "", "", "")
    return flags[flags.index("--method") + 1] in ("pimbrl", "pihybrid")


def variant_args(variant: str, true: str, prior: str, learn: str) -> list[str]:
    """`pimbrl train` flags of one variant (the environment always gets the true coefficients)."""
    env_kwargs = ["--env-kwargs", json.dumps(parse_prior(true))]
    if variant == "mbrl":
        return ["--method", "mbrl", *env_kwargs, "--model.prior", prior]
    if variant == "pimbrl-wrong":
        return ["--method", "pimbrl", *env_kwargs, "--model.prior", prior]
    if variant == "pimbrl-learned":
        return ["--method", "pimbrl", *env_kwargs, "--model.prior", prior, "--learn.coefficients", learn]
    if variant == "pimbrl-learned-correction":
        return variant_args("pimbrl-learned", true, prior, f"{learn},correction")
    if variant == "pimbrl-true":
        return ["--method", "pimbrl", *env_kwargs]
    if variant == "physics-wrong":
        return ["--method", "known-scheme", *env_kwargs, "--model.prior", prior]
    if variant == "physics-learned":
        return ["--method", "identified-scheme", *env_kwargs, "--model.prior", prior, "--learn.coefficients", learn]
    if variant == "hybrid-learned":
        return ["--method", "pihybrid", *env_kwargs, "--model.prior", prior, "--learn.coefficients", learn]
    if variant == "physics-true":
        return ["--method", "known-scheme", *env_kwargs]
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


#: the fields of a record that must agree for its runs to join another invocation's (``--include``)
SAME_STUDY = ("env", "true", "prior", "learn", "steps", "extra_flags", "pimbrl_flags")


def load_included(path: Path, study: dict, thresholds: list[float]) -> list[dict]:
    """The runs of an earlier record of the same study, with their step keys as integers again.

    Exits with a one-line message where the record is of another study (the first field that differs) or
    lacks one of ``thresholds``.
    """
    try:
        record = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise SystemExit(f"--include {path}: cannot read it as a JSON record ({exc})") from None
    record.setdefault("pimbrl_flags", [])  # records made before --pimbrl-args existed had none
    for key in SAME_STUDY:
        if record.get(key) != study[key]:
            raise SystemExit(
                f"--include {path}: a record of another study ({key} {record.get(key)!r} there, {study[key]!r} "
                "here); include only records made with the same system, prior, budget and flags"
            )
    missing = [t for t in thresholds if t not in record.get("thresholds", [])]
    if missing:
        raise SystemExit(
            f"--include {path}: the record has no steps to {', '.join(f'{t:g}' for t in missing)}; "
            f"ask only for its thresholds ({', '.join(f'{t:g}' for t in record.get('thresholds', []))})"
        )
    rows = record.get("runs", [])
    for row in rows:  # JSON turned the {step: value} keys into strings
        for key in ("model_val_mse", "returns_after_warmup", "model_val_mse_after_warmup"):
            row[key] = {int(k): v for k, v in row.get(key, {}).items()}
    return rows


def merge_runs(fresh: list[dict], included: dict[str, list[dict]], variants: list[str]) -> tuple[list[dict], list[str]]:
    """The runs of this invocation plus the included records' runs of ``variants``, ordered by seed.

    ``included`` maps each record's name to its runs. A variant and seed found in more than one place is
    kept once: the run of this invocation if it went as far as the recorded one (else the recorded run,
    so that a run still under way never replaces a finished one), and among records the first record's.
    Returns the runs and one line per such duplicate: whether the two agree at every evaluation after the
    warm-up they share or by how much their returns differ. Only a run trained in a new ``--out-dir``
    makes this a reproduction check; a run directory that the record was made from agrees with it by
    construction, and is named as such where both know their directory.
    """
    kept = {(r["variant"], r["seed"]): (r, "this invocation") for r in fresh}
    checks = []
    for name, rows in included.items():
        for row in rows:
            key = (row["variant"], row["seed"])
            if row["variant"] not in variants:
                continue
            if key not in kept:
                kept[key] = (row, name)
                continue
            other, where = kept[key]
            label = f"{key[0]} seed {key[1]}"
            if where == "this invocation" and other["steps"] < row["steps"]:
                kept[key] = (row, name)
                checks.append(
                    f"{label}: the run here has {other['steps']:,} steps, {name} has {row['steps']:,}: the recorded run is kept"
                )
                continue
            new, old = other["returns_after_warmup"], row["returns_after_warmup"]
            shared = sorted(set(new) & set(old))
            gap = max((abs(new[s] - old[s]) for s in shared), default=None)
            same_dir = other.get("run_dir") is not None and other.get("run_dir") == row.get("run_dir")
            if gap is None:
                verdict = f"no evaluation in common with {name}"
            elif gap == 0.0:
                verdict = f"equal to {name}'s at all {len(shared)} evaluations" + (
                    " (the same run directory: not a reproduction check)" if same_dir else ""
                )
            else:
                verdict = f"differs from {name}'s (largest return difference {gap:.4g} over {len(shared)} evaluations)"
            checks.append(f"{label}: {verdict}; the run of {where} is kept")
    merged = [row for row, _ in kept.values()]
    merged.sort(key=lambda r: (r["seed"], variants.index(r["variant"])))
    return merged, checks


def summarise(rows: list[dict], variants: list[str], thresholds: list[float]) -> dict[str, dict]:
    """Per variant: the seeds, the steps to each threshold per seed, their mean where every seed reached it,
    their median over the seeds (censored at the run's budget where a seed did not reach it), the final
    returns and the mean returns after the warm-up."""
    summary = {}
    for variant in variants:
        mine = [r for r in rows if r["variant"] == variant]
        entry: dict = {"seeds": len(mine), "seed_list": [r["seed"] for r in mine]}
        for t in thresholds:
            steps = [r[f"steps_to_{t:g}"] for r in mine]
            reached = [s for s in steps if s is not None]
            entry[f"steps_to_{t:g}"] = steps
            entry[f"mean_steps_to_{t:g}"] = statistics.mean(reached) if len(reached) == len(steps) and steps else None
            median = median_steps_to_threshold(
                [{"steps_to_threshold": s, "steps": r["steps"]} for s, r in zip(steps, mine, strict=True)]
            )
            entry[f"median_steps_to_{t:g}"] = median["steps_to_threshold_median"]
            entry[f"median_steps_to_{t:g}_above"] = median["steps_to_threshold_median_above"]
            entry[f"median_steps_to_{t:g}_at_most"] = median["steps_to_threshold_median_at_most"]
        entry["final_return"] = [r["final_return"] for r in mine]
        entry["mean_return_after_warmup"] = [r.get("mean_return_after_warmup") for r in mine]  # older records lack it
        summary[variant] = entry
    return summary


def model_errors(run: RunDirectory, eval_steps: list[int]) -> dict[int, float]:
    """The model's held-out MSE at each evaluation step: the last logged value at or before it.

    Metrics rows come every ``log_every`` steps, evaluations every ``eval_every``; rows without a value
    (before the model's first check), and a torn last row of a run still writing, are skipped.
    """
    logged = []
    for m in run.metrics([]).read():
        try:
            logged.append((int(float(m["step"])), float(m["model/val_mse"])))
        except (KeyError, TypeError, ValueError):
            continue
    out = {}
    for step in eval_steps:
        before = [value for at, value in logged if at <= step]
        if before:
            out[step] = before[-1]
    return out


def seed_range(label: str, series: list[dict[int, float]]) -> tuple[str, ...] | None:
    """``(label, steps, mean, low, high)`` over the steps every seed's ``{step: value}`` has (None if none)."""
    series = [s for s in series if s]
    steps = sorted(set.intersection(*(set(s) for s in series))) if series else []
    if not steps:
        return None
    import numpy as np

    values = np.array([[s[step] for step in steps] for s in series])
    n = len(series)
    return (f"{label} ({n} seed{'s' if n > 1 else ''})", np.array(steps), values.mean(0), values.min(0), values.max(0))


def draw(rows: list[dict], variants: list[str], thresholds: list[float], path: Path, title: str) -> None:
    """Two panels: the test return and the model's held-out MSE against real steps, after the warm-up.

    Per variant, the mean over seeds as a line and the seeds' range as a band (the spread of the seeds'
    means, not of the test episodes, so that variants stay apart), over the steps every seed reached.
    """
    import matplotlib.pyplot as plt

    from pimbrl.plotting import draw_curves, save_figure

    fig, (ax_return, ax_model) = plt.subplots(1, 2, figsize=(12, 4.5), sharex=True)

    def by_variant(key: str) -> list:
        curves = (seed_range(v, [r[key] for r in rows if r["variant"] == v]) for v in variants)
        return [c for c in curves if c is not None]

    returns, errors = by_variant("returns_after_warmup"), by_variant("model_val_mse_after_warmup")
    color_of = dict(zip([c[0] for c in returns], draw_curves(ax_return, returns, thresholds), strict=True))
    draw_curves(ax_model, errors, colors=[color_of.get(c[0]) for c in errors], legend_loc="best")
    ax_return.set_ylabel("test return (mean over the evaluation states)")
    ax_model.set_ylabel("model held-out next-state MSE")
    ax_model.set_yscale("log")
    for ax in (ax_return, ax_model):
        ax.set_xlabel("real environment steps")
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
        help="`pimbrl train` flags for the pimbrl variants only, e.g. --pimbrl-args='--physics.alone-from 0' "
        "(use = when the value starts with --; flags after the options go to every variant)",
    )
    parser.add_argument("--name", default=None, help="record as benchmarks/results/<name>.json")
    parser.add_argument("--no-run", action="store_true", help="summarise the runs as they are")
    parser.add_argument("--rerun", action="store_true", help="move aside runs made with another configuration")
    parser.add_argument(
        "--figure", default=None, help="draw the learning curves here: per variant, the seeds' mean and their range"
    )
    parser.add_argument(
        "--include",
        default="",
        help="comma-separated records of the same study (benchmarks/results/<name>.json) whose runs join the summary",
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
    unknown = [v for v in variants if v not in VARIANTS + OPTIONAL_VARIANTS]
    if unknown:
        parser.error(f"unknown variant(s) {', '.join(unknown)}; choose from {', '.join(VARIANTS + OPTIONAL_VARIANTS)}")
    if args.pimbrl_args and not any(uses_pimbrl(v) for v in variants):
        print("warning: --pimbrl-args is ignored: no pimbrl variant is run")
    specs = []
    for seed in seeds:  # seed by seed, so that runs cut short leave every variant on the first seeds
        for variant in variants:
            flags = variant_args(variant, args.true, args.prior, args.learn)
            if uses_pimbrl(variant):
                flags += shlex.split(args.pimbrl_args)
            argv = [args.env, "--seed", str(seed), "--threads", "1", "--steps", str(args.steps), *flags, *extra]
            specs.append(RunSpec(variant, seed, out / variant / f"seed{seed}", config_from_argv(argv)))
    # the runs' own threshold is not used here (the summary counts --thresholds), so it is not warned about
    warnings = {line for spec in specs for line in config_warnings(spec.config) if not line.startswith("threshold ")}
    for line in sorted(warnings):
        print(f"warning: {line}")
    study = {
        "env": args.env,
        "true": args.true,
        "prior": args.prior,
        "learn": args.learn,
        "steps": args.steps,
        "extra_flags": extra,
        "pimbrl_flags": shlex.split(args.pimbrl_args),
    }
    # read the earlier records before any run, so that a wrong one is refused before hours of training
    included = {Path(p): load_included(Path(p), study, thresholds) for p in args.include.split(",") if p}
    check_reuse(specs, rerun=args.rerun and not args.no_run)
    if not args.no_run:
        run_all(specs, jobs=args.jobs)
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
            "run_dir": str(spec.path.resolve()),
            **{f"steps_to_{t:g}": steps_to_threshold(evaluations, t) for t in thresholds},
            "final_return": returns[-1] if returns else None,
            "best_return": max(returns) if returns else None,
            # the model's held-out next-state MSE as the loop measured it, at each evaluation
            "model_val_mse": model_errors(run, [int(float(r["step"])) for r in evaluations]),
        }
        after = [r for r in evaluations if int(float(r["step"])) > spec.config.warmup_steps]
        row["returns_after_warmup"] = {int(float(r["step"])): float(r["return_mean"]) for r in after}
        # their mean (the area under the learning curve per evaluation): a sample-efficiency figure that one
        # lucky or unlucky evaluation moves less than steps to a threshold
        row["mean_return_after_warmup"] = statistics.mean(row["returns_after_warmup"].values()) if after else None
        row["model_val_mse_after_warmup"] = {k: v for k, v in row["model_val_mse"].items() if k > spec.config.warmup_steps}
        report = spec.path / "coefficients.json"
        if report.exists():
            coefficients = json.loads(report.read_text())
            row["identified"] = coefficients["current"]
            current = coefficients["current"]
            row["relative_error"] = {k: abs(v - truth[k]) / abs(truth[k]) for k, v in current.items() if k in truth}
            row["within_5pct_from_step"] = identified_within(coefficients["history"], truth)
        rows.append(row)
    rows, checks = merge_runs(rows, {path.name: earlier for path, earlier in included.items()}, variants)
    for line in checks:
        print(line)
    summary = summarise(rows, variants, thresholds)
    width = max(len(v) for v in variants)
    for variant, entry in summary.items():
        line = "  ".join(f"to {t:g}: {entry[f'steps_to_{t:g}']}" for t in thresholds)
        final = [round(x, 2) for x in entry["final_return"] if x is not None]
        area = [round(x, 2) for x in entry["mean_return_after_warmup"] if x is not None]
        print(f"{variant:>{width}}  seeds {entry['seed_list']}  {line}  final {final}  mean after warm-up {area}")
    print("median steps over the seeds (> N: the middle seeds did not all reach it within N; and <= M: an upper bound):")
    for variant, entry in summary.items():
        cells = []
        for t in thresholds:
            key = f"median_steps_to_{t:g}"
            cells.append(f"to {t:g}: {steps_text(entry[key], entry[f'{key}_above'], entry[f'{key}_at_most'])}")
        print(f"{variant:>{width}}  " + "  ".join(cells))
    print("model held-out MSE, mean over the seeds (at the steps every seed reached):")
    for variant in variants:
        curve = seed_range(variant, [r["model_val_mse"] for r in rows if r["variant"] == variant])
        if curve is None:
            continue
        _, at, mean, _, _ = curve
        summary[variant]["model_val_mse_mean"] = {int(k): float(v) for k, v in zip(at, mean, strict=True)}
        print(f"{variant:>{width}}  " + " ".join(f"{k:,d}: {v:.1e}" for k, v in zip(at, mean, strict=True)))
    for r in rows:
        if "identified" in r:
            within = r["within_5pct_from_step"]
            print(f"  {r['variant']} seed {r['seed']}: identified {r['identified']}, within 5 % from step {within}")
    if args.figure:
        draw(rows, variants, thresholds, Path(args.figure), f"{args.env}: true {args.true}, prior {args.prior}")
    payload = {
        **study,
        "thresholds": thresholds,
        "included": [str(p) for p in included],
        "runs": rows,
        "summary": summary,
    }
    if args.name:
        _common.record(args.name, payload)


if __name__ == "__main__":
    main()
