import time

import numpy as np
import pytest

import smdpjax as sj
from smdpjax import memory
from smdpjax.abstraction import compute_grid_clusters


def test_a_grid_that_cannot_fit_is_refused_at_once():
    start = time.perf_counter()
    with pytest.raises(memory.InsufficientMemoryError, match=r"8e\+09 cells .* GiB.*available; use fewer cells"):
        sj.StateGrid([0, 0, 0], [1, 1, 1], 2000)  # numpy used to fail on a 59.6 GiB array
    assert time.perf_counter() - start < 5.0


def test_clusters_are_refused_before_any_reachable_set(monkeypatch):
    system = sj.System(lambda x, u, w: x + 0.1 * u + w, actions=np.eye(2), noise=sj.Gaussian([0, 0], [0.1, 0.1]))
    grid = sj.StateGrid([0, 0], [1, 1], 20)
    noise = sj.NoiseGrid.ball([0, 0], 0.3, 4)
    compute_grid_clusters(system, grid, noise)  # fits
    calls = []
    monkeypatch.setattr(memory, "available_bytes", lambda: 100_000)
    monkeypatch.setattr(sj.abstraction.grid_clusters, "_chunk_fn", lambda *a: calls.append(a))
    with pytest.raises(memory.InsufficientMemoryError, match=r"clusters of 400 cells x 32 .* coarser state grid"):
        compute_grid_clusters(system, grid, noise)
    assert not calls  # nothing compiled or computed


def test_available_memory_and_sizes():
    assert memory.available_bytes() > 0
    assert memory.format_bytes(512) == "512 B"
    assert memory.format_bytes(3 * 2**30) == "3.0 GiB"
    memory.require(1.0, "one byte", "-")  # fits
