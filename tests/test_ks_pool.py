"""KS initial-state pools: seeded, disjoint, chaotic, cached; recorded uncontrolled returns are right."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from pimbrl.systems import KSPoolConfig, KuramotoSivashinsky, ks_initial_state_pool
from pimbrl.systems import ks as ks_states_module

from .conftest import SMALL_POOL


def test_pools_are_disjoint_and_finite(ks_small_pools) -> None:
    train, test = ks_small_pools
    assert train.states.shape == (SMALL_POOL.n_train, 64) and test.states.shape == (SMALL_POOL.n_test, 64)
    assert np.isfinite(train.states).all() and np.isfinite(test.states).all()
    dist = np.linalg.norm(train.states[:, None, :] - test.states[None, :, :], axis=-1)
    assert dist.min() > 1e-3
    # snapshots of one run are spaced apart: no near-duplicates inside a pool
    d_train = np.linalg.norm(train.states[:, None] - train.states[None], axis=-1) + np.eye(len(train.states)) * 1e9
    assert d_train.min() > 1e-3


def test_recorded_uncontrolled_returns_match_a_fresh_simulation(ks_small_pools) -> None:
    train, _ = ks_small_pools
    physics = KuramotoSivashinsky()
    returns = train.uncontrolled_returns(physics)
    env = gym.make("pimbrl/KuramotoSivashinsky-v0", initial_states=train.states)
    for i in (0, len(returns) - 1):
        env.reset(options={"initial_state": train.states[i]})
        total, done = 0.0, False
        while not done:
            _, r, term, trunc, _ = env.step(np.zeros(4, np.float32))
            total += r
            done = term or trunc
        assert total == pytest.approx(returns[i], rel=1e-10)
    # chaotic-phase episodes: about -0.6 per step, far from the settled state's -2.3 per step (-920)
    assert np.all(returns > -600) and np.all(returns < -100)
    # the physical reward reuses the same recorded integrands
    assert np.all(train.uncontrolled_returns(KuramotoSivashinsky(reward="physical")) < 0)


def test_pool_is_seeded_and_cached(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("PIMBRL_CACHE_DIR", str(tmp_path))
    cfg = KSPoolConfig(n_train=4, n_test=2, batch=8, seed=7)
    a = ks_initial_state_pool("test", cfg, verbose=False)
    files = list((tmp_path / "ks_pools").glob("*.npz"))
    assert len(files) == 1
    ks_states_module._MEMO.clear()
    b = ks_initial_state_pool("test", cfg, verbose=False)  # from disk
    np.testing.assert_array_equal(a.states, b.states)
    # a corrupt cache entry is regenerated, not trusted
    files[0].write_bytes(b"not an npz file")
    ks_states_module._MEMO.clear()
    c = ks_initial_state_pool("test", cfg, verbose=False)
    np.testing.assert_array_equal(a.states, c.states)
    # another seed gives other states
    ks_states_module._MEMO.clear()
    d = ks_initial_state_pool("test", KSPoolConfig(n_train=4, n_test=2, batch=8, seed=8), verbose=False)
    assert not np.allclose(a.states, d.states)


def test_bad_pool_arguments() -> None:
    with pytest.raises(ValueError, match="split"):
        ks_initial_state_pool("heldout")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n_train"):
        KSPoolConfig(n_train=0)
    with pytest.raises(ValueError, match="initial_states"):
        gym.make("pimbrl/KuramotoSivashinsky-v0", initial_states="holdout")
    with pytest.raises(ValueError, match="shape"):
        gym.make("pimbrl/KuramotoSivashinsky-v0", initial_states=np.zeros((3, 10)))


def test_pools_are_cached_per_simulator_kernel(monkeypatch) -> None:
    """A new kernel changes the chaotic runs at round-off: its pools must not be those of the previous one."""
    from pimbrl.systems import KuramotoSivashinsky
    from pimbrl.systems import ks as ks_states

    physics, cfg = KuramotoSivashinsky(), ks_states.KSPoolConfig()
    key = ks_states._cache_key(physics, cfg)
    monkeypatch.setattr(ks_states, "GENERATOR_VERSION", "999")
    assert ks_states._cache_key(physics, cfg) != key
