"""Collect the summaries of `pimbrl compare` and `pimbrl model-eval` directories into benchmarks/results/
and print them as Markdown tables (the tables of docs/results.md come from this script).

Usage: ``python benchmarks/collect_results.py [ROOT]`` with ROOT the directory that holds
``<env>/summary.json`` (compare) and ``model-eval/<env>/summary.json`` (default benchmarks/runs/final).
Copies each summary to ``benchmarks/results/compare_<env>.json`` / ``model_eval_<env>.json``.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

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
    for name, r in summary["ratios"].items():
        value = "—" if r["value"] is None else f"{r['value']:.3f}"
        rows.append(f"{name}: {value} ({r['note']})  ")
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


def main(root: Path) -> None:
    RESULTS.mkdir(exist_ok=True)
    for path in sorted(root.glob("*/summary.json")):
        summary = json.loads(path.read_text())
        env = path.parent.name
        shutil.copyfile(path, RESULTS / f"compare_{env}.json")
        print(f"## {env} ({summary['env']})\n\n{compare_table(summary)}\n")
    evals = {}
    for path in sorted(root.glob("model-eval/*/summary.json")):
        evals[path.parent.name] = json.loads(path.read_text())
        shutil.copyfile(path, RESULTS / f"model_eval_{path.parent.name}.json")
    if evals:
        print(f"## model errors (next-state MSE)\n\n{model_eval_table(evals)}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent / "runs" / "final")
