"""How much of each RL method's learning curve lies below its system's feedback floor.

    python benchmarks/floor_fractions.py      # writes benchmarks/results/floor_fractions.json

The floor is the final test return of the ``feedback`` arm of the control studies (gain tuned on validation
draws). For each RL study record: per arm, the fraction of its test evaluations (all seeds, all evaluation
steps) below the floor where the record holds curves; where it holds only final returns (records made before
the study engine), the fraction of final returns below the floor, labelled as such.
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
#: the control study holding each system's floor, and the RL studies read against it
FLOORS = {
    "pimbrl/Burgers-v0": ("control-pendulum-burgers", ["readme-main", "burgers-compare", "burgers-compare-lm5"]),
    "pimbrl/Pendulum-v0": ("control-pendulum-burgers", ["pendulum-compare"]),
    "pimbrl/CartPole-v0": ("control-cartpole", ["cartpole-compare"]),
    "pimbrl/KuramotoSivashinsky-v0": ("control-ks", ["ks-compare-55", "ks-headline", "ks-selection"]),
}


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
                below = sum(v < floor for v in points) / len(points)
                row = {"system": system, "floor": floor, "study": name, "arm": arm, "measure": what,
                       "points": len(points), "fraction_below_floor": below}  # fmt: skip
                out.append(row)
                print(f"{system} floor {floor:.2f}  {name:22s} {arm:20s} {below:6.1%} of {len(points)} {what} below")
    path = _common.record("floor_fractions", {"command": "python benchmarks/floor_fractions.py", "rows": out})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
