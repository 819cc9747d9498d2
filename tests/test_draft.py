"""`pimbrl study draft`: a confirmatory spec from a finished tuning study, by the protocol's rules."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pimbrl.cli import main
from pimbrl.config import ConfigError, load_yaml
from pimbrl.experiments.draft import draft_confirmatory
from pimbrl.experiments.report import load_record, study_report
from pimbrl.experiments.spec import load_spec, parse_spec

REPO = Path(__file__).resolve().parents[1]
PENDING = REPO / "benchmarks" / "pending"
REGISTERED = REPO / "benchmarks" / "confirmatory"


def _draft(tuning: str, tmp_path: Path, **kwargs):
    spec = load_spec(PENDING / f"{tuning}.yaml")
    out = REGISTERED / f"draft-of-{tuning}.yaml"  # never written: only its folder is used
    text = draft_confirmatory(spec, load_record(spec), out, **kwargs)
    assert not out.exists()
    return text, parse_spec(load_yaml(text), where="draft", base=REGISTERED, text=text)


@pytest.mark.parametrize("name", ["burgers", "partial-burgers"])
@pytest.mark.slow
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


@pytest.mark.slow
def test_h4_is_stated_against_every_rl_arm_and_h2_only_under_a_wrong_prior(tmp_path) -> None:
    _, draft = _draft("tune-burgers", tmp_path)
    ids = {h.id: (h.better, h.than) for h in draft.hypotheses}
    rl = ["mfrl", "crossq", "redq", "mbrl", "pimbrl", "known-scheme"]  # every RL arm but the rule's best
    assert ids["H4a"] == ("mpc", "mfrl-matched") and ids["H4b"] == ("dpc", "mfrl-matched")
    assert {i: v for i, v in ids.items() if i.startswith("H4a-")} == {f"H4a-{a}": ("mpc", a) for a in rl}
    assert {i: v for i, v in ids.items() if i.startswith("H4b-")} == {f"H4b-{a}": ("dpc", a) for a in rl}
    assert set(ids) == {"H1a", "H1b", "H3", "H4a", "H4b"} | {f"H4{x}-{a}" for x in "ab" for a in rl}
    assert ("mpc", "feedback") in draft.comparisons
    _, partial = _draft("tune-partial-burgers", tmp_path)
    assert [h.id for h in partial.hypotheses] == ["H2a", "H2b"]  # no H3 or H4 with a wrong prior (no controller)


def test_fewer_seeds_for_the_other_arms_keep_every_hypothesis_decidable(tmp_path) -> None:
    text, draft = _draft("tune-burgers", tmp_path, seeds=5, other_seeds=3, total_steps=6000)
    seeds = {a.name: draft.seeds_of(a) for a in draft.arms}
    # every arm of H1 and H3, the best RL arm (mfrl-matched), MPC, DPC, the best controller (MPC) and the paper's
    # model-free baseline (TD3 at one update per real step)
    main_arms = {"mfrl", "mfrl-matched", "mbrl", "pimbrl", "known-scheme", "mpc", "dpc"}
    assert {a for a, s in seeds.items() if len(s) == 5} == main_arms
    assert all(s == (100, 101, 102) for a, s in seeds.items() if a not in main_arms)
    for h in draft.hypotheses:  # none is inconclusive by the verdict rule's count of runs before it runs
        assert len(seeds[h.better]) >= 5 and len(seeds[h.than]) >= 5, h.id
    assert "H4a-crossq" not in {h.id for h in draft.hypotheses} and ("mpc", "crossq") in draft.comparisons
    assert "H4a-mfrl" in {h.id for h in draft.hypotheses}  # the baseline runs every seed: its H4 pairs are decidable
    assert "the paper's model-free baseline" in text
    assert draft.overrides["total_steps"] == 6000
    plan = " ".join(text.split())
    assert "RL arms scaled by 2 from the tuning runs' 3,000 steps to 6,000" in plan
    assert "mbrl 5.1" in plan and "dpc 28.4" in plan  # MBRL doubled; controllers not
    # MPC (horizon 20): its minutes a tuning run, not doubled, plus 100 holdout episodes at its inference cost
    # per control step in those runs
    from pimbrl.systems.registry import get_system

    mpc = [r for r in load_record(load_spec(PENDING / "tune-burgers.yaml"))["runs"] if r["arm"] == "mpc-h20"]
    holdout_steps = 100 * get_system("pimbrl/Burgers-v0").episode_steps
    minutes = np.mean([r["wall_s"] for r in mpc]) / 60 + np.mean([r["inference_s_per_step"] for r in mpc]) * holdout_steps / 60
    assert np.mean([r["wall_s"] for r in mpc]) / 60 < 2.0 < minutes and f"mpc {minutes:.1f}," in plan
    assert "with 100 holdout episodes each at the arm's inference cost per control step" in plan


@pytest.mark.slow
def test_the_steps_hypotheses_count_to_the_recipe_s_threshold_or_one_given(tmp_path) -> None:
    import dataclasses

    spec = load_spec(PENDING / "tune-burgers.yaml")
    record = load_record(spec)
    several = {**record, "thresholds": {"pimbrl/Burgers-v0": [-20.0, -11.0]}}  # as KS lists -100 and its -55
    text = draft_confirmatory(spec, several, None)
    steps = {h.id: h.threshold for h in parse_spec(load_yaml(text), where="d", base=PENDING).hypotheses if h.threshold}
    assert steps == {"H1a": -11.0, "H3": -11.0}  # the recipe's, not the first listed
    none = dataclasses.replace(spec, overrides={**spec.overrides, "threshold": None})
    bare = {**record, "thresholds": {}}
    with pytest.raises(ConfigError, match="recipe sets none: give --threshold T"):
        draft_confirmatory(none, bare, None)
    text = draft_confirmatory(none, bare, None, threshold=-10.5)
    assert {h.threshold for h in parse_spec(load_yaml(text), where="d", base=PENDING).hypotheses} == {None, -10.5}


def test_two_families_of_one_method_and_bad_counts_are_one_line_errors(tmp_path) -> None:
    import dataclasses

    spec = load_spec(PENDING / "tune-burgers.yaml")
    record = load_record(spec)
    twice = dataclasses.replace(spec, tuning={**spec.tuning, "mbrl-again": spec.tuning["mbrl"]})
    with pytest.raises(ConfigError, match="mbrl, mbrl-again all tune the method mbrl"):
        draft_confirmatory(twice, record, None)
    for kwargs in ({"seeds": 0}, {"seeds": 3, "other_seeds": 5}, {"holdout_episodes": 0}):
        with pytest.raises(ConfigError, match="each must be at least 1"):
            draft_confirmatory(spec, record, None, **kwargs)


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


def test_create_file_never_writes_over_a_file(tmp_path) -> None:
    from pimbrl.fileio import create_file

    create_file(tmp_path / "a" / "s.yaml", b"one")
    with pytest.raises(FileExistsError):
        create_file(tmp_path / "a" / "s.yaml", b"two")
    assert (tmp_path / "a" / "s.yaml").read_bytes() == b"one" and sorted(p.name for p in (tmp_path / "a").iterdir()) == ["s.yaml"]


@pytest.mark.slow
def test_the_threshold_rule_reads_the_lowest_chosen_iqm_of_the_steps_hypotheses_arms() -> None:
    import dataclasses

    from pimbrl.experiments.draft import THRESHOLD_RULE, _Family, rule_threshold

    def fam(name: str, iqm: float) -> _Family:
        return _Family(name, None, iqm, {})

    arms = {"pimbrl": "p", "mbrl": "m", "known-scheme": "k", "tuned model-free arm": "f"}
    assert rule_threshold("t", [fam("p", -9.766), fam("m", -9.71), fam("k", -9.6), fam("f", -9.9), fam("x", -50)], arms) == -9.9
    assert rule_threshold("t", [fam("p", -135.4), fam("m", -130.0)], arms) == -140.0  # toward worse, two figures
    assert rule_threshold("t", [fam("p", 187.3), fam("m", 200.0)], arms) == 180.0
    with pytest.raises(ConfigError, match="threshold rule has nothing to read"):
        rule_threshold("t", [fam("x", -1.0)], arms)

    spec = load_spec(PENDING / "tune-burgers.yaml")
    record = load_record(spec)
    with pytest.raises(ConfigError, match="recipe sets the threshold -11; the rule is for systems without one"):
        draft_confirmatory(spec, record, None, threshold="rule")
    none = dataclasses.replace(spec, overrides={**spec.overrides, "threshold": None})
    text = draft_confirmatory(none, {**record, "thresholds": {}}, None, threshold="rule")
    draft = parse_spec(load_yaml(text), where="d", base=PENDING)
    steps = {h.threshold for h in draft.hypotheses if h.threshold is not None}
    chosen = [float(line.split()[3]) for line in text.splitlines() if line.startswith(("  # pimbrl:", "  # mbrl:",
              "  # known-scheme:", "  # mfrl-matched:"))]  # fmt: skip
    assert len(chosen) == 4 and steps == {rule_threshold("t", [fam("a", min(chosen))], {"pimbrl": "a"})}
    assert THRESHOLD_RULE in " ".join(text.split())


@pytest.mark.slow
def test_an_amendment_s_methods_replace_the_first_study_s_and_the_rules_read_the_merged_choices(tmp_path) -> None:
    """A later tuning study of the same system and budget re-tunes some methods (controlgym Burgers's scheme)."""
    import dataclasses

    spec = load_spec(PENDING / "tune-burgers.yaml")
    record = load_record(spec)
    _, alone = _draft("tune-burgers", tmp_path)
    mbrl_arms = spec.tuning["mbrl"]
    amending = dataclasses.replace(spec, name="tune-burgers-mbrl", tuning={"mbrl": mbrl_arms})
    # the amendment's runs: MBRL's three settings again, the last now far ahead of every arm of the first study
    runs = [
        {**r, "final_return": 0.0 if r["arm"] == mbrl_arms[-1] else r["final_return"] - 100.0}
        for r in record["runs"]
        if r["arm"] in mbrl_arms
    ]
    text = draft_confirmatory(spec, record, None, amendments=[(amending, {**record, "runs": runs})])
    draft = parse_spec(load_yaml(text), where="d", base=PENDING)
    arms = {a.name: a for a in draft.arms}
    assert arms["mbrl"] == dataclasses.replace(spec.arm(mbrl_arms[-1]), name="mbrl")  # the amendment's choice
    assert {n: a for n, a in arms.items() if n != "mbrl"} == {
        n: a for n, a in {a.name: a for a in alone.arms}.items() if n != "mbrl"
    }
    assert f"# mbrl: {mbrl_arms[-1]} 0 by tune-burgers-mbrl (" in text
    assert "tune-burgers and tune-burgers-mbrl's choices" in text
    assert text.splitlines()[1] == (
        "# Drafted by `pimbrl study draft` from tune-burgers and tune-burgers-mbrl's records; reviewed before it was committed."
    )
    assert "from tune-burgers's record;" in _draft("tune-burgers", tmp_path)[0].splitlines()[1]  # one study: its record
    # the amendment's own report applies the rule to its methods alone (no model-free family), and says so
    report = study_report(dataclasses.replace(amending, reps=200), {**record, "runs": runs}).markdown
    assert "By the rule of docs/confirmatory.md among this study's methods alone, the best RL arm is mbrl (0)." in report
    assert (
        "By the rule of docs/confirmatory.md, the tuned model-free arm is"
        in study_report(dataclasses.replace(spec, reps=200), record).markdown
    )
    # the best RL arm by rule is now MBRL (IQM 0 against every other family's below it): H4 names it
    ids = {h.id: (h.better, h.than) for h in draft.hypotheses}
    assert ids["H4a"] == ("mpc", "mbrl") and ids["H4b"] == ("dpc", "mbrl")
    other = dataclasses.replace(amending, overrides={**spec.overrides, "total_steps": 600})
    with pytest.raises(ConfigError, match="tune-burgers-mbrl cannot amend tune-burgers: it has the overrides"):
        draft_confirmatory(spec, record, None, amendments=[(other, {**record, "runs": runs})])
    fewer = dataclasses.replace(amending, tuning={"mbrl": mbrl_arms[:2]})
    with pytest.raises(ConfigError, match=r"gives each method \(2, 2\) settings x seeds, not \(3, 2\)"):
        draft_confirmatory(spec, record, None, amendments=[(fewer, {**record, "runs": runs})])
