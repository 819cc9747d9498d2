"""Label-free physics-loss states, residual units, the equivariant model, hard constraints, the accuracy gate."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.models import EquivariantConvModel, MLPModel, ModelEnv, PhysicsResidual, make_model
from pimbrl.models.state_sources import available_sources, broad_actions, broad_states, choose_sources
from pimbrl.spaces import ActionAdapter
from pimbrl.systems import BurgersTask, CartPole, KuramotoSivashinsky, Pendulum
from pimbrl.training import create_run, resolve_config, train


def test_sources_exist_where_the_physics_declares_them() -> None:
    assert "box" in available_sources(CartPole()) and "symmetry" not in available_sources(CartPole())
    assert {"symmetry", "scaled", "noise"} <= set(available_sources(KuramotoSivashinsky()))
    assert "box" not in available_sources(KuramotoSivashinsky())
    with pytest.raises(ValueError, match="not available for"):
        choose_sources(("policy", "box"), KuramotoSivashinsky())
    assert choose_sources(("policy", "symmetry"), KuramotoSivashinsky()) == ("policy", "symmetry")
    assert choose_sources((), KuramotoSivashinsky()) == ("policy", "imagined", "symmetry", "scaled", "noise")
    assert choose_sources((), Pendulum()) == ("policy", "imagined", "box")


def test_box_states_cover_the_admissible_box() -> None:
    phys = CartPole()
    low, high = phys.admissible_box()
    u = broad_states(phys, "box", torch.zeros(1, 4), 4000, np.random.default_rng(0)).numpy()
    assert (u >= low - 1e-6).all() and (u <= high + 1e-6).all()
    assert (u.min(0) < low * 0.9).all() and (u.max(0) > high * 0.9).all()  # spread over the whole box
    assert np.abs(u[:, 0]).max() <= phys.x_threshold and np.abs(u[:, 2]).max() <= phys.theta_threshold_radians


def test_symmetry_states_are_shifts_and_reflections_of_the_seeds() -> None:
    phys = KuramotoSivashinsky()
    seed = torch.as_tensor(np.sin(phys.x * 2 / 8) + 0.3 * np.cos(phys.x * 3 / 8), dtype=torch.float32)[None]
    out = broad_states(phys, "symmetry", seed, 200, np.random.default_rng(1)).double().numpy()
    u = seed[0].double().numpy()
    images = [np.roll(u, s) for s in range(64)] + [np.roll(-np.roll(u[::-1], 1), s) for s in range(64)]
    for v in out:  # every state is exactly one of the 128 images
        assert min(np.abs(v - w).max() for w in images) < 1e-6
    # the discrete KS equation itself commutes with the reflection u(x) -> -u(-x) and with shifts
    a = np.zeros((1, 4))
    reflect = lambda v: -np.roll(v[:, ::-1], 1, axis=1)
    np.testing.assert_allclose(phys.step(reflect(u[None]), a, 10), reflect(phys.step(u[None], a, 10)), atol=1e-12)


def test_scaled_and_noisy_states_and_actions() -> None:
    phys = KuramotoSivashinsky()
    rng = np.random.default_rng(2)
    seeds = torch.randn(10, 64)
    scaled = broad_states(phys, "scaled", seeds, 500, rng)
    ratio = (scaled.norm(dim=1) / seeds.norm(dim=1).max()).numpy()
    assert ratio.max() <= 1.5 + 1e-6 and ratio.min() < 0.1
    noisy = broad_states(phys, "noise", seeds, 100, rng)
    assert noisy.shape == (100, 64) and torch.isfinite(noisy).all()
    a = broad_actions(phys, 2000, rng).numpy()
    assert (a >= phys.action_low - 1e-7).all() and (a <= phys.action_high + 1e-7).all()
    at_bounds = np.isclose(a, phys.action_low) | np.isclose(a, phys.action_high)
    assert 0.4 < at_bounds.all(axis=1).mean() < 0.7  # about half bang-bang


def test_step_units_scale_the_residual_by_n_squared() -> None:
    phys = KuramotoSivashinsky()
    u = torch.randn(4, 64, dtype=torch.float64) * 0.5
    a = torch.zeros(4, 4, dtype=torch.float64)
    path = PhysicsResidual(phys, 5).rollout(u, a) * 1.05  # coherently 5 % off
    sub = PhysicsResidual(phys, 5, units="substep").loss(u, path, a)
    step = PhysicsResidual(phys, 5, units="step").loss(u, path, a)
    assert float(step) == pytest.approx(25 * float(sub), rel=1e-12)
    with pytest.raises(ValueError, match="units must be"):
        PhysicsResidual(phys, 5, units="du/dt")


def test_equivariant_model_commutes_with_shifting_state_and_actuators() -> None:
    # 4 actuators, one every 16 grid points; wrapped, so that a shift by 16 maps actuator i onto i + 1 (the
    # authors' actuators cut the bump at x = 0 in half: the model is still equivariant in its forcing input)
    phys = KuramotoSivashinsky(periodic_actuators=True)
    torch.manual_seed(0)
    model = make_model(phys, 5, kind="equivariant")
    assert isinstance(model, EquivariantConvModel) and sum(p.numel() for p in model.parameters()) < 20_000
    u, a = torch.randn(3, 64), torch.rand(3, 4) - 0.5
    shifted = model(torch.roll(u, 16, dims=1), torch.roll(a, 1, dims=1))
    torch.testing.assert_close(shifted, torch.roll(model(u, a), 16, dims=2), atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="model kind"):
        make_model(phys, 5, kind="transformer")


def test_pendulum_predictions_respect_the_speed_limit() -> None:
    phys = Pendulum()
    model = MLPModel(phys, hidden=(8,))
    with torch.no_grad():
        model.net[-1].bias.fill_(1e3)  # a model that wants to spin up without bound
    out = model.predict_next(torch.zeros(5, 2), torch.zeros(5, 1)).detach()
    assert float(out[:, 1].abs().max()) <= phys.max_speed


def test_the_endpoint_reward_rule_ignores_the_intermediate_states() -> None:
    task = BurgersTask()
    adapter = ActionAdapter(task.action_space)
    model = make_model(task.physics, n_intermediate=3)
    u0 = task.sample_initial_states(np.random.default_rng(0), 8)
    model.fit_normalization(torch.tensor(u0, dtype=torch.float32), torch.tensor(u0, dtype=torch.float32) * 1.01)
    out = ModelEnv(model, task, adapter, use_path=False).rollout(u0, np.zeros(8, np.int64), lambda o: np.zeros((len(o), 2)), 2)
    expected = task.physics.reward(out.state, out.physical_action, out.next_state, out.k, None)
    np.testing.assert_allclose(out.reward, expected, rtol=1e-12)


def _pendulum(method: str, **settings) -> object:
    over = {"method": method, "total_steps": 400, "warmup_steps": 100, "update_after": 100, "eval_every": 400,
            "eval_episodes": 2, "agent.hidden": (16, 16), "agent.batch_size": 16}  # fmt: skip
    model = {"fit.batch_size": 16, "imagine.rollouts": 8, "imagine.rollout_length": 5, "check.validation_size": 32,
             "fit.steps": 3, **settings}  # fmt: skip
    return resolve_config("pimbrl/Pendulum-v0", {**over, **model})


@pytest.mark.slow
def test_physics_only_training_before_labels_and_the_relative_gate(tmp_path) -> None:
    """PiMBRL with physics_start trains its model from the box states alone before start_model_after; the
    relative gate compares the held-out error with the no-change prediction's."""
    cfg = _pendulum("pimbrl", **{"physics.alone_from": 100, "model.start_after": 10**6, "physics.sources": ("box",),
                    "physics.units": "step", "check.accuracy": "relative", "check.relative_threshold": 0.5})  # fmt: skip
    run = create_run(cfg, tmp_path / "pim", progress=False)
    train(run)
    m = run.model
    assert m.trainer.steps == 3 * 7  # phases at 100, 150, ..., 400
    assert "model/data_loss" not in m.metrics and m.metrics["model/physics_loss"] >= 0
    assert np.isfinite(m.val_mse) and np.isfinite(m.baseline_mse)
    assert m.in_use == (m.val_mse < 0.5 * m.baseline_mse)
    assert m.val_mse < m.baseline_mse  # the equation alone beat predicting no change on real transitions
    with pytest.raises(ConfigError, match=r"--physics\.alone-from is a setting of --method pimbrl, pihybrid, not mbrl"):
        _pendulum("mbrl", **{"physics.alone_from": 100})
    with pytest.raises(ConfigError, match="equivariant is a network on a PDE's grid"):
        _pendulum("pimbrl", **{"model.network": "equivariant"})


@pytest.mark.slow
def test_the_model_study_writes_errors_by_labels(tmp_path) -> None:
    out = tmp_path / "study"
    args = ["model-eval", "cartpole", "--run-dir", str(out), "--labels", "0,50", "--physics.sources", "policy,box", "--steps", "40",
            "--test-transitions", "20", "--seed-states", "60", "--rollout-lengths", "1,3"]  # fmt: skip
    assert main(args) == 0
    with open(out / "study.csv") as fh:
        rows = list(csv.DictReader(fh))
    models = {(r["labels"], r["model"]) for r in rows}
    assert models == {(n, m) for n in ("0", "50") for m in ("physics", "physics-only")} | {("0", "no-change"), ("50", "data")}
    assert {r["horizon"] for r in rows} == {"1", "3"} and {r["split"] for r in rows} == {"in", "out"}
    assert all(float(r["mean"]) >= 0 for r in rows) and (out / "study.png").exists()
    # the prior's scheme is Cart-Pole's exact solver step: error zero, whatever the labels
    assert all(float(r["mean"]) < 1e-10 for r in rows if r["model"] == "physics-only")
    # a study of some models only: the same test transitions (they depend on the seed alone)
    assert main([*args[:3], str(tmp_path / "only"), *args[4:], "--models", "data,physics-only"]) == 0
    with open(tmp_path / "only" / "study.csv") as fh:
        only = list(csv.DictReader(fh))
    assert {r["model"] for r in only} == {"no-change", "data", "physics-only"}
    assert [r for r in only if r["model"] == "data"] == [r for r in rows if r["model"] == "data"]
    assert main([*args[:3], str(tmp_path / "bad"), "--labels", "10", "--physics.sources", "symmetry"]) == 2
    assert main([*args[:3], str(tmp_path / "bad2"), *args[4:], "--models", "data,fourier"]) == 2
    assert main([*args[:3], str(tmp_path / "bad3"), *args[4:], "--models", ","]) == 2
    assert not (tmp_path / "bad2").exists() and not (tmp_path / "bad3").exists()  # refused before anything is written


def test_the_study_measures_errors_in_the_states_own_geometry() -> None:
    """A pendulum prediction just across the +-pi seam is a small error, not (2 pi)^2."""
    from pimbrl.experiments.model_study import _rollout_mse
    from pimbrl.models import TransitionData
    from pimbrl.systems import PendulumTask

    task = PendulumTask()
    near_pi = torch.tensor([[np.pi - 1e-3, 0.0]], dtype=torch.float32)
    across = torch.tensor([[-np.pi + 1e-3, 0.0]], dtype=torch.float32)
    step = [TransitionData(near_pi, torch.zeros(1, 1), across)]
    assert _rollout_mse(None, step, 1, task)[0] < 1e-5


def test_sources_an_environment_does_not_offer_are_a_config_error() -> None:
    with pytest.raises(ConfigError, match="box not available for pimbrl/KuramotoSivashinsky-v0"):
        resolve_config("pimbrl/KuramotoSivashinsky-v0", {"method": "pimbrl", "physics.sources": ["policy", "box"]})
    with pytest.raises(ConfigError, match="symmetry not available for pimbrl/CartPole-v0"):
        resolve_config("pimbrl/CartPole-v0", {"method": "pimbrl", "physics.sources": ["symmetry"]})
    assert resolve_config("pimbrl/CartPole-v0", {"method": "pimbrl"}).method.physics.sources == ()  # all it offers


@pytest.mark.slow
def test_the_physics_loss_stays_on_after_physics_start(tmp_path) -> None:
    """With physics_start below start_model_after, the physics loss is on in every model phase after it,
    also once labels are used and before n_sR is reached."""
    cfg = _pendulum(
        "pimbrl",
        **{"physics.alone_from": 100, "model.start_after": 250, "physics.start_after": 10**6, "physics.sources": ("box",)},
    )
    run = create_run(cfg, tmp_path / "run", progress=False)
    seen = []
    train(run, on_event=lambda name, r: seen.append(dict(r.model.metrics)) if name == "model_phase" else None)
    assert all("model/physics_loss" in m for m in seen)
    assert any("model/data_loss" in m for m in seen) and any("model/data_loss" not in m for m in seen)
