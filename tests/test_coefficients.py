"""Physical coefficients: environments built with coefficients the paper does not use, and priors that differ."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import pimbrl  # noqa: F401 - registers the environments
from pimbrl.models import PhysicsResidual
from pimbrl.physics.pde import ETDRK4, SemilinearPDE
from pimbrl.systems import Burgers, BurgersTask, KuramotoSivashinsky, ks_initial_state_pool

PDES = (Burgers, KuramotoSivashinsky)


@pytest.mark.parametrize("cls", PDES)
def test_operators_at_own_coefficients_equal_the_simulator_parts(cls: type[SemilinearPDE]) -> None:
    physics = cls().with_coefficients(damping=0.05, convection=1.2, actuator_width=0.9 * cls().actuator_width, drift=0.1)
    lam, nonlinear, shapes = physics.operators({})
    symbol = physics.linear.symbol(physics.n)[: physics.n // 2 + 1]
    assert np.iscomplexobj(lam) and np.abs(symbol.imag).max() > 0  # the drift: a non-symmetric operator
    np.testing.assert_allclose(lam, symbol, rtol=1e-12, atol=1e-9 * np.abs(symbol).max())
    assert nonlinear == physics.nonlinear_coef
    np.testing.assert_allclose(shapes, physics.actuator_shapes, rtol=1e-14)
    tensors = {k: torch.tensor(v, dtype=torch.float64) for k, v in physics.coefficient_values().items()}
    lam_t, nonlinear_t, shapes_t = physics.operators(tensors)
    np.testing.assert_allclose(lam_t.numpy(), lam, rtol=1e-12, atol=1e-9 * np.abs(symbol).max())
    drift_free = physics.with_coefficients(drift=0.0).operators({})[0]
    assert not np.iscomplexobj(drift_free)  # real eigenvalues (and a real ETD step) without a drift
    assert float(nonlinear_t) == pytest.approx(nonlinear, rel=1e-14)
    np.testing.assert_allclose(shapes_t.numpy(), shapes, rtol=1e-12)


def test_operators_are_differentiable_in_the_coefficients() -> None:
    physics = Burgers()
    nu = torch.tensor(0.01, dtype=torch.float64, requires_grad=True)
    lam, _, _ = physics.operators({"nu": nu})
    lam.sum().backward()
    d2 = physics.operators({"nu": 1.0, "damping": 0.0})[0]
    assert nu.grad is not None
    assert float(nu.grad) == pytest.approx(float(d2.sum()), rel=1e-12)


def test_differentiable_etd_step_equals_the_fixed_one_and_has_gradients() -> None:
    physics = KuramotoSivashinsky()
    u = torch.as_tensor(np.random.default_rng(0).normal(size=(3, physics.n)))
    fixed = physics.etdrk4(5)
    coef = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    lam, nonlinear, _ = physics.operators({"hyper_diffusion": coef})
    learned = ETDRK4(lam, physics.n, physics.control_dt / 5)
    out_fixed = fixed.step(u, lambda v: physics.nonlinear(v, 0.0))
    out = learned.step(u, lambda v: nonlinear * physics.upwind(v))
    np.testing.assert_allclose(out.detach().numpy(), out_fixed.numpy(), rtol=1e-9, atol=1e-12)
    out.pow(2).sum().backward()
    assert coef.grad is not None and torch.isfinite(coef.grad) and float(coef.grad) != 0.0


@pytest.mark.parametrize(
    ("cls", "changes"),
    [
        (Burgers, {"nu": 0.013, "damping": 0.1, "convection": 0.8, "actuator_width": 0.08, "drift": 0.05}),
        (KuramotoSivashinsky, {"anti_diffusion": 0.7, "hyper_diffusion": 1.3, "convection": 1.3, "damping": 0.1, "drift": 0.3}),
    ],
)
def test_compiled_simulator_follows_changed_coefficients(cls: type[SemilinearPDE], changes: dict[str, float]) -> None:
    default = cls()
    physics = default.with_coefficients(**changes)
    assert physics.coefficient_values() == {**default.coefficient_values(), **changes}
    rng = np.random.default_rng(1)
    u = 0.3 + 0.1 * rng.normal(size=(2, physics.n)) if cls is Burgers else rng.normal(size=(2, physics.n))
    a = rng.uniform(physics.action_low, physics.action_high, size=(2, physics.action_dim))
    fast, _ = physics.advance(u, a, np.zeros(2, dtype=np.int64))
    np.testing.assert_allclose(fast, physics.step(u, a), rtol=1e-10, atol=1e-12)
    assert not np.allclose(fast, default.advance(u, a, np.zeros(2, dtype=np.int64))[0], atol=1e-6)


def test_damping_removes_energy() -> None:
    u = np.random.default_rng(2).normal(size=(1, 64))
    a = np.zeros((1, 4))
    free = KuramotoSivashinsky().step(u, a)
    damped = KuramotoSivashinsky(damping=0.5).step(u, a)
    assert (damped**2).sum() < (free**2).sum()


def test_bad_coefficients_are_one_line_errors() -> None:
    with pytest.raises(ValueError, match=r"no coefficient 'nuu' \(did you mean 'nu'\?\); its coefficients are: nu, "):
        Burgers().with_coefficients(nuu=0.01)
    with pytest.raises(ValueError, match="must be a finite number"):
        Burgers().with_coefficients(nu=float("nan"))
    with pytest.raises(ValueError, match=r"burgers: nu must be a finite number in \[0, 1\], got nan"):
        Burgers(nu=float("nan"))
    with pytest.raises(ValueError, match=r"ks: drift must be a finite number in \[-1000, 1000\], got inf"):
        KuramotoSivashinsky(drift=float("inf"))
    with pytest.raises(ValueError, match=r"ks: hyper_diffusion must be a finite number in \(0, 100\]"):
        KuramotoSivashinsky(hyper_diffusion=0.0)
    with pytest.raises(ValueError, match=r"burgers: actuator_width must be a finite number in \[0.001, 1\]"):
        Burgers(actuator_width=0.0)
    # an unstable explicit solver step: refused by the environment (and by the simulator, at its first use),
    # not by the physics object, which a prior may hold without ever stepping it explicitly
    unstable = r"unstable \(it amplifies a mode 1.4 times more than the equation, per step\); give a smaller dt"
    prior = Burgers(nu=0.02)
    with pytest.raises(ValueError, match=unstable):
        BurgersTask(nu=0.02)
    with pytest.raises(ValueError, match=unstable):
        prior.advance(np.full((1, prior.n), 0.5), np.zeros((1, 2)), np.zeros(1, dtype=np.int64))
    with pytest.raises(ValueError, match=unstable):
        PhysicsResidual(prior, 5, scheme="solver")
    PhysicsResidual(prior, 5)  # the exponential scheme is stable for any coefficients
    assert Burgers().with_coefficients() is not None
    default = Burgers()
    assert default.with_coefficients() is default  # nothing to change: the object itself


@pytest.mark.parametrize(
    ("env_id", "name", "value"), [("pimbrl/Burgers-v0", "nu", 0.013), ("pimbrl/KuramotoSivashinsky-v0", "convection", 1.3)]
)
def test_environments_take_coefficients_as_keyword_arguments(env_id: str, name: str, value: float) -> None:
    env = gym.make(env_id, **{name: value})
    assert getattr(env.unwrapped.task.physics, name) == value
    default = gym.make(env_id)
    obs, _ = env.reset(seed=0)
    obs0, _ = default.reset(seed=0)
    np.testing.assert_array_equal(obs, obs0)  # the same initial state, different dynamics
    action = env.action_space.sample() * 0 + env.action_space.high
    assert not np.array_equal(env.step(action)[0], default.step(action)[0])
    with pytest.raises(ValueError, match="no coefficient"):
        gym.make(env_id, not_a_coefficient=1.0)


@pytest.mark.parametrize("cls", PDES)
def test_the_etd_residual_follows_a_drift(cls: type[SemilinearPDE]) -> None:
    """With a drift (complex eigenvalues) the coarse ETD step treats the linear part exactly, as without."""
    from pimbrl.models import PhysicsResidual

    rng = np.random.default_rng(3)
    k = np.zeros(4, dtype=np.int64)
    errors = {}
    for drift in (0.0, 0.2):
        physics = cls(drift=drift)
        u = BurgersTask().sample_initial_states(rng, 4) if cls is Burgers else ks_initial_state_pool("train").states[:4]
        a = rng.uniform(physics.action_low, physics.action_high, size=(4, physics.action_dim))
        truth, _ = physics.advance(u, a, k)
        coarse = PhysicsResidual(physics, 5).rollout(torch.as_tensor(u), torch.as_tensor(a))[:, -1].numpy()
        errors[drift] = float(np.mean((coarse - truth) ** 2))
        if drift:  # the scheme errs far less than the drift moves the step
            without, _ = cls().advance(u, a, k)
            assert errors[drift] < 1e-2 * float(np.mean((truth - without) ** 2))
        tiny = 1e-6 * (u - u.mean(-1, keepdims=True))  # the linear part alone (no forcing, no nonlinearity)
        zero = np.zeros_like(a)
        linear_truth, _ = physics.advance(tiny, zero, k)
        linear = PhysicsResidual(physics, 5).rollout(torch.as_tensor(tiny), torch.as_tensor(zero))[:, -1].numpy()
        # exact but for the simulator's own time-stepping error (explicit Euler for Burgers: ~6e-4 relative)
        assert np.abs(linear - linear_truth).max() < 2e-3 * np.abs(linear_truth).max()
    if cls is KuramotoSivashinsky:  # converges with the number of steps (Burgers: the Euler simulator's error is the floor)
        fine = PhysicsResidual(physics, 25).rollout(torch.as_tensor(u), torch.as_tensor(a))[:, -1].numpy()
        assert float(np.mean((fine - truth) ** 2)) < errors[0.2] / 3
