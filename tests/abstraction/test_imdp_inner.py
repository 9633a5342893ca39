"""The IMDP inner problem against a general LP solver, on random interval polytopes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linprog

from smdpjax.abstraction import imdp as imdp_module
from smdpjax.abstraction import interval_min
import smdpjax as sj


def random_instance(rng, n_states, k, rest):
    succ = rng.choice(n_states, size=k, replace=False)
    lower = rng.uniform(0, 1, k) * rng.integers(0, 2, k)
    lower *= rng.uniform(0.2, 0.9) / max(lower.sum(), 1e-12)
    upper = lower + rng.uniform(0, 0.6, k) + rest
    unlisted = n_states - k
    if upper.sum() + unlisted * rest < 1:  # make it feasible
        upper *= (1 - unlisted * rest) / upper.sum() + 0.05
    values = rng.choice([0.0, 0.25, 0.5, 1.0], size=n_states) if rng.uniform() < 0.3 else rng.uniform(0, 1, n_states)
    return succ, lower, upper, values


def lp_min(succ, lower, upper, rest, values):
    n = values.size
    lo = np.zeros(n)
    hi = np.full(n, rest)
    lo[succ], hi[succ] = lower, upper
    res = linprog(values, A_eq=np.ones((1, n)), b_eq=[1.0], bounds=list(zip(lo, hi)), method="highs")
    assert res.status == 0
    return res.fun


@pytest.mark.parametrize("explicit_columns", [0, 48], ids=["reduction", "columns"])
@pytest.mark.parametrize("rest", [0.0, 1e-3, 0.02])
def test_interval_min_matches_lp(rest, explicit_columns, monkeypatch):
    # both ways of summing over successors (chosen by K) must solve the same problem exactly
    monkeypatch.setattr(imdp_module, "_EXPLICIT_COLUMNS", explicit_columns)
    rng = np.random.default_rng(int(rest * 1e4))
    n_states, k = 40, 9
    inst = [random_instance(rng, n_states, k, rest) for _ in range(300)]
    pad = np.full((len(inst), 3), n_states + 1)
    succ = jnp.asarray(np.c_[np.stack([i[0] for i in inst]), pad])[:, None]
    lower = jnp.asarray(np.c_[np.stack([i[1] for i in inst]), 0 * pad])[:, None]
    upper = jnp.asarray(np.c_[np.stack([i[2] for i in inst]), 0 * pad])[:, None]
    values = jnp.asarray(np.stack([i[3] for i in inst]))
    solve = jax.vmap(interval_min, in_axes=(0, 0, 0, 0, None))  # traced afresh: the monkeypatch applies
    got_min = np.asarray(solve(values, succ, lower, upper, rest))[:, 0]
    got_max = -np.asarray(solve(-values, succ, lower, upper, rest))[:, 0]
    expect_min = [lp_min(i[0], i[1], i[2], rest, i[3]) for i in inst]
    expect_max = [-lp_min(i[0], i[1], i[2], rest, -i[3]) for i in inst]
    np.testing.assert_allclose(got_min, expect_min, atol=1e-9)
    np.testing.assert_allclose(got_max, expect_max, atol=1e-9)


def test_interval_min_batched_rows_are_independent():
    rng = np.random.default_rng(7)
    n_states, k, rest = 30, 6, 0.01
    inst = [random_instance(rng, n_states, k, rest) for _ in range(20)]
    values = inst[0][3]
    succ = np.stack([i[0] for i in inst])
    lower = np.stack([i[1] for i in inst])
    upper = np.stack([i[2] for i in inst])
    got = np.asarray(interval_min(jnp.asarray(values), jnp.asarray(succ), jnp.asarray(lower),
                                  jnp.asarray(upper), rest))
    expect = [lp_min(s, l, u, rest, values) for s, l, u in zip(succ, lower, upper)]
    np.testing.assert_allclose(got, expect, atol=1e-9)


def random_padded_imdp(rng, n_states, rows, actions, rest, max_k=12, pad=3):
    """A padded IMDP with lists of varying width (so that rows need different numbers of chunks) and up
    to three positive lower bounds per list, listed entries in increasing order."""
    from smdpjax.partition import NONTERMINAL

    k = max_k + pad
    succ = np.full((rows, actions, k), n_states, np.int64)
    lower, upper = np.zeros((rows, actions, k)), np.zeros((rows, actions, k))
    for r in range(rows):
        width = rng.integers(2, max_k + 1) if r % 3 else max_k  # row widths differ; each row has its own
        for a in range(actions):
            s, lo, up, _ = random_instance(rng, n_states, int(rng.integers(1, width + 1)), rest)
            keep = np.argsort(s)
            lo = lo[keep] * (rng.uniform(size=s.size) < 0.4)  # sparse lower bounds
            succ[r, a, :s.size], lower[r, a, :s.size], upper[r, a, :s.size] = s[keep], lo, up[keep]
    labels = np.full(n_states, NONTERMINAL, np.int8)
    return sj.IMDP(successors=jnp.asarray(succ, jnp.int16), lower=jnp.asarray(lower), upper=jnp.asarray(upper),
                   upper_rest=jnp.asarray(rest), rows=jnp.arange(rows, dtype=jnp.int32), labels=jnp.asarray(labels))


@pytest.mark.parametrize("rest, explicit_columns, chunk", [
    (0.0, 48, None), (1e-3, 48, 1), (0.02, 48, 4), (0.0, 48, 20), (0.02, 0, None), (1e-3, 0, 4)])
def test_compact_imdp_equals_padded_and_lp(rest, explicit_columns, chunk, monkeypatch):
    """Chunked lists and sparse lower bounds solve the padded IMDP's inner problem: against the
    LP and against ``interval_min`` on the padded lists, every action, a fixed strategy, ``restrict``."""
    from smdpjax.abstraction import imdp_compact

    monkeypatch.setattr(imdp_compact, "_EXPLICIT_COLUMNS", explicit_columns)
    rng = np.random.default_rng(int(rest * 1e4) + 5)
    n_states, rows, actions = 40, 30, 3
    padded = random_padded_imdp(rng, n_states, rows, actions, rest)
    compact = imdp_compact.CompactIMDP.from_imdp(padded, chunk=chunk)
    assert compact.num_lower >= 2 and compact.chunk == (chunk or compact.chunk)
    if chunk is not None and chunk < compact.width:
        assert compact.num_chunks > rows  # rows split over several chunks
    if chunk is None or chunk < compact.width:
        assert compact.nbytes < padded.nbytes
    for name in ("successors", "lower", "upper"):  # the padded views give the lists back (widest list's width)
        np.testing.assert_array_equal(np.asarray(getattr(compact, name)),
                                      np.asarray(getattr(padded, name))[..., :compact.width])
    strategy = jnp.asarray(rng.integers(0, actions, rows), jnp.int32)
    # a sum over the last axis may add in another order for one action than for all (1 ulp)
    same = np.testing.assert_array_equal if explicit_columns else \
        (lambda a, b: np.testing.assert_allclose(a, b, rtol=0, atol=4e-16))
    # jitted once per test (the monkeypatched column rule is read when tracing)
    q = jax.jit(lambda a, v, adversary, s: a.q_values(v, adversary, s), static_argnums=2)
    succ, lo, up = (np.asarray(x) for x in (padded.successors, padded.lower, padded.upper))
    for trial in range(4):
        values = rng.uniform(0, 1, n_states) if trial % 2 else rng.choice([0.0, 0.25, 0.5, 1.0], n_states)
        v = jnp.asarray(values)
        for adversary in ("min", "max"):
            got = np.asarray(q(compact, v, adversary, None))
            np.testing.assert_allclose(got, np.asarray(q(padded, v, adversary, None)), rtol=0, atol=1e-15)
            fixed = np.asarray(q(compact, v, adversary, strategy))
            same(fixed, got[np.arange(rows), np.asarray(strategy)])
            np.testing.assert_array_equal(np.asarray(q(compact.restrict(strategy), v, adversary, None))[:, 0], fixed)
            if adversary == "min":
                for r in range(0, rows, 4):
                    for a in range(actions):
                        keep = succ[r, a] < n_states
                        expect = lp_min(succ[r, a][keep], lo[r, a][keep], up[r, a][keep], rest, values)
                        assert got[r, a] == pytest.approx(expect, abs=1e-9)


def test_chunk_width_minimizes_slots_plus_overhead():
    from smdpjax.abstraction.imdp_compact import chunk_layout, chunk_width

    assert chunk_width(np.full(50, 7)) == 7  # equal widths: one chunk per row, no padding
    wide = np.r_[np.full(5000, 10), np.full(5000, 1000)]
    w = chunk_width(wide, overhead=8)
    cost = lambda c: int(np.sum(-(-wide // c) * (c + 8)))
    assert all(cost(w) <= cost(c) for c in (4, 8, 12, 16, 24, 32, 48, 64, 128, 256, 512, 1000))
    # by hand: W = 64 costs 5000 * 72 + 5000 * 16 * 72 = 6.12e6 slots, 48 costs 6.16e6, 96 6.24e6,
    # one chunk of 1000 per row 10.08e6
    assert w == 64 and cost(w) == 6_120_000
    rng = np.random.default_rng(3)
    widths = rng.integers(1, 300, 1000)
    row, within, width, most = chunk_layout(widths, 16)
    assert width == 16 and most == 19 and np.all(np.diff(row) >= 0)
    np.testing.assert_array_equal(np.bincount(row, minlength=1000), -(-widths // 16))
    np.testing.assert_array_equal(within, np.concatenate([np.arange(c) for c in -(-widths // 16)]))
    with pytest.raises(ValueError, match="at least 1"):
        chunk_layout(widths, 0)


def test_wide_lists_are_cut_into_explicit_column_chunks():
    """Lists that fit in ``_EXPLICIT_COLUMNS`` slots keep ``chunk_width``'s choice (one chunk per
    row where the widths are equal); wider ones are cut into chunks of at most
    ``WIDE_LIST_CHUNK``, never one chunk per row, by the same cost over the narrow candidates."""
    from smdpjax.abstraction.imdp_compact import (_EXPLICIT_COLUMNS, WIDE_LIST_CHUNK, chunk_width,
                                                  list_chunk_width)

    assert WIDE_LIST_CHUNK <= _EXPLICIT_COLUMNS
    assert list_chunk_width(np.full(50, 36)) == 36 == chunk_width(np.full(50, 36))
    assert list_chunk_width(np.full(50, _EXPLICIT_COLUMNS)) == _EXPLICIT_COLUMNS
    wide = np.full(50, 1156)  # chunk_width: one chunk per row (no padding at all)
    assert chunk_width(wide) == 1156 and list_chunk_width(wide) == WIDE_LIST_CHUNK
    # by hand, cost sum ceil(w / W) (W + 8) over W in 4..32 for widths 49 and 10: W = 12 costs
    # 5 * 20 + 1 * 20 = 120, as does W = 32 (2 * 40 + 40); the first of the cheapest is taken
    assert list_chunk_width(np.array([49, 10])) == 12


def test_abstract_imdp_is_compact_and_synthesizes_as_padded():
    system = sj.System(lambda x, u, w: x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w),
                       actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Gaussian([0, 0], [0.5, 0.5]))
    grid = sj.StateGrid([0, 0], [1, 1], 12, reach=[([0.75, 0.75], [1, 1])], avoid=[([0.4, 0.2], [0.6, 0.6])])
    noise = sj.NoiseGrid.ball([0, 0], 2.0, 6)
    compact = sj.abstract(system, grid, noise, "imdp")
    assert isinstance(compact, sj.CompactIMDP)
    padded = compact.padded()
    assert compact.nbytes < padded.nbytes
    for horizon in (None, 7):
        a, b = sj.synthesize(compact, horizon=horizon), sj.synthesize(padded, horizon=horizon)
        np.testing.assert_allclose(np.asarray(a.lower), np.asarray(b.lower), rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(a.upper), np.asarray(b.upper), rtol=0, atol=1e-12)
        np.testing.assert_array_equal(np.asarray(a.policy), np.asarray(b.policy))


@pytest.mark.parametrize("rows_per_block", [1, 4, 7, None])
def test_blocked_inner_problem_equals_all_rows_at_once(rows_per_block, assert_same_q_values):
    """Rows solved a block at a time (``inner_blocks``; the last block overlaps the one before it,
    rows own 1-3 chunks) give the values of all rows at once, for every action, a strategy and
    ``restrict``."""
    import dataclasses

    from smdpjax.abstraction import imdp_compact

    rng = np.random.default_rng(rows_per_block or 0)
    n_states, rows, actions, rest = 40, 31, 3, 1e-3
    compact = imdp_compact.CompactIMDP.from_imdp(random_padded_imdp(rng, n_states, rows, actions, rest), chunk=4)
    whole = dataclasses.replace(compact, block_rows=0, block_chunks=0, strategy_blocks=(0, 0))
    counts = np.bincount(np.asarray(compact.chunk_row))
    assert counts.min() < counts.max()  # rows own different numbers of chunks
    budget = int(np.ceil((rows_per_block or rows) * counts.mean() * actions * compact.chunk))
    slots = compact.num_chunks * compact.chunk / rows  # per row and action
    block_rows, block_chunks = imdp_compact.inner_blocks(compact.chunk_row, rows, actions * slots, budget)
    if rows_per_block is None:
        assert block_rows == 0  # everything fits one block
    else:
        assert block_rows == rows_per_block and (rows % block_rows or block_rows == 1)  # the last block overlaps
        assert block_chunks == max(counts[s:s + block_rows].sum() for s in range(0, rows - block_rows + 1))
    # one action per row: blocks of as many slots, so more rows
    strategy_blocks = imdp_compact.inner_blocks(compact.chunk_row, rows, slots, budget)
    blocked = dataclasses.replace(compact, block_rows=block_rows, block_chunks=block_chunks,
                                  strategy_blocks=strategy_blocks)
    assert blocked.restrict(jnp.zeros(rows, jnp.int32)).block_rows == strategy_blocks[0]
    strategy = jnp.asarray(rng.integers(0, actions, rows), jnp.int32)
    values = [jnp.asarray(rng.uniform(0, 1, n_states) if trial else rng.choice([0.0, 0.5, 1.0], n_states))
              for trial in range(3)]
    assert_same_q_values(blocked, whole, values, strategy, atol=4e-16)


def test_inner_blocks_sizes():
    from smdpjax.abstraction.imdp_compact import inner_blocks

    chunk_row = np.repeat(np.arange(10), [1, 1, 1, 1, 1, 3, 3, 3, 3, 3])  # 20 chunks
    assert inner_blocks(chunk_row, 10, 16, budget=1 << 20) == (0, 0)  # one block
    # 16 slots a row: 2 rows a block; rows 5-9 own 3 chunks each, the last block is rows 8-9
    assert inner_blocks(chunk_row, 10, 16, budget=32) == (2, 6)
    assert inner_blocks(chunk_row, 10, 16, budget=48) == (3, 9)  # blocks 0-2, 3-5, 6-8, 7-9
    assert inner_blocks(chunk_row, 10, 16, budget=1) == (1, 3)  # at least one row a block


def test_list_stats_against_numpy():
    """``list_stats``: padding before a listed entry, each row's widest list, most positive lower
    bounds per list; ``from_lists`` moves listed entries first only where padding came first."""
    from smdpjax.abstraction.imdp_compact import CompactIMDP, list_stats

    rng = np.random.default_rng(3)
    n_states = 9
    succ = rng.integers(0, n_states + 3, (5, 3, 6)).astype(np.int32)  # >= n_states: padding
    lower = np.where(rng.random(succ.shape) < 0.3, 0.1, 0.0)
    listed = succ < n_states
    gaps, widths, num_lower = (np.asarray(x) for x in list_stats(jnp.asarray(succ), jnp.asarray(lower), n_states))
    assert bool(gaps) == bool(np.any(listed[..., 1:] & ~listed[..., :-1]))
    np.testing.assert_array_equal(widths, listed.sum(-1).max(1))
    assert int(num_lower) == ((lower > 0) & listed).sum(-1).max()
    front = np.argsort(~listed, axis=-1, kind="stable")
    ordered = np.take_along_axis(succ, front, axis=-1)
    assert not bool(list_stats(jnp.asarray(ordered), jnp.asarray(lower), n_states)[0])

    upper = np.where(listed, 0.5, 0.0)
    labels = np.zeros(n_states, np.int32)
    gapped = CompactIMDP.from_lists(succ, lower * listed, upper, 0.0, np.arange(5), labels)
    sorted_first = CompactIMDP.from_lists(ordered, np.take_along_axis(lower * listed, front, -1),
                                          np.take_along_axis(upper, front, -1), 0.0, np.arange(5), labels)
    for a, b in zip(jax.tree_util.tree_leaves(gapped), jax.tree_util.tree_leaves(sorted_first)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
