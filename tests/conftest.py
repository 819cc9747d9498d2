"""Shared fixtures. A small KS pool keeps the suite fast; the default pool is exercised by the CLI job."""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np
import pytest
import torch

import pimbrl  # noqa: F401  (registers the environments)
from pimbrl.systems import KSPoolConfig, ks_initial_state_pool

SMALL_POOL = KSPoolConfig(n_train=24, n_test=8, batch=16, seed=123)


@pytest.fixture(scope="session", autouse=True)
def _single_thread() -> None:
    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def ks_small_pools():
    """(train, test) KSPool objects from a small, fast generator config."""
    return ks_initial_state_pool("train", SMALL_POOL, verbose=False), ks_initial_state_pool("test", SMALL_POOL, verbose=False)


@pytest.fixture(scope="session")
def ks_states(ks_small_pools) -> np.ndarray:
    return ks_small_pools[0].states
