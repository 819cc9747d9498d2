"""Gymnasium environments: API conformance, vector == stacked single, seeding, Gymnasium parity, errors."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

from pimbrl import ENV_IDS
from pimbrl.systems import BurgersTask, KSTask, PendulumTask

from .conftest import SMALL_POOL

KS = "pimbrl/KuramotoSivashinsky-v0"


def _kwargs(env_id: str, ks_states: np.ndarray) -> dict:
    return {"initial_states": ks_states} if env_id == KS else {}


def _actions(space: gym.Space, rng: np.random.Generator, n: int) -> list:
    if isinstance(space, gym.spaces.Discrete):
        return [int(rng.integers(2)) for _ in range(n)]
    return [rng.uniform(space.low, space.high).astype(np.float32) for _ in range(n)]


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_check_env(env_id: str, ks_states: np.ndarray) -> None:
    env = gym.make(env_id, **_kwargs(env_id, ks_states))
    check_env(env.unwrapped, skip_render_check=True)
    assert env.spec is not None and env.spec.max_episode_steps == env.unwrapped.task.max_episode_steps


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_vector_step_equals_stacked_single_steps(env_id: str, ks_states: np.ndarray) -> None:
    n, steps = 3, 5
    rng = np.random.default_rng(0)
    single = [gym.make(env_id, **_kwargs(env_id, ks_states)) for _ in range(n)]
    obs_single = [env.reset(seed=10 + i)[0] for i, env in enumerate(single)]
    init = np.stack([env.unwrapped.state for env in single])
    vec = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **_kwargs(env_id, ks_states))
    obs_vec, _ = vec.reset(seed=0, options={"initial_state": init})
    np.testing.assert_array_equal(obs_vec, np.stack(obs_single))
    for _ in range(steps):
        acts = _actions(single[0].action_space, rng, n)
        results = [env.step(a) for env, a in zip(single, acts)]
        obs_vec, rew_vec, term_vec, _trunc_vec, _ = vec.step(np.stack(acts))
        np.testing.assert_array_equal(obs_vec, np.stack([r[0] for r in results]))
        np.testing.assert_array_equal(rew_vec, np.array([r[1] for r in results]))
        np.testing.assert_array_equal(term_vec, np.array([r[2] for r in results]))
        if term_vec.any():
            break


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_same_seed_same_trajectory(env_id: str, ks_states: np.ndarray) -> None:
    def rollout(seed: int) -> tuple[np.ndarray, np.ndarray]:
        env = gym.make(env_id, **_kwargs(env_id, ks_states))
        env.action_space.seed(seed)
        obs, _ = env.reset(seed=seed)
        traj, rews = [obs], []
        for _ in range(6):
            obs, r, term, trunc, _ = env.step(env.action_space.sample())
            traj.append(obs)
            rews.append(r)
            if term or trunc:
                break
        return np.array(traj), np.array(rews)

    a, b, c = rollout(3), rollout(3), rollout(4)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0][0], c[0][0])


def test_cartpole_matches_gymnasium() -> None:
    ours = gym.make("pimbrl/CartPole-v0")
    ref = gym.make("CartPole-v0").unwrapped
    rng = np.random.default_rng(1)
    for episode in range(5):
        _obs, _ = ours.reset(seed=episode)
        ref.reset(seed=episode)
        ref.state = ours.unwrapped.state.copy()
        while True:
            a = int(rng.integers(2))
            o1, r1, t1, tr1, _ = ours.step(a)
            o2, r2, t2, _, _ = ref.step(a)
            np.testing.assert_array_equal(ours.unwrapped.state, ref.state)
            np.testing.assert_array_equal(o1, o2)
            assert r1 == r2 and t1 == t2
            if t1 or tr1:
                break


@pytest.mark.parametrize("observation", ["theta", "cos_sin"])
def test_pendulum_matches_gymnasium(observation: str) -> None:
    ours = gym.make("pimbrl/Pendulum-v0", observation=observation)
    ref = gym.make("Pendulum-v1").unwrapped
    rng = np.random.default_rng(2)
    for episode in range(3):
        ours.reset(seed=episode)
        ref.reset(seed=episode)
        ref.state = ours.unwrapped.state.copy()
        for _ in range(200):
            a = rng.uniform(-2.5, 2.5, size=1)  # float64, partly outside the box: both clip
            o1, r1, _, tr1, _ = ours.step(a)
            o2, r2, _, _, _ = ref.step(a)
            np.testing.assert_array_equal(ours.unwrapped.state, ref.state)
            # rewards agree to one ulp: Gymnasium squares NumPy scalars with pow(), we square arrays
            assert r1 == pytest.approx(r2, rel=1e-15, abs=1e-15)
            if observation == "cos_sin":
                np.testing.assert_array_equal(o1, o2)
            if tr1:
                break


def test_initial_state_option_and_time_limit(ks_states: np.ndarray) -> None:
    env = gym.make(KS, initial_states=ks_states)
    u0 = ks_states[3]
    obs, _ = env.reset(options={"initial_state": u0})
    np.testing.assert_array_equal(obs, u0.astype(np.float32))
    env = gym.make("pimbrl/Burgers-v0")
    env.reset(seed=0)
    steps, truncated, terminated = 0, False, False
    while not (terminated or truncated):
        _, _, terminated, truncated, _ = env.step(np.zeros(2, np.float32))
        steps += 1
    assert steps == 60 and truncated and not terminated
    with pytest.raises(ValueError, match="shape"):
        env.reset(options={"initial_state": np.zeros(3)})
    with pytest.raises(ValueError, match="NaN or inf"):
        env.reset(options={"initial_state": np.full(150, np.nan)})


@pytest.mark.parametrize("env_id", [KS, "pimbrl/Burgers-v0", "pimbrl/Pendulum-v0"])
def test_nan_action_is_a_clear_error(env_id: str, ks_states: np.ndarray) -> None:
    env = gym.make(env_id, **_kwargs(env_id, ks_states))
    env.reset(seed=0)
    bad = np.zeros(env.action_space.shape, np.float32)
    bad[0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        env.step(bad)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(7, np.float32))


def test_cartpole_rejects_invalid_actions() -> None:
    env = gym.make("pimbrl/CartPole-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"0 \(push left\) or 1"):
        env.unwrapped.step(2)
    with pytest.raises(ValueError, match="NaN"):
        env.unwrapped.step(np.nan)


def test_actions_outside_the_box_are_clipped(ks_states: np.ndarray) -> None:
    env = gym.make(KS, initial_states=ks_states)
    u0 = ks_states[0]
    env.reset(options={"initial_state": u0})
    o1, r1, *_ = env.step(np.full(4, 3.0, np.float32))
    env.reset(options={"initial_state": u0})
    o2, r2, *_ = env.step(np.full(4, 0.5, np.float32))
    np.testing.assert_array_equal(o1, o2)
    assert r1 == r2


def test_blow_up_terminates_with_flag_and_finite_observation() -> None:
    # a Burgers field with negative velocities and |u| ~ 9: the backward (upwind for u > 0) scheme and the
    # advective CFL number 1.35 make explicit Euler explode within the first control step
    env = gym.make("pimbrl/Burgers-v0")
    x = env.unwrapped.physics.x
    u0 = 9.0 * np.sin(2 * np.pi * x)
    env.reset(options={"initial_state": u0})
    obs, reward, terminated, truncated, info = env.step(np.zeros(2, np.float32))
    assert terminated and not truncated and info["diverged"]
    assert np.isfinite(obs).all() and np.isfinite(reward)
    assert reward == env.unwrapped.task.divergence_penalty
    np.testing.assert_array_equal(env.unwrapped.state, u0)  # the last finite state is kept
    # the vector env flags only the diverged sub-environment
    vec = gym.make_vec("pimbrl/Burgers-v0", num_envs=2, vectorization_mode="vector_entry_point")
    vec.reset(seed=0)
    vec.reset(options={"initial_state": np.stack([u0, vec.unwrapped.states[1]])})
    obs, reward, terminated, _, info = vec.step(np.zeros((2, 2), np.float32))
    assert terminated.tolist() == [True, False] and info["diverged"].tolist() == [True, False]
    assert np.isfinite(obs).all() and np.isfinite(reward).all()


def test_vector_env_autoreset_modes() -> None:
    env_id = "pimbrl/CartPole-v0"
    # NEXT_STEP (default): the step after a termination resets, with zero reward
    vec = gym.make_vec(env_id, num_envs=4, vectorization_mode="vector_entry_point")
    assert vec.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    vec.reset(seed=0)
    done_before = np.zeros(4, bool)
    for _ in range(60):
        _, rew, term, trunc, _ = vec.step(np.ones(4, dtype=np.int64))
        assert np.all(rew[done_before] == 0.0) and not np.any(term[done_before])
        done_before = term | trunc
    # SAME_STEP: final observation reported in info, fresh observation returned
    vec = gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point", autoreset_mode=AutoresetMode.SAME_STEP)
    vec.reset(seed=0)
    for _ in range(60):
        obs, _, term, trunc, info = vec.step(np.ones(2, dtype=np.int64))
        if (term | trunc).any():
            i = int(np.argmax(term | trunc))
            assert info["_final_obs"][i]
            assert abs(info["final_obs"][i][2]) > 0.2  # the pole had fallen
            assert np.all(np.abs(obs[i]) <= 0.05)  # a fresh start state
            break
    else:
        pytest.fail("no episode ended")
    # the vector env truncates by itself at the registered time limit
    vec = gym.make_vec("pimbrl/Pendulum-v0", num_envs=2, vectorization_mode="vector_entry_point")
    vec.reset(seed=1)
    for t in range(200):
        _, _, term, trunc, _ = vec.step(np.zeros((2, 1), np.float32))
        assert not term.any()
        assert trunc.all() == (t == 199)


def test_test_initial_states_are_fixed_and_ks_takes_its_test_pool(ks_small_pools) -> None:
    for task in (BurgersTask(), PendulumTask()):
        a = task.test_initial_states(5, seed=11)
        np.testing.assert_array_equal(a, task.sample_initial_states(np.random.default_rng(11), 5))
        np.testing.assert_array_equal(a, task.test_initial_states(5, seed=11))
    train, test = ks_small_pools
    ks = KSTask(pool_config=SMALL_POOL)
    assert ks.test_pool_size == len(test.states) == SMALL_POOL.n_test
    np.testing.assert_array_equal(ks.test_initial_states(3, seed=0), test.states[:3])
    np.testing.assert_array_equal(ks.test_initial_states(3, seed=99), test.states[:3])  # the seed plays no part
    # a task that trains from given states still evaluates on the test pool
    custom = KSTask(initial_states=train.states[:2], pool_config=SMALL_POOL)
    np.testing.assert_array_equal(custom.test_initial_states(SMALL_POOL.n_test, seed=0), test.states)
    with pytest.raises(ValueError, match="test pool holds 8"):
        ks.test_initial_states(SMALL_POOL.n_test + 1, seed=0)


def test_ks_authors_protocol_takes_fixed_training_rows_and_other_tasks_refuse_it(ks_small_pools, monkeypatch) -> None:
    from pimbrl.training import Evaluator

    train, test = ks_small_pools
    ks = KSTask(pool_config=SMALL_POOL)
    assert ks.eval_protocols == ("test", "validation", "holdout", "authors")
    np.testing.assert_array_equal(ks.protocol_initial_states("test", 3, seed=0), test.states[:3])
    # the paper's rows need a training pool of at least 200 states; the small one holds 24
    with pytest.raises(ValueError, match="pool holds 24 states"):
        ks.protocol_initial_states("authors", None, seed=0)
    monkeypatch.setattr(KSTask, "AUTHORS_EVAL_ROWS", (0, 7, 23))
    np.testing.assert_array_equal(ks.protocol_initial_states("authors", None, seed=0), train.states[[0, 7, 23]])
    with pytest.raises(ValueError, match="has 3 episodes, not 5"):
        ks.protocol_initial_states("authors", 5, seed=0)
    with pytest.raises(ValueError, match="not defined for PendulumTask; choose from 'test', 'validation'"):
        PendulumTask().protocol_initial_states("authors", None, seed=0)

    ev = Evaluator("pimbrl/KuramotoSivashinsky-v0", {"pool_config": SMALL_POOL}, None, 0, protocol="authors")
    assert ev.episodes == 3
    np.testing.assert_array_equal(ev.initial_states, train.states[[0, 7, 23]])
    result = ev.run(lambda o: np.zeros((len(o), 4), np.float32))
    # the uncontrolled return of a pool state is recorded by the pool generator
    np.testing.assert_allclose(result.returns, train.uncontrolled_returns(ks.physics)[[0, 7, 23]], rtol=1e-9)
    with pytest.raises(ValueError, match="not defined for PendulumTask"):
        Evaluator("pimbrl/Pendulum-v0", {}, None, 0, protocol="authors")


def test_evaluation_quartiles_are_numpy_quantiles() -> None:
    from pimbrl.training.evaluation import EvalResult

    r = EvalResult(np.array([-5.0, -1.0, -3.0, -2.0, -4.0]), np.full(5, 400))
    assert r.quartiles() == {"return_q25": -4.0, "return_median": -3.0, "return_q75": -2.0}
