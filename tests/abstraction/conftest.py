"""Shared data of the abstraction tests."""

import numpy as np
import pytest


@pytest.fixture
def random_lps():
    """``make(seed, rest)``: the arguments of a ``ClusterLPs`` of 23 small random LPs (padding
    anywhere in the successor lists, some fixed entries, clusters of up to 4 slots)."""
    return _random_lps


def _random_lps(seed, rest):
    rng = np.random.default_rng(seed)
    p, k, j, l, n = 23, 9, 5, 4, 40
    succ = np.sort(rng.choice(n, size=(p, k)), axis=1)
    succ = np.where(rng.random((p, k)) < 0.2, n + 1, succ)  # padding anywhere
    succ = np.sort(np.where(np.diff(succ, prepend=-1, axis=1) == 0, n + 1, succ), axis=1)  # distinct ids
    upper = np.where(succ < n, rng.uniform(0.05, 0.6, (p, k)), 0.0) + rest
    lower = np.where((succ < n) & (rng.random((p, k)) < 0.3), rng.uniform(0, 0.04, (p, k)), 0.0)
    upper = np.where(rng.random((p, k)) < 0.1, lower, upper)  # some fixed entries (no variable)
    slots = np.sort(np.where(rng.random((p, j, l)) < 0.8, rng.integers(0, k, (p, j, l)), k), axis=-1)
    clo, cup = rng.uniform(0, 0.3, (p, j)), rng.uniform(0.2, 1.0, (p, j))
    return succ, lower, upper, rest, slots, clo, cup, n
