"""Evaluate the latest checkpoint of finished runs on two protocols: held-out test states and the authors' 5.

With ``--policy selected`` the policy evaluated is the one model-based policy selection kept
(``--imagine.select-episodes``; :mod:`pimbrl.training.selection`) instead of the checkpoint's latest.

For each run directory given (e.g. every ``<method>/seed<k>`` of a ``pimbrl compare`` directory), the
deterministic policy of its latest checkpoint is run

* on the run's own held-out test states (``test``: KS, the 200 states of the test pool), and
* on the 5 fixed training-pool states the paper reports its mean return on (``authors``: rows 0, 49, 99,
  149, 199; see :meth:`pimbrl.systems.ks.KSTask.protocol_initial_states`),

and the mean, quartiles, minimum and maximum of the returns are printed and recorded per run, with the
mean over the runs of each label (the name of the directory holding ``seed<k>``, as ``pimbrl compare`` lays
out e.g. ``mfrl-matched/seed0``, else the run's method). Runs are only
read (``pimbrl.training.load_run``), so a run still in progress can be evaluated at its last checkpoint. A run
made with another simulator kernel is refused: its KS training pool, hence the ``authors`` states, differ from
this kernel's (evaluate it with the pimbrl it was made with).

Usage::

    python benchmarks/eval_protocols.py /work/ks/cmp/*/seed* --threshold -55 --name ks_protocols
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import _common

from pimbrl.training.config import POLICIES
from pimbrl.training.rundir import kernel_note

PROTOCOLS = ("test", "authors")


def evaluate(run_dir: Path, threshold: float | None = None, policy: str = "latest") -> dict:
    """Method, seed, step, training summary and, per protocol, the return statistics of the latest checkpoint.

    ``policy`` ``"selected"``: the policy model-based policy selection kept (``policy_step`` records its step)
    instead of the latest. The training summary is the run's own record at ``threshold`` (``None``: the
    run's configured threshold): its steps and training wall-clock to the first evaluation at or above it,
    final and best mean test return, wall-clock and agent updates.
    """
    run = _common.load_checkpointed_run(run_dir)
    cfg = run.cfg
    note = kernel_note(run.run_dir.read_config().get("versions", {}))
    if note:  # the 'authors' rows would not all be states the agent trained on
        raise SystemExit(f"{run_dir}: {note}")
    label = run_dir.parent.name if run_dir.name.startswith("seed") else cfg.method
    row: dict = {"run_dir": str(run_dir), "label": label, "method": cfg.method, "seed": cfg.seed, "step": run.t}
    row["policy"] = policy
    if policy == "selected":
        try:
            row["policy_step"] = run.use_selected_policy()
        except ValueError as exc:
            raise SystemExit(str(exc)) from None
    trained = run.run_dir.result(threshold) or {}
    keys = ("steps_to_threshold", "wall_s_to_threshold", "final_return", "best_return", "wall_s", "updates")
    row["training"] = {key: trained.get(key) for key in keys}
    for protocol in PROTOCOLS:
        result = run.evaluator_for(protocol).run(lambda o: run.agent.act(o, deterministic=True))
        row[protocol] = {**result.summary(), **result.quartiles(), "returns": result.returns.tolist()}
    return row


def by_label(rows: list[dict], threshold: float | None) -> dict:
    """Per label and protocol: mean over the runs of the mean return, its range, and runs at or above ``threshold``."""
    out: dict = {}
    for label in sorted({r["label"] for r in rows}):
        runs = [r for r in rows if r["label"] == label]
        entry: dict = {"seeds": [r["seed"] for r in runs], "steps": [r["step"] for r in runs]}
        for protocol in PROTOCOLS:
            means = [r[protocol]["return_mean"] for r in runs]
            entry[protocol] = {
                "return_mean": statistics.fmean(means),
                "range": [min(means), max(means)],
                "median_of_medians": statistics.median(r[protocol]["return_median"] for r in runs),
            }
            if threshold is not None:
                entry[protocol]["runs_at_threshold"] = sum(m >= threshold for m in means)
        out[label] = entry
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", type=Path)
    parser.add_argument("--threshold", type=float, default=None, help="count the runs whose mean return reaches it")
    parser.add_argument("--name", default=None, help="record benchmarks/results/<name>.json")
    parser.add_argument(
        "--policy",
        choices=POLICIES,
        default="latest",
        help="the latest checkpoint's policy, or the one model-based policy selection kept (--imagine.select-episodes)",
    )
    args = parser.parse_args()
    rows = []
    for run_dir in args.run_dirs:
        row = evaluate(run_dir, args.threshold, args.policy)
        rows.append(row)
        parts = [
            f"{p} mean {row[p]['return_mean']:8.2f} (quartiles {row[p]['return_q25']:.1f}/{row[p]['return_median']:.1f}/"
            f"{row[p]['return_q75']:.1f}, min {row[p]['return_min']:.1f}, max {row[p]['return_max']:.1f})"
            for p in PROTOCOLS
        ]
        at = f"step {row['step']:>7,d}" + (f" (policy of step {row['policy_step']:,d})" if "policy_step" in row else "")
        print(f"{row['label']:>13s} seed {row['seed']} {at}  " + "  ".join(parts), flush=True)
        if args.threshold is not None:
            t = row["training"]
            wall = "—" if t["wall_s_to_threshold"] is None else f"{t['wall_s_to_threshold']:,.0f} s"
            reached = "not reached" if t["steps_to_threshold"] is None else f"{t['steps_to_threshold']:,d} steps"
            print(f"{'':>13s} training: {args.threshold:g} first at {reached} ({wall} of training wall-clock)")
    summary = by_label(rows, args.threshold)
    for label, entry in summary.items():
        parts = [f"{p} {entry[p]['return_mean']:.2f} [{entry[p]['range'][0]:.2f}, {entry[p]['range'][1]:.2f}]" for p in PROTOCOLS]
        print(f"{label:>13s} ({len(entry['seeds'])} runs at steps {entry['steps']}): " + ", ".join(parts))
    if args.name:
        path = _common.record(args.name, {"threshold": args.threshold, "runs": rows, "by_label": summary})
        print(f"recorded {path}")


if __name__ == "__main__":
    main()
