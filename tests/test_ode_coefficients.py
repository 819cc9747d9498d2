"""Physical coefficients of the ODE systems (Pendulum, Cart-Pole): defaults, friction terms, environments, errors."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.envs.classic_control.cartpole import CartPoleEnv as GymCartPole
from gymnasium.envs.classic_control.pendulum import PendulumEnv as GymPendulum

import pimbrl  # noqa: F401 - registers the environments
from pimbrl.physics.base import Physics
from pimbrl.systems import CartPole, CartPoleTask, Pendulum, PendulumTask

PENDULUM_CHANGES = {"g": 9.81, "m": 1.3, "l": 0.8, "damping": 0.2}
CARTPOLE_CHANGES = {
    "gravity": 9.81,
    "masscart": 1.2,
    "masspole": 0.15,
    "length": 0.6,
    "cart_friction": 0.3,
    "pole_friction": 0.01,
}


def _pendulum_states(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    u = np.stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-8.0, 8.0, n)], -1)
    return u, rng.uniform(-2.0, 2.0, (n, 1))


def _cartpole_states(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    u = rng.uniform([-2.4, -2.0, -0.5, -2.5], [2.4, 2.0, 0.5, 2.5], (n, 4))
    return u, rng.choice([-10.0, 10.0], (n, 1))


def _states(physics: Physics, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    return _pendulum_states(rng, n) if isinstance(physics, Pendulum) else _cartpole_states(rng, n)


# ------------------------------------------------------------------ defaults unchanged
def _gymnasium_pendulum_step(u: np.ndarray, a: np.ndarray, g: float = 10.0, m: float = 1.0, l: float = 1.0) -> np.ndarray:  # noqa: E741
    """Gymnasium's ``PendulumEnv.step`` formula, as before coefficients existed."""
    th, thdot = u[:, 0], u[:, 1]
    newthdot = thdot + (3 * g / (2 * l) * np.sin(th) + 3.0 / (m * l**2) * a[:, 0]) * 0.05
    newthdot = np.clip(newthdot, -8.0, 8.0)
    return np.stack([th + newthdot * 0.05, newthdot], -1)


def _gymnasium_cartpole_step(u: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Gymnasium's ``CartPoleEnv.step`` formula (explicit Euler), as before coefficients existed."""
    x, x_dot, theta, theta_dot = u.T
    total_mass, polemass_length = 1.1, 0.1 * 0.5
    costheta, sintheta = np.cos(theta), np.sin(theta)
    temp = (a[:, 0] + polemass_length * np.square(theta_dot) * sintheta) / total_mass
    thetaacc = (9.8 * sintheta - costheta * temp) / (0.5 * (4.0 / 3.0 - 0.1 * np.square(costheta) / total_mass))
    xacc = temp - polemass_length * thetaacc * costheta / total_mass
    return np.stack([x + 0.02 * x_dot, x_dot + 0.02 * xacc, theta + 0.02 * theta_dot, theta_dot + 0.02 * thetaacc], -1)


@pytest.mark.parametrize(
    ("default", "explicit", "reference"),
    [
        (Pendulum(), Pendulum(g=10.0, m=1.0, l=1.0, damping=0.0), _gymnasium_pendulum_step),
        (
            CartPole(),
            CartPole(gravity=9.8, masscart=1.0, masspole=0.1, length=0.5, cart_friction=0.0, pole_friction=0.0),
            _gymnasium_cartpole_step,
        ),
    ],
)
def test_default_dynamics_are_unchanged_bit_for_bit(default: Physics, explicit: Physics, reference) -> None:
    u, a = _states(default, np.random.default_rng(0), 64)
    expected = reference(u, a)
    zeros = {name: 0.0 for name in ("damping", "cart_friction", "pole_friction") if name in default.coefficients}
    for physics in (default, explicit, default.with_coefficients(), default.with_coefficients(**zeros)):
        u_next, _ = physics.advance(u, a, np.zeros(len(u), dtype=np.int64))
        np.testing.assert_array_equal(u_next, expected)
        np.testing.assert_array_equal(physics.step(u, a), expected)


def test_pendulum_with_other_mass_and_length_equals_gymnasium_bit_for_bit() -> None:
    ours = Pendulum().with_coefficients(g=9.81, m=1.3, l=0.8)
    ref = GymPendulum(g=9.81)
    ref.m, ref.l = 1.3, 0.8
    u, a = _pendulum_states(np.random.default_rng(1), 20)
    for state, torque in zip(u, a, strict=True):
        ref.state = state.copy()
        ref.step(torque)
        np.testing.assert_array_equal(ours.step(state[None], torque[None])[0], ref.state)
    np.testing.assert_array_equal(ours.step(u, a), _gymnasium_pendulum_step(u, a, 9.81, 1.3, 0.8))


def test_frictionless_cartpole_with_other_masses_equals_gymnasium_bit_for_bit() -> None:
    changes = {k: v for k, v in CARTPOLE_CHANGES.items() if "friction" not in k}
    ours = CartPole().with_coefficients(**changes)
    ref = GymCartPole()
    ref.gravity, ref.masscart, ref.masspole, ref.length = (changes[k] for k in ("gravity", "masscart", "masspole", "length"))
    ref.total_mass = ref.masspole + ref.masscart
    ref.polemass_length = ref.masspole * ref.length
    u, _ = _cartpole_states(np.random.default_rng(2), 20)
    for i, state in enumerate(u):
        action = i % 2
        ref.state, ref.steps_beyond_terminated = state.copy(), None
        ref.step(action)
        force = np.array([[ours.force_mag if action == 1 else -ours.force_mag]])
        np.testing.assert_array_equal(ours.step(state[None], force)[0], ref.state)


# ------------------------------------------------------------------ with_coefficients
@pytest.mark.parametrize(
    ("base", "changes", "kept"),
    [
        (Pendulum(max_speed=6.0, max_torque=3.0, dt=0.02), PENDULUM_CHANGES, ("dt", "max_speed", "max_torque")),
        (CartPole(force_mag=7.0, tau=0.01, x_threshold=3.0), CARTPOLE_CHANGES, ("dt", "force_mag", "x_threshold")),
    ],
)
def test_with_coefficients_changes_only_what_is_asked(base: Physics, changes: dict[str, float], kept: tuple[str, ...]) -> None:
    assert set(changes) == set(base.coefficients)
    rng = np.random.default_rng(3)
    u, a = _states(base, rng, 32)
    a = 0.5 * a  # inside every bound used here
    for name, value in changes.items():
        physics = base.with_coefficients(**{name: value})
        assert type(physics) is type(base)
        assert physics.coefficient_values() == {**base.coefficient_values(), name: value}
        for attribute in kept:
            assert getattr(physics, attribute) == getattr(base, attribute)
        assert not np.array_equal(physics.step(u, a), base.step(u, a)), name  # every coefficient acts
    everything = base.with_coefficients(**changes)
    assert everything.coefficient_values() == changes
    assert base.with_coefficients(**changes).with_coefficients(**base.coefficient_values()).coefficient_values() == (
        base.coefficient_values()
    )


# ------------------------------------------------------------------ the friction terms
def _pendulum_power(p: Pendulum, u: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``dE/dt`` of ``E = m l^2 theta_dot^2 / 6 + m g l cos(theta) / 2`` along ``rhs``, and the expected power."""
    theta, theta_dot = u[:, 0], u[:, 1]
    theta_ddot = p.rhs(u, a)[:, 1]
    de_dt = p.m * p.l**2 / 3 * theta_dot * theta_ddot - p.m * p.g * p.l / 2 * np.sin(theta) * theta_dot
    return de_dt, a[:, 0] * theta_dot - p.damping * theta_dot**2


def _cartpole_power(p: CartPole, u: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``dE/dt`` of the cart-pole's mechanical energy along ``rhs``, and the power of the external forces."""
    _, x_dot, theta, theta_dot = u.T
    m, big_m, l, g = p.masspole, p.masscart + p.masspole, p.length, p.gravity  # noqa: E741
    rhs = p.rhs(u, a)
    x_acc, theta_acc = rhs[:, 1], rhs[:, 3]
    # E = M x_dot^2 / 2 + m l x_dot theta_dot cos(theta) + (2/3) m l^2 theta_dot^2 + m g l cos(theta)
    de_dt = (
        (big_m * x_dot + m * l * theta_dot * np.cos(theta)) * x_acc
        + (m * l * x_dot * np.cos(theta) + 4.0 / 3.0 * m * l**2 * theta_dot) * theta_acc
        - (m * l * x_dot * theta_dot * np.sin(theta) + m * g * l * np.sin(theta)) * theta_dot
    )
    expected = a[:, 0] * x_dot - p.cart_friction * np.abs(x_dot) - p.pole_friction * theta_dot**2
    return de_dt, expected


@pytest.mark.parametrize(
    ("physics", "power"),
    [
        (Pendulum(), _pendulum_power),
        (Pendulum(**PENDULUM_CHANGES), _pendulum_power),
        (Pendulum(damping=1.5), _pendulum_power),
        (CartPole(), _cartpole_power),
        (CartPole(**CARTPOLE_CHANGES), _cartpole_power),
        (CartPole(cart_friction=2.0), _cartpole_power),
        (CartPole(pole_friction=0.05), _cartpole_power),
    ],
)
def test_energy_balance_friction_dissipates(physics: Physics, power) -> None:
    """The equations of motion conserve energy up to the input power and the friction losses.

    ``dE/dt = F x_dot - mu_c |x_dot| - mu_p theta_dot^2`` (cart-pole), ``T theta_dot - damping theta_dot^2``
    (pendulum): a friction term with the wrong sign or scale breaks the balance.
    """
    u, a = _states(physics, np.random.default_rng(4), 200)
    de_dt, expected = power(physics, u, a)
    np.testing.assert_allclose(de_dt, expected, rtol=1e-10, atol=1e-10)


def test_cartpole_friction_is_barto_sutton_anderson() -> None:
    """Barto, Sutton & Anderson (1983, appendix), written as they do (Gymnasium's sign of ``g``)."""
    p = CartPole(**CARTPOLE_CHANGES)
    u, a = _cartpole_states(np.random.default_rng(5), 50)
    _, x_dot, theta, theta_dot = u.T
    m, big_m, l, g, force = p.masspole, p.masscart + p.masspole, p.length, p.gravity, a[:, 0]  # noqa: E741
    mu_c, mu_p, c, s = p.cart_friction, p.pole_friction, np.cos(theta), np.sin(theta)
    theta_acc = (g * s + c * (-force - m * l * theta_dot**2 * s + mu_c * np.sign(x_dot)) / big_m - mu_p * theta_dot / (m * l)) / (
        l * (4.0 / 3.0 - m * c**2 / big_m)
    )
    x_acc = (force + m * l * (theta_dot**2 * s - theta_acc * c) - mu_c * np.sign(x_dot)) / big_m
    np.testing.assert_allclose(p.rhs(u, a), np.stack([x_dot, x_acc, theta_dot, theta_acc], -1), rtol=1e-12, atol=1e-12)


def test_pendulum_damping_slows_the_swing() -> None:
    free, damped = Pendulum(), Pendulum(damping=0.3)
    u = np.array([[np.pi - 1.0, 0.0]])  # released 1 rad from hanging down, no torque
    a = np.zeros((1, 1))
    peaks_free, peaks_damped = [], []
    uf, ud = u, u
    for _ in range(400):
        uf, ud = free.step(uf, a), damped.step(ud, a)
        peaks_free.append(abs(uf[0, 1]))
        peaks_damped.append(abs(ud[0, 1]))
    # the undamped swing keeps its amplitude; the damped one loses most of it
    assert max(peaks_free[-100:]) > 0.9 * max(peaks_free[:100])
    assert max(peaks_damped[-100:]) < 0.3 * max(peaks_damped[:100])
    # one step from the same moving state: the friction torque opposes the motion
    moving = np.array([[0.4, 3.0], [0.4, -3.0]])
    diff = damped.rhs(moving, a.repeat(2, 0)) - free.rhs(moving, a.repeat(2, 0))
    np.testing.assert_allclose(diff[:, 1], -3.0 * 0.3 * moving[:, 1], rtol=1e-12)


def test_cart_friction_stops_a_sliding_cart() -> None:
    free, rough = CartPole(), CartPole(cart_friction=0.5)
    u = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0]])  # pole upright at rest, cart sliding
    a = np.zeros((2, 1))
    np.testing.assert_array_equal(free.step(u, a)[:, 1], u[:, 1])  # no friction: the speed is kept
    after = rough.step(u, a)
    assert np.all(np.abs(after[:, 1]) < np.abs(u[:, 1]))
    assert np.all(np.sign(after[:, 1]) == np.sign(u[:, 1]))
    # the pole's pivot is pulled back, so it tips forward, the way the cart was moving
    assert np.all(np.sign(rough.rhs(u, a)[:, 3]) == np.sign(u[:, 1]))


def test_pole_friction_slows_the_pole() -> None:
    free, rough = CartPole(), CartPole(pole_friction=0.02)
    u = np.array([[0.0, 0.0, 0.05, 1.5], [0.0, 0.0, -0.05, -1.5]])
    a = np.zeros((2, 1))
    assert np.all(np.abs(rough.step(u, a)[:, 3]) < np.abs(free.step(u, a)[:, 3]))


# ------------------------------------------------------------------ NumPy, torch, residual
@pytest.mark.parametrize("physics", [Pendulum(**PENDULUM_CHANGES), CartPole(**CARTPOLE_CHANGES)])
def test_torch_and_numpy_give_the_same_batched_step(physics: Physics) -> None:
    u, a = _states(physics, np.random.default_rng(6), 24)
    u, a = u.reshape(2, 12, -1), a.reshape(2, 12, -1)
    out_np = physics.step(u, a)
    out_t = physics.step(torch.tensor(u), torch.tensor(a))
    assert out_t.dtype == torch.float64 and out_t.shape == u.shape
    np.testing.assert_allclose(out_t.numpy(), out_np, rtol=1e-13, atol=1e-13)
    # a batched step equals the single steps
    singles = np.stack([physics.step(u[i, j][None], a[i, j][None])[0] for i in range(2) for j in range(12)])
    np.testing.assert_array_equal(out_np.reshape(24, -1), singles)
    # float32 tensors keep their dtype and stay differentiable
    u32 = torch.tensor(u, dtype=torch.float32, requires_grad=True)
    out32 = physics.step(u32, torch.tensor(a, dtype=torch.float32))
    assert out32.dtype == torch.float32
    out32.square().sum().backward()
    assert u32.grad is not None and torch.isfinite(u32.grad).all()


@pytest.mark.parametrize(("cls", "changes"), [(Pendulum, PENDULUM_CHANGES), (CartPole, CARTPOLE_CHANGES)])
def test_residual_of_a_true_step_vanishes_with_changed_coefficients(cls: type[Physics], changes: dict[str, float]) -> None:
    physics = cls().with_coefficients(**changes)
    u, a = _states(physics, np.random.default_rng(7), 16)
    u_next, _ = physics.advance(u, a, np.zeros(len(u), dtype=np.int64))
    ut, u1, at = torch.tensor(u), torch.tensor(u_next), torch.tensor(a)
    assert physics.residual(ut, u1, at).abs().max().item() <= 1e-10
    # the default system's residual of the same transition is clearly not zero: the coefficients matter
    assert cls().residual(ut, u1, at).abs().max().item() > 1e-2


# ------------------------------------------------------------------ environments
@pytest.mark.parametrize(
    ("env_id", "changes", "action"),
    [
        ("pimbrl/Pendulum-v0", {"m": 1.3}, np.array([1.0], dtype=np.float32)),
        ("pimbrl/Pendulum-v0", {"damping": 0.5, "g": 9.81}, np.array([1.0], dtype=np.float32)),
        ("pimbrl/CartPole-v0", {"masspole": 0.15}, 1),
        ("pimbrl/CartPole-v0", {"cart_friction": 0.5, "pole_friction": 0.01}, 1),
    ],
)
def test_environments_take_ode_coefficients_as_keyword_arguments(env_id: str, changes: dict[str, float], action) -> None:
    env = gym.make(env_id, **changes)
    default = gym.make(env_id)
    physics = env.unwrapped.task.physics
    assert physics.coefficient_values() == {**default.unwrapped.task.physics.coefficient_values(), **changes}
    obs, _ = env.reset(seed=0)
    obs0, _ = default.reset(seed=0)
    np.testing.assert_array_equal(obs, obs0)  # the same initial state, different dynamics
    assert not np.array_equal(env.step(action)[0], default.step(action)[0])
    vec = gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point", **changes)
    assert vec.unwrapped.task.physics.coefficient_values() == physics.coefficient_values()
    vec.close()


@pytest.mark.parametrize(
    ("env_id", "kwargs", "match"),
    [
        (
            "pimbrl/Pendulum-v0",
            {"dampng": 0.1},
            r"no coefficient 'dampng' \(did you mean 'damping'\?\); its coefficients are: g, m, l",
        ),
        ("pimbrl/Pendulum-v0", {"friction": 0.1}, "pendulum has no coefficient 'friction'; its coefficients are"),
        ("pimbrl/CartPole-v0", {"pole_fricton": 0.1}, r"no coefficient 'pole_fricton' \(did you mean 'pole_friction'\?\)"),
        ("pimbrl/CartPole-v0", {"masspole": float("inf")}, "coefficient masspole must be a finite number"),
        ("pimbrl/CartPole-v0", {"masspole": 0.0}, re.escape("CartPole: masspole must be a finite number in (0, 1000], got 0.0")),
        ("pimbrl/Pendulum-v0", {"damping": -0.1}, re.escape("Pendulum: damping must be a finite number in [0, 1000], got -0.1")),
    ],
)
def test_bad_environment_coefficients_are_one_line_errors(env_id: str, kwargs: dict[str, float], match: str) -> None:
    with pytest.raises(ValueError, match=match) as info:
        gym.make(env_id, **kwargs)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: Pendulum(m=0.0), "Pendulum: m must be a finite number in (0, 1000], got 0.0"),
        (lambda: Pendulum(l=-1.0), "Pendulum: l must be a finite number in (0, 1000], got -1.0"),
        (lambda: Pendulum(damping=-0.5), "Pendulum: damping must be a finite number in [0, 1000]"),
        (lambda: Pendulum(g=float("nan")), "Pendulum: g must be a finite number in [-100, 100], got nan"),
        (lambda: Pendulum(m=float("inf")), "Pendulum: m must be a finite number in (0, 1000], got inf"),
        (lambda: Pendulum().with_coefficients(l=0.0), "Pendulum: l must be a finite number in (0, 1000]"),
        (lambda: CartPole(masscart=0.0), "CartPole: masscart must be a finite number in (0, 1000], got 0.0"),
        (lambda: CartPole(masspole=-0.1), "CartPole: masspole must be a finite number in (0, 1000]"),
        (lambda: CartPole(length=0.0), "CartPole: length must be a finite number in (0, 100]"),
        (lambda: CartPole(cart_friction=-1e-3), "CartPole: cart_friction must be a finite number in [0, 1000]"),
        (lambda: CartPole(pole_friction=-1e-6), "CartPole: pole_friction must be a finite number in [0, 1000]"),
        (lambda: CartPole(gravity=float("inf")), "CartPole: gravity must be a finite number in [-100, 100], got inf"),
        (lambda: CartPole().with_coefficients(masspole=float("nan")), "cartpole: coefficient masspole must be a finite"),
        (lambda: PendulumTask(m=-1.0), "Pendulum: m must be a finite number in (0, 1000]"),
        (lambda: CartPoleTask(length=-0.5), "CartPole: length must be a finite number in (0, 100]"),
    ],
)
def test_invalid_coefficients_are_one_line_errors(build, match: str) -> None:
    with pytest.raises(ValueError, match=re.escape(match)) as info:
        build()
    assert "\n" not in str(info.value)


def test_zero_friction_and_negative_gravity_are_allowed() -> None:
    assert CartPole(cart_friction=0.0, pole_friction=0.0).coefficient_values()["cart_friction"] == 0.0
    assert Pendulum(g=-10.0).g == -10.0  # any finite gravity: a hanging-down convention is a sign flip
    assert Pendulum(damping=0.0).damping == 0.0


def test_run_configuration_accepts_coefficients_and_lists_them_for_a_typo() -> None:
    from pimbrl.training.config import ConfigError, check_env_kwargs

    check_env_kwargs("pimbrl/Pendulum-v0", {"m": 1.3, "damping": 0.1, "observation": "theta"})
    check_env_kwargs("pimbrl/CartPole-v0", {"masspole": 0.15, "pole_friction": 0.01})
    with pytest.raises(
        ConfigError, match=r"takes no keyword argument 'dampin' \(did you mean 'damping'\?\); it takes: observation, g, m"
    ):
        check_env_kwargs("pimbrl/Pendulum-v0", {"dampin": 0.1})
    with pytest.raises(ConfigError, match="it takes: gravity, masscart, masspole, length, cart_friction, pole_friction"):
        check_env_kwargs("pimbrl/CartPole-v0", {"friction": 0.1})
