"""How much of each RL method's learning curve lies below its system's feedback floor.

    python benchmarks/floor_fractions.py      # writes benchmarks/results/floor_fractions.json

The floor is the final test return of the ``feedback`` arm of the control studies (gain tuned on validation
draws). For each RL study record: per arm, the fraction of its test evaluations (all seeds, all evaluation
steps) below the floor where the record holds curves; where it holds only final returns (records made before
the study engine), the fraction of final returns below the floor, labelled as such.

A system's confirmatory study, once its record exists, is read against its own feedback arm (the same code,
seeds and states): each RL arm's test evaluations against the feedback run's test return, and its runs'
holdout returns against the feedback run's holdout return.
"""

from __future__ import annotations

from pathlib import Path

import _common

from pimbrl.experiments.report import load_record
from pimbrl.experiments.spec import load_spec

ROOT = Path(__file__).resolve().parent
STUDIES = ROOT / "studies"
#: the control studies, until the pages are generated again (benchmarks/pending/README.md)
PENDING = ROOT / "pending"
#: the control study holding each system's floor, and the exploratory RL studies read against it (records made
#: before the study engine only where no confirmatory record of the system exists yet: KS)
FLOORS = {
    "pimbrl/Burgers-v0": ("control-pendulum-burgers", ["readme-main"]),
    "pimbrl/KuramotoSivashinsky-v0": ("control-ks", ["ks-compare-55", "ks-headline", "ks-selection"]),
}
CONFIRMATORY = ROOT / "confirmatory"
#: the confirmatory study of each system, read against its own feedback arm where its record exists
CONFIRMATORY_STUDIES = {
    "pimbrl/Burgers-v0": "confirmatory-burgers",
    "pimbrl/Pendulum-v0": "confirmatory-pendulum",
    "pimbrl/CartPole-v0": "confirmatory-cartpole",
    "example/AllenCahn-v0": "confirmatory-allen-cahn",  # the example system of examples/allen_cahn.py
}
#: the arms that are controllers, not RL methods
CONTROLLERS = {"feedback", "mpc", "dpc"}


def fraction_row(system: str, floor: float, study: str, arm: str, what: str, points: list[float]) -> dict:
    """The share of ``points`` (an arm's returns of kind ``what``) below ``floor``, as a record row; printed too."""
    below = sum(v < floor for v in points) / len(points)
    print(f"{system} floor {floor:.2f}  {study:22s} {arm:20s} {below:6.1%} of {len(points)} {what} below")
    return {"system": system, "floor": floor, "study": study, "arm": arm, "measure": what,
            "points": len(points), "fraction_below_floor": below}  # fmt: skip


def confirmatory_rows(system: str, name: str) -> list[dict]:
    """Each RL arm of a confirmatory record against the record's own feedback arm: test curves and holdout returns."""
    try:
        record = load_record(load_spec(CONFIRMATORY / f"{name}.yaml"))
    except FileNotFoundError as exc:
        print(f"{system}: {exc}; skipped")
        return []
    runs = [r for r in record["runs"] if r["system"] == system and r["finished"]]
    feedback = [r for r in runs if r["method"] == "feedback"]
    if not feedback:
        print(f"{system}: no finished feedback run in {name}; skipped")
        return []
    floors = {"evaluations": feedback[0]["final_return"], "holdout returns": feedback[0]["holdout_return"]}
    arms: dict[str, list[dict]] = {}
    for r in runs:
        if r["method"] not in CONTROLLERS:
            arms.setdefault(r["arm"], []).append(r)
    rows = []
    for arm, arm_runs in arms.items():
        measured = {
            "evaluations": [v for r in arm_runs for v in r["curve"]["return_mean"]],
            "holdout returns": [r["holdout_return"] for r in arm_runs],
        }
        rows += [fraction_row(system, floors[what], name, arm, what, points) for what, points in measured.items()]
    return rows


def main() -> None:
    out = []
    for system, (control, studies) in FLOORS.items():
        try:
            where = PENDING if (PENDING / f"{control}.yaml").exists() else STUDIES
            record = load_record(load_spec(where / f"{control}.yaml"))
        except FileNotFoundError as exc:
            print(f"{system}: {exc}; skipped")
            continue
        floors = [r["final_return"] for r in record["runs"] if r["arm"] == "feedback" and r["system"] == system and r["finished"]]
        if not floors:
            print(f"{system}: no finished feedback run in {control}; skipped")
            continue
        floor = floors[0]
        for name in studies:
            rec = load_record(load_spec(STUDIES / f"{name}.yaml"))
            arms: dict[str, list[dict]] = {}
            for r in rec["runs"]:
                if r["system"] == system:
                    arms.setdefault(r["arm"], []).append(r)
            for arm, runs in arms.items():
                curves = [r["curve"]["return_mean"] for r in runs if r.get("curve")]
                if curves:
                    points = [v for c in curves for v in c]
                    what = "evaluations"
                else:
                    points = [r["final_return"] for r in runs]
                    what = "final returns"
                out.append(fraction_row(system, floor, name, arm, what, points))
    for system, name in CONFIRMATORY_STUDIES.items():
        out.extend(confirmatory_rows(system, name))
    path = _common.record("floor_fractions", {"command": "python benchmarks/floor_fractions.py", "rows": out})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
