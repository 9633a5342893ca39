"""Structured SMDP clusters for additive noise: the stored index boxes' values, bit for bit."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.abstraction import SMDP, compute_grid_clusters
from smdpjax.abstraction.structured import diagonal_noise_boxes, noise_axes


def _unicycle_g(x, u):
    return jnp.array([x[0] + 0.1 * u[0] * jnp.cos(x[2]), x[1] + 0.1 * u[0] * jnp.sin(x[2]), x[2] + 0.1 * u[1]])


def _problems():
    """(system, grid, noise grid): a 2-D drift with a diagonal B and bounded noise, a 3-D
    nonlinear g with a periodic heading, a permuted B and Gaussian noise with a remainder, and
    a 3-D system with noise along one axis only."""
    drift = sj.System.additive(lambda x, u: x + 0.1 * u, [0.1, 0.05], actions=[[1.0, 0.0], [0.0, -1.0], [0.5, 0.5]],
                               noise=sj.Uniform([-1, -1], [1, 1]))
    drift_grid = sj.StateGrid([0, 0], [1, 1], [12, 10], reach=[([0.75, 0.7], [1, 1])], avoid=[([0.4, 0.4], [0.5, 0.6])])
    B = np.array([[0.0, 0.03], [0.02, 0.0], [0.0, 0.1]])  # state dims 0 and 2 driven by noise axis 1
    unicycle = sj.System.additive(_unicycle_g, B, actions=[[1.0, -3.0], [1.0, 3.0], [0.5, 0.0]],
                                  noise=sj.Gaussian([0.0, 0.0], [1.0, 1.0]))
    unicycle_grid = sj.StateGrid([0, 0, 0], [1, 1, 2 * np.pi], [9, 8, 10], periodic=[False, False, True],
                                 reach=[([0.7, 0.7, 0], [1, 1, 2 * np.pi])])
    return [(drift, drift_grid, sj.NoiseGrid.box([-1, -1], [1, 1], [3, 4])),
            (unicycle, unicycle_grid, sj.NoiseGrid.ball([0, 0], 2.0, [4, 5]))]


@pytest.mark.parametrize("case", [0, 1])
def test_structured_clusters_are_the_stored_index_boxes(case):
    system, grid, noise = _problems()[case]
    stored = compute_grid_clusters(system, grid, noise, method="natural", structured=False)
    smdp = SMDP.structured(system, grid, noise, method="natural")
    via_pieces = compute_grid_clusters(system, grid, noise, method="natural", compact=True)
    assert via_pieces.boxes.start.dtype == np.int8
    boxes = smdp.clusters.index_boxes()
    for field in ("start", "length", "sink"):
        np.testing.assert_array_equal(np.asarray(getattr(boxes, field)), np.asarray(getattr(stored.boxes, field)))
        np.testing.assert_array_equal(np.asarray(getattr(via_pieces.boxes, field)),
                                      np.asarray(getattr(stored.boxes, field)))
    reference = SMDP.from_clusters(grid, stored, encoding="boxes")
    assert smdp.clusters.shape == reference.clusters.shape
    assert smdp.clusters.spec == reference.clusters.spec
    assert smdp.nbytes < reference.nbytes
    rng = np.random.default_rng(case)
    for _ in range(3):
        v = jnp.asarray(rng.random(grid.num_states))
        for adversary in ("min", "max"):
            np.testing.assert_array_equal(np.asarray(jax.jit(lambda a, v: a.q_values(v, adversary))(smdp, v)),
                                          np.asarray(reference.q_values(v, adversary)))
    low, ref_low = sj.synthesize(smdp), sj.synthesize(reference)
    np.testing.assert_array_equal(np.asarray(low.lower), np.asarray(ref_low.lower))
    np.testing.assert_array_equal(np.asarray(low.upper), np.asarray(ref_low.upper))
    np.testing.assert_array_equal(np.asarray(low.policy), np.asarray(ref_low.policy))
    np.testing.assert_array_equal(np.asarray(smdp.members), np.asarray(reference.members))


def test_abstract_builds_structured_clusters_and_a_fixed_policy_restricts_them():
    system, grid, noise = _problems()[0]
    smdp = sj.abstract(system, grid, noise, "smdp", method="natural", encoding="structured")
    assert smdp.encoding == "structured" and "structured" in repr(smdp)
    policy = np.random.default_rng(1).integers(0, system.num_actions, grid.num_cells)
    fixed = sj.abstract(system, grid, noise, "smdp", method="natural", encoding="structured", policy=policy)
    reference = sj.abstract(system, grid, noise, "smdp", method="natural", policy=policy)
    np.testing.assert_array_equal(np.asarray(sj.verify(fixed).lower), np.asarray(sj.verify(reference).lower))
    restricted = smdp.restrict(jnp.asarray(policy[np.asarray(smdp.rows)]))
    v = jnp.asarray(np.random.default_rng(2).random(grid.num_states))
    np.testing.assert_array_equal(np.asarray(restricted.q_values(v)), np.asarray(fixed.q_values(v)))


def test_noise_axes_and_diagonal_boxes():
    system, _, noise = _problems()[1]
    np.testing.assert_array_equal(noise_axes(system), [1, 0, 1])
    w_lo, w_hi = diagonal_noise_boxes(noise)  # 4 x 5 cells: 5 boxes, axis 0 stops at its last cell
    assert w_lo.shape == (5, 2)
    np.testing.assert_array_equal(w_lo[:, 0], np.asarray(noise.edges[0])[[0, 1, 2, 3, 3]])
    np.testing.assert_array_equal(w_hi[:, 1], np.asarray(noise.edges[1])[1:])


def test_structured_needs_one_noise_axis_per_dimension():
    plain = sj.System(lambda x, u, w: x + 0.1 * u + w, actions=np.eye(2), noise=sj.Uniform([-1, -1], [1, 1]))
    grid, noise = sj.StateGrid([0, 0], [1, 1], 4), sj.NoiseGrid.box([-1, -1], [1, 1], 2)
    with pytest.raises(ValueError, match="System.additive"):
        SMDP.structured(plain, grid, noise)
    mixed = sj.System.additive(lambda x, u: x + 0.1 * u, [[0.1, 0.1], [0.0, 0.1]], actions=np.eye(2),
                               noise=sj.Uniform([-1, -1], [1, 1]))
    with pytest.raises(ValueError, match="one nonzero per row"):
        sj.abstract(mixed, grid, noise, "smdp", encoding="structured")
    with pytest.raises(ValueError, match="built from the system"):
        SMDP.from_clusters(grid, compute_grid_clusters(mixed, grid, noise), encoding="structured")


def test_auto_picks_structured_where_it_halves_the_memory():
    system, grid, noise = _problems()[0]  # 3 x 4 noise cells: 12 x 5 bytes stored, 4 x 6 structured
    assert sj.abstract(system, grid, noise, "smdp", method="natural").encoding == "structured"
    assert sj.abstract(system, grid, noise, "smdp", method="natural", encoding="boxes").encoding == "boxes"
    one_axis = sj.NoiseGrid.box([-1, -1], [1, 1], [3, 1])  # 3 stored boxes vs 3 pieces: no gain
    assert sj.abstract(system, grid, one_axis, "smdp", method="natural").encoding == "boxes"
    plain = sj.System(system.dynamics, actions=system.actions, noise=system.noise)  # not declared additive
    assert sj.abstract(plain, grid, noise, "smdp", method="natural").encoding == "boxes"
