"""Collect the summaries of `pimbrl compare` and `pimbrl model-eval` directories into benchmarks/results/
and print them as Markdown tables (the tables of docs/results.md come from this script).

Usage: ``python benchmarks/collect_results.py [ROOT ...] [--load TEXT]`` with each ROOT a compare or sweep directory
or one that holds ``<name>/summary.json`` (of a compare or a sweep) and ``model-eval/<env>/summary.json`` (default
benchmarks/runs/final). Copies each summary to ``benchmarks/results/compare_<name>.json``,
``sweep_<name>.json`` or ``model_eval_<env>.json``; ``--load`` (what else ran on the cores while the model-eval
runs were timed, in words) is added to each ``model_eval_<env>.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from pimbrl.experiments.compare import ratio_lines

RESULTS = Path(__file__).resolve().parent / "results"


def _fmt_steps(values: list) -> str:
    return ", ".join("—" if v is None else f"{v:,}" for v in values)


def compare_table(summary: dict) -> str:
    rows = [
        f"threshold {summary['threshold']}",
        "",
        "| method | seeds reaching it | steps to threshold (per seed) | mean | final return (mean) | "
        "updates per real step | wall-clock per run (mean) |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, m in summary["methods"].items():
        if m["steps_to_threshold_mean"] is not None:
            mean = f"{m['steps_to_threshold_mean']:,.0f}"
        elif m["reached"]:
            mean = f"≥ {m['steps_to_threshold_lower_bound']:,.0f}"
        else:
            mean = f"> {m['max_steps']:,}"
        rows.append(
            f"| {label} | {m['reached']}/{m['seeds']} | {_fmt_steps(m['steps_to_threshold'])} | {mean} | "
            f"{m['final_return_mean']:.2f} | {m['update_to_data']:.2f} | {m['wall_s_mean']:.0f} s |"
        )
    if summary["ratios"]:
        rows.append("")
    rows += [f"{line}  " for line in ratio_lines(summary["ratios"], missing="—")]  # two spaces: a Markdown break
    return "\n".join(rows)


def sweep_table(summary: dict) -> str:
    rows = [
        f"sweep {summary['name']}, threshold {summary['threshold']}",
        "",
        "| env | method | setting | seed | steps | steps to threshold | final return | best return |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in summary["rows"]:
        to = "—" if r["steps_to_threshold"] is None else f"{r['steps_to_threshold']:,}"
        rows.append(
            f"| {r['env']} | {r['method']} | {r['setting']} | {r['seed']} | {r['steps']:,} | {to} | "
            f"{r['final_return']:.2f} | {r['best_return']:.2f} |"
        )
    return "\n".join(rows)


def model_eval_table(summaries: dict[str, dict]) -> str:
    rows = [
        "| env | training transitions | split | data-only mean | physics-informed mean | data-only median | "
        "physics-informed median | physics / data (mean) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for env, s in summaries.items():
        for split in ("in", "out"):
            d, p = s[f"data_{split}"], s[f"physics_{split}"]
            rows.append(
                f"| {env} | {s['config']['transitions']} | {split} | {d['mean']:.2e} | {p['mean']:.2e} | "
                f"{d['median']:.2e} | {p['median']:.2e} | {p['mean'] / d['mean']:.2f} |"
            )
    return "\n".join(rows)


def model_study_table(record: dict) -> str:
    """One row per label count: mean (min-max over seeds) one-step MSE of each model, in and out of sample."""
    rows = [
        f"{record['env']} ({record['seeds']} seeds, {record['steps']} gradient steps, model "
        f"{'mlp' if record['env'] in ('cartpole', 'pendulum') else record['model']}; one-step next-state MSE, "
        "mean over seeds (min to max))",
        "",
        "| labels | split | data-only | physics, loop sources (substep units) | physics, broad sources (step units) | "
        "data / physics (broad) |",
        "|---|---|---|---|---|---|",
    ]

    def cell(block: dict | None, labels: int, model: str, split: str) -> tuple[str, float | None]:
        if not block:
            return "—", None
        for r in block["summary"]:
            if (r["labels"], r["model"], r["split"], r["horizon"]) == (labels, model, split, 1):
                return f"{r['mean']:.1e} ({r['min']:.1e} to {r['max']:.1e})", r["mean"]
        return "—", None

    loop, broad = record.get("loop_substep"), record.get("broad_step")
    labels = sorted({r["labels"] for b in (loop, broad) if b for r in b["summary"]})
    for n in labels:
        for split in ("in", "out"):
            data, d = cell(broad or loop, n, "data" if n else "no-change", split)
            lp, _ = cell(loop, n, "physics", split)
            bp, b = cell(broad, n, "physics", split)
            ratio = f"{d / b:.1f}" if d and b else "—"
            rows.append(f"| {n:,} | {split} | {data} | {lp} | {bp} | {ratio} |")
    return "\n".join(rows)


def main(roots: list[Path], load: str | None = None) -> None:
    RESULTS.mkdir(exist_ok=True)
    evals = {}
    for root in roots:
        if not root.is_dir():
            raise SystemExit(f"{root} is not a directory; pass the folder that holds the compare/sweep directories")
        own = [root / "summary.json"] if (root / "summary.json").exists() else []  # ROOT is itself one
        for path in own + sorted(root.glob("*/summary.json")):
            summary = json.loads(path.read_text())
            name = path.parent.name
            if "rows" in summary:  # a `pimbrl sweep` directory
                shutil.copyfile(path, RESULTS / f"sweep_{name}.json")
                print(f"## {name}\n\n{sweep_table(summary)}\n")
            else:  # a `pimbrl compare` directory
                shutil.copyfile(path, RESULTS / f"compare_{name}.json")
                print(f"## {name} ({summary['env']})\n\n{compare_table(summary)}\n")
        for path in sorted(root.glob("model-eval/*/summary.json")):
            evals[path.parent.name] = json.loads(path.read_text())
            if load:
                record = {**evals[path.parent.name], "load": load}
                (RESULTS / f"model_eval_{path.parent.name}.json").write_text(json.dumps(record, indent=2) + "\n")
            else:
                shutil.copyfile(path, RESULTS / f"model_eval_{path.parent.name}.json")
    if evals:
        print(f"## model errors (next-state MSE)\n\n{model_eval_table(evals)}")
    for path in sorted(RESULTS.glob("model_study_*.json")):
        record = json.loads(path.read_text())
        if "seeds" in record:  # a labels study (run_model_study.py); the partial-physics model studies have no table here
            print(f"## {path.stem}\n\n{model_study_table(record)}\n")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("roots", nargs="*", type=Path, default=[Path(__file__).resolve().parent / "runs" / "final"])
    parser.add_argument("--load", default=None, help="what else ran on the cores during the model-eval runs, in words")
    args = parser.parse_args()
    main(args.roots, args.load)
