"""2I-MDP: block layout, Lemma 1 block bounds, and the tailored solver against an LP."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linprog

import smdpjax as sj
from smdpjax.abstraction import compute_grid_clusters
from smdpjax.abstraction.twolayer import TwoLayerIMDP, block_layout


def drift(x, u, w):
    return x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)


def bounded(x, u, w):
    return jnp.array([x[0] + 0.1 * u[0] + 0.08 * w[0] * (1 + x[1]), 0.9 * x[1] + 0.1 * jnp.sin(3 * x[0]) + 0.06 * w[1]])


PROBLEMS = {
    "gaussian": (sj.System(drift, actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Gaussian([0, 0], [0.6, 0.6])),
                 sj.StateGrid([0, 0], [1, 1], 8, reach=[([0.75, 0.75], [1, 1])], avoid=[([0.375, 0.25], [0.5, 0.625])]),
                 sj.NoiseGrid.ball([0, 0], 1.2, 3)),
    "uniform": (sj.System(bounded, actions=[[-1.0], [1.0]], noise=sj.Uniform([-1, -1], [1, 1])),
                sj.StateGrid([0, 0], [1, 1], [7, 6], reach=[([0.0, 0.0], [2 / 7, 1 / 3])]),
                sj.NoiseGrid.box([-1, -1], [1, 1], [3, 2])),
}


def dense_polytope(tl, row, action, grid):
    """All constraints of one (s, a) over the N+1 states, for the LP."""
    n = grid.num_states
    cells_of = np.concatenate([np.asarray(tl.cells_of), np.full((1, tl.cells_of.shape[1]), n)])  # padding block
    cells = cells_of[np.asarray(tl.blocks)[row, action]]
    lo, up = np.zeros(n), np.full(n, float(tl.upper_rest))
    valid = cells < n
    lo[cells[valid]] = np.asarray(tl.lower)[row, action][valid]
    up[cells[valid]] = np.asarray(tl.upper)[row, action][valid]
    a_ub, b_ub = [], []
    met = set()
    for t, block in enumerate(np.asarray(tl.blocks)[row, action]):
        if block >= tl.cells_of.shape[0]:
            continue
        met.add(int(block))
        members = np.asarray(tl.cells_of)[block]
        ind = np.zeros(n)
        ind[members[members < n]] = 1
        a_ub += [ind, -ind]
        b_ub += [float(tl.block_upper[row, action, t]), -float(tl.block_lower[row, action, t])]
    for block, members in enumerate(np.asarray(tl.cells_of)):
        if block not in met:  # only the remainder cell reaches it
            ind = np.zeros(n)
            ind[members[members < n]] = 1
            a_ub.append(ind)
            b_ub.append(float(tl.upper_rest))
    return lo, up, np.array(a_ub), np.array(b_ub)


def lp(values, lo, up, a_ub, b_ub):
    res = linprog(values, A_ub=a_ub, b_ub=b_ub, A_eq=np.ones((1, values.size)), b_eq=[1.0],
                  bounds=list(zip(lo, up)), method="highs")
    assert res.status == 0, res.message
    return res.fun


def test_block_layout_partitions_the_grid():
    grid = sj.StateGrid([0, 0], [1, 1], [5, 4])
    block_of, cells_of = block_layout(grid, (2, 3))
    assert cells_of.shape == (3 * 2 + 1, 6)
    listed = cells_of[cells_of <= grid.sink]
    assert sorted(listed.tolist()) == list(range(grid.num_states))  # every state in exactly one block
    for b, cells in enumerate(cells_of):
        assert np.all(block_of[cells[cells <= grid.sink]] == b)


@pytest.mark.parametrize("name, block", [("gaussian", (2, 2)), ("uniform", (2, 2)), ("uniform", (3, 2))])
def test_tailored_solver_equals_lp(name, block):
    """Blocks of 4 and 6 cells; on the 7 x 6 grid some blocks hold padding (odd sizes exercise
    the binary search over a block's sorted ranks)."""
    system, grid, noise = PROBLEMS[name]
    tl = TwoLayerIMDP.from_clusters(grid, compute_grid_clusters(system, grid, noise), block=block)
    rng = np.random.default_rng(0)
    solve = jax.jit(lambda v, adv: tl.q_values(v, adv), static_argnums=1)
    checked = 0
    for trial in range(6):
        v = rng.uniform(0, 1, grid.num_states) if trial % 3 else rng.choice([0.0, 0.5, 1.0], grid.num_states)
        v[-1] = 0.0
        q_min = np.asarray(solve(jnp.asarray(v), "min"))
        q_max = np.asarray(solve(jnp.asarray(v), "max"))
        for row in range(tl.num_rows):
            for a in range(tl.num_actions):
                poly = dense_polytope(tl, row, a, grid)
                assert q_min[row, a] == pytest.approx(lp(v, *poly), abs=1e-9)
                assert q_max[row, a] == pytest.approx(-lp(-v, *poly), abs=1e-9)
                checked += 2
    assert checked >= 900


def test_two_layer_lies_between_imdp_and_smdp():
    system, grid, noise = PROBLEMS["gaussian"]
    clusters = compute_grid_clusters(system, grid, noise)
    tl = TwoLayerIMDP.from_clusters(grid, clusters, block=(2, 2))
    imdp = sj.IMDP.from_clusters(grid, clusters)
    rng = np.random.default_rng(1)
    for _ in range(5):
        v = jnp.asarray(rng.uniform(0, 1, grid.num_states)).at[-1].set(0.0)
        assert np.all(np.asarray(tl.q_values(v, "min")) >= np.asarray(imdp.q_values(v, "min")) - 1e-12)
        assert np.all(np.asarray(tl.q_values(v, "max")) <= np.asarray(imdp.q_values(v, "max")) + 1e-12)


def test_default_block_and_abstract_option():
    system, grid, noise = PROBLEMS["uniform"]
    tl = sj.abstract(system, grid, noise, "2imdp")
    assert all(b >= 2 for b in tl.block_shape)
    tl3 = sj.abstract(system, grid, noise, "2imdp", block=3)
    assert tl3.block_shape == (3, 3)
    with pytest.raises(ValueError, match="positive"):
        sj.abstract(system, grid, noise, "2imdp", block=0)


@pytest.mark.parametrize("size", [1, 7, 16, 17, 81, 128, 200])
def test_prefix_sums_match_cumsum(size):
    from smdpjax.abstraction.twolayer import _MATMUL_PREFIX_MAX, _ONE_LEVEL_MAX, _prefix_sums

    x = np.random.default_rng(size).uniform(0, 1, (3, 4, size))
    got = np.asarray(_prefix_sums(jnp.asarray(x)))
    np.testing.assert_allclose(got, np.cumsum(x, -1), rtol=1e-15, atol=size * 1e-16)
    assert (size > _MATMUL_PREFIX_MAX) == (size == 200)  # every path is exercised
    assert (size <= _ONE_LEVEL_MAX) == (size in (1, 7, 16))


@pytest.mark.parametrize("on_cpu", [True, False])  # a sequential pass, or a cumulative sum
def test_count_table_counts_each_blocks_cells_below_every_rank(on_cpu, monkeypatch):
    from smdpjax.abstraction import twolayer
    from smdpjax.abstraction.twolayer import block_ranking

    monkeypatch.setattr(twolayer, "_on_cpu", lambda: on_cpu)
    grid = sj.StateGrid([0, 0], [1, 1], [7, 6])
    _, cells_of = block_layout(grid, (3, 2))  # partial blocks at the edge, padded
    w = jnp.asarray(np.random.default_rng(0).choice([0.0, 0.25, 1.0], grid.num_states))  # ties
    ranking = block_ranking(w, jnp.asarray(cells_of), count_table=True)
    rank = np.asarray(ranking["rank"])
    cells = np.concatenate([cells_of, np.full((1, cells_of.shape[1]), grid.num_states)])
    ranks = np.where(cells < grid.num_states, rank[np.minimum(cells, grid.num_states - 1)], grid.num_states)
    expect = (ranks[None, :, :] < np.arange(grid.num_states + 1)[:, None, None]).sum(-1)
    np.testing.assert_array_equal(np.asarray(ranking["count"]), expect)


def test_solver_same_with_count_table_or_binary_search(monkeypatch):
    from smdpjax.abstraction import twolayer

    system, grid, noise = PROBLEMS["uniform"]
    tl = TwoLayerIMDP.from_clusters(grid, compute_grid_clusters(system, grid, noise), block=(3, 2))
    v = jnp.asarray(np.random.default_rng(4).uniform(0, 1, grid.num_states)).at[-1].set(0.0)
    wants = lambda: twolayer.wants_count_table(tl.num_states, tl.cells_of.shape[0], tl.blocks.size)
    monkeypatch.setattr(twolayer, "COUNT_TABLE_READS", 0)
    assert wants()
    with_table = np.asarray(tl.q_values(v, "min"))
    monkeypatch.setattr(twolayer, "COUNT_TABLE_MAX", 0)
    assert not wants()
    np.testing.assert_array_equal(np.asarray(tl.q_values(v, "min")), with_table)


@pytest.mark.parametrize("block_rows", [0, 1, 4, 5, 9])
def test_pair_counts_cover_every_block_of_rows(block_rows):
    """``most_per_block`` of the met pairs is the most any block of rows of ``in_row_blocks``
    holds (the last block overlapping the one before it): fewer would put two pairs on one row."""
    from smdpjax.abstraction.imdp_compact import in_row_blocks, most_per_block

    met = np.random.default_rng(block_rows).integers(0, 7, 23)
    # every row gets its block's total; every block gives the result at least one row
    block_total = lambda by_row, by_chunk, rows: jnp.broadcast_to(by_row[0].sum(), by_row[0].shape)
    totals = in_row_blocks(block_total, (jnp.asarray(met),), (jnp.zeros(23),), (0.0,), jnp.arange(23),
                           (block_rows, 1))
    assert most_per_block(met, block_rows) == int(totals.max())


def test_solver_same_with_either_prefix_sum(monkeypatch):
    from smdpjax.abstraction import twolayer

    system, grid, noise = PROBLEMS["gaussian"]
    tl = TwoLayerIMDP.from_clusters(grid, compute_grid_clusters(system, grid, noise), block=(3, 3))
    v = jnp.asarray(np.random.default_rng(3).uniform(0, 1, grid.num_states)).at[-1].set(0.0)
    by_matmul = np.asarray(tl.q_values(v, "min"))
    monkeypatch.setattr(twolayer, "_MATMUL_PREFIX_MAX", 0)
    by_cumsum = np.asarray(tl.q_values(v, "min"))
    np.testing.assert_allclose(by_cumsum, by_matmul, rtol=0, atol=1e-15)


@pytest.mark.parametrize("chunk", [None, 3])
@pytest.mark.parametrize("name, block", [("gaussian", (2, 2)), ("uniform", (3, 2))])
def test_sparse_fine_layer_equals_dense_solver(name, block, chunk):
    """The chunked, sparse fine layer gives the dense solver's values (``two_layer_min`` on the
    dense ``(R, A, T, S)`` views), for every action, a fixed strategy and ``restrict``, and
    stores fewer bytes than those views."""
    from smdpjax.abstraction import twolayer

    system, grid, noise = PROBLEMS[name]
    tl = TwoLayerIMDP.from_clusters(grid, compute_grid_clusters(system, grid, noise), block=block, chunk=chunk)
    if chunk is not None:
        assert tl.chunk == chunk and tl.num_chunks > tl.num_rows
    dense = (tl.blocks, tl.block_lower, tl.block_upper, tl.lower, tl.upper)
    assert tl.nbytes < sum(np.asarray(a).nbytes for a in dense)
    assert tl.block_rows == 0 and tl.block_pairs[0] < tl.blocks.size  # capacities laid out for the met pairs only
    rng = np.random.default_rng(5)
    strategy = jnp.asarray(rng.integers(0, tl.num_actions, tl.num_rows), jnp.int32)
    q = jax.jit(lambda a, v, adversary, s: a.q_values(v, adversary, s), static_argnums=2)
    dense_min = jax.jit(lambda w: twolayer.two_layer_min(w, *dense, tl.cells_of, tl.upper_rest))
    for _ in range(3):
        v = jnp.asarray(rng.uniform(0, 1, grid.num_states)).at[-1].set(0.0)
        for adversary, sign in (("min", 1.0), ("max", -1.0)):
            expect = sign * np.asarray(dense_min(sign * v))
            got = np.asarray(q(tl, v, adversary, None))
            np.testing.assert_allclose(got, expect, rtol=0, atol=1e-15)
            fixed = np.asarray(q(tl, v, adversary, strategy))
            # the same sums in other programs (other shapes, the strategy's picks fused in), which XLA
            # may round differently in the last bit
            np.testing.assert_allclose(fixed, got[np.arange(tl.num_rows), np.asarray(strategy)], rtol=0, atol=1e-15)
            np.testing.assert_allclose(np.asarray(q(tl.restrict(strategy), v, adversary, None))[:, 0], fixed, rtol=0,
                                       atol=1e-15)


@pytest.mark.parametrize("name, rows_per_block", [("gaussian", 1), ("gaussian", 7), ("uniform", 5)])
def test_blocks_of_rows_equal_all_rows(name, rows_per_block, assert_same_q_values):
    """The inner problem a block of rows at a time (the last block overlapping the one before it,
    rows owning different numbers of chunks) gives the values of all rows at once: every action,
    a fixed strategy, ``restrict``."""
    import dataclasses

    from smdpjax.abstraction.imdp_compact import inner_blocks

    system, grid, noise = PROBLEMS[name]
    tl = TwoLayerIMDP.from_clusters(grid, compute_grid_clusters(system, grid, noise), block=(2, 2), chunk=3)
    rows = tl.num_rows
    counts = np.bincount(np.asarray(tl.chunk_row))
    assert counts.min() < counts.max() and (rows % rows_per_block or rows_per_block == 1)
    whole = dataclasses.replace(tl, block_rows=0, block_chunks=0, strategy_blocks=(0, 0))
    blocks = lambda actions: inner_blocks(tl.chunk_row, rows, actions, budget=actions * rows_per_block)
    blocked = dataclasses.replace(tl, block_rows=blocks(tl.num_actions)[0], block_chunks=blocks(tl.num_actions)[1],
                                  strategy_blocks=blocks(1))
    assert blocked.block_rows == rows_per_block == blocked.strategy_blocks[0]
    rng = np.random.default_rng(rows_per_block)
    strategy = jnp.asarray(rng.integers(0, tl.num_actions, rows), jnp.int32)
    values = [jnp.asarray(rng.uniform(0, 1, grid.num_states)).at[-1].set(0.0) for _ in range(2)]
    assert_same_q_values(blocked, whole, values, strategy, atol=1e-15)


def test_fine_slots_find_each_successors_block_in_its_list():
    """The slot ``t S + i`` of each listed successor against NumPy's search of each list's sorted
    blocks."""
    from smdpjax.abstraction import twolayer

    cells, block = (9, 8), (3, 2)
    block_of, cells_of, offset_of = (np.asarray(a) for a in twolayer._layout(cells, block)[:3])
    num_blocks, size = cells_of.shape[0] - 1, cells_of.shape[1]
    n = int(np.prod(cells))  # cells; the sink is n, padding n + 1
    rng = np.random.default_rng(1)
    lists, t_count, width = (5, 3), 6, 10
    blocks = np.full(lists + (t_count,), num_blocks + 1, np.int16)
    succ = np.full(lists + (width,), n + 1, np.int32)
    for r in np.ndindex(lists):
        met = np.sort(rng.choice(num_blocks + 1, rng.integers(1, t_count + 1), replace=False))
        blocks[r][:met.size] = met
        states = np.concatenate([cells_of[b][cells_of[b] <= n] for b in met])  # the sink is block B's
        chosen = rng.choice(states, min(width - 2, states.size), replace=False)
        succ[r][:chosen.size] = chosen
        succ[r] = rng.permutation(succ[r])
    got = np.asarray(twolayer._fine_slots(jnp.asarray(succ), jnp.asarray(blocks), jnp.asarray(block_of),
                                          jnp.asarray(offset_of), size))
    listed = succ <= n
    t = np.zeros_like(succ)
    for r in np.ndindex(lists):
        t[r] = np.searchsorted(blocks[r], block_of[np.minimum(succ[r], n + 1)])
    expected = np.where(listed, t * size + offset_of[np.minimum(succ, n + 1)], t_count * size)
    np.testing.assert_array_equal(got, expected)
    assert listed.sum() > 20 and (~listed).sum() > 0


def test_block_budget_sets_blocks_and_their_pairs(assert_same_q_values):
    """``with_block_budget`` re-blocks the rows and lays the capacities out for the most met
    pairs of its blocks (all rows' pairs at budget 0): the same values as all rows at once."""
    from smdpjax.abstraction.imdp_compact import most_per_block

    system, grid, noise = PROBLEMS["gaussian"]
    tl = TwoLayerIMDP.from_clusters(grid, compute_grid_clusters(system, grid, noise), block=(2, 2), chunk=3)
    met = np.asarray(tl.blocks < tl.cells_of.shape[0]).sum(-1)  # (R, A)
    slots = tl.num_block_slots * tl.cells_of.shape[1] + tl.num_chunks * tl.chunk / tl.num_rows
    whole = tl.with_block_budget(0)
    assert whole.block_rows == 0 and whole.block_pairs == (met.sum(), met.max(1).sum())
    blocked = tl.with_block_budget(int(7 * tl.num_actions * slots) + 1)
    assert blocked.block_rows == 7 and blocked.strategy_blocks[0] == int(7 * tl.num_actions)
    assert blocked.block_pairs == (most_per_block(met.sum(1), 7), most_per_block(met.max(1), blocked.strategy_blocks[0]))
    assert blocked.block_pairs[0] < whole.block_pairs[0]
    rng = np.random.default_rng(8)
    strategy = jnp.asarray(rng.integers(0, tl.num_actions, tl.num_rows), jnp.int32)
    values = [jnp.asarray(rng.uniform(0, 1, grid.num_states)).at[-1].set(0.0) for _ in range(2)]
    assert_same_q_values(blocked, whole, values, strategy, atol=1e-15)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("longest", [40, 130])  # 130: medians among extents past EXTENT_BINS
def test_default_block_is_the_median_extent_of_the_nonempty_boxes(seed, longest):
    from smdpjax.abstraction.clusters import IndexBoxes
    from smdpjax.abstraction.twolayer import default_block

    rng = np.random.default_rng(seed)
    length = rng.integers(1, [4, 9, longest], (30, 2, 5, 3)).astype(np.int32)
    length[rng.random(length.shape[:-1]) < 0.3, rng.integers(0, 3)] = 0  # empty boxes do not count
    boxes = IndexBoxes(start=jnp.zeros_like(length), length=jnp.asarray(length), sink=jnp.zeros(length.shape[:-1], bool))
    flat = length.reshape(-1, 3)
    kept = flat[np.all(flat > 0, axis=1)]
    expected = tuple(int(max(2, round(np.median(kept[:, d])))) for d in range(3))
    assert default_block(type("Clusters", (), {"boxes": boxes})()) == expected
    nothing = IndexBoxes(start=jnp.zeros((2, 1, 1, 3), jnp.int32), length=jnp.zeros((2, 1, 1, 3), jnp.int32),
                         sink=jnp.ones((2, 1, 1), bool))
    assert default_block(type("Clusters", (), {"boxes": nothing})()) == (2, 2, 2)


@pytest.mark.parametrize("size", [1, 2, 7, 8, 1000])
def test_median_of_counts_is_numpys_median(size):
    from smdpjax.abstraction.twolayer import _median_count

    rng = np.random.default_rng(size)
    for _ in range(20):
        values = rng.integers(1, 9, size)
        assert _median_count(np.bincount(values)) == np.median(values)
