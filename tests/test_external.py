"""Someone else's simulator (issue 28): an external Gymnasium env with a declared system as its physics prior.

The external simulator here is written in this file the way another library would write it (its own
integrator, its own seeding; the adapter's contract only: ``reset(seed=)``, ``reset(options={"state": u})``
and ``info["state"]``). The prior believes a wrong damping; PiMBRL learns it from the simulator's data.
controlgym's PDEs (benchmarks/controlgym_systems.py) are checked where controlgym is installed.
"""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from pimbrl.cli import main
from pimbrl.systems import Coefficient, ODESystem, SystemSpecError, declare_external, xp_of

from .test_training import TINY

ROOT = Path(__file__).resolve().parents[1]


class OtherLibraryOscillator(gym.Env):
    """A damped, forced oscillator ``x'' = -c x' - x + a`` by 'another library': 10 explicit Euler steps of 0.01."""

    def __init__(self, damping: float = 0.4) -> None:
        self.damping = damping
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float64)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
        self.u = np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        if options and options.get("state") is not None:
            self.u = np.array(options["state"], dtype=np.float64)
        else:
            self.u = self.np_random.uniform(-1.0, 1.0, 2)
        return self.u.copy(), {"state": self.u.copy()}

    def step(self, action):
        a = float(np.asarray(action).reshape(-1)[0])
        reward = -float(self.u @ self.u) - 0.1 * a * a  # on the state before the step
        for _ in range(10):
            x, v = self.u
            self.u = self.u + 0.01 * np.array([v, -self.damping * v - x + a])
        return self.u.copy(), reward, False, False, {"state": self.u.copy()}


class OscillatorPrior(ODESystem):
    """What the user believes: the same oscillator, damping unknown (prior 0.1), the same Euler steps."""

    name = "oscillator"
    state_dim = 2
    action_low, action_high = [-1.0], [1.0]
    dt, substeps, integrator = 0.01, 10, "euler"
    episode_steps = 40
    divergence_bound = 50.0
    coefficients = {"c": Coefficient(0.1, low=0.0, high=5.0)}  # noqa: RUF012

    def rhs(self, u, a):
        xp = xp_of(u)
        return xp.stack([u[..., 1], -self.c * u[..., 1] - u[..., 0] + a[..., 0]], -1)

    def reward(self, u, a, u_next, k, path=None):
        return -(u**2).sum(-1) - 0.1 * a[..., 0] ** 2

    def initial_states(self, rng, n):  # not used: the simulator draws the initial states
        raise AssertionError("an external system's initial states come from the simulator")


@pytest.fixture(scope="module")
def oscillator() -> str:
    return declare_external(OscillatorPrior, OtherLibraryOscillator, "test/ExternalOscillator-v0", aliases=("ext-osc",)).id


def test_an_external_simulator_is_a_checked_env_driven_by_its_own_dynamics(oscillator: str) -> None:
    env = gym.make(oscillator)
    check_env(env.unwrapped, skip_render_check=True)
    _, info = env.reset(seed=3)
    u0 = info["state"]
    _, reward, _, _, info = env.step(np.array([0.5], dtype=np.float32))
    sim = OtherLibraryOscillator()
    sim.reset(options={"state": u0})
    expected, expected_reward, *_ = sim.step([0.5])
    np.testing.assert_array_equal(info["state"], expected)  # the simulator's transition, not the prior's
    assert reward == expected_reward
    task = env.unwrapped.task
    assert not np.allclose(task.physics.step(u0, np.array([0.5])), expected)  # the prior (c = 0.1) is wrong
    validation, test = task.validation_initial_states(5), task.test_initial_states(5, seed=0)
    assert not (validation[:, None, :] == test[None, :, :]).all(-1).any()


@pytest.mark.slow  # a few seconds: the whole suite runs it, the fast tier does not
def test_pimbrl_learns_the_prior_s_wrong_coefficient_from_the_simulator(oscillator: str, tmp_path) -> None:
    run = tmp_path / "run"
    flags = ["--steps", "400", "--warmup-steps", "80", "--update-after", "80", "--eval-every", "200", "--eval-episodes", "2"]
    flags += [
        "--model.start-after",
        "80",
        "--physics.start-after",
        "80",
        "--learn.coefficients",
        "c",
        "--learn.lr",
        "0.05",
    ]
    assert main(["train", "ext-osc", "--method", "pimbrl", *flags, "--run-dir", str(run), *TINY]) == 0
    metrics = (run / "metrics.csv").read_text().splitlines()
    header = metrics[0].split(",")
    learned = float(metrics[-1].split(",")[header.index("coef/c")])
    assert abs(learned - 0.4) < 0.02, learned  # from the prior's 0.1 to the simulator's 0.4


def test_the_simulator_s_own_termination_ends_an_episode() -> None:
    class Fence(OtherLibraryOscillator):
        def step(self, action):
            obs, reward, _, truncated, info = super().step(action)
            return obs, reward, bool(abs(self.u[0]) > 0.5), truncated, info

    env = gym.make(declare_external(OscillatorPrior, Fence, "test/Fence-v0").id)
    env.reset(seed=0, options={"initial_state": np.array([0.45, 1.0])})
    _, _, terminated, truncated, info = env.step(np.array([1.0], dtype=np.float32))
    assert terminated and not truncated and abs(info["state"][0]) > 0.5


def test_a_declared_reward_that_is_not_the_simulator_s_is_refused() -> None:
    class WrongReward(OscillatorPrior):
        def reward(self, u, a, u_next, k, path=None):
            return -(u_next**2).sum(-1)  # after the step: not what the simulator pays

    with pytest.raises(SystemSpecError, match="the declared reward differs from the external simulator's"):
        declare_external(WrongReward, OtherLibraryOscillator, "test/WrongReward-v0")


def test_a_simulator_without_the_state_in_info_is_refused() -> None:
    class Opaque(OtherLibraryOscillator):
        def reset(self, *, seed=None, options=None):
            obs, _ = super().reset(seed=seed, options=options)
            return obs, {}

    with pytest.raises(SystemSpecError, match=r"must return the physical state in info\['state'\]"):
        declare_external(OscillatorPrior, Opaque, "test/Opaque-v0")


#: controlgym is a benchmark-only install: the README's suite skips these tests, `.ci/run` installs it for them
needs_controlgym = pytest.mark.skipif(
    importlib.util.find_spec("controlgym") is None, reason="controlgym is a benchmark-only install"
)


def _controlgym_systems() -> types.ModuleType:
    """``benchmarks/controlgym_systems.py``, imported (importing it registers controlgym's envs)."""
    if str(ROOT / "benchmarks") not in sys.path:
        sys.path.insert(0, str(ROOT / "benchmarks"))
    import controlgym_systems

    return controlgym_systems


@needs_controlgym
@pytest.mark.slow
def test_controlgym_priors_match_the_simulator() -> None:
    import torch

    cg = _controlgym_systems()

    for env_id, tolerance in (("controlgym/Burgers-v0", 2e-3), ("controlgym/AllenCahn-v0", 2e-3)):
        task = gym.make(env_id).unwrapped.task
        rng = np.random.default_rng(0)
        u = task.sample_initial_states(rng, 4)
        a = rng.uniform(-1, 1, size=(4, cg.N_ACTION))
        out = task.advance(u, a, np.zeros(4, dtype=np.int64))
        etd = task.physics.etdrk4(10)
        f = task.physics.forcing(torch.as_tensor(a))
        v = torch.as_tensor(u)
        physics = task.physics
        for _ in range(10):
            v = etd.step(v, lambda w, physics=physics, f=f: physics.nonlinear(w, f))
        error = np.abs(v.numpy() - out.state).max() / np.abs(out.state - u).max()
        assert error < tolerance, (env_id, error)  # the prior's coarse step is the simulator's scheme


@needs_controlgym
@pytest.mark.slow
@pytest.mark.parametrize("name", ["burgers", "allen_cahn"])
def test_controlgym_shortcuts_are_bit_for_bit(name: str) -> None:
    """The adapter's cheaper noise draws and cached forcing give controlgym's states, rewards and draws exactly."""
    cg = _controlgym_systems()

    plain, adapter = cg.make_controlgym(name), cg.ControlGymPDE(name)
    assert isinstance(adapter.pde.rng, cg._ZeroNoiseDraws)
    rng = np.random.default_rng(0)
    for reset in ({"seed": 5}, {"state": np.linspace(-0.5, 0.5, cg.N_STATE) ** 2}, {}):
        plain.reset(**reset)
        adapter.reset(seed=reset.get("seed"), options={"state": reset["state"]} if "state" in reset else None)
        assert isinstance(adapter.pde.rng, cg._ZeroNoiseDraws)  # a seeded reset's new generator is wrapped too
        for a in rng.uniform(-3.0, 3.0, size=(4, cg.N_ACTION)):
            with np.errstate(all="ignore"):
                reward = plain.step(a)[1]
            assert adapter.step(a)[1] == float(reward)
            assert plain.state.tobytes() == adapter.pde.state.tobytes()
        assert plain.rng.bit_generator.state == adapter.pde.rng.bit_generator.state


@needs_controlgym
@pytest.mark.slow
def test_a_copied_or_pickled_controlgym_env_steps_as_its_original() -> None:
    """The adapter's stand-ins go with a deep copy and a pickle of the env, bound to the copy."""
    import copy
    import pickle

    cg = _controlgym_systems()

    env = cg.ControlGymPDE("burgers")
    env.reset(seed=2)
    a = np.full(cg.N_ACTION, 0.5)
    env.step(a)
    twins = [copy.deepcopy(env), pickle.loads(pickle.dumps(env))]
    assert all(twin.pde._compute_fourier_nonlinear_op.pde is twin.pde for twin in twins)  # bound to the copy
    assert all(isinstance(twin.pde.rng, cg._ZeroNoiseDraws) for twin in twins)  # the shortcut goes with the copy
    assert all(twin.pde.rng.bit_generator is not env.pde.rng.bit_generator for twin in twins)  # on its own stream
    reward, state = env.step(a)[1], env.pde.state.tobytes()
    for twin in twins:
        assert twin.step(a)[1] == reward and twin.pde.state.tobytes() == state
        assert twin.pde.rng.bit_generator.state == env.pde.rng.bit_generator.state  # the same draws were taken


@needs_controlgym
def test_the_adapters_step_takes_no_svd(monkeypatch) -> None:
    """The shortcuts are taken: a zero-noise reset or step of the adapter never factors a covariance (numpy's does)."""
    cg = _controlgym_systems()

    plain, adapter = cg.make_controlgym("burgers"), cg.ControlGymPDE("burgers")
    assert isinstance(adapter.pde._compute_fourier_nonlinear_op, cg._CachedForcingOp)
    plain.reset(seed=1)

    def no_svd(*args, **kwargs):
        raise AssertionError("an SVD was taken")

    monkeypatch.setattr(np.linalg, "svd", no_svd)
    adapter.reset(seed=1)  # a seeded reset's observation draw too (DPC draws its start states so)
    adapter.step(np.zeros(cg.N_ACTION))
    with pytest.raises(AssertionError, match="an SVD was taken"), np.errstate(all="ignore"):
        plain.step(np.zeros(cg.N_ACTION))  # the check can fail: controlgym's own step factors its covariances


@needs_controlgym
@pytest.mark.slow
def test_controlgym_noise_is_still_numpys_where_it_is_not_zero() -> None:
    """With process noise, the adapter hands each draw to numpy: states, rewards and stream stay controlgym's."""
    cg = _controlgym_systems()

    plain, adapter = cg.make_controlgym("burgers", process_noise_cov=1e-4), cg.ControlGymPDE("burgers", process_noise_cov=1e-4)
    quiet = cg.ControlGymPDE("burgers")
    for env in (plain, adapter, quiet):
        env.reset(seed=3)
    actions = np.random.default_rng(1).uniform(-1.0, 1.0, size=(3, cg.N_ACTION))
    quiet.step(actions[0])
    for i, a in enumerate(actions):
        with np.errstate(all="ignore"):
            reward = plain.step(a)[1]
        assert adapter.step(a)[1] == float(reward)
        assert plain.state.tobytes() == adapter.pde.state.tobytes()
        if i == 0:
            assert not np.array_equal(quiet.pde.state, adapter.pde.state)  # the noise was drawn, not dropped
    assert plain.rng.bit_generator.state == adapter.pde.rng.bit_generator.state


@needs_controlgym
def test_zero_noise_draws_are_numpys_draws() -> None:
    """The zero-covariance shortcut alone: numpy's values and numpy's stream (importing the adapter needs controlgym)."""
    cg = _controlgym_systems()

    for n in (1, 10, 256):
        ours, theirs = cg._ZeroNoiseDraws(np.random.PCG64(7)), np.random.Generator(np.random.PCG64(7))
        for mean in (np.zeros(n), np.linspace(-1.0, 1.0, n)):
            got, want = ours.multivariate_normal(mean, np.zeros((n, n))), theirs.multivariate_normal(mean, np.zeros((n, n)))
            assert got.tobytes() == want.tobytes()
            assert ours.bit_generator.state == theirs.bit_generator.state
        cov = 0.01 * np.eye(n)  # a nonzero covariance is numpy's own draw
        assert ours.multivariate_normal(np.zeros(n), cov).tobytes() == theirs.multivariate_normal(np.zeros(n), cov).tobytes()
    with pytest.raises(TypeError):  # as numpy: a complex mean is refused, not cast
        cg._ZeroNoiseDraws(np.random.PCG64(0)).multivariate_normal(np.zeros(2, complex), np.zeros((2, 2)))
