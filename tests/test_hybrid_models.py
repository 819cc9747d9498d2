"""Models with the physics inside: the prior's coarse scheme alone (physics) or with a correction (hybrid)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.models import HybridModel, ModelTrainer, PhysicsModel, PhysicsResidual, TransitionData, make_model
from pimbrl.systems import Burgers, KuramotoSivashinsky, Pendulum
from pimbrl.training import RunDirectory, create_run, resolve_config, train

from .settings import DYNA_SMOKE_SETTINGS, ENV_IDS, SMALL_MODEL_SETTINGS, TINY_SETTINGS, for_method


def _ks_transitions(ks_states, n: int = 24, seed: int = 0) -> TransitionData:
    """``n`` KS transitions of the simulator under random actions, as float32 tensors."""
    phys = KuramotoSivashinsky()
    rng = np.random.default_rng(seed)
    u = np.asarray(ks_states[:n], dtype=np.float64)
    a = rng.uniform(-0.5, 0.5, size=(n, 4))
    u1 = phys.advance_terms(u, a)[0]
    return TransitionData(*(torch.as_tensor(x, dtype=torch.float32) for x in (u, a, u1)))


def test_the_physics_model_is_the_coarse_scheme_and_accurate_without_a_label(ks_states) -> None:
    data = _ks_transitions(ks_states)
    model = make_model(KuramotoSivashinsky(), 5, kind="physics")
    assert isinstance(model, PhysicsModel) and not list(model.parameters())
    path = model(data.state, data.action)
    assert path.shape == (24, 5, 64) and path.dtype == torch.float32
    expected = PhysicsResidual(KuramotoSivashinsky(), 5).rollout(data.state.double(), data.action.double())
    np.testing.assert_allclose(path.numpy(), expected.numpy(), rtol=0, atol=1e-5)
    trainer = ModelTrainer(model)
    mse = trainer.validation_mse(data)
    assert mse < 1e-6  # the equivariant network, untrained: ~6e-3; after 300 steps on 100 labels: ~2e-5
    # nothing to fit: fit draws no batch and changes nothing
    rng = np.random.default_rng(0)
    assert trainer.fit(5, 8, rng, labelled=data) == {}
    assert rng.bit_generator.state == np.random.default_rng(0).bit_generator.state
    assert trainer.validation_mse(data) == mse
    assert trainer.state_dict()["optimizer"] is None


def test_a_wrong_prior_makes_a_wrong_physics_model(ks_states) -> None:
    data = _ks_transitions(ks_states)
    right = ModelTrainer(make_model(KuramotoSivashinsky(), 5, kind="physics")).validation_mse(data)
    wrong = ModelTrainer(make_model(KuramotoSivashinsky(convection=1.3), 5, kind="physics")).validation_mse(data)
    assert wrong > 100 * right


def test_the_physics_model_follows_the_residuals_learned_coefficients(ks_states) -> None:
    data = _ks_transitions(ks_states, n=8)
    prior = KuramotoSivashinsky(convection=1.3)
    residual = PhysicsResidual(prior, 5, learned={"convection": None})
    model = make_model(prior, 5, kind="physics", scheme=residual)
    before = model(data.state, data.action)
    assert residual.coefficients is not None
    with torch.no_grad():  # a free coefficient is prior * (1 + theta): move it to the true 1.0
        residual.coefficients.theta.fill_((1.0 - 1.3) / 1.3)
    assert residual.current_physics().coefficient_values()["convection"] == pytest.approx(1.0)
    after = model(data.state, data.action)
    exact = make_model(KuramotoSivashinsky(), 5, kind="physics")(data.state, data.action)
    np.testing.assert_allclose(after.numpy(), exact.numpy(), rtol=0, atol=1e-5)
    assert (after - before).abs().max() > 1e-3


def test_the_hybrid_model_starts_as_the_physics_and_trains_only_its_correction(ks_states) -> None:
    data = _ks_transitions(ks_states)
    torch.manual_seed(0)
    hybrid = make_model(KuramotoSivashinsky(), 5, kind="hybrid")
    assert isinstance(hybrid, HybridModel)
    physics = make_model(KuramotoSivashinsky(), 5, kind="physics")
    trainer = ModelTrainer(hybrid, lr=1e-3)
    trainer.ensure_normalization(data)
    torch.testing.assert_close(hybrid(data.state, data.action), physics(data.state, data.action), rtol=0, atol=0)
    start = trainer.validation_mse(data)
    trainer.fit(20, 16, np.random.default_rng(0), labelled=data)
    correction = hybrid.correction(data.state, data.action).detach()
    assert correction.abs().max() > 0  # the data loss moved the correction
    # scaled small: 20 Adam steps leave the model within a few times the physics' own error
    assert trainer.validation_mse(data) < 10 * start + 1e-8
    grads = [p.grad for p in hybrid.parameters()]
    assert all(g is not None for g in grads)


@pytest.mark.slow  # a few seconds: the whole suite runs it, the fast tier does not
def test_the_hybrids_correction_makes_up_for_a_wrong_prior() -> None:
    """Burgers with nu 0.013, the prior's 0.01: the correction fitted to labels beats the wrong scheme alone."""
    import gymnasium as gym

    task = gym.make("pimbrl/Burgers-v0", nu=0.013).unwrapped.task
    rng = np.random.default_rng(0)
    u = task.sample_initial_states(rng, 40)
    states, actions, nexts = [], [], []
    for k in range(5):
        a = rng.uniform(-1, 1, size=(40, 2)) * task.physics.action_high
        nxt = task.advance(u, a, np.full(40, k)).state
        states.append(u), actions.append(a), nexts.append(nxt)
        u = nxt
    s, a, s1 = (torch.as_tensor(np.concatenate(x), dtype=torch.float32) for x in (states, actions, nexts))
    train, test = TransitionData(s[:150], a[:150], s1[:150]), TransitionData(s[150:], a[150:], s1[150:])
    prior = Burgers(nu=0.01)
    physics_only = ModelTrainer(make_model(prior, 5, kind="physics")).validation_mse(test)
    torch.manual_seed(0)
    trainer = ModelTrainer(make_model(prior, 5, kind="hybrid"))
    trainer.ensure_normalization(train)
    assert trainer.validation_mse(test) == pytest.approx(physics_only, rel=1e-6)
    trainer.fit(200, 32, np.random.default_rng(0), labelled=train)
    assert trainer.validation_mse(test) < 0.75 * physics_only  # measured: 0.53x


def test_a_rollout_at_learned_coefficients_builds_its_step_once_with_the_same_states(ks_states) -> None:
    data = _ks_transitions(ks_states, n=8)
    residual = PhysicsResidual(KuramotoSivashinsky(convection=1.3), 5, learned={"convection": None, "correction": None})
    with torch.no_grad():
        residual.coefficients.theta.fill_(-0.1)
        residual.coefficients.correction.fill_(0.01)
    u = data.state.double()
    stepwise = [u]
    for _ in range(5):
        stepwise.append(residual.coarse_step(stepwise[-1], data.action.double()))
    torch.testing.assert_close(residual.rollout(u, data.action.double()), torch.stack(stepwise[1:], 1), rtol=0, atol=0)


def test_on_an_ode_the_physics_model_is_the_solver_step() -> None:
    phys = Pendulum()
    rng = np.random.default_rng(0)
    u = torch.as_tensor(rng.uniform(-1, 1, size=(16, 2)), dtype=torch.float64)
    a = torch.as_tensor(rng.uniform(-2, 2, size=(16, 1)), dtype=torch.float64)
    model = make_model(phys, kind="physics")
    assert model.n_intermediate == 1
    torch.testing.assert_close(model(u, a)[:, 0], phys.canonical(phys.step(u, a)), rtol=0, atol=0)
    hybrid = make_model(phys, kind="hybrid", hidden=(16, 16))
    assert isinstance(hybrid, HybridModel)
    hybrid.fit_normalization(u.float(), model(u, a)[:, 0].float())
    torch.testing.assert_close(hybrid(u.float(), a.float()), model(u.float(), a.float()), rtol=0, atol=0)
    # near the +-pi seam and the speed limit, with a correction that pushes across both
    edge = torch.tensor([[np.pi - 1e-3, 7.99], [-np.pi + 1e-3, -7.99]], dtype=torch.float32)
    push = torch.zeros(2, 1)
    with torch.no_grad():
        hybrid.net.net[-1].bias.copy_(torch.tensor([1e3, 1e3]))  # a large correction of both angle and speed
    out = hybrid(edge, push)[:, 0]
    assert bool((out[:, 0] >= -np.pi).all() and (out[:, 0] <= np.pi).all())  # the angle is wrapped
    assert bool((out[:, 1].abs() <= 8.0).all())  # the speed limit holds


def test_unknown_model_kind_and_bad_scale_are_refused() -> None:
    with pytest.raises(ValueError, match="model kind must be one of convlstm, equivariant, mlp, physics, hybrid"):
        make_model(Burgers(), kind="fourier")
    with pytest.raises(ValueError, match="correction_scale"):
        make_model(Burgers(), kind="hybrid", correction_scale=0.0)


@pytest.mark.parametrize(
    ("env", "overrides", "message"),
    [
        ("cartpole", {"method": "mbrl", "model.network": "equivariant"}, "network on a PDE's grid"),
        (
            "burgers",
            {"method": "known-scheme", "model.correction_scale": 0.1},
            "--model.correction-scale is a setting of --method hybrid, pihybrid, not known-scheme",
        ),
    ],
)
def test_model_kind_settings_that_cannot_work_are_refused(env: str, overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        resolve_config(ENV_IDS[env], overrides)


@pytest.mark.slow
@pytest.mark.parametrize(("env", "kind"), [("burgers", "physics"), ("burgers", "hybrid"), ("pendulum", "hybrid")])
def test_a_run_uses_the_physics_model_from_its_first_phase_and_resumes(env: str, kind: str, tmp_path) -> None:
    method = "known-scheme" if kind == "physics" else "hybrid"
    settings = {**DYNA_SMOKE_SETTINGS[env], **TINY_SETTINGS, **SMALL_MODEL_SETTINGS, "checkpoint_every": 60}
    if env == "pendulum":  # end on an episode boundary (200 steps), where a resumed run extends exactly
        settings["total_steps"] = 200
    settings = {"method": method, **for_method(settings, method)}  # no physics loss (nor, for the known scheme, a fit)
    run = create_run(resolve_config(ENV_IDS[env], settings), tmp_path / "run", progress=False)
    train(run)
    rows = RunDirectory(tmp_path / "run").metrics([]).read()
    assert all(r["model/in_use"] == "1" for r in rows if int(r["step"]) > settings["model.start_after"])
    assert int(rows[-1]["imagined_total"]) > 0
    assert ("model/data_loss" in rows[-1] and rows[-1]["model/data_loss"] != "") == (kind == "hybrid")
    # a longer budget continues from the checkpoint (the physics model has no optimiser state) exactly as
    # a run given that budget from the start
    longer = settings["total_steps"] + 60
    assert main(["resume", str(tmp_path / "run"), "--total-steps", str(longer), "--quiet"]) == 0
    whole = resolve_config(ENV_IDS[env], {**settings, "total_steps": longer})
    train(create_run(whole, tmp_path / "whole", progress=False))
    resumed, uninterrupted = RunDirectory(tmp_path / "run"), RunDirectory(tmp_path / "whole")

    def rows(log) -> list[dict]:
        return [{k: v for k, v in r.items() if k != "wall_s"} for r in log.read()]

    assert rows(resumed.episodes) == rows(uninterrupted.episodes)
    assert rows(resumed.evaluations)[-1] == rows(uninterrupted.evaluations)[-1]  # (the short run's end adds an evaluation)


@pytest.mark.parametrize("kind", ["physics", "hybrid"])
@pytest.mark.slow
def test_a_pimbrl_runs_physics_model_steps_the_learned_coefficients(kind: str, tmp_path) -> None:
    """The model steps the run's own residual, so it predicts with the coefficients the labels identified."""
    method = "identified-scheme" if kind == "physics" else "pihybrid"
    settings = for_method({**DYNA_SMOKE_SETTINGS["burgers"], **TINY_SETTINGS, **SMALL_MODEL_SETTINGS}, method)
    learn = {"env_kwargs": {"nu": 0.013}, "model.prior": {"nu": 0.01}, "learn.coefficients": {"nu": None}, "learn.lr": 0.05}
    run = create_run(
        resolve_config(ENV_IDS["burgers"], {"method": method, **settings, **learn}), tmp_path / "run", progress=False
    )
    train(run)
    assert run.model is not None
    model, residual = run.model.model, run.model.trainer.residual
    assert isinstance(model, PhysicsModel) and model.scheme is residual
    nu = json.loads((tmp_path / "run" / "coefficients.json").read_text())["current"]["nu"]
    assert abs(nu - 0.013) < 0.0015  # moved from 0.01 towards the truth
    u = torch.as_tensor(np.random.default_rng(0).normal(scale=0.1, size=(4, 150)), dtype=torch.float32)
    a = torch.zeros(4, 2)
    at_nu = make_model(Burgers(nu=nu), 5, kind="physics")(u, a)
    torch.testing.assert_close(model.physics_path(u, a), at_nu, rtol=0, atol=1e-6)


@pytest.mark.slow
def test_the_model_study_fits_the_schemes_coefficients_without_a_network(tmp_path) -> None:
    """physics-only-learned: the wrong prior's scheme with nu fitted to 50 labels beats the scheme as given."""
    out = tmp_path / "study"
    argv = ["model-eval", "burgers", "--run-dir", str(out), "--labels", "0,50", "--steps", "150", "--test-transitions", "20",
            "--seed-states", "60", "--rollout-lengths", "1", "--env-coefficients", "nu=0.013", "--physics-prior", "nu=0.01",
            "--learn-coefficients", "nu", "--models", "physics-only,physics-only-learned"]  # fmt: skip
    assert main(argv) == 0
    payload = json.loads((out / "study.json").read_text())
    error = {(r["labels"], r["model"]): r["mean"] for r in payload["summary"] if r["split"] == "out"}
    assert error[(0, "physics-only-learned")] == error[(0, "physics-only")]  # no label, nothing fitted
    assert error[(50, "physics-only-learned")] < 0.2 * error[(50, "physics-only")]
    (found,) = payload["identified"]
    assert found["model"] == "physics-only-learned" and abs(found["nu"] - 0.013) < 0.1 * 0.003
