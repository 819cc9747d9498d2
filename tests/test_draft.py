"""`pimbrl study draft`: a confirmatory spec from a finished tuning study, by the protocol's rules."""

from __future__ import annotations

from pathlib import Path

import pytest

from pimbrl.cli import main
from pimbrl.config import ConfigError, load_yaml
from pimbrl.experiments.draft import draft_confirmatory
from pimbrl.experiments.report import load_record
from pimbrl.experiments.spec import load_spec, parse_spec

REPO = Path(__file__).resolve().parents[1]
PENDING = REPO / "benchmarks" / "pending"
REGISTERED = REPO / "benchmarks" / "confirmatory"


def _draft(tuning: str, tmp_path: Path, **kwargs):
    spec = load_spec(PENDING / f"{tuning}.yaml")
    out = REGISTERED / f"draft-of-{tuning}.yaml"  # never written: only its folder is used
    text = draft_confirmatory(spec, load_record(spec), out, **kwargs)
    return text, parse_spec(load_yaml(text), where="draft", base=REGISTERED, text=text)


@pytest.mark.parametrize("name", ["burgers", "partial-burgers"])
def test_the_draft_of_a_finished_tuning_study_has_the_registered_spec_s_arms_and_hypotheses(name: str, tmp_path) -> None:
    _, draft = _draft(f"tune-{name}", tmp_path)
    registered = load_spec(REGISTERED / f"confirmatory-{name}.yaml")
    assert draft.name == registered.name and draft.kind == "confirmatory" and draft.outcome == "holdout"
    assert draft.seeds == registered.seeds == tuple(range(100, 110))
    assert draft.overrides == registered.overrides and draft.record.path == registered.record.path
    drafted = {a.name: a for a in draft.arms}
    for arm in registered.arms:  # every registered arm, as drafted (the draft may hold more families)
        assert drafted[arm.name] == arm, arm.name
    drafted_h = {h.id: h for h in draft.hypotheses}
    for h in registered.hypotheses:
        got = drafted_h[h.id]
        assert (got.better, got.than, got.metric, got.threshold) == (h.better, h.than, h.metric, h.threshold), h.id


def test_h4_is_stated_against_every_rl_arm_and_h2_only_under_a_wrong_prior(tmp_path) -> None:
    _, draft = _draft("tune-burgers", tmp_path)
    ids = {h.id: h for h in draft.hypotheses}
    rl = [a.name for a in draft.arms if a.method not in ("feedback", "mpc", "dpc")]
    assert ids["H4a"].than == ids["H4b"].than == "mfrl-matched"  # the rule's best RL arm keeps the plain id
    assert {f"H4a-{a}" for a in rl if a != "mfrl-matched"} <= set(ids) and "H4a-mpc" not in ids
    assert not any(i.startswith("H2") for i in ids)
    _, partial = _draft("tune-partial-burgers", tmp_path)
    assert [h.id for h in partial.hypotheses] == ["H2a", "H2b"]  # no H3 or H4 with a wrong prior (no controller)


def test_fewer_seeds_for_the_other_arms_and_a_longer_budget_scale_the_plan(tmp_path) -> None:
    text, draft = _draft("tune-burgers", tmp_path, seeds=5, other_seeds=3, total_steps=6000)
    seeds = {a.name: draft.seeds_of(a) for a in draft.arms}
    main_arms = {"mfrl-matched", "pimbrl", "known-scheme", "mpc"}  # the protocol's; MPC is the best controller
    assert {a for a, s in seeds.items() if len(s) == 5} == main_arms
    assert all(s == (100, 101, 102) for a, s in seeds.items() if a not in main_arms)
    assert draft.overrides["total_steps"] == 6000
    assert "scaled by 2 from the tuning runs' 3,000 steps to 6,000" in " ".join(text.split())


def test_an_unfinished_or_non_tuning_study_gives_no_draft(tmp_path) -> None:
    spec = load_spec(PENDING / "tune-burgers.yaml")
    record = load_record(spec)
    partial = {**record, "runs": [r for r in record["runs"] if r["arm"] != "dpc-h40"]}
    with pytest.raises(ConfigError, match="no choice yet for dpc"):
        draft_confirmatory(spec, partial, tmp_path / "d.yaml")
    registered = load_spec(REGISTERED / "confirmatory-burgers.yaml")
    with pytest.raises(ConfigError, match="not a tuning study"):
        draft_confirmatory(registered, record, tmp_path / "d.yaml")


def test_the_cli_writes_a_draft_once_and_never_over_a_file(tmp_path, capsys) -> None:
    out = tmp_path / "confirmatory" / "c.yaml"
    assert main(["study", "draft", str(PENDING / "tune-partial-burgers.yaml"), "--out", str(out)]) == 0
    assert "commit it alone before its first run" in capsys.readouterr().out
    spec = load_spec(out)
    assert [h.id for h in spec.hypotheses] == ["H2a", "H2b"]
    assert spec.record.path == REPO / "benchmarks" / "results" / "confirmatory-partial-burgers.json"
    before = out.read_bytes()
    assert main(["study", "draft", str(PENDING / "tune-partial-burgers.yaml"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0] and "never rewritten" in err[0]
    assert out.read_bytes() == before
