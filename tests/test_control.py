"""Control that knows the physics: feedback floors, gradient MPC, DPC, identification, and their runs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.control.base import play, task_of
from pimbrl.control.dpc import DPCPolicy, DPCTrainer
from pimbrl.control.feedback import LQR, declared_feedback, make_feedback, riccati_gain, tune_gain
from pimbrl.control.identify import collect_random, identify_coefficients
from pimbrl.control.mpc import GradientMPC
from pimbrl.control.plant import make_plant
from pimbrl.training import resolve_config
from pimbrl.training.loop import create_run, open_run, train

PENDULUM = "pimbrl/Pendulum-v0"
BURGERS = "pimbrl/Burgers-v0"
CARTPOLE = "pimbrl/CartPole-v0"


class Zero:
    """No control (a controller's interface; what the floors must beat)."""

    transitions = 0

    def __init__(self, dim: int) -> None:
        self.dim = dim

    def reset(self, batch: int) -> None:
        pass

    def __call__(self, states: np.ndarray, k: np.ndarray) -> np.ndarray:
        return np.zeros((len(states), self.dim))


# ----------------------------------------------------------------------------- feedback floors
def test_each_builtin_system_declares_its_floor() -> None:
    kinds = {env: declared_feedback(env, task_of(env, {}).physics)[0] for env in (PENDULUM, BURGERS, CARTPOLE)}
    assert kinds == {PENDULUM: "energy-lqr", BURGERS: "proportional", CARTPOLE: "lqr"}
    with pytest.raises(ValueError, match="unknown feedback 'pid'"):
        declared_feedback(PENDULUM, task_of(PENDULUM, {}).physics, "pid")


def test_lqr_balances_the_cartpole_and_energy_pumping_swings_the_pendulum_up() -> None:
    cart = task_of(CARTPOLE, {})
    states = cart.validation_initial_states(8)
    lqr = make_feedback(cart, "lqr", 0.1, {"q": (1.0, 1.0, 10.0, 1.0)})
    assert play(CARTPOLE, {}, lqr, states).returns.tolist() == [200.0] * 8
    assert play(CARTPOLE, {}, Zero(1), states).mean < 50
    pend = task_of(PENDULUM, {})
    states = pend.validation_initial_states(8)
    swing = play(PENDULUM, {}, make_feedback(pend, "energy-lqr", 0.5), states)
    none = play(PENDULUM, {}, Zero(1), states)
    assert swing.mean > none.mean + 300  # measured: about -140 against -600 and below
    assert swing.mean > -200


def test_proportional_feedback_averages_the_observation_under_each_actuator() -> None:
    task = task_of(BURGERS, {})
    fb = make_feedback(task, "proportional", 2.0)
    u = task.validation_initial_states(3)
    k = np.zeros(3, dtype=np.int64)
    obs = task.observe(u, k).astype(np.float64)
    shapes = np.asarray(task.physics.actuator_shapes)
    expected = -2.0 * obs @ (shapes / shapes.sum(1, keepdims=True)).T
    np.testing.assert_allclose(fb(u, k), np.clip(expected, task.physics.action_low, task.physics.action_high), rtol=1e-12)
    with pytest.raises(ValueError, match="PDE systems with localised actuators"):
        make_feedback(task_of(PENDULUM, {}), "proportional", 1.0)


def test_riccati_gain_stabilises_and_refuses_what_cannot_be_stabilised() -> None:
    a = np.array([[1.1, 0.1], [0.0, 0.9]])
    b = np.array([[0.0], [1.0]])
    k = riccati_gain(a, b, np.eye(2), np.eye(1))
    assert np.max(np.abs(np.linalg.eigvals(a - b @ k))) < 1.0
    with pytest.raises(ValueError, match="not stabilisable"):
        riccati_gain(np.array([[1.5]]), np.array([[0.0]]), np.eye(1), np.eye(1))


def test_lqr_linearises_the_systems_own_step() -> None:
    cart = task_of(CARTPOLE, {}).physics
    lqr = LQR(cart, np.eye(4), np.eye(1))
    # the closed loop of the linearised step is stable: its spectral radius is below one
    from pimbrl.control.feedback import linearise

    a, b = linearise(cart, np.zeros(4), np.zeros(1))
    assert np.allclose(a[0], [1.0, cart.dt, 0.0, 0.0])  # x' = x + dt x_dot (explicit Euler)
    assert np.max(np.abs(np.linalg.eigvals(a - b @ lqr.k))) < 1.0


def test_the_gain_is_tuned_on_validation_draws_never_on_test_states(monkeypatch) -> None:
    task = task_of(BURGERS, {})

    def forbidden(*args, **kwargs):
        raise AssertionError("the test states were read while tuning")

    monkeypatch.setattr(type(task), "test_initial_states", forbidden)
    states = task.validation_initial_states(4)
    best, scores, steps = tune_gain(BURGERS, {}, task, "proportional", (0.0, 1.0, 5.0), states)
    assert [g for g, _ in scores] == [0.0, 1.0, 5.0]
    assert best == max(scores, key=lambda s: s[1])[0] and best > 0
    assert steps == 3 * 4 * task.max_episode_steps


# ----------------------------------------------------------------------------- MPC
def _first_row_blows_up(step):
    """``step`` (a plant's) with the first row of every batch blown up: its next state NaN, its reward kept."""

    def blowing_up(u, a, k):
        u_next, r = step(u, a, k)
        row = torch.ones(len(u), 1, dtype=u.dtype)
        row[0] = float("nan")
        return u_next * row, r

    return blowing_up


@pytest.mark.slow
def test_mpc_plans_each_state_independently_of_its_batch() -> None:
    task = task_of(PENDULUM, {})
    plant = make_plant(task.physics)
    states = task.validation_initial_states(3)
    k = np.zeros(3, dtype=np.int64)
    together = GradientMPC(plant, 10, 3, 0.1, 5, 200)(states, k)
    alone = GradientMPC(plant, 10, 3, 0.1, 5, 200)(states[1:2], k[1:2])
    np.testing.assert_allclose(together[1:2], alone, atol=1e-12)


def test_mpc_warm_starts_from_its_shifted_plan_and_counts_its_scheme_steps() -> None:
    task = task_of(PENDULUM, {})
    mpc = GradientMPC(make_plant(task.physics), 6, 2, 0.1, 4, 200)
    states = task.validation_initial_states(2)
    mpc(states, np.zeros(2, dtype=np.int64))
    assert mpc.transitions == 4 * 6 * 2  # first step: first_iterations x horizon x states
    plan = mpc.plan.clone()
    assert torch.equal(plan[:, -1], plan[:, -2])  # shifted, the last action repeated
    mpc(states, np.ones(2, dtype=np.int64))
    assert mpc.transitions == 4 * 6 * 2 + 2 * 6 * 2


def test_mpc_simulates_nothing_past_the_episodes_end_and_plans_as_if_it_did() -> None:
    task = task_of(PENDULUM, {})
    plant = make_plant(task.physics)
    states = task.validation_initial_states(2)
    near_end = np.full(2, 197, dtype=np.int64)  # 3 steps left of 200
    cut = GradientMPC(plant, 10, 3, 0.1, 5, 200)
    action = cut(states, near_end)
    assert cut.transitions == 3 * 3 * 2  # iterations x the 3 steps left x states
    # the same plan as an episode long enough to simulate the whole horizon, with the rewards past 200 not counted
    long = GradientMPC(plant, 10, 3, 0.1, 5, 10_000)
    long.episode_steps = 200
    long.span = lambda k0: 10  # type: ignore[method-assign]  # the old objective: simulate on, count nothing
    np.testing.assert_allclose(action, long(states, near_end), atol=1e-12)


def test_mpc_counts_the_decisions_on_which_the_scheme_blew_up() -> None:
    """MPC keeps a blown-up row's last finite plan (its action stays finite); the decisions so made are counted."""
    task = task_of(PENDULUM, {})
    plant = make_plant(task.physics)
    step = plant.step
    blowing_up = _first_row_blows_up(step)
    states = task.validation_initial_states(3)
    plant.step = blowing_up  # type: ignore[method-assign]
    mpc = GradientMPC(plant, 3, 2, 0.1, 2, 200)
    result = play(PENDULUM, {}, mpc, states)
    # row 0 at 199 of the episode's 200 control steps (the last plans one step, whose reward precedes the NaN
    # state), rows 1 and 2 never
    assert result.blown_up == mpc.blown_up == 199
    assert np.all(np.isfinite(result.returns))
    plant.step = step  # type: ignore[method-assign]
    assert play(PENDULUM, {}, GradientMPC(plant, 3, 2, 0.1, 2, 200), states).blown_up == 0


@pytest.mark.slow
def test_mpc_with_the_known_equation_beats_the_pendulums_floor_on_validation_states() -> None:
    task = task_of(PENDULUM, {})
    states = task.validation_initial_states(6)
    mpc = play(PENDULUM, {}, GradientMPC(make_plant(task.physics), 20, 5, 0.1, 30, 200), states)
    floor = play(PENDULUM, {}, make_feedback(task, "energy-lqr", 0.5), states)
    assert mpc.mean > floor.mean - 5  # measured on the test states: -148.5 against -156.1
    # the first step's 30 iterations, then 5 per step over the horizon, cut at the episode's end (200 steps)
    assert mpc.scheme_transitions == 6 * (30 * 20 + sum(5 * min(20, 200 - k) for k in range(1, 200)))
    assert mpc.inference_s_per_step > 0


def test_identification_recovers_a_coefficient_from_a_wrong_prior() -> None:
    task = task_of(PENDULUM, {"m": 1.3})
    prior = task.physics.with_coefficients(m=1.0)  # 30 % wrong
    data = collect_random(PENDULUM, {"m": 1.3}, 300, seed=0)
    values = identify_coefficients(prior, {"m": None}, data, 1, 300, 128, 0.05, seed=0)
    assert abs(values["m"] - 1.3) / 1.3 < 0.05


# ----------------------------------------------------------------------------- DPC
def test_dpc_learns_through_the_scheme_and_keeps_the_best_policy_on_validation() -> None:
    task = task_of(PENDULUM, {})
    plant = make_plant(task.physics)
    policy = DPCPolicy(plant, (32, 32), seed=0)
    trainer = DPCTrainer(policy, task, horizon=10, batch_size=16, lr=3e-3, continue_fraction=0.5, seed=0)
    u0 = torch.as_tensor(task.validation_initial_states(32))

    def predicted() -> float:  # the scheme's 10-step return of the policy from fixed states
        with torch.no_grad():
            u, k, total = u0, torch.zeros(32, dtype=torch.int64), 0.0
            for _ in range(10):
                u, r = plant.step(u, policy.forward(u, k), k)
                k, total = k + 1, total + r
            return float(total.mean())

    before = predicted()
    for _ in range(61):
        trainer.step()
    assert predicted() > before + 1.0
    scores = iter([(-300.0, 10), (-100.0, 10), (-200.0, 10)])
    for _ in range(3):
        trainer.validate(lambda p: next(scores))
    assert trainer.best_return == -100.0 and trainer.best_step == 61 and trainer.validation_transitions == 30
    state = trainer.state_dict()
    again = DPCTrainer(DPCPolicy(plant, (32, 32), seed=1), task, 10, 16, 3e-3, 0.5, seed=0)
    again.load_state_dict(state)
    assert again.step() == trainer.step()  # the same next step: policy, optimiser, pool and stream restored


def test_dpc_whose_every_gradient_step_was_skipped_stops_at_its_validation_with_the_fix() -> None:
    """A scheme that blows up on some row of every batch gives no finite gradient: DPC says so, not a result."""
    task = task_of(BURGERS, {})
    plant = make_plant(task.physics)
    step = plant.step
    blowing_up = _first_row_blows_up(step)
    plant.step = blowing_up  # type: ignore[method-assign]
    trainer = DPCTrainer(DPCPolicy(plant, (16,), seed=0), task, horizon=3, batch_size=4, lr=1e-3, continue_fraction=0.5, seed=0)
    before = [p.detach().clone() for p in trainer.policy.parameters()]
    for _ in range(3):
        trainer.step()
    assert trainer.skipped == 3 and all(torch.equal(p, q) for p, q in zip(before, trainer.policy.parameters(), strict=True))
    with pytest.raises(FloatingPointError, match=r"all 3 gradient steps so far were skipped.*--model.n-intermediate"):
        trainer.validate(lambda p: (-1.0, 1))
    with pytest.raises(FloatingPointError, match="all 3 gradient steps"):  # as a resumed run checks after its last step
        trainer.check_applied()
    plant.step = step  # type: ignore[method-assign]
    trainer.step()  # one step applied: validation goes on
    assert trainer.validate(lambda p: (-1.0, 1)) == -1.0


# ----------------------------------------------------------------------------- runs
def _cfg(env: str, method: str, **overrides):
    return resolve_config(env, {"method": method, "eval_episodes": 6, **overrides})


def test_a_feedback_run_writes_the_run_directory_of_any_run(tmp_path) -> None:
    path = tmp_path / "fb"
    summary = train(create_run(_cfg(BURGERS, "feedback", **{"model.gains": (0.5, 2.0)}), path, progress=False))
    rows = (path / "evaluations.csv").read_text().splitlines()
    assert rows[0].startswith("step,return_mean") and len(rows) == 2 and rows[1].startswith("0,")
    payload = json.loads((path / "config.json").read_text())
    assert payload["status"] == "finished"
    s = payload["summary"]
    assert s["real_transitions"] == 0 and s["scheme_transitions"] == 0
    assert s["validation_transitions"] == 2 * 20 * 60  # two gains on 20 validation episodes of 60 steps
    assert s["inference_s_per_step"] > 0 and s["final_return_mean"] == summary.final_return_mean
    control = json.loads((path / "control.json").read_text())
    assert control["feedback"]["gain"] in (0.5, 2.0) and len(control["feedback"]["validation"]) == 2


@pytest.mark.slow
def test_an_mpc_run_resumes_its_test_chunks_and_gives_the_uninterrupted_result(tmp_path, monkeypatch) -> None:
    cfg = _cfg(PENDULUM, "mpc", **{"model.horizon": 5, "model.iterations": 2, "model.first_iterations": 3, "model.batch": 2})
    whole = train(create_run(cfg, tmp_path / "whole", progress=False))
    import pimbrl.training.control_run as control_run

    real_play = control_run.play
    calls = {"n": 0}

    def dying(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real_play(*args, **kwargs)

    monkeypatch.setattr(control_run, "play", dying)
    with pytest.raises(KeyboardInterrupt):
        train(create_run(cfg, tmp_path / "cut", progress=False))
    state = json.loads((tmp_path / "cut" / "control.json").read_text())
    assert len(state["test"]["chunks"]) == 1 and not state.get("done")
    monkeypatch.setattr(control_run, "play", real_play)
    resumed = train(open_run(tmp_path / "cut", progress=False))
    assert resumed.final_return_mean == pytest.approx(whole.final_return_mean, abs=1e-9)
    assert resumed.scheme_transitions == whole.scheme_transitions
    assert len((tmp_path / "cut" / "evaluations.csv").read_text().splitlines()) == 2


@pytest.mark.slow
def test_an_mpc_run_with_a_wrong_prior_identifies_the_coefficient_first_and_counts_those_real_steps(tmp_path) -> None:
    cfg = _cfg(
        PENDULUM,
        "mpc",
        env_kwargs={"m": 1.3},
        **{
            "model.prior": {"m": 1.0},
            "learn.coefficients": {"m": None},
            "learn.lr": 0.05,
            "identify.steps": 300,
            "identify.iterations": 300,
            "model.horizon": 5,
            "model.iterations": 2,
        },
    )
    summary = train(create_run(cfg, tmp_path / "id", progress=False))
    assert summary.real_transitions == 300 and summary.steps == 300
    ident = json.loads((tmp_path / "id" / "control.json").read_text())["identify"]
    assert ident["prior"] == {"m": 1.0} and ident["true"] == {"m": 1.3}
    assert abs(ident["identified"]["m"] - 1.3) < 0.065


def test_control_methods_refuse_what_they_cannot_do_in_one_line() -> None:
    with pytest.raises(ConfigError, match="cartpole's reward has none"):
        resolve_config(CARTPOLE, {"method": "mpc"})
    with pytest.raises(ConfigError, match="identifies coefficients only"):
        resolve_config(BURGERS, {"method": "dpc", "learn.correction": True})
    with pytest.raises(ConfigError, match="has no coefficient 'mass'"):
        resolve_config(PENDULUM, {"method": "mpc", "model.prior": {"mass": 1.0}})
    with pytest.raises(ConfigError, match="validation pool holds 50"):
        resolve_config("pimbrl/KuramotoSivashinsky-v0", {"method": "feedback", "model.validation_episodes": 60})
    with pytest.raises(ConfigError, match=r"--agent\.policy-delay is a setting of the RL methods. training"):
        resolve_config(PENDULUM, {"method": "feedback", "agent.policy_delay": 3})
    with pytest.raises(ConfigError, match="--utd is a setting of the RL methods' training, not of --method mpc"):
        resolve_config(PENDULUM, {"method": "mpc", "utd": 5})
    with pytest.raises(ConfigError, match="--agent does nothing with --method dpc"):
        resolve_config(PENDULUM, {"method": "dpc", "agent": "sac"})
    # identification must start from what the controller believes, never from the environment's truth
    with pytest.raises(ConfigError, match="would start from the environment's true value"):
        resolve_config(BURGERS, {"method": "mpc", "env_kwargs": {"nu": 0.013}, "learn.coefficients": {"nu": None}})
    with pytest.raises(ConfigError, match=r"--identify\.\* does nothing without --learn\.coefficients"):
        resolve_config(BURGERS, {"method": "mpc", "identify.steps": 500})
    with pytest.raises(ConfigError, match=r"physics prior: .*nu"):
        resolve_config(BURGERS, {"method": "mpc", "model.prior": {"nu": -1.0}})
    with pytest.raises(ConfigError, match="energy-lqr is the pendulum's floor"):
        resolve_config(BURGERS, {"method": "feedback", "model.kind": "energy-lqr"})
    with pytest.raises(ConfigError, match="proportional feedback is for PDE systems"):
        resolve_config(PENDULUM, {"method": "feedback", "model.kind": "proportional"})


def test_pimbrl_eval_and_extend_of_a_control_run_say_what_it_is(tmp_path, capsys) -> None:
    path = tmp_path / "fb"
    train(create_run(_cfg(PENDULUM, "feedback", **{"model.gains": (0.5,)}), path, progress=False))
    assert main(["eval", str(path)]) == 2
    assert "has no agent to evaluate" in capsys.readouterr().err
    assert main(["resume", str(path), "--total-steps", "5000"]) == 2
    assert "has no step budget to raise" in capsys.readouterr().err
    assert json.loads((path / "config.json").read_text())["status"] == "finished"


@pytest.mark.slow
def test_compare_and_the_study_report_carry_a_controllers_costs(tmp_path, capsys) -> None:
    run_dir = tmp_path / "cmp"
    args = ["compare", "pendulum", "--methods", "feedback", "--seeds", "1", "--run-dir", str(run_dir), "--jobs", "1"]
    assert main([*args, "--", "--model.gains", "0.5", "--model.validation-episodes", "2", "--eval-episodes", "2"]) == 0
    capsys.readouterr()
    record = json.loads((run_dir / "record.json").read_text())
    (entry,) = record["runs"]
    assert entry["method"] == "feedback" and entry["agent"] is None and entry["real_transitions"] == 0
    assert entry["validation_transitions"] == 2 * 200 and entry["inference_s_per_step"] > 0
    assert entry["feedback"]["kind"] == "energy-lqr" and entry["feedback"]["gain"] == 0.5  # the choice, in the record
    assert [v["gain"] for v in entry["feedback"]["validation"]] == [0.5]
    assert main(["study", "report", str(run_dir / "study.yaml")]) == 0
    out = capsys.readouterr().out
    assert "| validation transitions | inference (ms per control step) |" in out
    assert "| feedback | 1 |" in out and "| 400 |" in out


def test_a_ratio_of_median_steps_to_a_controller_that_needs_none_is_undefined_not_a_crash() -> None:
    from pimbrl.experiments.report import _median_ratio, _ratio_text

    identified = {"median": 600, "at_most": None, "above": None}
    known = {"median": 0, "at_most": None, "above": None}
    assert _ratio_text(_median_ratio(identified, known)) == "unknown"
    assert _median_ratio(known, identified) == {"value": 0.0, "bound": "="}
    never = {"median": None, "at_most": None, "above": 3000}  # a model-free arm that never reached it
    assert _median_ratio(known, never) == {"value": 0.0, "bound": "="} and _ratio_text(_median_ratio(known, never)) == "0.00"
