"""Environment inputs: initial states, task kwargs, stepping after termination, rendering."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from pimbrl import ENV_IDS
from pimbrl.systems import BurgersTask, KSPoolConfig, KSTask

from .conftest import SMALL_POOL

KS = "pimbrl/KuramotoSivashinsky-v0"


def _kwargs(env_id: str, ks_states: np.ndarray) -> dict:
    return {"initial_states": ks_states} if env_id == KS else {}


def _single(env_id: str, ks_states: np.ndarray, **kwargs) -> gym.Env:
    return gym.make(env_id, **_kwargs(env_id, ks_states), **kwargs)


def _vector(env_id: str, ks_states: np.ndarray, n: int = 2) -> gym.vector.VectorEnv:
    return gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **_kwargs(env_id, ks_states))


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("value", [1e300, 1e30, -1e30])
def test_a_huge_initial_state_is_rejected_single_and_vector(env_id: str, value: float, ks_states: np.ndarray) -> None:
    env = _single(env_id, ks_states)
    state = np.full(env.unwrapped.task.state_dim, value)
    with pytest.raises(ValueError, match=r"options\['initial_state'\]") as exc:
        env.reset(options={"initial_state": state})
    assert "\n" not in str(exc.value)
    vec = _vector(env_id, ks_states)
    with pytest.raises(ValueError, match=r"options\['initial_state'\]"):
        vec.reset(options={"initial_state": state})
    with pytest.raises(ValueError, match=r"options\['initial_state'\]"):  # one bad state among good ones
        vec.reset(options={"initial_state": np.stack([env.unwrapped.task.test_initial_states(1, 0)[0], state])})


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_a_single_bad_component_is_rejected_and_in_range_states_accepted(env_id: str, ks_states: np.ndarray) -> None:
    env = _single(env_id, ks_states)
    task = env.unwrapped.task
    good = task.test_initial_states(1, 0)[0]
    obs, _ = env.reset(options={"initial_state": good})
    assert env.observation_space.contains(obs)
    bad = good.copy()
    bad[-1] = 1e300
    with pytest.raises(ValueError, match=r"options\['initial_state'\]"):
        env.reset(options={"initial_state": bad})


def test_ks_state_beyond_the_divergence_bound_names_the_bound(ks_states: np.ndarray) -> None:
    env = gym.make(KS, initial_states=ks_states)
    u = ks_states[0].copy()
    u[5] = 101.0
    with pytest.raises(ValueError, match=r"divergence bound.*100"):
        env.reset(options={"initial_state": u})
    u[5] = 100.0  # on the bound: a step accepts it, so does reset
    obs, _ = env.reset(options={"initial_state": u})
    assert env.observation_space.contains(obs)


def test_burgers_state_beyond_the_divergence_bound_is_rejected() -> None:
    env = gym.make("pimbrl/Burgers-v0")
    with pytest.raises(ValueError, match=r"divergence bound.*10"):
        env.reset(options={"initial_state": np.full(150, 10.5)})


def test_pendulum_speed_outside_the_observation_space_is_rejected() -> None:
    env = gym.make("pimbrl/Pendulum-v0")
    with pytest.raises(ValueError, match="observation space"):
        env.reset(options={"initial_state": np.array([0.0, 9.0])})
    env.reset(options={"initial_state": np.array([0.0, 8.0])})


@pytest.mark.parametrize("env_id", ["pimbrl/Burgers-v0", KS])
@pytest.mark.parametrize("penalty", [np.nan, np.inf, -np.inf, "-5", True])
def test_a_non_finite_or_non_numeric_divergence_penalty_is_rejected(env_id: str, penalty, ks_states: np.ndarray) -> None:
    with pytest.raises((ValueError, TypeError), match="divergence_penalty"):
        _single(env_id, ks_states, divergence_penalty=penalty)
    with pytest.raises((ValueError, TypeError), match="divergence_penalty"):
        gym.make_vec(
            env_id,
            num_envs=2,
            vectorization_mode="vector_entry_point",
            divergence_penalty=penalty,
            **_kwargs(env_id, ks_states),
        )
    assert BurgersTask(divergence_penalty=-50).divergence_penalty == -50.0  # an int is a number


@pytest.mark.parametrize("num_envs", [1.5, 2.0, "2", True, 0])
def test_num_envs_must_be_a_positive_integer(num_envs) -> None:
    with pytest.raises((ValueError, TypeError), match="num_envs"):
        gym.make_vec("pimbrl/Pendulum-v0", num_envs=num_envs, vectorization_mode="vector_entry_point")
    vec = gym.make_vec("pimbrl/Pendulum-v0", num_envs=np.int64(3), vectorization_mode="vector_entry_point")
    assert vec.num_envs == 3


@pytest.mark.parametrize("steps", [2.5, "10", 0])
def test_max_episode_steps_must_be_a_positive_integer(steps) -> None:
    from pimbrl.systems import PendulumVectorEnv

    with pytest.raises((ValueError, TypeError), match="max_episode_steps"):
        PendulumVectorEnv(num_envs=2, max_episode_steps=steps)


@pytest.mark.parametrize("value", ["false", "true", 0, 1, None])
def test_periodic_actuators_must_be_a_bool(value, ks_states: np.ndarray) -> None:
    with pytest.raises((ValueError, TypeError), match="periodic_actuators"):
        KSTask(periodic_actuators=value, initial_states=ks_states)
    with pytest.raises((ValueError, TypeError), match="periodic_actuators"):
        gym.make(KS, periodic_actuators=value, initial_states=ks_states)
    assert KSTask(periodic_actuators=np.bool_(True), initial_states=ks_states).physics.periodic_actuators


def test_ks_pool_config_fields_are_typed() -> None:
    with pytest.raises((ValueError, TypeError), match="n_train"):
        KSPoolConfig(n_train=10.5)
    with pytest.raises((ValueError, TypeError), match="settle_rate"):
        KSPoolConfig(settle_rate=float("nan"))
    with pytest.raises((ValueError, TypeError), match="seed"):
        KSTask(pool_config={**SMALL_POOL.__dict__, "seed": 1.7})


def _run_to_termination(env: gym.Env) -> None:
    env.reset(seed=0)
    for _ in range(200):
        _, _, terminated, _, _ = env.step(1)
        if terminated:
            return
    pytest.fail("Cart-Pole pushed right did not terminate")


def test_stepping_after_termination_warns_once_per_episode() -> None:
    env = gym.make("pimbrl/CartPole-v0").unwrapped
    _run_to_termination(env)
    with pytest.warns(UserWarning, match=r"step\(\).*terminated = True.*reset\(\)"):
        env.step(1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env.step(1)  # warned once for this episode
        _run_to_termination(env)  # a new episode: no warning before its termination
    with pytest.warns(UserWarning, match="reset"):
        env.step(0)


def test_stepping_after_a_blow_up_warns() -> None:
    env = gym.make("pimbrl/Burgers-v0").unwrapped
    x = env.physics.x
    env.reset(options={"initial_state": 9.0 * np.sin(2 * np.pi * x)})
    _, _, terminated, _, _ = env.step(np.zeros(2, np.float32))
    assert terminated
    with pytest.warns(UserWarning, match="terminated = True"):
        env.step(np.zeros(2, np.float32))


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_rgb_array_rendering(env_id: str, ks_states: np.ndarray) -> None:
    env = _single(env_id, ks_states, render_mode="rgb_array")
    assert "rgb_array" in env.metadata["render_modes"]
    assert env.metadata["render_fps"] == round(1 / env.unwrapped.physics.control_dt)  # one frame per control step
    env.reset(seed=0)
    frame = env.render()
    assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.shape[0] >= 100 and frame.shape[1] >= 100
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 1  # something is drawn
    env.step(env.action_space.sample())
    frame2 = env.render()
    assert frame2.shape == frame.shape
    check_env(env.unwrapped)  # with the render check


def test_render_shows_the_state() -> None:
    env = gym.make("pimbrl/Pendulum-v0", render_mode="rgb_array")
    env.reset(options={"initial_state": np.array([0.0, 0.0])})
    up = env.render()
    env.reset(options={"initial_state": np.array([np.pi, 0.0])})
    down = env.render()
    assert not np.array_equal(up, down)


def test_render_mode_none_stays_the_default_and_unknown_modes_are_refused() -> None:
    from pimbrl.systems import PendulumEnv, PendulumVectorEnv

    assert gym.make("pimbrl/Pendulum-v0").unwrapped.render_mode is None
    with pytest.raises(ValueError, match="render_mode='human'"):
        PendulumEnv(render_mode="human")
    with pytest.raises(ValueError, match="render_mode"):
        PendulumVectorEnv(num_envs=2, render_mode="rgb_array")
