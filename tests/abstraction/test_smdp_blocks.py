"""SMDP backups over blocks of rows (``backup_rows``): the values of one block, every encoding."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.abstraction import SMDP, smdp as smdp_module


def _problem():
    system = sj.System.additive(lambda x, u: x + 0.1 * u, [0.1, 0.05], actions=[[1.0, 0.0], [0.0, -1.0], [0.5, 0.5]],
                                noise=sj.Gaussian([0, 0], [1, 1]))
    grid = sj.StateGrid([0, 0], [1, 1], [13, 11], reach=[([0.75, 0.7], [1, 1])], avoid=[([0.4, 0.4], [0.5, 0.6])])
    return system, grid, sj.NoiseGrid.ball([0, 0], 2.0, [3, 4])


@pytest.mark.parametrize("encoding", ["boxes", "structured", "members"])
def test_blocks_of_rows_give_the_one_block_backup(encoding):
    system, grid, noise = _problem()
    whole = sj.abstract(system, grid, noise, "smdp", encoding=encoding)
    whole = dataclasses.replace(whole, backup_rows=0)
    rows = whole.num_rows
    assert whole.block_rows() == rows and rows % 7 != 0  # 7-row blocks leave a rest
    q = jax.jit(lambda a, v, adversary, act: a.q_values(v, adversary, act), static_argnums=2)
    rng = np.random.default_rng(0)
    strategy = jnp.asarray(rng.integers(0, whole.num_actions, rows), jnp.int32)
    for block in (1, 7, rows - 1):
        part = dataclasses.replace(whole, backup_rows=block)
        assert part.block_rows() == block
        for _ in range(2):
            v = jnp.asarray(rng.uniform(size=grid.num_states))
            for adversary in ("min", "max"):
                # a dot over fewer rows may add the noise cells in another order: 1 ulp at most
                np.testing.assert_allclose(np.asarray(q(part, v, adversary, None)),
                                           np.asarray(q(whole, v, adversary, None)), rtol=0, atol=4e-16)
                np.testing.assert_allclose(np.asarray(q(part, v, adversary, strategy)),
                                           np.asarray(q(whole, v, adversary, strategy)), rtol=0, atol=4e-16)
    a, b = sj.synthesize(whole), sj.synthesize(dataclasses.replace(whole, backup_rows=7))
    np.testing.assert_allclose(np.asarray(b.lower), np.asarray(a.lower), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(b.upper), np.asarray(a.upper), rtol=0, atol=1e-12)


def test_default_block_from_the_byte_budget(monkeypatch):
    system, grid, noise = _problem()
    smdp = sj.abstract(system, grid, noise, "smdp", encoding="boxes")
    r, a, c = smdp.clusters.shape
    assert smdp.backup_rows is None and smdp.block_rows() == r  # small: one block
    monkeypatch.setattr(smdp_module, "BACKUP_BLOCK_BYTES", 10 * a * c * smdp_module.BYTES_PER_CLUSTER)
    assert smdp.block_rows() == 10
    monkeypatch.setattr(smdp_module, "BACKUP_BLOCK_BYTES", 1)
    assert smdp.block_rows() == 1  # never fewer than one row
    assert isinstance(smdp, SMDP)
