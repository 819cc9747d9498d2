"""A physics prior that can be wrong, and coefficients learned from labelled transitions (the inverse problem)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.config import ConfigError, parse_learned, parse_prior
from pimbrl.models import ModelTrainer, PhysicsResidual, make_model
from pimbrl.models.coefficients import LearnedCoefficients
from pimbrl.systems import Burgers, CartPole, KuramotoSivashinsky, Pendulum, ks_initial_state_pool
from pimbrl.training import RunDirectory, resolve_config

from .settings import DYNA_SMOKE_SETTINGS, ENV_IDS, POOL_KWARGS, SMALL_MODEL_SETTINGS, TINY_SETTINGS
from .test_dyna import DYNA_SMOKE, SMALL_MODEL
from .test_training import TINY


def test_specifications_parse_and_bad_ones_say_what_is_wrong() -> None:
    assert parse_prior("") == {}
    assert parse_prior("nu=0.007, damping=0") == {"nu": 0.007, "damping": 0.0}
    assert parse_learned("nu, damping:0:1") == {"nu": None, "damping": (0.0, 1.0)}
    with pytest.raises(ConfigError, match="each item is name=value"):
        parse_prior("nu")
    with pytest.raises(ConfigError, match="'abc' is not a number"):
        parse_prior("nu=abc")
    with pytest.raises(ConfigError, match="need low < high"):
        parse_learned("nu:1:0")
    with pytest.raises(ConfigError, match="each item is name or name:low:high"):
        parse_learned("nu:1")


def test_learned_coefficients_start_at_the_prior_and_respect_their_range() -> None:
    prior = Burgers(nu=0.007)
    learned = LearnedCoefficients(prior, {"nu": None, "damping": (0.0, 1.0)})
    with pytest.raises(ValueError, match=r"prior's value 0.0 lies outside its range \[0.1, 1.0\]"):
        LearnedCoefficients(prior, {"damping": (0.1, 1.0)})  # the prior's damping is 0
    start = learned.current()
    assert start["nu"] == pytest.approx(0.007, rel=1e-12)
    assert start["damping"] == 0.0  # the prior is the range's edge: it starts there
    with torch.no_grad():
        learned.theta.fill_(50.0)
    learned.project()
    assert learned.current()["damping"] == 1.0
    with torch.no_grad():
        learned.theta.fill_(-3.0)
    learned.project()
    assert learned.current()["damping"] == 0.0
    assert LearnedCoefficients(Pendulum(), {"m": None, "damping": (0.0, 1.0)}).current() == {"m": 1.0, "damping": 0.0}
    with pytest.raises(ValueError, match="is a linear operator on a PDE's grid; pendulum is an ODE system"):
        LearnedCoefficients(Pendulum(), {"correction": None})
    with pytest.raises(ValueError, match="has no coefficient 'nuu'"):
        LearnedCoefficients(prior, {"nuu": None})


def test_learned_residual_at_the_true_values_equals_the_fixed_one() -> None:
    physics = Burgers()
    fixed = PhysicsResidual(physics, 5)
    learned = PhysicsResidual(physics, 5, learned={"nu": None, "convection": None})
    rng = np.random.default_rng(0)
    u = torch.as_tensor(0.3 + 0.05 * rng.normal(size=(4, physics.n)))
    a = torch.as_tensor(rng.uniform(physics.action_low, physics.action_high, size=(4, 2)))
    torch.testing.assert_close(learned.rollout(u, a), fixed.rollout(u, a), rtol=1e-10, atol=1e-12)


def test_the_physics_loss_uses_the_coefficients_without_moving_them() -> None:
    physics = KuramotoSivashinsky()
    residual = PhysicsResidual(physics, 5, learned={"convection": None})
    u = torch.as_tensor(ks_initial_state_pool("train").states[:4], dtype=torch.float32)
    path = (residual.rollout(u.double(), torch.zeros(4, 4, dtype=torch.float64)).float() + 0.01).requires_grad_()
    residual.loss(u, path, torch.zeros(4, 4)).backward()
    assert residual.coefficients is not None
    assert path.grad is not None and float(path.grad.abs().sum()) > 0  # the loss pulls the model's states
    assert residual.coefficients.theta.grad is None  # but not the coefficients


def _fit(residual: PhysicsResidual, u, a, u1, steps: int) -> None:
    assert residual.coefficients is not None
    optimizer = torch.optim.Adam(residual.coefficients.parameters(), lr=1e-2)
    states, actions, nxt = (torch.as_tensor(x, dtype=torch.float32) for x in (u, a, u1))
    for _ in range(steps):
        loss = residual.coefficient_loss(states, actions, nxt)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        residual.coefficients.project()


@pytest.mark.parametrize(
    ("name", "true", "prior", "bounds"),
    [("convection", 1.3, 1.0, None), ("convection", 0.7, 1.0, None), ("damping", 0.1, 0.0, (0.0, 1.0))],
)
@pytest.mark.slow  # several seconds: the whole suite runs it, the fast tier does not
def test_a_wrong_or_missing_ks_coefficient_is_identified_from_labelled_transitions(
    name: str, true: float, prior: float, bounds: tuple[float, float] | None
) -> None:
    """KS with the convection term 30 % off, or a damping term the prior lacks: identified within 1 %."""
    system = KuramotoSivashinsky(**{name: true})
    rng = np.random.default_rng(0)
    u = ks_initial_state_pool("train").states[rng.integers(0, 500, 256)]
    a = rng.uniform(-0.5, 0.5, size=(256, 4))
    u1, _ = system.advance(u, a, np.zeros(256, dtype=np.int64))
    residual = PhysicsResidual(system.with_coefficients(**{name: prior}), 5, learned={name: bounds})
    _fit(residual, u, a, u1, 150)
    assert residual.coefficients is not None
    assert residual.coefficients.current()[name] == pytest.approx(true, rel=0.01)


def test_trainer_fits_coefficients_on_labelled_batches_and_checkpoints_them() -> None:
    from pimbrl.models import TransitionData

    system = Burgers(nu=0.013)
    prior = system.with_coefficients(nu=0.01)
    rng = np.random.default_rng(1)
    u = 0.3 + 0.05 * rng.normal(size=(64, system.n))
    a = rng.uniform(system.action_low, system.action_high, size=(64, 2))
    u1, _ = system.advance(u, a, np.zeros(64, dtype=np.int64))
    data = TransitionData(*(torch.as_tensor(x, dtype=torch.float32) for x in (u, a, u1)))
    trainer = ModelTrainer(make_model(prior), PhysicsResidual(prior, 5, learned={"nu": None}), coefficient_lr=2e-2)
    metrics = trainer.fit(30, 32, np.random.default_rng(0), labelled=data)
    assert metrics["model/coefficient_loss"] > 0
    assert trainer.coefficients is not None
    moved = trainer.coefficients.current()["nu"]
    assert abs(moved - 0.013) < abs(0.01 - 0.013) / 2  # well on its way from the prior to the truth
    again = ModelTrainer(make_model(prior), PhysicsResidual(prior, 5, learned={"nu": None}))
    again.load_state_dict(trainer.state_dict())
    assert again.coefficients is not None
    assert again.coefficients.current() == trainer.coefficients.current()


def test_configuration_errors_name_the_problem() -> None:
    ok = resolve_config("pimbrl/Burgers-v0", {"method": "pimbrl", "learn.coefficients": {"nu": None}})
    assert ok.method.learn.coefficients == {"nu": None} and ok.method.learn.ranges() == {"nu": None}
    with pytest.raises(ConfigError, match=r"has no coefficient 'nuu' \(did you mean 'nu'\?\)"):
        resolve_config("pimbrl/Burgers-v0", {"method": "pimbrl", "learn.coefficients": {"nuu": None}})
    with pytest.raises(ConfigError, match=r"model.prior: pimbrl/Burgers-v0 has no coefficient 'm'"):
        resolve_config("pimbrl/Burgers-v0", {"method": "mbrl", "model.prior": {"m": 1.0}})
    with pytest.raises(ConfigError, match="needs the etd scheme"):
        resolve_config("pimbrl/Burgers-v0", {"method": "pimbrl", "learn.coefficients": {"nu": None}, "model.scheme": "solver"})


def test_learned_coefficient_flags_are_refused_where_they_do_nothing(tmp_path) -> None:
    assert main(["train", "burgers", "--method", "mbrl", "--learn.coefficients", "nu", "--run-dir", str(tmp_path / "a")]) == 2
    assert main(["train", "pendulum", "--method", "mbrl", "--learn.coefficients", "m", "--run-dir", str(tmp_path / "b")]) == 2
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def _train_with_wrong_prior(run, env: str, true: dict, prior: str, learn: str) -> dict:
    """A small pimbrl run of ``env`` with coefficients ``true``, the model side held to ``prior`` and learning
    ``learn``; returns its ``coefficients.json``."""
    args = [
        "train", env, "--method", "pimbrl", "--run-dir", str(run), *DYNA_SMOKE[env], *TINY, *SMALL_MODEL,
        "--env-kwargs", json.dumps(true), "--model.prior", prior, "--learn.coefficients", learn,
        "--learn.lr", "0.05",
    ]  # fmt: skip
    assert main(args) == 0
    return json.loads((run / "coefficients.json").read_text())


@pytest.mark.slow
def test_a_run_with_a_wrong_prior_learns_the_coefficient_and_writes_coefficients_json(tmp_path) -> None:
    run = tmp_path / "run"
    report = _train_with_wrong_prior(run, "burgers", {"nu": 0.013}, "nu=0.01", "nu")
    assert report["environment"]["nu"] == 0.013 and report["prior"]["nu"] == 0.01
    assert report["learned"] == {"nu": None}
    history = report["history"]
    assert len(history) >= 2 and history[0]["step"] < history[-1]["step"]
    assert abs(report["current"]["nu"] - 0.013) < abs(0.01 - 0.013) / 2
    assert report["current"]["nu"] == history[-1]["nu"]
    from pimbrl.training import RunDirectory

    last = RunDirectory(run).metrics([]).read()[-1]
    assert float(last["coef/nu"]) == pytest.approx(report["current"]["nu"], rel=1e-6)
    assert float(last["model/coefficient_loss"]) > 0


@pytest.mark.slow
def test_the_correction_finds_a_term_of_a_form_the_prior_lacks_and_stays_small_where_nothing_is_missing() -> None:
    """KS whose true system has a drift -0.2 u_x that no coefficient of the prior names: the correction's
    first-derivative coefficient converges to -0.2; with the exact prior it stays near zero."""
    rng = np.random.default_rng(0)
    u = ks_initial_state_pool("train").states[rng.integers(0, 500, 256)]
    a = rng.uniform(-0.5, 0.5, size=(256, 4))
    for drift in (0.2, 0.0):
        u1, _ = KuramotoSivashinsky(drift=drift).advance(u, a, np.zeros(256, dtype=np.int64))
        residual = PhysicsResidual(KuramotoSivashinsky(), 5, learned={"correction": None})
        _fit(residual, u, a, u1, 150)
        assert residual.coefficients is not None
        found = residual.coefficients.current()
        assert set(found) == {"correction_u", "correction_u_x", "correction_u_xx", "correction_u_xxx", "correction_u_xxxx"}
        if drift:
            assert found["correction_u_x"] == pytest.approx(-drift, rel=0.05)
        else:
            assert abs(found["correction_u_x"]) < 0.01 and abs(found["correction_u"]) < 0.01


def test_the_correction_is_a_pde_option_with_a_clear_error_elsewhere() -> None:
    assert resolve_config("pimbrl/Burgers-v0", {"method": "pimbrl", "learn.coefficients": {"nu": None}, "learn.correction": True})
    with pytest.raises(ConfigError, match=r"--learn.correction applies to the PDE systems .*, not pimbrl/CartPole-v0"):
        resolve_config("pimbrl/CartPole-v0", {"method": "pimbrl", "learn.correction": True})
    with pytest.raises(ConfigError, match="correction-penalty applies to the PDE systems"):
        resolve_config(
            "pimbrl/CartPole-v0",
            {"method": "pimbrl", "learn.coefficients": {"masspole": None}, "learn.correction_penalty": 1.0},
        )
    with pytest.raises(ValueError, match="takes no range"):
        LearnedCoefficients(Burgers(), {"correction": (0.0, 1.0)})


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"env_kwargs": {"nu": 0.013}, "learn.coefficients": {"nu": None}}, "nu would start from the environment's true value"),
        ({"learn.lr": 0.05}, "--learn.lr does nothing without --learn.coefficients"),
        ({"learn.coefficients": {"nu": None}, "learn.correction_penalty": 1.0}, "does nothing without --learn.correction true"),
        ({"learn.coefficients": {"nu": [0.1, 0.0]}}, re.escape("must be a mapping of coefficient names to null or [low, high]")),
        ({"model.prior": {"nu": -1}}, re.escape("physics prior: burgers: nu must be a finite number in [0, 1], got -1.0")),
        ({"model.prior": {"damping": 0.5}, "learn.coefficients": {"damping": [0, 0.1]}}, "lies outside its range"),
        ({"model.prior": "nu=0.01"}, re.escape('model.prior takes a mapping, e.g. {"nu": 0.01}')),
    ],
)
def test_every_coefficient_problem_is_refused_before_anything_runs(fields: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        resolve_config("pimbrl/Burgers-v0", {"method": "pimbrl", **fields})


def test_a_positive_free_coefficient_cannot_cross_zero() -> None:
    learned = LearnedCoefficients(Burgers(), {"nu": None})
    with torch.no_grad():
        learned.theta.fill_(-5.0)  # nu = 0.01 - 0.05 < 0
    learned.project()
    assert learned.current()["nu"] == pytest.approx(1e-4)  # 1 % of the prior


@pytest.mark.slow  # several seconds: the whole suite runs it, the fast tier does not
def test_a_run_with_learned_coefficients_continues_bit_for_bit(tmp_path) -> None:
    """Trained to an episode boundary, then extended: the same files and coefficients as one longer run."""
    args = [
        *DYNA_SMOKE["burgers"], *TINY, *SMALL_MODEL, "--method", "pimbrl",
        "--env-kwargs", '{"nu": 0.013}', "--model.prior", "nu=0.01", "--learn.coefficients", "nu,correction",
    ]  # fmt: skip
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert main(["train", "burgers", "--run-dir", str(whole), *args]) == 0  # 180 steps: 3 episodes
    assert main(["train", "burgers", "--run-dir", str(cut), *args, "--steps", "120"]) == 0
    assert main(["resume", str(cut), "--total-steps", "180", "--quiet"]) == 0

    def table(path, name: str) -> list[dict]:
        d = RunDirectory(path)
        rows = (
            d.evaluations.read() if name == "evaluations" else d.episodes.read() if name == "episodes" else d.metrics([]).read()
        )
        return [{k: v for k, v in r.items() if "wall" not in k and "time/" not in k and "per_s" not in k} for r in rows]

    for name in ("evaluations", "episodes", "metrics"):
        assert table(whole, name) == table(cut, name), name
    history = [json.loads((p / "coefficients.json").read_text())["history"] for p in (whole, cut)]
    assert history[0] == history[1] and len(history[0]) >= 2


@pytest.mark.parametrize(
    ("system", "values"),
    [
        (Pendulum(damping=0.05), {"l": 1.2, "damping": 0.0}),
        (CartPole(pole_friction=0.01), {"masspole": 0.13, "cart_friction": 0.0}),
    ],
)
def test_ode_steps_with_tensor_coefficients_equal_the_float_ones_and_carry_their_gradient(system, values) -> None:
    rng = np.random.default_rng(3)
    u = torch.as_tensor(rng.uniform(-0.2, 0.2, size=(16, system.state_dim)))
    a = torch.as_tensor(rng.uniform(system.action_low, system.action_high, size=(16, 1)))
    tensors = {k: torch.tensor(v, dtype=torch.float64, requires_grad=True) for k, v in values.items()}
    stepped = system.with_coefficient_tensors(tensors).step(u, a)
    torch.testing.assert_close(stepped, system.with_coefficients(**values).step(u, a), rtol=1e-13, atol=1e-15)
    stepped.pow(2).sum().backward()
    # a term the float system skips at 0 (a friction, a damping) is computed for a tensor: it has a gradient
    assert all(t.grad is not None and float(t.grad) != 0.0 for t in tensors.values())
    with pytest.raises(ValueError, match="has no coefficient 'mass'"):
        system.with_coefficient_tensors({"mass": torch.tensor(1.0)})
    with pytest.raises(ValueError, match="only the ODE systems take them"):
        Burgers().with_coefficient_tensors({"nu": torch.tensor(0.01)})


@pytest.mark.parametrize(
    ("system", "prior", "learned"),
    [
        (Pendulum(l=1.3), {"l": 1.0}, {"l": None}),
        (Pendulum(l=0.7), {"l": 1.0}, {"l": None}),
        (Pendulum(damping=0.1), {}, {"damping": (0.0, 1.0)}),
        (CartPole(masspole=0.13), {"masspole": 0.1}, {"masspole": None}),
        (CartPole(pole_friction=0.002), {}, {"pole_friction": (0.0, 0.01)}),
    ],
)
def test_a_wrong_or_missing_ode_coefficient_is_identified_from_labelled_transitions(system, prior, learned) -> None:
    """Pendulum length 30 % off, a missing pendulum damping, Cart-Pole pole mass 30 % off, a missing pole friction."""
    rng = np.random.default_rng(0)
    box_low, box_high = system.admissible_box()
    u = rng.uniform(box_low, box_high, size=(256, system.state_dim)) * (0.5 if isinstance(system, CartPole) else 1.0)
    a = rng.uniform(system.action_low, system.action_high, size=(256, 1))
    u1, _ = system.advance(u, a, np.zeros(256, dtype=np.int64))
    start = system.with_coefficients(**prior)
    start = start.with_coefficients(**{name: 0.0 for name in learned if name not in prior})
    residual = PhysicsResidual(start, start.substeps, learned=learned)
    _fit(residual, u, a, u1, 300)
    assert residual.coefficients is not None
    (name,) = learned
    assert residual.coefficients.current()[name] == pytest.approx(getattr(system, name), rel=0.01)


@pytest.mark.slow
def test_a_pendulum_run_with_a_wrong_length_learns_it(tmp_path) -> None:
    run = tmp_path / "run"
    report = _train_with_wrong_prior(run, "pendulum", {"l": 1.3}, "l=1.0", "l")
    assert report["environment"]["l"] == 1.3 and report["prior"]["l"] == 1.0
    assert abs(report["current"]["l"] - 1.3) < 0.3 / 2  # well on its way from the prior to the truth
    # the model side judges imagined steps with the learned length (restored from the checkpoint here)
    from pimbrl.training import load_run

    loaded = load_run(run)
    assert loaded.model is not None
    assert loaded.model.model_env.physics.l == report["current"]["l"]


def test_a_free_coefficient_from_zero_that_cannot_be_negative_needs_a_range() -> None:
    with pytest.raises(ValueError, match=r"its prior is 0 and pendulum refuses negative values.*e\.g\. damping:0:1"):
        LearnedCoefficients(Pendulum(), {"damping": None})
    with pytest.raises(ConfigError, match=r"give it a range, e\.g\. pole_friction:0:1"):
        resolve_config("pimbrl/CartPole-v0", {"method": "pimbrl", "learn.coefficients": {"pole_friction": None}})
    assert LearnedCoefficients(Pendulum(), {"damping": (0.0, 1.0)}).current() == {"damping": 0.0}
    # a coefficient that may be negative (a drift) is learned free from 0
    assert LearnedCoefficients(Burgers(), {"drift": None}).current() == {"drift": 0.0}


# ---------------------------------------------------------------------- a learned actuator width on the model side
WIDTH_PRIOR, WIDTH_TRUE = 1 / 15, 0.0866667  # Burgers: the true actuators 30 % wider than the prior believes


def _burgers_width_data(n: int = 64) -> tuple:
    """Labelled Burgers transitions of a system whose actuators are 30 % wider than the prior's."""
    from pimbrl.models import TransitionData

    system = Burgers(actuator_width=WIDTH_TRUE)
    rng = np.random.default_rng(2)
    u = 0.3 + 0.05 * rng.normal(size=(n, system.n))
    a = rng.uniform(system.action_low, system.action_high, size=(n, 2))
    u1, _ = system.advance(u, a, np.zeros(n, dtype=np.int64))
    return TransitionData(*(torch.as_tensor(x, dtype=torch.float32) for x in (u, a, u1)))


def test_the_equivariant_models_forcing_input_follows_the_learned_width() -> None:
    prior = Burgers(actuator_width=WIDTH_PRIOR)
    model = make_model(prior, kind="equivariant")
    residual = PhysicsResidual(prior, 5, learned={"actuator_width": None})
    trainer = ModelTrainer(model, residual, coefficient_lr=2e-2)
    trainer.fit(20, 32, np.random.default_rng(0), labelled=_burgers_width_data())
    assert residual.coefficients is not None
    width = residual.coefficients.current()["actuator_width"]
    assert abs(width - WIDTH_TRUE) < abs(WIDTH_PRIOR - WIDTH_TRUE) / 2  # on its way to the truth
    expected = torch.as_tensor(prior.with_coefficients(actuator_width=width).actuator_shapes, dtype=torch.float32)
    shapes = model.get_buffer("shapes")
    assert torch.equal(shapes, expected)  # the current width, not the prior's
    assert not shapes.requires_grad  # the data loss never reaches the width
    assert all(p is not residual.coefficients.theta for p in model.parameters())
    with pytest.raises(ValueError, match=r"actuator shapes must have shape \(2, 150\), got \(3, 150\)"):
        model.set_actuator_shapes(np.ones((3, 150)))


def test_a_learned_coefficient_other_than_the_width_leaves_the_forcing_input_alone() -> None:
    prior = Burgers(nu=0.01)
    model = make_model(prior, kind="equivariant")
    before = model.get_buffer("shapes").clone()
    trainer = ModelTrainer(model, PhysicsResidual(prior, 5, learned={"nu": None}), coefficient_lr=2e-2)
    trainer.fit(5, 32, np.random.default_rng(0), labelled=_burgers_width_data())
    assert torch.equal(model.get_buffer("shapes"), before)


def test_a_range_with_values_the_physics_refuses_is_an_error() -> None:
    with pytest.raises(ValueError, match=r"learned coefficient nu: its range \[-1.0, 1.0\] admits a bad value .*nu must be"):
        LearnedCoefficients(Burgers(), {"nu": (-1.0, 1.0)})


def _ks_dyna(tmp_path, name: str):
    """The model side of a KS pimbrl run (equivariant model) whose prior's actuators are 30 % too narrow."""
    from pimbrl.training import build_run

    settings = {"method": "pimbrl", "env_kwargs": {**POOL_KWARGS, "actuator_width": 1.3}, "eval_episodes": 2,
                "model.prior": {"actuator_width": 1.0}, "learn.coefficients": {"actuator_width": None}, **TINY_SETTINGS}  # fmt: skip
    run = build_run(resolve_config(ENV_IDS["ks"], settings), RunDirectory(tmp_path / name), progress=False)
    assert run.model is not None
    return run.model


def test_imagined_rewards_and_a_resumed_model_side_use_the_learned_width(tmp_path, ks_states) -> None:
    """KS's reward holds ``mean(u f)``, so it depends on the actuator width: imagined rewards must use the
    learned one, also after the model side is restored from a checkpoint."""
    dyna = _ks_dyna(tmp_path, "a")
    residual = dyna.trainer.residual
    assert residual is not None and residual.coefficients is not None
    with torch.no_grad():
        residual.coefficients.theta.fill_(0.3)  # actuator_width = 1 + 1 * 0.3, as if fitted
    dyna.trainer.follow_coefficients()
    # as a model phase's fit does: the values go into the history (a run restored before any fit keeps the prior)
    dyna.coefficient_history.append({"step": 0, **residual.coefficients.current(), "loss": 0.0})
    restored_before_fit = _ks_dyna(tmp_path, "c")
    restored = _ks_dyna(tmp_path, "b")
    restored.load_state_dict(dyna.state_dict())
    assert restored.trainer.coefficients is not None
    assert restored.trainer.coefficients.current()["actuator_width"] == pytest.approx(1.3)
    assert torch.equal(restored.model.get_buffer("shapes"), dyna.model.get_buffer("shapes"))
    assert restored.model_env.physics.coefficient_values()["actuator_width"] == pytest.approx(1.3)
    state_before_fit = dyna.state_dict()
    state_before_fit["coefficient_history"] = []
    restored_before_fit.load_state_dict(state_before_fit)
    assert restored_before_fit.model_env.physics is restored_before_fit.trainer.residual.physics  # the prior itself

    rng = np.random.default_rng(0)
    state = np.asarray(ks_states[:8], dtype=np.float64)
    action = rng.uniform(-1, 1, size=(8, 4)).astype(np.float32)
    k = np.zeros(8, dtype=np.int64)
    nxt, reward, _, valid, phys_a = restored.model_env.step(state, k, action)
    assert valid.all()
    learned = KuramotoSivashinsky(actuator_width=1.3).reward(state, phys_a, nxt, k)
    prior = KuramotoSivashinsky().reward(state, phys_a, nxt, k)
    np.testing.assert_allclose(reward, learned, rtol=1e-12)
    assert np.abs(reward - prior).max() > 1e-3 * np.abs(prior).max()  # the prior's shapes would give other rewards


@pytest.mark.slow
def test_a_run_learning_the_width_feeds_it_to_the_model_and_the_imagined_steps(tmp_path) -> None:
    """Burgers, equivariant model, actuators 30 % wider than the prior's: after the run (no reload), the
    forcing input and the imagined steps' physics hold the width of coefficients.json."""
    from pimbrl.training import create_run, train

    settings = {**DYNA_SMOKE_SETTINGS["burgers"], **TINY_SETTINGS, **SMALL_MODEL_SETTINGS, "method": "pimbrl",
                "model.network": "equivariant", "env_kwargs": {"actuator_width": WIDTH_TRUE},
                "model.prior": {"actuator_width": WIDTH_PRIOR}, "learn.coefficients": {"actuator_width": None},
                "learn.lr": 0.05}  # fmt: skip
    run = create_run(resolve_config(ENV_IDS["burgers"], settings), tmp_path / "run", progress=False)
    train(run)
    width = json.loads((tmp_path / "run" / "coefficients.json").read_text())["current"]["actuator_width"]
    assert abs(width - WIDTH_TRUE) < abs(WIDTH_PRIOR - WIDTH_TRUE) / 2
    assert run.model is not None
    assert run.model.model_env.physics.coefficient_values()["actuator_width"] == width
    expected = Burgers(actuator_width=width).actuator_shapes
    np.testing.assert_array_equal(run.model.model.get_buffer("shapes").numpy(), expected.astype(np.float32))
