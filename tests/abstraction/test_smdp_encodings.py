"""The SMDP's two cluster encodings (index boxes + range minima, padded member lists) are the same
abstraction: equal clusters, equal inner problems (exactly: a min is exact), equal synthesis."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.abstraction import SMDP, compute_grid_clusters
from smdpjax.abstraction.smdp import BoxClusters, MemberClusters

DT = 0.1


def linear_unicycle(x, u, w):
    """The 2-D unicycle of benchmarks/core_2d.py: heading u fixed per action, linear in x and w."""
    return x + DT * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)


def car(x, u, w):
    """Constant speed, heading x[2] (periodic) turned by the action: nonlinear in the state."""
    return jnp.array([x[0] + 0.25 * jnp.cos(x[2]) + 0.01 * w[0], x[1] + 0.25 * jnp.sin(x[2]) + 0.01 * w[1],
                      x[2] + u[0] + 0.1 * w[1]])


def unicycle_2d():
    system = sj.System(linear_unicycle, actions=(np.arange(8) * np.pi / 4)[:, None],
                       noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 16, reach=[([0.8, 0.8], [1.0, 1.0])],
                        avoid=[([0.40, 0.30], [0.60, 0.70]), ([0.75, 0.50], [0.90, 0.65])])
    return system, grid, sj.NoiseGrid.ball([0.0, 0.0], 2.1, 8)


def car_3d():
    system = sj.System(car, actions=[[-np.pi / 4], [0.0], [np.pi / 4]], noise=sj.Gaussian([0.0, 0.0], [1.0, 1.0]))
    grid = sj.StateGrid([0, 0, 0], [1, 1, 2 * np.pi], [8, 8, 16], periodic=[False, False, True],
                        reach=[([0.5, 0.0, 0], [1, 1, 2 * np.pi])], avoid=[([0.2, 0.4, 0], [0.4, 0.6, 2 * np.pi])])
    return system, grid, sj.NoiseGrid.ball([0.0, 0.0], 2.0, [3, 3])


@functools.lru_cache(maxsize=None)
def build_pair(name):
    """(grid, SMDP with index boxes, SMDP with member lists) built from the same clusters."""
    system, grid, noise = (unicycle_2d if name == "2d_linear" else car_3d)()
    clusters = compute_grid_clusters(system, grid, noise)
    boxes = SMDP.from_clusters(grid, clusters)
    members = SMDP.from_clusters(grid, clusters, encoding="members")
    return grid, boxes, members


@pytest.fixture(scope="module", params=["2d_linear", "3d_periodic"])
def pair(request):
    return build_pair(request.param)


def random_values(grid, seed):
    """Values in [0, 1] with many ties (few distinct levels), reach cells 1, avoid cells and sink 0."""
    rng = np.random.default_rng(seed)
    v = rng.integers(0, 12, grid.num_states) / 11.0
    labels = np.asarray(grid.state_labels)
    v = np.where(labels == sj.partition.REACH, 1.0, np.where(labels == sj.partition.AVOID, 0.0, v))
    v[grid.sink] = rng.choice([0.0, 0.5])
    return jnp.asarray(v)


def test_auto_picks_boxes_and_members_can_be_forced(pair):
    grid, boxes, members = pair
    assert boxes.encoding == "boxes" and isinstance(boxes.clusters, BoxClusters)
    assert members.encoding == "members" and isinstance(members.clusters, MemberClusters)
    assert boxes.clusters.start.dtype == jnp.int8  # every grid axis has < 128 cells
    assert boxes.clusters.spec.cells == tuple(grid.cells.tolist())
    assert boxes.clusters.spec.periodic == tuple(grid.periodic.tolist())
    assert "encoding=boxes" in repr(boxes) and "encoding=members" in repr(members)


def test_boxes_expand_to_the_same_member_lists(pair):
    _, boxes, members = pair
    expanded = boxes.members
    assert expanded.dtype == members.members.dtype
    np.testing.assert_array_equal(np.asarray(expanded), np.asarray(members.members))


def test_periodic_case_has_wrapping_clusters():
    grid, boxes, _ = build_pair("3d_periodic")
    assert grid.periodic[2]
    c = boxes.clusters
    wraps = np.asarray(c.start[..., 2]).astype(int) + np.asarray(c.length[..., 2]) > grid.cells[2]
    assert wraps.any()  # the seam at 2 pi is exercised


@pytest.mark.parametrize("adversary", ["min", "max"])
def test_q_values_are_identical(pair, adversary):
    grid, boxes, members = pair
    rng = np.random.default_rng(1)
    actions = jnp.asarray(rng.integers(0, boxes.num_actions, boxes.num_rows), jnp.int32)
    q = jax.jit(lambda a, v, act: a.q_values(v, adversary, act))
    for seed in range(3):
        v = random_values(grid, seed)
        all_b, all_m = boxes.q_values(v, adversary), members.q_values(v, adversary)
        assert all_b.shape == (boxes.num_rows, boxes.num_actions)
        np.testing.assert_array_equal(np.asarray(all_b), np.asarray(all_m))
        one_b, one_m = q(boxes, v, actions), q(members, v, actions)
        assert one_b.shape == (boxes.num_rows,)
        np.testing.assert_array_equal(np.asarray(one_b), np.asarray(one_m))
        # a fixed action is the same inner problem (up to the order of the sum's terms: 1 ulp)
        np.testing.assert_allclose(np.asarray(one_b), np.asarray(all_b)[np.arange(boxes.num_rows), actions],
                                   rtol=4e-16, atol=0)
        np.testing.assert_array_equal(np.asarray(boxes.restrict(actions).q_values(v, adversary))[:, 0],
                                      np.asarray(members.restrict(actions).q_values(v, adversary))[:, 0])


def test_cluster_extremes_match_member_lists_per_cluster(pair):
    """Cluster by cluster (no noise-probability sum that could hide a wrong min): the range minimum
    over the box plus the sink flag is the minimum over the cluster's members."""
    grid, boxes, members = pair
    v = jnp.asarray(np.random.default_rng(7).normal(size=grid.num_states))  # distinct values: no ties
    for minimize in (True, False):
        np.testing.assert_array_equal(np.asarray(boxes.clusters.extreme(v, minimize)),
                                      np.asarray(members.clusters.extreme(v, minimize)))


def test_boxes_are_much_smaller(pair):
    _, boxes, members = pair
    c = boxes.clusters
    shared = sum(np.asarray(x).nbytes for x in (boxes.prob, boxes.prob_rest, boxes.rows, boxes.labels))
    # the paper's metric counts the arrays only; the static grid spec is no leaf
    assert boxes.nbytes == shared + c.start.nbytes + c.length.nbytes + c.sink.nbytes
    assert boxes.nbytes - shared < (members.nbytes - shared) / 2


def test_jit_and_vmap_over_probabilities(pair):
    grid, boxes, members = pair
    v = random_values(grid, 3)
    scales = jnp.linspace(0.5, 1.0, 3)

    def lowest(smdp, s):
        return smdp.with_probabilities(smdp.prob * s, smdp.prob_rest).q_values(v, "min").max(axis=1)

    batched = jax.jit(jax.vmap(lowest, in_axes=(None, 0)))
    np.testing.assert_array_equal(np.asarray(batched(boxes, scales)), np.asarray(batched(members, scales)))


def test_synthesis_is_identical(pair):
    _, boxes, members = pair
    sol_b, sol_m = sj.synthesize(boxes, tol=1e-9), sj.synthesize(members, tol=1e-9)
    assert sol_b.converged and sol_b.iterations == sol_m.iterations
    assert sol_b.evaluation_iterations == sol_m.evaluation_iterations
    for name in ("lower", "upper", "policy", "lower_optimal"):
        np.testing.assert_array_equal(np.asarray(getattr(sol_b, name)), np.asarray(getattr(sol_m, name)))
    lower = np.asarray(sol_b.lower)[np.asarray(boxes.rows)]
    assert np.mean(lower > 0.01) > 0.05 and np.unique(lower).size > 5  # values worth comparing
    fin_b, fin_m = sj.synthesize(boxes, horizon=6), sj.synthesize(members, horizon=6)
    for name in ("lower", "upper", "policy"):
        np.testing.assert_array_equal(np.asarray(getattr(fin_b, name)), np.asarray(getattr(fin_m, name)))


def test_unknown_encoding():
    system, grid, noise = unicycle_2d()
    with pytest.raises(ValueError, match="encoding"):
        sj.abstract(system, grid, noise, "smdp", encoding="dense")
