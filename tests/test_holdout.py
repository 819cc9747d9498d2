"""The holdout pool (fresh draws only a run's final evaluation plays) and evaluations on validation draws."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pimbrl.config import ConfigError
from pimbrl.control.base import task_of
from pimbrl.envs import HOLDOUT_SEED, VALIDATION_SEED
from pimbrl.experiments.report import _outcome
from pimbrl.experiments.spec import parse_spec
from pimbrl.fileio import UnsafeFileError
from pimbrl.training import create_run, resolve_config, train
from pimbrl.training.evaluation import Evaluator
from pimbrl.training.holdout import read_holdout
from pimbrl.training.loop import open_run
from pimbrl.training.runs import extend_run

PENDULUM = "pimbrl/Pendulum-v0"
TINY = {"total_steps": 300, "warmup_steps": 100, "update_after": 100, "update_every": 50, "eval_every": 150,
        "eval_episodes": 3, "checkpoint_every": 100, "agent.hidden": (16, 16), "agent.batch_size": 16}  # fmt: skip


def _returns(path) -> list[str]:
    rows = (path / "evaluations.csv").read_text().splitlines()
    column = rows[0].split(",").index("return_mean")
    return [row.split(",")[column] for row in rows[1:]]


@pytest.mark.parametrize("env", [PENDULUM, "pimbrl/Burgers-v0", "pimbrl/CartPole-v0"])
def test_holdout_draws_are_fixed_and_none_is_a_test_or_validation_draw(env: str) -> None:
    task = task_of(env, {})
    holdout = task.protocol_initial_states("holdout", 20, seed=2021)
    assert np.array_equal(holdout, task.holdout_initial_states(20))  # the same on every call, whatever the seed
    others = np.concatenate([task.test_initial_states(20, 2021), task.validation_initial_states(20)])
    distance = np.abs(holdout[:, None, :] - others[None, :, :]).max(-1)
    assert distance.min() > 1e-6
    assert "holdout" in task.eval_protocols


@pytest.mark.slow  # generates the KS holdout pool where it is not cached (about a minute)
def test_the_ks_holdout_pool_comes_from_runs_of_its_own() -> None:
    task = task_of("pimbrl/KuramotoSivashinsky-v0", {})
    holdout = task.holdout_initial_states(200)
    for other in (task.test_initial_states(200, 0), task.validation_initial_states(50)):
        assert np.abs(holdout[:, None, :] - other[None, :, :]).max(-1).min() > 1e-3
    with pytest.raises(ValueError, match="holdout pool holds 200"):
        task.holdout_initial_states(201)


def test_a_gymnasium_env_plays_its_holdout_and_validation_episodes_from_their_own_seed_streams() -> None:
    assert Evaluator("Pendulum-v1", {}, 2, 2021, protocol="holdout").seed == HOLDOUT_SEED
    assert Evaluator("Pendulum-v1", {}, 2, 2021, protocol="validation").seed == VALIDATION_SEED
    assert Evaluator("Pendulum-v1", {}, 2, 2021).seed == 2021


@pytest.mark.slow  # three short runs
def test_a_run_plays_the_holdout_pool_once_at_its_end_and_nothing_before_reads_it(tmp_path) -> None:
    plain = train(create_run(resolve_config(PENDULUM, TINY), tmp_path / "plain", progress=False))
    path = tmp_path / "holdout"
    summary = train(create_run(resolve_config(PENDULUM, {**TINY, "holdout_episodes": 4}), path, progress=False))
    # the holdout changes nothing the run does before its end: the same test returns at every evaluation
    assert _returns(path) == _returns(tmp_path / "plain") and summary.final_return_mean == plain.final_return_mean
    holdout = json.loads((path / "holdout.json").read_text())
    assert holdout["step"] == 300 and holdout["episodes"] == 4 and len(holdout["returns"]) == 4
    assert summary.holdout_return_mean == pytest.approx(np.mean(holdout["returns"]))
    assert summary.holdout_return_mean != summary.final_return_mean  # other states than the test pool's
    saved = json.loads((path / "config.json").read_text())["summary"]
    assert saved["holdout_return_mean"] == summary.holdout_return_mean and saved["holdout_episodes"] == 4
    assert plain.holdout_return_mean is None and not (tmp_path / "plain" / "holdout.json").exists()

    # reopening the finished run does not play the pool again; extending it plays it for the new final policy
    before = (path / "holdout.json").stat().st_mtime_ns
    open_run(path, progress=False).run_dir.close()
    assert (path / "holdout.json").stat().st_mtime_ns == before
    extend_run(path, 400)
    extended = train(open_run(path, progress=False))
    assert json.loads((path / "holdout.json").read_text())["step"] == 400
    assert extended.holdout_return_mean == pytest.approx(json.loads((path / "holdout.json").read_text())["return_mean"])


def test_a_holdout_file_pimbrl_did_not_write_is_refused_in_one_line(tmp_path) -> None:
    path = tmp_path / "r"
    train(create_run(resolve_config(PENDULUM, {**TINY, "holdout_episodes": 2}), path, progress=False))
    payload = json.loads((path / "holdout.json").read_text())
    payload["return_mean"] = 0.0  # a mean its returns do not give
    (path / "holdout.json").write_text(json.dumps(payload))
    run = open_run(path, progress=False, inspect_only=True)
    try:
        with pytest.raises(UnsafeFileError, match="not a holdout evaluation pimbrl wrote"):
            read_holdout(run.run_dir)
    finally:
        run.run_dir.close()


def test_evaluations_on_the_validation_draws_read_no_test_state(tmp_path) -> None:
    cfg = resolve_config(PENDULUM, {**TINY, "eval_protocol": "validation"})
    run = create_run(cfg, tmp_path / "tune", progress=False)
    task = task_of(PENDULUM, {})
    assert np.array_equal(run.evaluator.initial_states, task.validation_initial_states(3))
    train(run)
    with pytest.raises(ConfigError, match="eval_protocol"):
        resolve_config(PENDULUM, {"eval_protocol": "holdout"})  # the holdout pool is the final evaluation's alone


def test_a_control_run_plays_the_holdout_pool_after_its_test_states(tmp_path) -> None:
    cfg = resolve_config(PENDULUM, {"method": "feedback", "eval_episodes": 4, "holdout_episodes": 5, "model.gains": (1.0,)})
    summary = train(create_run(cfg, tmp_path / "fb", progress=False))
    holdout = json.loads((tmp_path / "fb" / "holdout.json").read_text())
    assert holdout["episodes"] == 5 and summary.holdout_return_mean == pytest.approx(holdout["return_mean"])
    control = json.loads((tmp_path / "fb" / "control.json").read_text())
    assert [len(c["returns"]) for c in control["test"]["chunks"]] == [4]
    assert [len(c["returns"]) for c in control["holdout"]["chunks"]] == [5]


def test_a_study_judged_on_the_holdout_pool_needs_holdout_episodes_and_reads_only_them(tmp_path) -> None:
    spec = {"name": "h", "systems": ["pendulum"], "seeds": 1, "methods": ["mfrl"], "outcome": "holdout"}
    with pytest.raises(ConfigError, match="needs holdout_episodes"):
        parse_spec(spec, where="h.yaml")
    parsed = parse_spec({**spec, "overrides": {"holdout_episodes": 10}}, where="h.yaml")
    assert _outcome(parsed, {"final_return": -100.0, "holdout_return": -150.0}) == -150.0
    with pytest.raises(ValueError, match="has no holdout evaluation"):
        _outcome(parsed, {"final_return": -100.0, "holdout_return": None, "path": "x"})


# ---------------------------------------------------------------------------------- tuning studies
def _tuning_spec(tuning, overrides=None) -> dict:
    arms = {
        "mfrl-a": {"method": "mfrl", "overrides": {"agent.actor_lr": 1e-3}},
        "mfrl-b": {"method": "mfrl", "overrides": {"agent.actor_lr": 3e-4}},
        "pimbrl-a": {"method": "pimbrl", "overrides": {"physics.weight": 0.01}},
        "pimbrl-b": {"method": "pimbrl", "overrides": {"physics.weight": 0.1}},
    }
    return {"name": "tune", "systems": ["pendulum"], "seeds": 2, "methods": arms, "tuning": tuning,
            "statistics": {"reps": 200}, "overrides": {"eval_protocol": "validation"} if overrides is None else overrides}  # fmt: skip


def test_a_tuning_study_gives_every_method_the_same_budget_on_validation_draws() -> None:
    spec = parse_spec(_tuning_spec({"mfrl": ["mfrl-a", "mfrl-b"], "pimbrl": ["pimbrl-a", "pimbrl-b"]}), where="t.yaml")
    assert spec.tuning == {"mfrl": ("mfrl-a", "mfrl-b"), "pimbrl": ("pimbrl-a", "pimbrl-b")}
    with pytest.raises(ConfigError, match=r"unequal budgets \(mfrl 2, pimbrl 1"):
        parse_spec(_tuning_spec({"mfrl": ["mfrl-a", "mfrl-b"], "pimbrl": ["pimbrl-a"]}), where="t.yaml")
    with pytest.raises(ConfigError, match="evaluated on the test draws"):
        parse_spec(_tuning_spec({"mfrl": ["mfrl-a"], "pimbrl": ["pimbrl-a"]}, overrides={}), where="t.yaml")
    with pytest.raises(ConfigError, match="candidate of both"):
        parse_spec(_tuning_spec({"mfrl": ["mfrl-a", "mfrl-b"], "x": ["mfrl-a", "pimbrl-a"]}), where="t.yaml")
    with pytest.raises(ConfigError, match="not an arm"):
        parse_spec(_tuning_spec({"mfrl": ["mfrl-c"]}), where="t.yaml")


@pytest.mark.slow  # the bootstrap of four arms
def test_a_tuning_report_names_each_methods_choice_and_none_before_every_candidate_finished() -> None:
    from pimbrl.experiments.report import study_report

    spec = parse_spec(_tuning_spec({"mfrl": ["mfrl-a", "mfrl-b"], "pimbrl": ["pimbrl-a", "pimbrl-b"]}), where="t.yaml")
    returns = {"mfrl-a": -300.0, "mfrl-b": -200.0, "pimbrl-a": -150.0, "pimbrl-b": -180.0}
    runs = []
    for arm, base in returns.items():
        for seed in range(2):
            curve = {"step": [40, 80], "return_mean": [base, base], "return_min": [0, 0], "return_max": [0, 0]}
            runs.append({"system": "pimbrl/Pendulum-v0", "arm": arm, "setting": "default", "seed": seed, "finished": True,
                         "steps": 80, "final_return": base + seed, "curve": curve})  # fmt: skip
    record = {"runs": runs, "thresholds": {}, "spec_sha256": spec.sha256}
    tuning = study_report(spec, record).stats["groups"]["pimbrl/Pendulum-v0 default"]["tuning"]
    assert tuning["mfrl"]["chosen"] == "mfrl-b" and tuning["pimbrl"]["chosen"] == "pimbrl-a"
    partial = study_report(spec, {**record, "runs": runs[:-1]})
    assert partial.stats["groups"]["pimbrl/Pendulum-v0 default"]["tuning"]["pimbrl"]["chosen"] is None
    assert "not yet: runs missing or unfinished" in partial.markdown


# ---------------------------------------------------------------------------------- review: what must not slip
def test_a_gymnasium_envs_holdout_seeds_meet_no_test_or_validation_seed() -> None:
    holdout = Evaluator("Pendulum-v1", {}, 50, 2021, protocol="holdout").reset_seeds
    validation = Evaluator("Pendulum-v1", {}, 10_000, 2021, protocol="validation").reset_seeds
    test = Evaluator("Pendulum-v1", {}, 10_000, 2021).reset_seeds
    assert len(set(holdout)) == 50 and not set(holdout) & (set(validation) | set(test))
    assert validation[:2] == [VALIDATION_SEED, VALIDATION_SEED + 1] and test[:2] == [2021, 2022]  # as before


def test_every_run_of_a_holdout_study_plays_the_holdout_pool() -> None:
    base = {"name": "h", "systems": ["pendulum"], "seeds": 1, "outcome": "holdout", "overrides": {"holdout_episodes": 10}}
    arms = {"mfrl": {"method": "mfrl"}, "off": {"method": "mfrl", "overrides": {"holdout_episodes": 0, "utd": 2.0}}}
    with pytest.raises(ConfigError, match=r"arm\(s\) off have none"):
        parse_spec({**base, "methods": arms}, where="h.yaml")
    with pytest.raises(ConfigError, match="have none"):
        parse_spec({**base, "methods": ["mfrl"], "overrides": {}, "grid": {"holdout_episodes": [0, 10]}}, where="h.yaml")
    assert parse_spec({**base, "methods": ["mfrl"], "overrides": {}, "grid": {"holdout_episodes": [5, 10]}}, where="h.yaml")


def test_a_tuning_study_never_reads_the_holdout_pool() -> None:
    tuning = {"mfrl": ["mfrl-a", "mfrl-b"], "pimbrl": ["pimbrl-a", "pimbrl-b"]}
    with pytest.raises(ConfigError, match="outcome: holdout' is refused"):
        parse_spec({**_tuning_spec(tuning), "outcome": "holdout", "overrides": {"eval_protocol": "validation", "holdout_episodes": 5}},
                   where="t.yaml")  # fmt: skip
    with pytest.raises(ConfigError, match="plays the holdout pool"):
        parse_spec(_tuning_spec(tuning, overrides={"eval_protocol": "validation", "holdout_episodes": 5}), where="t.yaml")
    with pytest.raises(ConfigError, match="evaluated on the test draws"):
        parse_spec({**_tuning_spec(tuning), "grid": {"eval_protocol": ["validation", "test"]}, "overrides": {}}, where="t.yaml")


def test_a_run_asking_a_finite_pool_for_too_many_states_stops_before_it_starts(tmp_path) -> None:
    from pimbrl.training.evaluation import check_pool_sizes

    task = task_of("pimbrl/KuramotoSivashinsky-v0", {})
    with pytest.raises(ConfigError, match="eval_episodes 200: the validation pool holds 50 states"):
        check_pool_sizes(task, "validation", 200, 0)
    with pytest.raises(ConfigError, match="holdout_episodes 201: the holdout pool holds 200"):
        check_pool_sizes(task, "test", 200, 201)
    check_pool_sizes(task, "test", 200, 200)
    check_pool_sizes(task_of(PENDULUM, {}), "validation", 5000, 5000)  # drawn without limit
    cfg = resolve_config("pimbrl/KuramotoSivashinsky-v0", {"method": "feedback", "holdout_episodes": 500})
    with pytest.raises(ConfigError, match="holdout pool holds 200"):
        create_run(cfg, tmp_path / "ks", progress=False)
    assert not (tmp_path / "ks").exists()


@pytest.mark.slow  # generates two small KS pools
def test_the_ks_holdout_pool_of_another_size_is_not_served_from_memory(tmp_path, monkeypatch) -> None:
    from pimbrl.systems import ks

    monkeypatch.setenv("PIMBRL_CACHE_DIR", str(tmp_path))
    ks._MEMO.clear()
    small = ks.KSPoolConfig(n_train=4, n_test=2, n_validation=2, n_holdout=2, batch=8, seed=3)
    two = ks.ks_initial_state_pool("holdout", small, verbose=False)
    three = ks.ks_initial_state_pool("holdout", ks.KSPoolConfig(**{**small.__dict__, "n_holdout": 3}), verbose=False)
    assert len(two.states) == 2 and len(three.states) == 3
    ks._MEMO.clear()


def test_a_missing_holdout_file_is_played_again_and_the_summary_follows(tmp_path) -> None:
    path = tmp_path / "fb"
    cfg = resolve_config(PENDULUM, {"method": "feedback", "eval_episodes": 3, "holdout_episodes": 4, "model.gains": (1.0,)})
    first = train(create_run(cfg, path, progress=False))
    (path / "holdout.json").unlink()
    again = train(open_run(path, progress=False))
    assert again.holdout_return_mean == pytest.approx(first.holdout_return_mean)
    assert json.loads((path / "config.json").read_text())["summary"]["holdout_return_mean"] == again.holdout_return_mean


def test_mpc_with_every_episode_ended_has_nothing_to_plan() -> None:
    from pimbrl.control.mpc import GradientMPC
    from pimbrl.control.plant import make_plant

    task = task_of(PENDULUM, {})
    mpc = GradientMPC(make_plant(task.physics), 5, 2, 0.1, 2, 200)
    action = mpc(task.validation_initial_states(2), np.full(2, 200, dtype=np.int64))
    assert action.shape == (2, 1) and mpc.transitions == 0


def test_an_arm_may_run_its_own_seeds_and_a_tuning_candidate_may_not_run_fewer(tmp_path) -> None:
    from pimbrl.experiments.engine import plan_study

    base = {"name": "s", "systems": ["pendulum"], "seeds": [0, 1, 2], "overrides": {"total_steps": 300}}
    methods = {"mfrl": {"method": "mfrl"}, "mpc": {"method": "mpc", "seeds": [0]}}
    spec = parse_spec({**base, "methods": methods}, where="s.yaml")
    assert spec.seeds_of("mfrl") == (0, 1, 2) and spec.seeds_of("mpc") == (0,)
    runs = plan_study(spec, tmp_path)
    assert sorted((r.arm, r.seed) for r in runs) == [("mfrl", 0), ("mfrl", 1), ("mfrl", 2), ("mpc", 0)]
    with pytest.raises(ConfigError, match=r"s\.yaml: arm mpc: seed 0 is given twice"):
        parse_spec({**base, "methods": {"mpc": {"method": "mpc", "seeds": [0, 0]}}}, where="s.yaml")
    arms = _tuning_spec({})["methods"]
    arms["pimbrl-b"] = {**arms["pimbrl-b"], "seeds": [0]}
    tuning = {"mfrl": ["mfrl-a", "mfrl-b"], "pimbrl": ["pimbrl-a", "pimbrl-b"]}
    with pytest.raises(ConfigError, match=r"unequal numbers of seeds \(1, 2\)"):
        parse_spec({**_tuning_spec(tuning), "methods": arms}, where="t.yaml")
