"""Range minima/maxima over index boxes (sparse table) against brute force over the boxes' cells."""

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from smdpjax.abstraction.range_min import (TABLE_BUDGET, RangeSpec, build_table, default_every_length, query_table,
                                          range_max, range_min)


def brute_force(a, start, length, op):
    """op of ``a`` over every box, cell by cell (indices taken modulo the grid: only periodic
    dimensions ever reach past the end)."""
    out = np.empty(len(start))
    for i, (s, l) in enumerate(zip(start, length)):
        if np.any(l == 0):
            out[i] = np.inf if op == "min" else -np.inf
            continue
        cells = a[np.ix_(*[np.arange(si, si + li) % c for si, li, c in zip(s, l, a.shape)])]
        out[i] = cells.min() if op == "min" else cells.max()
    return out


def random_boxes(rng, spec, count):
    """Boxes within the contract, with the edge cases forced in: length 0, 1, the maximum (a full
    wrap where max_length == cells on a periodic dimension), and boxes ending at the last cell."""
    length = np.stack([rng.integers(0, m + 1, count) for m in spec.max_lengths], axis=-1)
    length[:5] = [0] * spec.n
    length[5:10] = [1] * spec.n
    length[10:20] = spec.max_lengths
    length[20, 0] = 0  # empty in one dimension only: still no cell
    start = np.empty_like(length)
    for d, (c, periodic) in enumerate(zip(spec.cells, spec.periodic)):
        if periodic:
            start[:, d] = rng.integers(0, c, count)
            start[10:15, d] = c - 1  # wraps around at once
        else:
            start[:, d] = rng.integers(0, c - length[:, d] + 1)
            start[15:20, d] = c - length[15:20, d]  # ends at the last cell
    return start, length


# (cells, periodic, max_lengths): every n from 1 to 4; max lengths that are no powers of two,
# 1 (no levels), 2 (one window), and the whole periodic dimension (full wrap).
CASES = [
    ((13,), (False,), (5,)),
    ((11,), (True,), (11,)),
    ((9, 7), (False, False), (3, 7)),
    ((10, 6), (False, True), (6, 6)),
    ((6, 5, 7), (False, False, True), (3, 1, 7)),
    ((5, 6, 8), (True, False, True), (5, 2, 6)),
    ((4, 5, 3, 6), (False, True, False, True), (3, 5, 3, 6)),
    ((5, 4, 4, 3), (True, True, False, False), (4, 3, 4, 2)),
]


@pytest.mark.parametrize("cells, periodic, max_lengths", CASES)
@pytest.mark.parametrize("dtype, windows", [(jnp.int8, "powers of two"), (jnp.int16, "every length"),
                                            (jnp.int32, "alternating"), (jnp.int16, "default")])
def test_range_extremes_equal_brute_force(cells, periodic, max_lengths, dtype, windows):
    every = {"powers of two": (False,) * len(cells), "every length": (True,) * len(cells),
             "alternating": tuple(d % 2 == 1 for d in range(len(cells))), "default": None}[windows]
    spec = RangeSpec(cells, periodic, max_lengths, every)
    rng = np.random.default_rng(sum(cells) + len(cells))
    # few distinct values: ties between cells are common, as in value vectors
    a = rng.integers(0, 50, cells).astype(np.float64) / 7
    start, length = random_boxes(rng, spec, 400)
    args = (jnp.asarray(a.ravel()), jnp.asarray(start, dtype), jnp.asarray(length, dtype), spec)
    lo, hi = np.asarray(range_min(*args)), np.asarray(range_max(*args))
    np.testing.assert_array_equal(lo, brute_force(a, start, length, "min"))
    np.testing.assert_array_equal(hi, brute_force(a, start, length, "max"))
    assert np.isposinf(lo[:5]).all() and np.isneginf(hi[:5]).all() and np.isposinf(lo[20])


def test_boxes_may_have_any_leading_shape_and_values_the_grid_shape():
    spec = RangeSpec((7, 9), (True, False), (4, 3))
    rng = np.random.default_rng(3)
    a = rng.normal(size=spec.cells)
    start, length = random_boxes(rng, spec, 60)
    flat = range_min(jnp.asarray(a.ravel()), jnp.asarray(start), jnp.asarray(length), spec)
    shaped = range_min(jnp.asarray(a), jnp.asarray(start.reshape(3, 4, 5, 2)), jnp.asarray(length.reshape(3, 4, 5, 2)),
                       spec)
    assert shaped.shape == (3, 4, 5)
    np.testing.assert_array_equal(np.asarray(shaped).ravel(), np.asarray(flat))


def test_table_holds_only_the_levels_the_longest_box_needs():
    spec = RangeSpec((30, 30, 30), (False, False, True), (5, 1, 8), every_length=(False, False, False))
    assert spec.levels == (3, 1, 4)  # 2^2 <= 5 < 2^3; 1 = 2^0; 2^3 = 8
    assert spec.extended == (30, 30, 37)  # periodic: 7 = max_length - 1 extra cells
    assert spec.corners == (2, 1, 2)
    table = build_table(jnp.zeros(27000), spec, "min")
    assert table.shape == (3, 1, 4, 30, 30, 37)
    every = RangeSpec((30, 30, 30), (False, False, True), (5, 1, 8), every_length=(True, False, False))
    assert every.levels == (5, 1, 4) and every.corners == (1, 1, 2)


def test_default_windows_stay_within_the_table_budget():
    # 3-D friction unicycle: power-of-two windows would need 8 lookups per box; every length in
    # the heading dimension (3 levels instead of 2) halves that and the table still fits
    spec = RangeSpec((30, 30, 30), (False, False, True), (5, 5, 3))
    assert spec.every_length == (False, False, True) and spec.corners == (2, 2, 1)
    assert np.prod(spec.table_shape) <= TABLE_BUDGET
    assert default_every_length((30, 30, 30), (False, False, True), (5, 5, 3), budget=1000) == (False,) * 3
    small = RangeSpec((30, 30), (False, False), (6, 6))  # a small grid: one lookup per box
    assert small.every_length == (True, True) and small.corners == (1, 1)
    assert RangeSpec((9,), (False,), (2,)).every_length == (False,)  # one window already



def test_large_grids_trade_table_size_for_fewer_lookups():
    # 4-D double integrator at 32^4 cells: 16 lookups per box with power-of-two windows; with the
    # boxes queried per build given, one dimension switches (8 lookups, 25.2M entries <= boxes / 2)
    cells, periodic, lengths = (32,) * 4, (False,) * 4, (3,) * 4
    assert default_every_length(cells, periodic, lengths) == (False,) * 4  # 16.8M entries > budget
    spec = RangeSpec(cells, periodic, lengths, default_every_length(cells, periodic, lengths, boxes=94_617_600))
    assert math.prod(spec.corners) == 8 and math.prod(spec.table_shape) == 3 * 2 * 2 * 2 * 32 ** 4
    # fewer boxes: the table may not outgrow half of them
    few = 2 * math.prod(spec.table_shape)
    assert sum(default_every_length(cells, periodic, lengths, boxes=few)) == 1
    assert sum(default_every_length(cells, periodic, lengths, boxes=few - 2)) == 0
    # 3-D at 46^3 (6x6x3 boxes): 8 lookups is few enough, no switch past the budget
    assert default_every_length((46,) * 3, (False, False, True), (6, 6, 3), boxes=10 ** 9) == (False,) * 3


def test_three_or_more_dimensions_keep_two_lookups():
    # 10^4 cells in 4-D: the whole every-length table would fit the budget, but one lookup per
    # query ran slower than two; 2-D grids go down to one
    spec = RangeSpec((10,) * 4, (False,) * 4, (3,) * 4)
    assert math.prod(spec.corners) == 2 and math.prod(spec.table_shape) <= TABLE_BUDGET
    assert math.prod(RangeSpec((22,) * 3, (False, False, True), (4, 5, 3)).corners) == 2
    assert math.prod(RangeSpec((30, 30), (False, False), (6, 6)).corners) == 1

def test_table_entries_are_window_minima():
    """Level k of a powers-of-two dimension is windows of 2^k cells, of an every-length one k + 1."""
    spec = RangeSpec((6, 5), (True, False), (6, 4), every_length=(False, True))
    a = np.random.default_rng(4).normal(size=spec.cells)
    table = np.asarray(build_table(jnp.asarray(a), spec, "min"))
    ext = a[np.arange(spec.extended[0]) % 6]
    for k0, k1 in itertools.product(range(spec.levels[0]), range(spec.levels[1])):
        w0, w1 = 1 << k0, k1 + 1
        for p0 in range(spec.extended[0] - w0 + 1):
            for p1 in range(spec.extended[1] - w1 + 1):
                assert table[k0, k1, p0, p1] == ext[p0:p0 + w0, p1:p1 + w1].min()


def test_jit_vmap_and_integer_values():
    spec = RangeSpec((8, 6), (False, True), (5, 6))
    rng = np.random.default_rng(5)
    start, length = random_boxes(rng, spec, 50)
    values = rng.normal(size=(3, 48))
    batched = jax.vmap(range_min, in_axes=(0, None, None, None))(jnp.asarray(values), jnp.asarray(start),
                                                                    jnp.asarray(length), spec)
    for b in range(3):
        np.testing.assert_array_equal(np.asarray(batched[b]),
                                      brute_force(values[b].reshape(spec.cells), start, length, "min"))
    ints = rng.integers(-100, 100, spec.cells).astype(np.int32)
    got = query_table(build_table(jnp.asarray(ints), spec, "max"), jnp.asarray(start), jnp.asarray(length), spec, "max")
    expect = brute_force(ints.astype(float), start, length, "max")
    nonempty = np.all(length > 0, axis=-1)
    np.testing.assert_array_equal(np.asarray(got)[nonempty], expect[nonempty])
    assert np.all(np.asarray(got)[~nonempty] == np.iinfo(np.int32).min)


def test_spec_validation():
    with pytest.raises(ValueError, match="one entry per dimension"):
        RangeSpec((4, 4), (False,), (2, 2))
    with pytest.raises(ValueError, match="max_lengths"):
        RangeSpec((4,), (True,), (5,))
    with pytest.raises(ValueError, match="max_lengths"):
        RangeSpec((4,), (False,), (0,))
    with pytest.raises(ValueError, match="every_length"):
        RangeSpec((4, 4), (False, False), (2, 2), every_length=(True,))
    with pytest.raises(ValueError, match="op"):
        build_table(jnp.zeros(4), RangeSpec((4,), (False,), (2,)), "mean")
    assert hash(RangeSpec((4,), (False,), (2,))) == hash(RangeSpec([np.int64(4)], [np.False_], [2]))
