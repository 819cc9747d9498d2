"""Transition models and the physics loss: exactness on solver output, gradients, label-free learning,
imagined rollouts, and the model-eval command."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.experiments.model_eval import out_of_sample
from pimbrl.models import ConvLSTMModel, MLPModel, ModelEnv, ModelTrainer, PhysicsResidual, TransitionData, make_model
from pimbrl.physics.kernels import build_pde_kernel
from pimbrl.spaces import ActionAdapter
from pimbrl.systems import Burgers, BurgersTask, CartPole, CartPoleTask, KuramotoSivashinsky, Pendulum, PendulumTask


def _divisors(n: int) -> list[int]:
    return [d for d in range(1, n + 1) if n % d == 0]


def _solver_path(phys, u0: np.ndarray, a: np.ndarray, n_intermediate: int) -> torch.Tensor:
    """States of the compiled simulator at t + i/N (float64): the ground truth."""
    kernel = build_pde_kernel(phys.kernel_spec())
    m = phys.substeps // n_intermediate
    u, path = u0, []
    for _ in range(n_intermediate):
        u, _, _ = kernel(u, a, phys.actuator_shapes, phys.dt, m, False, np.zeros(4))
        path.append(u)
    return torch.tensor(np.stack(path, axis=1))


@pytest.mark.parametrize("system", ["ks", "burgers"])
def test_physics_loss_vanishes_on_exact_solver_outputs_for_every_supported_n(system: str, ks_states) -> None:
    rng = np.random.default_rng(0)
    if system == "ks":
        phys, u0, a = KuramotoSivashinsky(), ks_states[:2], rng.uniform(-0.5, 0.5, (2, 4))
        ns = _divisors(250)
    else:
        phys = Burgers()
        u0 = 0.3 + 0.1 * np.sin(2 * np.pi * phys.x)[None].repeat(2, 0)
        a = rng.uniform(-0.025, 0.075, (2, 2))
        ns = [1, 2, 5, 10, 25, 50, 100, 250, 500]
    u0_t, a_t = torch.tensor(u0), torch.tensor(a)
    for n in ns:
        # the simulator's own scheme: exact on the simulator's output
        solver = PhysicsResidual(phys, n, "solver")
        assert solver.loss(u0_t, _solver_path(phys, u0, a, n), a_t).item() <= 1e-10, n
        # the coarse exponential scheme: exact on its own output, and close to the simulator's
        etd = PhysicsResidual(phys, n, "etd")
        assert etd.loss(u0_t, etd.rollout(u0_t, a_t), a_t).item() <= 1e-10, n
        assert etd.loss(u0_t, _solver_path(phys, u0, a, n), a_t).item() <= 1e-4, n
        # and the loss sees a wrong path
        bad = _solver_path(phys, u0, a, n) + 1e-2 * torch.randn(2, n, phys.n, dtype=torch.float64)
        assert solver.loss(u0_t, bad, a_t).item() > 1e-6


@pytest.mark.parametrize("phys", [CartPole(), Pendulum()])
def test_ode_physics_loss_vanishes_on_exact_steps(phys) -> None:
    rng = np.random.default_rng(1)
    u = torch.tensor(rng.uniform(-1, 1, (20, phys.state_dim)))
    a = torch.tensor(rng.uniform(phys.action_low, phys.action_high, (20, 1)))
    nxt = phys.canonical(phys.step(u, a))
    res = PhysicsResidual(phys, 1)
    assert res.loss(u, nxt[:, None, :], a).item() <= 1e-10
    with pytest.raises(ValueError, match="one state per solver step"):
        PhysicsResidual(phys, 2)


def test_solver_scheme_rejects_non_divisors() -> None:
    with pytest.raises(ValueError, match="divide"):
        PhysicsResidual(KuramotoSivashinsky(), 3, "solver")


@pytest.mark.parametrize("model_kind", ["mlp", "convlstm"])
def test_gradients_reach_every_parameter(model_kind: str) -> None:
    torch.manual_seed(0)
    if model_kind == "mlp":
        phys = Pendulum()
        model = MLPModel(phys, hidden=(32, 32))
        u, a = torch.rand(16, 2) * 2 - 1, torch.rand(16, 1) * 4 - 2
    else:
        phys = KuramotoSivashinsky()
        model = ConvLSTMModel(phys, n_intermediate=3)
        u, a = torch.randn(16, 64), torch.rand(16, 4) - 0.5
    trainer = ModelTrainer(model, PhysicsResidual(phys, model.n_intermediate))
    labelled = TransitionData(u, a, u + 0.01 * torch.randn_like(u))
    trainer.ensure_normalization(labelled)
    trainer.optimizer.zero_grad()
    path = model(u, a)
    loss = phys.state_difference(path[:, -1], labelled.next_state).pow(2).mean() + trainer.residual.loss(u, path, a)
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


@pytest.mark.slow
def test_ode_model_learns_from_the_physics_loss_alone() -> None:
    """No labels: the equation alone teaches the Cart-Pole model its dynamics."""
    torch.manual_seed(0)
    phys = CartPole()
    rng = np.random.default_rng(0)
    lo, hi = [-2, -2, -0.2, -2], [2, 2, 0.2, 2]

    def states(n: int) -> torch.Tensor:
        return torch.tensor(rng.uniform(lo, hi, (n, 4)), dtype=torch.float32)

    def actions(n: int) -> torch.Tensor:
        return torch.tensor(rng.choice([-10.0, 10.0], (n, 1)), dtype=torch.float32)

    unlabelled = TransitionData(states(20_000), actions(20_000))
    trainer = ModelTrainer(MLPModel(phys, hidden=(64, 64)), PhysicsResidual(phys, 1), lr=1e-3)
    trainer.fit(1500, 256, rng, unlabelled=unlabelled)
    s, a = states(2000), actions(2000)
    held_out = TransitionData(s, a, phys.step(s.double(), a.double()).float())
    assert trainer.validation_mse(held_out) <= 1e-4


def test_model_env_makes_one_batched_call_per_step_and_uses_the_physics_reward() -> None:
    task = BurgersTask()
    adapter = ActionAdapter(task.action_space)
    model = make_model(task.physics, n_intermediate=2)
    u0 = task.sample_initial_states(np.random.default_rng(0), 32)
    model.fit_normalization(torch.tensor(u0, dtype=torch.float32), torch.tensor(u0, dtype=torch.float32) * 1.01)
    env = ModelEnv(model, task, adapter)
    out = env.rollout(u0, np.zeros(32, dtype=np.int64), lambda obs: np.zeros((len(obs), 2), np.float32), length=4)
    assert env.model_calls == 4 and len(out) == 4 * 32
    np.testing.assert_array_equal(out.k, np.repeat(np.arange(4), 32))
    # rewards are the physics' reward of the predicted states
    expected = task.physics.reward(out.state, out.physical_action, out.next_state, out.k)
    np.testing.assert_allclose(out.reward, expected, rtol=1e-12)
    np.testing.assert_allclose(out.next_obs, task.observe(out.next_state, out.k + 1), rtol=1e-6)
    assert np.isfinite(out.obs).all() and np.isfinite(out.next_obs).all()


def test_model_env_drops_blown_up_predictions_and_stops_on_termination() -> None:
    task = CartPoleTask()
    adapter = ActionAdapter(task.action_space)

    class Exploding(MLPModel):
        def forward(self, u, a):
            out = super().forward(u, a).clone()
            out[0] = float("nan")  # the first rollout blows up
            out[1, :, 2] = 1.0  # the second one tips the pole over (terminates)
            return out

    model = Exploding(task.physics, hidden=(8,))
    env = ModelEnv(model, task, adapter)
    u0 = np.zeros((4, 4))
    out = env.rollout(u0, np.zeros(4, dtype=np.int64), lambda obs: np.zeros((len(obs), 1), np.float32), length=3)
    assert np.isfinite(out.next_state).all() and np.isfinite(out.reward).all()
    assert out.terminated.sum() >= 1  # the tipped rollout ended with a terminal transition
    first_step = out.k == 0
    assert first_step.sum() == 3  # the NaN row was dropped


def test_model_eval_command_writes_errors_and_histograms(tmp_path, capsys) -> None:
    run = tmp_path / "me"
    args = ["model-eval", "cartpole", "--run-dir", str(run), "--transitions", "300", "--test-transitions", "40"]
    assert main([*args, "--steps", "60", "--batch-size", "64", "--refresh-every", "30"]) == 0
    with open(run / "model_errors.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert set(rows[0]) == {"model", "split", "mse"}
    assert len(rows) == 2 * 2 * 40
    assert {(r["model"], r["split"]) for r in rows} == {("data", "in"), ("data", "out"), ("physics", "in"), ("physics", "out")}
    assert all(float(r["mse"]) >= 0 for r in rows)
    assert (run / "model_errors.png").stat().st_size > 10_000 and (run / "summary.json").exists()
    assert main(["model-eval", "cartpole", "--run-dir", str(run), "--scheme", "rk2"]) == 2
    assert "scheme must be 'etd' or 'solver'" in capsys.readouterr().err


def test_model_eval_out_of_sample_states_respect_the_physics_bounds() -> None:
    rng = np.random.default_rng(0)
    cart = CartPoleTask()
    u = out_of_sample("pimbrl/CartPole-v0")(cart, rng, 500)
    assert np.abs(u[:, 0]).max() < cart.physics.x_threshold
    assert np.abs(u[:, 2]).max() < cart.physics.theta_threshold_radians
    assert not np.asarray(cart.physics.terminated(u)).any()
    pend = PendulumTask()
    u = out_of_sample("pimbrl/Pendulum-v0")(pend, rng, 500)
    assert np.abs(u[:, 1]).max() <= pend.physics.max_speed and np.abs(u[:, 1]).max() > 0.9 * pend.physics.max_speed
