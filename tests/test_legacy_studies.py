"""The previous studies, re-expressed as specs in benchmarks/studies/, reproduce the numbers their records hold.

Each spec names a record made before the study engine; its report (computed afresh from the runs the
importer reads) must give the per-arm means, reached counts, steps and censored medians the record itself
stored when it was made. The stored summaries are read here straight from the JSON, independently of the
importer. Bootstrap intervals use fewer resamples than the specs' (their point values do not depend on it).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import statistics
from functools import cache
from pathlib import Path
from typing import Any

import pytest
import yaml

from pimbrl.config import ConfigError
from pimbrl.experiments.legacy_records import KNOWN_SCHEME, PARTIAL_METHODS, import_record
from pimbrl.experiments.report import Report, load_record, study_report
from pimbrl.experiments.spec import StudySpec, load_spec, parse_spec
from pimbrl.simulate import resolve_env_id

ROOT = Path(__file__).resolve().parents[1]
STUDIES = ROOT / "benchmarks" / "studies"
#: legacy specs whose studies ran again through the engine (their specs in benchmarks/studies/ replaced), kept
#: here with their old records so that the importer's tests keep a compare and a partial record to read
FIXTURES = ROOT / "tests" / "data" / "legacy_studies"
REPS = 200
TOL = 1e-9


def _legacy_specs() -> list[Path]:
    out = []
    for path in [*sorted(STUDIES.glob("*.yaml")), *sorted(FIXTURES.glob("*.yaml"))]:
        record = (yaml.safe_load(path.read_text()) or {}).get("record") or {}
        if record.get("format", "study") != "study":
            out.append(path)
    return out


SPECS = _legacy_specs()
IDS = [p.stem for p in SPECS]


@cache
def _study(path: Path) -> tuple[StudySpec, dict[str, Any], Report]:
    spec = dataclasses.replace(load_spec(path), reps=REPS)
    record = load_record(spec)
    return spec, record, study_report(spec, record)


def _raw(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text())


def _files(spec: StudySpec) -> list[Path]:
    assert spec.record is not None
    return [spec.record.path, *[(spec.record.path.parent / f).resolve() for f in spec.record.select.get("include", [])]]


def _arm(spec: StudySpec, label: str) -> str:
    assert spec.record is not None
    return spec.record.relabel.get(label, label)


def _group(report: Report, system: str, setting: str = "default") -> dict[str, Any]:
    return report.stats["groups"][f"{resolve_env_id(system)} {setting}"]["arms"]


def _key(t: float) -> str:
    return f"{float(t):g}"


def _close(a: float | None, b: float | None, tol: float = TOL) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return math.isclose(float(a), float(b), rel_tol=tol, abs_tol=tol)


def _median_of(stored: dict[str, Any], prefix: str) -> dict[str, Any]:
    return {"median": stored[prefix], "above": stored[f"{prefix}_above"], "at_most": stored[f"{prefix}_at_most"]}


def test_every_previous_study_has_a_spec() -> None:
    names = {p.stem for p in SPECS} | {p.stem for p in STUDIES.glob("*.yaml")}  # a legacy spec, or its rerun's
    assert len(names) >= 30  # legacy specs shrink as their studies are run again through the engine
    for name in (
        "paper-burgers",  # burgers-compare run again (its legacy spec is a fixture)
        "paper-pendulum",  # pendulum-compare run again
        "paper-cartpole",  # cartpole-compare run again
        "ks-headline",
        "ks-selection",
        "partial-burgers-nu+30",
        "partial-burgers-nu-30",
        "partial-ks-convection+30",
        "partial-ks-convection-30",
        "partial-ks-width+30",
        "partial-cartpole-length+30",
        "partial-pendulum-l+30",
        "ks-ablation-rollout-length",
    ):
        assert name in names


@pytest.mark.parametrize("path", SPECS, ids=IDS)
def test_spec_parses_imports_and_reports(path: Path) -> None:
    spec, record, report = _study(path)
    assert spec.name == path.stem and spec.kind == "exploratory" and spec.question and spec.record is not None
    assert spec.record.command and spec.record.note
    assert record["format"] == "pimbrl-study-record/1" and record["study"] == spec.name and record["spec_sha256"] == spec.sha256
    assert record["runs"] and all(r["arm"] in spec.arm_names for r in record["runs"])
    assert {r["arm"] for r in record["runs"]} == set(spec.arm_names)
    assert report.label == "exploratory" and report.markdown.startswith(f"## {spec.name}")
    assert sum(a["runs"] for g in report.stats["groups"].values() for a in g["arms"].values()) == len(record["runs"])
    for pair in spec.comparisons:  # each comparison the old docs made is computed in some group
        assert any(f"{pair[0]} vs {pair[1]}" in g["comparisons"] for g in report.stats["groups"].values())


@pytest.mark.parametrize("path", SPECS, ids=IDS)
def test_report_reproduces_the_recorded_numbers(path: Path) -> None:
    spec, record, report = _study(path)
    assert spec.record is not None
    check = {
        "compare": _check_compare,
        "sweep": _check_sweep,
        "partial": _check_partial,
        "steps_ratio": _check_steps_ratio,
        "selection": _check_selection,
        "protocols": _check_protocols,
    }[spec.record.format]
    check(spec, record, report)


def _check_compare(spec: StudySpec, record: dict[str, Any], report: Report) -> None:
    for file in _files(spec):
        data = _raw(file)
        group = _group(report, data["env"])
        t = _key(data["threshold"])
        for label, stored in data["methods"].items():
            arm = group[_arm(spec, label)]
            steps = arm["thresholds"][t]["steps"]
            assert arm["runs"] == stored["seeds"]
            assert _close(arm["mean"]["value"], stored["final_return_mean"]), (label, arm["mean"], stored["final_return_mean"])
            assert arm["thresholds"][t]["reached"] == stored["reached"]
            assert [steps[s] for s in sorted(steps)] == stored["steps_to_threshold"]
            if stored["steps_to_threshold_mean"] is not None:
                assert _close(statistics.fmean(steps.values()), stored["steps_to_threshold_mean"])
            budgets = {r["seed"]: r["steps"] for r in data["runs"] if r["method"] == label}
            lower = statistics.fmean(budgets[s] if v is None else v for s, v in steps.items())
            assert _close(lower, stored["steps_to_threshold_lower_bound"])
            assert _close(arm["wall_s"], stored["wall_s_mean"])
            assert _close(arm["updates"] / arm["real_transitions"], stored["update_to_data"])


def _check_sweep(spec: StudySpec, record: dict[str, Any], report: Report) -> None:
    assert spec.record is not None
    data = _raw(spec.record.path)
    t = _key(data["threshold"])
    assert len(report.stats["groups"]) == len(data["rows"])
    for row in data["rows"]:
        key, value = row["setting"].split("=")
        new = {"dyna.rollout_length": "imagine.rollout_length", "dyna.threshold": "check.threshold"}.get(key, key)
        setting = f"{new}={value}"
        arm = _group(report, row["env"], setting)[_arm(spec, row["method"])]
        assert arm["outcome"] == {row["seed"]: row["final_return"]}
        assert arm["thresholds"][t]["steps"] == {row["seed"]: row["steps_to_threshold"]}
        assert _close(arm["wall_s"], row["wall_s"]) and arm["updates"] == row["updates"]


def _check_partial(spec: StudySpec, record: dict[str, Any], report: Report) -> None:
    assert spec.record is not None
    data = _raw(spec.record.path)
    group = _group(report, data["env"])
    assert set(group) == {_arm(spec, v) for v in data["summary"]}
    for variant, stored in data["summary"].items():
        arm = group[_arm(spec, variant)]
        seeds = stored.get("seed_list") or sorted(r["seed"] for r in data["runs"] if r["variant"] == variant)
        assert arm["runs"] == stored["seeds"] == len(seeds)
        assert [arm["outcome"][s] for s in seeds] == stored["final_return"]
        assert _close(arm["mean"]["value"], statistics.fmean(stored["final_return"]))
        for t in data["thresholds"]:
            k = _key(t)
            mine = arm["thresholds"][k]
            assert [mine["steps"][s] for s in seeds] == stored[f"steps_to_{k}"]
            assert mine["reached"] == sum(s is not None for s in stored[f"steps_to_{k}"])
            mean = stored[f"mean_steps_to_{k}"]
            assert _close(statistics.fmean(mine["steps"].values()) if mine["reached"] == len(seeds) else None, mean)
            if f"median_steps_to_{k}" in stored:
                assert mine["median"] == _median_of(stored, f"median_steps_to_{k}")


def _check_steps_ratio(spec: StudySpec, record: dict[str, Any], report: Report) -> None:
    assert spec.record is not None
    data = _raw(spec.record.path)
    t = _key(data["threshold"])
    group = _group(report, spec.systems[0])
    a, b = _arm(spec, "a"), _arm(spec, "b")
    for label in ("a", "b"):
        stored, arm = data["groups"][label], group[_arm(spec, label)]
        assert arm["runs"] == stored["seeds"]
        assert _close(arm["mean"]["value"], stored["final_return_mean"])
        assert _close(arm["wall_s"], stored["wall_s_mean"])
        assert arm["thresholds"][t]["reached"] == stored["reached"]
        assert [arm["thresholds"][t]["steps"][s] for s in sorted(arm["thresholds"][t]["steps"])] == stored["steps_to_threshold"]
        assert arm["thresholds"][t]["median"] == _median_of(stored, "steps_to_threshold_median")
    comparisons = report.stats["groups"][f"{resolve_env_id(spec.systems[0])} default"]["comparisons"]
    ratio = comparisons[f"{a} vs {b}"]["thresholds"][t]["median_ratio"]
    assert _close(ratio["value"], data["ratio"]["median"]["value"])
    assert ratio["bound"] == ("<" if "upper bound" in data["ratio"]["median"]["note"] else "=")
    steps_a, steps_b = group[a]["thresholds"][t]["steps"], group[b]["thresholds"][t]["steps"]
    paired = {str(s): steps_a[s] / steps_b[s] for s in steps_a if s in steps_b and steps_a[s] and steps_b[s]}
    assert paired.keys() == data["paired_by_seed"].keys()
    assert all(_close(paired[s], v) for s, v in data["paired_by_seed"].items())


def _check_selection(spec: StudySpec, record: dict[str, Any], report: Report) -> None:
    assert spec.outcome == "selected"
    for file in _files(spec):
        data = _raw(file)
        arm = _arm(spec, file.stem)
        stats = _group(report, spec.systems[0])[arm]
        assert stats["runs"] == len(data["runs"])
        assert _close(stats["mean"]["value"], data["mean"]["selected_return"])
        assert [min(stats["outcome"].values()), max(stats["outcome"].values())] == data["range"]["selected_return"]
        finals = [r["final_return"] for r in record["runs"] if r["arm"] == arm]
        assert _close(statistics.fmean(finals), data["mean"]["final_return"])
        t = _key(data["threshold"])
        assert [stats["thresholds"][t]["steps"][s] for s in sorted(stats["outcome"])] == [
            r["steps_to_threshold"] for r in data["runs"]
        ]


def _check_protocols(spec: StudySpec, record: dict[str, Any], report: Report) -> None:
    assert spec.record is not None
    protocol = spec.record.select.get("protocol", "test")
    group = _group(report, spec.systems[0])
    count = 0
    for file in _files(spec):
        data = _raw(file)
        for label, stored in data["by_label"].items():
            outcome = group[_arm(spec, label)]["outcome"]
            mine = [outcome[s] for s in stored["seeds"]]
            summary = stored[protocol]
            assert _close(statistics.fmean(mine), summary["return_mean"])
            assert [min(mine), max(mine)] == summary["range"]
            assert sum(v >= data["threshold"] for v in mine) == summary["runs_at_threshold"]
            count += len(mine)
    assert count == len(record["runs"])
    if len(_files(spec)) == 1 and len(group) == len(_raw(spec.record.path)["by_label"]):
        for label, stored in _raw(spec.record.path)["by_label"].items():  # the report's own mean, not just the outcomes
            assert _close(group[_arm(spec, label)]["mean"]["value"], stored[protocol]["return_mean"])


def test_the_ks_headline_is_the_known_scheme_against_mfrl() -> None:
    spec, _, report = _study(STUDIES / "ks-headline.yaml")
    assert spec.arm_names == ("known-scheme", "mfrl") and spec.arm("known-scheme").method == "known-scheme"
    assert not any("pimbrl" in a for a in spec.arm_names)
    ratio = report.stats["groups"]["pimbrl/KuramotoSivashinsky-v0 default"]["comparisons"]["known-scheme vs mfrl"]
    assert ratio["thresholds"]["-55"]["median_ratio"] == {"value": 56250 / 400000, "bound": "<"}
    assert "known equation's coarse scheme" in spec.record.note and "test states" in spec.record.note  # type: ignore[union-attr]


@pytest.mark.parametrize("path", SPECS, ids=IDS)
def test_no_known_scheme_run_is_called_pimbrl(path: Path) -> None:
    spec, record, _ = _study(path)
    for arm in spec.arms:  # an arm named for PiMBRL ran PiMBRL (the network with the physics loss)
        assert ("pimbrl" in arm.name) == (arm.method == "pimbrl"), arm
        assert arm.method != "known-scheme" or "known-scheme" in arm.name, arm
    scheme_labels = {label for labels in KNOWN_SCHEME.values() for label in labels}
    for run in record["runs"]:
        if run["label"] in scheme_labels or PARTIAL_METHODS.get(run["label"]) == "known-scheme":
            assert spec.arm(run["arm"]).method == "known-scheme" and "pimbrl" not in run["arm"], run["arm"]


def _spec_with(path: Path, tmp_path: Path, record: dict[str, Any] | None = None, **changes: Any) -> StudySpec:
    """The spec at ``path`` with ``changes`` to its data and its record's (``record``: a replaced record file)."""
    data = yaml.safe_load(path.read_text())
    source = (path.parent / data["record"]["path"]).resolve()
    data["record"]["path"] = str(source)
    select = data["record"].get("select") or {}
    if "include" in select:
        select["include"] = [str(source.parent / f) for f in select["include"]]
    if record is not None:
        copy_path = tmp_path / source.name
        copy_path.write_text(json.dumps(record))
        data["record"]["path"] = str(copy_path)
    for key, value in changes.items():
        if key.startswith("record."):
            data["record"][key.split(".", 1)[1]] = value
        else:
            data[key] = value
    return dataclasses.replace(parse_spec(data, where=str(path), base=path.parent, text=yaml.safe_dump(data)), reps=REPS)


def _bump(node: Any, prefix: str) -> int:
    """Add 1000 to every number under a key starting with ``prefix``; how many were changed."""
    changed = 0
    if isinstance(node, dict):
        for key in list(node):
            if key.startswith(prefix) and isinstance(node[key], float):
                node[key] += 1000.0
                changed += 1
            else:
                changed += _bump(node[key], prefix)
    elif isinstance(node, list):
        changed += sum(_bump(item, prefix) for item in node)
    return changed


@pytest.mark.parametrize(
    "path",
    [
        FIXTURES / "burgers-compare.yaml",
        STUDIES / "ks-ablation-rollout-length.yaml",
        FIXTURES / "partial-burgers-width+30.yaml",
        STUDIES / "ks-headline.yaml",
        STUDIES / "ks-selection.yaml",
        STUDIES / "ks-scheme-60k.yaml",
    ],
    ids=lambda p: p.stem,
)
def test_best_return_never_enters_a_report(path: Path, tmp_path: Path) -> None:
    spec, _, report = _study(path)
    assert spec.record is not None
    data = copy.deepcopy(_raw(spec.record.path))
    assert _bump(data, "best_return") > 0  # the record holds best returns: the check is not vacuous
    changed = _spec_with(path, tmp_path, data)
    assert study_report(changed, import_record(changed)).stats == report.stats
    # the check can fail: the same change to the field the outcome is read from does change the report
    control = copy.deepcopy(_raw(spec.record.path))
    field = {"protocols": "return_mean", "selection": "selected_return"}.get(spec.record.format, "final_return")
    assert _bump(control, field) > 0
    changed = _spec_with(path, tmp_path, control)
    assert study_report(changed, import_record(changed)).stats != report.stats


def test_a_known_scheme_run_relabelled_as_pimbrl_is_refused(tmp_path: Path) -> None:
    path = STUDIES / "ks-headline.yaml"
    methods = {"pimbrl": {"method": "pimbrl"}, "mfrl": {"method": "mfrl"}}
    spec = _spec_with(path, tmp_path, methods=methods, comparisons=[], **{"record.relabel": {"a": "pimbrl", "b": "mfrl"}})
    with pytest.raises(ConfigError, match=r"'a' run of seed 0 ran known-scheme, but the spec's arm 'pimbrl' is pimbrl"):
        import_record(spec)
    path = STUDIES / "partial-ks-convection+30.yaml"
    data = yaml.safe_load(path.read_text())
    relabel = {**data["record"]["relabel"], "physics-true": "pimbrl-true"}  # the scheme's runs into the network's arm
    with pytest.raises(ConfigError, match=r"'physics-true' run of seed 0 ran known-scheme"):
        import_record(_spec_with(path, tmp_path, **{"record.relabel": relabel}))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"thresholds": [-12]}, r"compare_burgers\.json: threshold -12: the record holds no steps to it"),
        ({"seeds": [0, 1]}, r"compare_burgers\.json: the 'mfrl' run of seed 2: seed 2 is not one of the spec's seeds"),
        ({"seeds": [0, 1, 2, 3]}, r"compare_burgers\.json: the spec's seed 3 has no run in the record"),
        ({"methods": ["mfrl", "mbrl", "pimbrl"], "comparisons": []}, r"'mfrl-matched' is not an arm of the spec"),
        ({"methods": ["mfrl", "mbrl", "pimbrl", "mfrl-matched", "known-scheme"]}, r"arm 'known-scheme' has no run in the record"),
        ({"methods": {"mfrl": {}, "mbrl": {}, "pimbrl": {}, "mfrl-matched": {"method": "mfrl"}}}, r"needs match_updates"),
        ({"systems": ["pendulum"]}, r"is on pimbrl/Burgers-v0, not one of the spec's systems"),
        ({"record.relabel": {"mbrl": "pimbrl"}}, r"ran mbrl, but the spec's arm 'pimbrl' is pimbrl"),
        ({"record.select": {"labels": ["mfrl"]}}, r"the spec's arm 'mbrl' has no run in the record"),
        ({"record.select": {"group": "a"}}, r"record\.select: unknown key 'group'"),
        ({"grid": {"imagine.rollout_length": [3]}}, r"has the setting 'default', not one of the spec's"),
    ],
)
def test_a_spec_that_does_not_say_what_the_record_holds_is_refused(change: dict[str, Any], message: str, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=message):
        import_record(_spec_with(FIXTURES / "burgers-compare.yaml", tmp_path, **change))


def test_the_final_return_of_a_selected_policy_on_the_authors_protocol_is_not_invented(tmp_path: Path) -> None:
    path = STUDIES / "ks-selection-authors-protocol.yaml"
    with pytest.raises(ConfigError, match=r"no final return on this protocol .*set outcome: selected"):
        import_record(_spec_with(path, tmp_path, outcome="final"))
    _, record, _ = _study(path)
    assert all(r["final_return"] is None and r["selected_return"] is not None for r in record["runs"])


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.pop("runs"), r"compare_burgers\.json: not a compare record \(missing field 'runs'\)"),
        (
            lambda d: d["runs"][0].pop("final_return"),
            r"compare_burgers\.json: not a compare record \(missing field 'final_return'\)",
        ),
        (
            lambda d: d["runs"][0].update(final_return="-10"),
            r"compare_burgers\.json: not a compare record \(final_return is '-10', not a number\)",
        ),
        (lambda d: d["runs"][0].update(seed=True), r"not a compare record \(seed is True, not a number\)"),
        (lambda d: d.update(runs=[d["runs"][0], d["runs"][0]]), r"is given twice"),
        (lambda d: d.update(env="nosuch"), r"compare_burgers\.json: the 'mfrl' run of seed 0: unknown environment 'nosuch'"),
    ],
)
def test_a_garbled_record_is_a_one_line_error_naming_the_file(mutate: Any, message: str, tmp_path: Path) -> None:
    path = FIXTURES / "burgers-compare.yaml"
    data = _raw(ROOT / "benchmarks/results/compare_burgers.json")
    mutate(data)
    with pytest.raises(ConfigError, match=message) as info:
        import_record(_spec_with(path, tmp_path, data))
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (b"{not json", r"not valid JSON"),
        (b"[1, 2]", r"not a compare record \(a JSON object was expected"),
        (b'{"a": NaN}', r"NaN is not a finite number"),
    ],
)
def test_a_file_that_is_not_a_record_is_refused(text: bytes, message: str, tmp_path: Path) -> None:
    spec = _spec_with(FIXTURES / "burgers-compare.yaml", tmp_path, **{"record.path": str(tmp_path / "bad.json")})
    (tmp_path / "bad.json").write_bytes(text)
    with pytest.raises(ConfigError, match=message):
        import_record(spec)
    (tmp_path / "bad.json").unlink()
    with pytest.raises(ConfigError, match=r"bad\.json: the record does not exist"):
        import_record(spec)


def test_a_report_with_the_specs_own_statistics_has_the_same_point_values() -> None:
    path = STUDIES / "ks-selection.yaml"
    spec = load_spec(path)
    assert spec.reps == 10_000
    full = study_report(spec, load_record(spec)).stats["groups"]["pimbrl/KuramotoSivashinsky-v0 default"]["arms"]["known-scheme"]
    fast = _group(_study(path)[2], "ks")["known-scheme"]
    assert full["mean"]["value"] == fast["mean"]["value"] and full["iqm"]["value"] == fast["iqm"]["value"]
    assert _close(
        full["mean"]["value"],
        _raw(ROOT / "benchmarks/results/ks_selection_lm25_reset0.5_10seeds.json")["mean"]["selected_return"],
    )
    assert full["mean"]["low"] < full["mean"]["value"] < full["mean"]["high"]
