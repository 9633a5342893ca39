"""Lemma 1 from index boxes (``box_bounds.region_bounds``) against exact rational sums over a
brute-force enumeration of the cells every box covers."""

import itertools
from fractions import Fraction

import jax.numpy as jnp
import numpy as np
import pytest

from smdpjax.abstraction.box_bounds import FRACTION_BITS, region_bounds
from smdpjax.abstraction.clusters import IndexBoxes

CASES = {  # cells, periodic, block
    "1d": ((7,), (False,), (1,)),
    "1d_periodic_blocks": ((9,), (True,), (4,)),  # a partial last block on a circle
    "2d": ((6, 5), (False, False), (1, 1)),
    "2d_periodic": ((5, 8), (False, True), (1, 1)),
    "2d_blocks": ((7, 6), (True, False), (3, 2)),
    "3d_periodic": ((4, 5, 6), (False, False, True), (1, 1, 1)),
    "3d_blocks": ((5, 4, 7), (False, True, True), (2, 3, 2)),
}


def random_boxes(rng, cells, periodic, rows, actions, clusters):
    n = len(cells)
    start = np.zeros((rows, actions, clusters, n), np.int32)
    length = np.zeros_like(start)
    for d, (m, p) in enumerate(zip(cells, periodic)):
        # rows centred somewhere (wrapping on periodic axes), boxes near the centre
        centre = rng.integers(0, m, (rows, actions, 1))
        s = centre + rng.integers(-2, 2, (rows, actions, clusters))
        ln = rng.integers(1, 4, (rows, actions, clusters))
        if p:
            full = rng.random((rows, actions, clusters)) < 0.05
            start[..., d] = np.where(full, 0, np.mod(s, m))
            length[..., d] = np.where(full, m, ln)
        else:
            lo, hi = np.clip(s, 0, m - 1), np.clip(s + ln, 1, m)
            start[..., d], length[..., d] = lo, np.maximum(hi - lo, 1)
    sink = rng.random((rows, actions, clusters)) < 0.2
    miss = rng.random((rows, actions, clusters)) < 0.05  # misses the grid: the sink alone
    start[miss], length[miss], sink[miss] = 0, 0, True
    return IndexBoxes(start=jnp.asarray(start), length=jnp.asarray(length), sink=jnp.asarray(sink))


def random_prob(rng, clusters):
    prob = rng.dirichlet(np.ones(clusters)) * 0.9
    prob[0] = 0.0  # a zero-probability cell: its regions are still listed
    prob[1] = 1e-300  # far below the fixed-point quantum: rounded up, never down, in ``upper``
    return prob


def exact_bounds(cells, periodic, block, start, length, sink, prob):
    """{region: (lower, upper)} as Fractions, by enumerating every cell of every box."""
    shape = tuple(-(-c // b) for c, b in zip(cells, block))
    sink_region = int(np.prod(shape))
    met, lower, upper = set(), {}, {}
    for c in range(len(prob)):
        p = Fraction(float(prob[c]))
        regions = set()
        if np.all(length[c] > 0):
            ranges = [[(s + k) % m if per else s + k for k in range(ln)]
                      for s, ln, m, per in zip(start[c], length[c], cells, periodic)]
            for cell in itertools.product(*ranges):
                regions.add(int(np.ravel_multi_index(tuple(x // b for x, b in zip(cell, block)), shape)))
        if sink[c]:
            regions.add(sink_region)
        met |= regions
        for r in regions:
            upper[r] = upper.get(r, 0) + p
        if len(regions) == 1:  # inside one region (a box that misses the grid: the sink)
            (r,) = regions
            lower[r] = lower.get(r, 0) + p
    return {r: (lower.get(r, Fraction(0)), upper.get(r, Fraction(0))) for r in met}, sink_region


@pytest.mark.parametrize("case", sorted(CASES))
def test_bounds_are_exact_sums_rounded_outward(case):
    cells, periodic, block = CASES[case]
    rng = np.random.default_rng(sorted(CASES).index(case))
    rows, actions, clusters = 6, 2, 12
    boxes = random_boxes(rng, cells, periodic, rows, actions, clusters)
    prob = random_prob(rng, clusters)
    ids, lower, upper = (np.asarray(t) for t in region_bounds(cells, periodic, boxes, jnp.asarray(prob), block))
    quantum = Fraction(clusters, 2 ** FRACTION_BITS)
    widest = 0
    for r, a in itertools.product(range(rows), range(actions)):
        want, sink_region = exact_bounds(cells, periodic, block, *(np.asarray(x)[r, a] for x in
                                                                  (boxes.start, boxes.length, boxes.sink)), prob)
        listed = ids[r, a][ids[r, a] <= sink_region]
        widest = max(widest, listed.size)
        assert np.all(np.diff(listed) > 0), "successors must be distinct and increasing"
        assert np.all(ids[r, a][listed.size:] == sink_region + 1), "padding after the listed regions"
        assert np.all(lower[r, a][listed.size:] == 0) and np.all(upper[r, a][listed.size:] == 0)
        assert set(listed.tolist()) == set(want), "exactly the regions some box meets"
        for k, region in enumerate(listed):
            lo, up = want[int(region)]
            got_lo, got_up = Fraction(float(lower[r, a, k])), Fraction(float(upper[r, a, k]))
            assert got_lo <= lo and lo - got_lo <= quantum + Fraction(np.spacing(float(lo)))
            assert got_up >= up and got_up - up <= quantum + Fraction(np.spacing(float(up)))
            assert got_up > 0
    assert ids.shape[-1] == widest, "lists exactly as wide as the widest row"


def test_full_turn_and_wrapping_windows():
    """Boxes that wrap around, and a row whose boxes together cover the whole circle (the
    window's fallback to the exact circular hull)."""
    cells, periodic = (10,), (True,)
    start = np.array([8, 2, 5, 0], np.int32).reshape(1, 1, 4, 1)
    length = np.array([4, 4, 4, 0], np.int32).reshape(1, 1, 4, 1)  # 8..1, 2..5, 5..8: all 10 cells
    sink = np.array([False, False, False, True]).reshape(1, 1, 4)
    boxes = IndexBoxes(start=jnp.asarray(start), length=jnp.asarray(length), sink=jnp.asarray(sink))
    prob = jnp.array([0.25, 0.25, 0.25, 0.25])
    ids, lower, upper = region_bounds(cells, periodic, boxes, prob)
    np.testing.assert_array_equal(np.asarray(ids[0, 0]), np.arange(11))
    expected = np.array([1, 1, 1, 1, 1, 2, 1, 1, 2, 1, 1]) * 0.25  # cells 5 and 8 in two boxes; sink last
    np.testing.assert_array_equal(np.asarray(upper[0, 0]), expected)
    np.testing.assert_array_equal(np.asarray(lower[0, 0]), [0] * 10 + [0.25])  # the box that misses the grid


def test_bad_input_is_rejected():
    boxes = IndexBoxes(start=jnp.zeros((2, 1, 3, 2), jnp.int32), length=jnp.ones((2, 1, 3, 2), jnp.int32),
                       sink=jnp.zeros((2, 1, 3), bool))
    with pytest.raises(ValueError, match="block"):
        region_bounds((4, 4), (False, False), boxes, jnp.ones(3) / 3, block=(0, 1))
    with pytest.raises(ValueError, match="prob"):
        region_bounds((4, 4), (False, False), boxes, jnp.ones(4) / 4)
    with pytest.raises(ValueError, match="dimensions"):
        region_bounds((4, 4, 4), (False,) * 3, boxes, jnp.ones(3) / 3)


def test_quantized_widths_grow_by_at_most_half():
    from smdpjax.abstraction.box_bounds import _quantized_width

    widths = [_quantized_width(w) for w in range(1, 5000)]
    assert widths[:32] == [32] * 32 and all(q >= w for w, q in zip(range(1, 5000), widths))
    assert all(q <= 1.5 * w for w, q in zip(range(33, 5000), widths[32:]))
    assert len(set(widths)) == 16  # 32, 48, 64, 96, ... 4096, 6144


def test_chunk_widths_do_not_change_the_lists(monkeypatch):
    """Chunks of 2 rows whose lists are cut to 2, 3, 4, 6, ... slots (not 32 and up) give the
    same lists as one chunk, the last chunk (one real row, one copy) cut to its real rows."""
    from smdpjax.abstraction import box_bounds

    cells, periodic, block = (9, 7), (False, True), (1, 1)
    rng = np.random.default_rng(5)
    boxes = random_boxes(rng, cells, periodic, 7, 2, 12)
    prob = jnp.asarray(random_prob(rng, 12))
    whole = [np.asarray(t) for t in region_bounds(cells, periodic, boxes, prob, block)]
    monkeypatch.setattr(box_bounds, "ROWS_PER_CHUNK", 4)
    monkeypatch.setattr(box_bounds, "_WIDTH_QUANTUM", 2)
    chunked = [np.asarray(t) for t in region_bounds(cells, periodic, boxes, prob, block)]
    assert whole[0].shape[-1] > 2
    for a, b in zip(whole, chunked):
        assert a.dtype == b.dtype and a.shape == b.shape == whole[0].shape and a.shape[0] == 7
        np.testing.assert_array_equal(a, b)


def test_rows_per_chunk_fits_small_models():
    """A model with fewer rows than a chunk holds gets the least power of two that holds them,
    never more than ``ROWS_PER_CHUNK // actions``."""
    from smdpjax.abstraction.box_bounds import ROWS_PER_CHUNK, _rows_per_chunk

    assert _rows_per_chunk(144, 1) == 256 and _rows_per_chunk(1, 1) == 1 and _rows_per_chunk(2, 3) == 2
    assert _rows_per_chunk(256, 1) == 256 and _rows_per_chunk(257, 1) == 512
    assert _rows_per_chunk(10 ** 6, 1) == ROWS_PER_CHUNK and _rows_per_chunk(10 ** 6, 8) == ROWS_PER_CHUNK // 8
    assert _rows_per_chunk(5, 8) == 8 and _rows_per_chunk(300, 8) == ROWS_PER_CHUNK // 8


def test_rows_per_loop_step_do_not_change_the_bounds(monkeypatch):
    """The difference arrays built one row per loop step or ``MAP_BATCH`` (here 3, which does not
    divide the 7 rows) at a time: the same lists and bounds, bit for bit."""
    from smdpjax.abstraction import box_bounds

    cells, periodic, block = (6, 5, 4), (False, True, False), (1, 1, 1)
    rng = np.random.default_rng(11)
    boxes = random_boxes(rng, cells, periodic, 7, 1, 9)
    prob = jnp.asarray(random_prob(rng, 9))
    results = []
    for batch in (1, 3):
        monkeypatch.setattr(box_bounds, "MAP_BATCH", batch)
        box_bounds._window_bounds.clear_cache()  # MAP_BATCH is read when the function is traced
        results.append([np.asarray(t) for t in region_bounds(cells, periodic, boxes, prob, block)])
    for a, b in zip(*results):
        np.testing.assert_array_equal(a, b)


def factored_boxes(rng, cells, periodic, rows, noise_shape, axes):
    """Random boxes of ``(rows, 1, prod(noise_shape))`` whose dimension d depends on noise axis
    ``axes[d]`` alone (-1: on none), with sink flags that are an "or" of per-axis flags."""
    n, m = len(cells), len(noise_shape)
    grid = np.stack(np.unravel_index(np.arange(int(np.prod(noise_shape))), noise_shape), -1)  # (C, m)
    pieces = random_boxes(rng, cells, periodic, rows, 1, max(noise_shape))  # per (row, axis index) ranges
    start, length = np.array(pieces.start), np.array(pieces.length)
    start[..., 1, :] = np.mod(start[..., 0, :] + 1, cells)  # the first two pieces differ in every dimension
    length[..., 1, :] = np.maximum(length[..., 0, :], 1)
    length = np.where(np.asarray(periodic), length, np.minimum(length, np.asarray(cells) - start))  # in the grid
    g = [rng.random((rows, 1, k)) < 0.2 for k in noise_shape]
    for d, k in enumerate(axes):  # a dimension that misses the grid sends the box to the sink
        if k >= 0:
            g[k] |= length[..., :noise_shape[k], d] == 0
        else:
            length[..., 0, d] = np.maximum(length[..., 0, d], 1)
    pick = lambda x, d: x[..., grid[:, axes[d]] if axes[d] >= 0 else np.zeros(len(grid), int), d]
    start = np.stack([pick(start, d) for d in range(n)], -1)
    length = np.stack([pick(length, d) for d in range(n)], -1)
    sink = np.zeros(start.shape[:-1], bool)
    for k in range(m):
        sink |= g[k][..., grid[:, k]]
    return IndexBoxes(start=jnp.asarray(start, jnp.int32), length=jnp.asarray(length, jnp.int32),
                      sink=jnp.asarray(sink))


FACTORED = {  # cells, periodic, block, noise shape, noise axis of each dimension
    "2d": ((6, 5), (False, False), (1, 1), (3, 4), (0, 1)),
    "2d_periodic_blocks": ((7, 8), (True, False), (2, 3), (4, 2), (1, 0)),
    "3d_shared_and_none": ((5, 4, 6), (False, True, False), (1, 1, 1), (3, 2), (0, 0, -1)),
    "3d_axis_unused": ((4, 5, 6), (False, False, True), (1, 2, 1), (2, 3, 2), (2, -1, 0)),
}


@pytest.fixture
def factored_calls(monkeypatch):
    """Every chunk may take the product form (whatever its size); counts the chunks that do."""
    from smdpjax.abstraction import box_bounds

    calls = []
    product_form = box_bounds._factored_window_bounds

    def counted(*args):
        calls.append(args[-1])
        return product_form(*args)

    monkeypatch.setattr(box_bounds, "FACTOR_MIN_CORNERS", 0)
    monkeypatch.setattr(box_bounds, "_factored_window_bounds", counted)
    return calls


@pytest.mark.parametrize("case", sorted(FACTORED))
def test_factored_sums_equal_the_difference_arrays(case, factored_calls):
    """Boxes whose dimensions each follow one noise axis: the product form is taken (the axes are
    recognised) and gives the difference arrays' lists and bounds bit for bit, which are the exact
    sums rounded outward."""
    from smdpjax.abstraction.box_bounds import _chunk_rows, _factor_axes, _noise_dependence

    cells, periodic, block, noise_shape, axes = FACTORED[case]
    rng = np.random.default_rng(sorted(FACTORED).index(case))
    rows, clusters = 9, int(np.prod(noise_shape))
    boxes = factored_boxes(rng, cells, periodic, rows, noise_shape, axes)
    prob = random_prob(rng, clusters)
    assert _factor_axes(*_noise_dependence(_chunk_rows(boxes, 0, rows), noise_shape)) == axes
    generic = [np.asarray(t) for t in region_bounds(cells, periodic, boxes, jnp.asarray(prob), block)]
    factored = [np.asarray(t) for t in region_bounds(cells, periodic, boxes, jnp.asarray(prob), block,
                                                     noise_shape=noise_shape)]
    assert factored_calls == [axes]
    for a, b in zip(generic, factored):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    ids, lower, upper = factored
    quantum = Fraction(clusters, 2 ** FRACTION_BITS)
    for r in range(rows):
        want, sink_region = exact_bounds(cells, periodic, block, *(np.asarray(x)[r, 0] for x in
                                                                  (boxes.start, boxes.length, boxes.sink)), prob)
        listed = ids[r, 0][ids[r, 0] <= sink_region]
        assert set(listed.tolist()) == set(want)
        for k, region in enumerate(listed):
            lo, up = want[int(region)]
            got_lo, got_up = Fraction(float(lower[r, 0, k])), Fraction(float(upper[r, 0, k]))
            assert got_lo <= lo and lo - got_lo <= quantum + Fraction(np.spacing(float(lo)))
            assert got_up >= up and got_up - up <= quantum + Fraction(np.spacing(float(up)))


def test_boxes_that_do_not_factor_take_the_difference_arrays(factored_calls):
    """One box moved, or one sink flag that is no "or" of per-axis flags: no product form, and
    the bounds are still the difference arrays'."""
    from smdpjax.abstraction.box_bounds import _chunk_rows, _factor_axes, _noise_dependence

    cells, periodic, block, noise_shape, axes = FACTORED["2d"]
    rng = np.random.default_rng(3)
    boxes = factored_boxes(rng, cells, periodic, 4, noise_shape, axes)
    prob = jnp.asarray(random_prob(rng, 12))
    sink = np.array(boxes.sink)
    sink[1, 0] = False
    sink[1, 0, 5] = True  # cell (1, 1) alone
    start = np.array(boxes.start)
    start[2, 0, 7, 0] = (start[2, 0, 7, 0] + 1) % cells[0]
    for changed in (IndexBoxes(start=boxes.start, length=boxes.length, sink=jnp.asarray(sink)),
                    IndexBoxes(start=jnp.asarray(start), length=boxes.length, sink=boxes.sink)):
        assert _factor_axes(*_noise_dependence(_chunk_rows(changed, 0, 4), noise_shape)) is None
        generic = region_bounds(cells, periodic, changed, prob, block)
        factored = region_bounds(cells, periodic, changed, prob, block, noise_shape=noise_shape)
        for a, b in zip(generic, factored):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert factored_calls == []
    with pytest.raises(ValueError, match="noise_shape"):
        region_bounds(cells, periodic, boxes, prob, block, noise_shape=(3, 3))
