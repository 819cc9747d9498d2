"""The model-error study of docs/results.md: data-only vs physics-informed models, by labelled transitions.

For one environment, runs ``pimbrl model-eval ENV --labels ...`` twice over the same seeds, labels and
test sets: with the physics loss on the loop's own sources (``policy,imagined``, per sub-step units: the
model of the previous release) and with the broad label-free sources in control-step units (the new
default). Records both summaries, and the ratios data-only / physics-informed of the out-of-sample
one-step error per label count, in ``benchmarks/results/model_study_<env>.json``.

Usage (one thread per process; each configuration is resumable only as a whole)::

    python benchmarks/run_model_study.py cartpole --seeds 3 --out-dir benchmarks/runs/model-study
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import _common

#: per environment: (labels, steps, the broad sources, the PDE model kind)
SETTINGS = {
    "cartpole": ("0,100,300,1000", 1500, "policy,box", "convlstm"),
    "pendulum": ("0,100,300,1000", 1500, "policy,box", "convlstm"),
    "burgers": ("0,100,300,1000", 1500, "policy,symmetry,scaled,noise", "convlstm"),
    "ks": ("0,100,1000", 3000, "policy,symmetry,scaled,noise", "equivariant"),
}
CONFIGS = {
    "loop_substep": ("policy,imagined", "substep"),
    "broad_step": (None, "step"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("env", choices=sorted(SETTINGS))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--out-dir", required=True)
    parser.add_argument("--configs", default=",".join(CONFIGS))
    parser.add_argument("--model", default=None, help="PDE model kind (default: the setting's)")
    _common.add_load_argument(parser)
    args = parser.parse_args()
    labels, steps, broad, kind = SETTINGS[args.env]
    kind = args.model or kind
    record: dict[str, object] = {"env": args.env, "seeds": args.seeds, "labels": labels, "steps": steps, "model": kind}
    for name in args.configs.split(","):
        sources, units = CONFIGS[name]
        out = Path(args.out_dir) / f"{args.env}_{kind}_{name}"
        cmd = [
            sys.executable, "-m", "pimbrl.cli", "model-eval", args.env, "--run-dir", str(out), "--labels", labels,
            "--seeds", str(args.seeds), "--physics.sources", sources or broad, "--physics.units", units, "--steps", str(steps),
            "--test-transitions", "300", "--rollout-lengths", "1,3,8",
        ]  # fmt: skip
        if args.env in ("burgers", "ks"):
            cmd += ["--network", kind]
        if not (out / "study.json").exists():
            subprocess.run(cmd, check=True)
        study = json.loads((out / "study.json").read_text())
        record[name] = {"command": " ".join(["pimbrl", *cmd[3:]]), "summary": study["summary"], "wall_s": study["wall_s"]}
        print(f"{args.env} {name}:")
        for r in study["summary"]:
            if r["horizon"] == 1:
                spread = f"[{r['min']:.2e}, {r['max']:.2e}]"
                print(f"  labels {r['labels']:5d} {r['model']:9s} {r['split']:3s}  mean {r['mean']:.2e} {spread}")
    record["ratio_data_over_physics"] = _ratios(record)
    _common.record(f"model_study_{args.env}_{kind}", record, load=args.load)


def _ratios(record: dict[str, object]) -> dict[str, dict[str, float]]:
    """Per config and label count: data-only / physics-informed one-step error (in and out of sample)."""
    out: dict[str, dict[str, float]] = {}
    for name in CONFIGS:
        block = record.get(name)
        if not isinstance(block, dict):
            continue
        rows = block["summary"]
        mean = {(r["labels"], r["model"], r["split"]): r["mean"] for r in rows if r["horizon"] == 1}
        for (labels, model, split), value in mean.items():
            if model == "physics" and (labels, "data", split) in mean:
                out.setdefault(name, {})[f"{split}@{labels}"] = mean[(labels, "data", split)] / value
    return out


if __name__ == "__main__":
    main()
