"""Lemma 1 on a grid straight from index boxes, without expanding clusters into member lists.

Lemma 1 bounds the probability of landing in a region B (a grid cell, or a block of cells in the
2I-MDP's coarse layer) by sums over the bounded noise cells c:

    upper(B) = sum_c P_W(c) 1(box_c meets B),    lower(B) = sum_c P_W(c) 1(box_c inside B).

On a grid the regions a box meets form an index box again, so ``upper`` over a window of
H_1 x ... x H_n regions around a row's reachable sets is a sum of box indicators: each box adds
+-P_W(c) at the 2^n corners of an n-dimensional difference array, and n prefix sums turn it into
the sums. A box inside one region (one region per dimension, no sink) adds P_W(c) to that region's
``lower``. Per row that is O(C 2^n + prod(H + 1) n) work, against the O(C K log(C K)) sort of the
C x K expanded members it replaces (K cells per cluster); measured on the 4-room model (257 noise
cells, 20 736 rows): 172 s -> about 7 s.

Exactness: prefix sums of +-P cancel terms, which in floating point would leave rounding residue
(a region no box meets could get 1e-17, a sum could drop below the true one). So the sums are
done in integers: P_W(c) in fixed point, multiples of 2^-61, rounded up for ``upper`` and down
for ``lower``; integer sums are exact; the totals are converted back to float64 rounded outward.
Every bound is thus on the safe side of the exact Lemma 1 value, off by at most C 2^-61 plus one
ulp (2e-15 at C = 4225).

Product form: where dimension d of every box of a chunk depends on one noise axis alone (diagonal
additive or multiplicative noise on a product noise grid) and the sink flags are an "or" over the
axes, ``upper = sum_c P_W(c) prod_d 1(range_d(c_{axis(d)}) holds h_d)`` is one contraction of the
table of P_W with per-dimension indicators (``_factored_window_bounds``), O(prod K * H) per row
instead of C 2^n scatters. The same fixed-point integers are summed, so the bounds are the same
bit for bit; the structure is checked on the boxes themselves (``_noise_dependence``).

The window of a row starts at the first region its boxes meet in each dimension; on a periodic
dimension it starts just after the longest gap in the row's coverage, so no box wraps inside it,
unless the row's boxes cover the whole circle: then a wrapping range [lo, m) + [0, end - m) adds
a third difference term per dimension (only in such rows). The window's size per dimension is the
largest extent over all rows (a static shape).
"""

from __future__ import annotations

import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .clusters import IndexBoxes

# Rows x actions per compiled chunk: bounds the (rows, C) range and (rows, prod(H + 1)) window temporaries.
ROWS_PER_CHUNK = 1 << 11
# P_W is summed exactly as integer multiples of 2^-FRACTION_BITS (sums of probabilities stay < 2^63).
FRACTION_BITS = 61
# Successor-list widths of chunks are rounded up to at least this many slots (``_quantized_width``).
_WIDTH_QUANTUM = 32
# Chunks of fewer (row, noise cell, corner) terms than this take the difference arrays even where
# the sums factor over the noise axes: the check costs more than it saves on the 2-room model
# (144 rows x 16 noise cells x 4 corners).
FACTOR_MIN_CORNERS = 1 << 16
# Rows whose boxes are checked for the product form before any chunk is (the check of every chunk
# made the 2-D unicycle's 2I-MDP build, whose boxes never factor, 5-7% slower).
FACTOR_SAMPLE_ROWS = 16
# Rows whose difference arrays are built side by side in each step of the loop over rows: one row
# per step paid the loop's overhead 2 048 times on the 3-D temperature model (window_bounds 15.7 ->
# 8.8 ms at 16), 16 rows keep the buffers in cache (3-D unicycle, 224 100 lists: 5.9 -> 5.1 s).
MAP_BATCH = 16


def region_bounds(cells, periodic, boxes: IndexBoxes, prob, block=None, noise_shape=None, counts: bool = False):
    """Lemma 1 bounds of every region the boxes of a row meet, as padded successor lists.

    Args:
        cells: ``(n,)`` cells per dimension of the grid.
        periodic: ``(n,)`` bools, dimensions that wrap around.
        boxes: ``IndexBoxes`` with leading shape ``(R, A, C)`` (from ``compute_grid_clusters``).
        prob: ``(C,)`` P_W of the bounded noise cells.
        block: ``(n,)`` cells per region and dimension (default 1: regions are the grid cells).
            Regions are C-order flat indices over ``ceil(cells / block)`` per dimension; a last
            block that does not fit the grid is partial, as in ``twolayer.block_layout``.
        noise_shape: optional ``(K_1, ..., K_m)``, the noise cells as a C-order product grid
            (``NoiseGrid.shape``). Where each dimension of the boxes varies along one noise axis
            at most and the sink flags are an "or" of per-axis flags (``_noise_dependence``,
            checked per chunk), the sums are computed as products over the axes
            (``_factored_window_bounds``), with the same result bit for bit.
        counts: also return ``list_counts`` of the lists (in the program that shapes them, where
            there is one chunk).
    Returns:
        ``(regions, lower, upper)``, each ``(R, A, W)``: per row the regions met, in increasing
        order (the sink region ``num_regions`` last), padded with ``num_regions + 1`` (bounds 0
        there); ``lower`` sums P_W over the clusters inside one region (not meeting the sink),
        ``upper`` over the clusters that meet it. The sink's ``lower`` sums the clusters that miss
        the grid, its ``upper`` those that meet the sink. ``W`` is the most regions any row meets.
        The remainder cell of unbounded noise is not included (the callers add it).
    """
    cells = tuple(int(c) for c in np.asarray(cells).reshape(-1))
    n = len(cells)
    periodic = tuple(bool(p) for p in np.broadcast_to(np.asarray(periodic, bool), (n,)))
    block = (1,) * n if block is None else tuple(int(b) for b in np.broadcast_to(np.asarray(block), (n,)))
    if any(b <= 0 for b in block):
        raise ValueError(f"block shape must be positive, got {list(block)}")
    if boxes.start.ndim != 4 or boxes.start.shape[-1] != n:
        raise ValueError(f"boxes must have leading shape (R, A, C) and {n} dimensions, got {boxes.start.shape}")
    prob = jnp.asarray(prob)
    if prob.shape != boxes.start.shape[2:3]:
        raise ValueError(f"prob must have shape ({boxes.start.shape[2]},), got {prob.shape}")
    geometry = (cells, periodic, block)
    r, a, c, _ = boxes.start.shape
    if noise_shape is not None:
        noise_shape = tuple(int(k) for k in noise_shape)
        if math.prod(noise_shape) != c:
            raise ValueError(f"noise_shape {list(noise_shape)} has {math.prod(noise_shape)} cells, the boxes {c}")
    step = _rows_per_chunk(r, a)

    # One chunk: the rows themselves, flattened inside each program (no copy, no padding rows).
    # More: sliced lazily (a copy of all boxes at once can be gigabytes), the last one padded with
    # copies of its last row (one compiled shape).
    single = boxes if step >= r else None

    def chunks():
        if single is not None:
            yield single
            return
        for s in range(0, r, step):
            yield _chunk_rows(boxes, s, step)

    factor = noise_shape is not None and step * a * c * 2 ** n >= FACTOR_MIN_CORNERS
    if factor:  # the first rows first: a model whose boxes do not factor shows it there
        sample = _chunk_rows(boxes, 0, min(r, FACTOR_SAMPLE_ROWS))
        factor = _factor_axes(*_noise_dependence(sample, noise_shape)) is not None
    windows, dependence = [], []
    for part in chunks():
        windows.append(_windows(geometry, part))
        dependence.append(_noise_dependence(part, noise_shape) if factor else None)
    size = tuple(int(v) for v in np.max(np.concatenate([np.asarray(e) for _, e in windows]), axis=0))
    size = tuple(max(v, 1) for v in size)
    sentinel = math.prod(_regions_per_dim(geometry)) + 1
    pieces, widths = [], []
    for part, (anchor, _), depends in zip(chunks(), windows, dependence):
        axes = None if depends is None else _factor_axes(*depends)
        lower, upper, listed = _piece_bounds(geometry, size, part, anchor, prob, noise_shape, axes)
        widths.append(int(listed))
        chunk_width = max(1, min(upper.shape[-1], _quantized_width(widths[-1])))
        if single is not None:  # one chunk: compacted, cut to its width and shaped in one program
            lists = _compact_lists(geometry, size, anchor, lower, upper, chunk_width, widths[-1], sentinel, (r, a),
                                   counts)
            return lists[:3] + (lists[3:],) if counts else lists
        pieces.append(_compact(geometry, size, anchor, lower, upper, chunk_width))
    width = max(widths)  # padding rows copy a real row, so they never widen the lists

    # the last chunk's padding rows are cut off with its lists' widening: one copy per piece
    last_rows = r * a - (len(pieces) - 1) * step * a
    pieces = [_to_width(piece, width, sentinel, last_rows if i == len(pieces) - 1 else piece[0].shape[0])
              for i, piece in enumerate(pieces)]
    ids, lower, upper = (jnp.concatenate(arrays).reshape(r, a, width) for arrays in zip(*pieces))
    if counts:
        return ids, lower, upper, _list_counts(ids, lower, sentinel)
    return ids, lower, upper


def list_counts(ids, lower, sentinel: int):
    """Of padded lists ``(R, A, K)`` (listed: ``ids < sentinel``): the widest list of each row
    ``(R,)`` and the most positive lower bounds of any list (a scalar)."""
    listed = ids < sentinel
    return jnp.sum(listed, axis=-1).max(axis=1), jnp.max(jnp.sum((lower > 0) & listed, axis=-1), initial=0)


_list_counts = jax.jit(list_counts, static_argnums=2)


@functools.partial(jax.jit, static_argnums=(0, 1, 5, 6))
def _piece_bounds(geometry, size, boxes: IndexBoxes, anchor, prob, noise_shape, axes):
    """``(lower, upper, listed)``: a chunk's window bounds (``_window_bounds``, or
    ``_factored_window_bounds`` along ``axes``) and the most regions any of its rows lists."""
    boxes = _flat_rows(boxes)
    if axes is None:
        lower, upper = _window_bounds(geometry, size, boxes, anchor, prob)
    else:
        lower, upper = _factored_window_bounds(geometry, size, boxes, anchor, prob, noise_shape, axes)
    return lower, upper, jnp.max(jnp.sum(upper > 0, axis=-1))


@functools.partial(jax.jit, static_argnums=(0, 1, 5, 6, 7, 8, 9))
def _compact_lists(geometry, size, anchor, lower, upper, chunk_width: int, width: int, sentinel: int, lead: tuple,
                   counts: bool = False):
    """``_compact`` of the only chunk, cut to ``width`` slots and shaped ``lead + (width,)``
    (``counts``: then their ``list_counts``)."""
    rows = math.prod(lead)
    lists = tuple(x.reshape(lead + (width,)) for x in _to_width(_compact(geometry, size, anchor, lower, upper,
                                                                         chunk_width), width, sentinel, rows))
    return lists + list_counts(lists[0], lists[1], sentinel) if counts else lists


def _rows_per_chunk(rows: int, actions: int) -> int:
    """Rows per compiled chunk: ``ROWS_PER_CHUNK // actions``, or for fewer rows than that the
    least power of two that holds them (a model of 144 rows padded to 2 048 took 8x the work;
    powers of two keep the number of compiled shapes small)."""
    step = max(1, ROWS_PER_CHUNK // actions)
    return min(step, 1 << max(0, rows - 1).bit_length())


@functools.partial(jax.jit, static_argnums=2)
def _chunk_rows(boxes: IndexBoxes, start, size: int) -> IndexBoxes:
    """Rows ``start .. start + size - 1`` of ``(R, A, C)`` boxes as ``(size * A, C)`` boxes, rows
    past the last one copies of it (one compiled program for every chunk, not a gather per field;
    ``size == R``: all rows, ``start`` 0)."""
    rows = boxes.start.shape[0]
    if size == rows:
        return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), boxes)
    take = jnp.minimum(start + jnp.arange(size), rows - 1)
    return jax.tree.map(lambda x: x[take].reshape((-1,) + x.shape[2:]), boxes)


def _flat_rows(boxes: IndexBoxes) -> IndexBoxes:
    """``(R, A, C)`` boxes as ``(R A, C)`` boxes (a chunk of ``_chunk_rows`` is already flat)."""
    if boxes.start.ndim == 3:
        return boxes
    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), boxes)


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _to_width(piece, width: int, sentinel: int, rows: int):
    """A chunk's ``(ids, lower, upper)`` lists cut or padded to ``width`` slots, first ``rows`` rows."""
    def fit(x, fill):
        x = x[:rows, :width]
        return jnp.pad(x, ((0, 0), (0, width - x.shape[1])), constant_values=fill)

    ids, lower, upper = piece
    return fit(ids, sentinel), fit(lower, 0.0), fit(upper, 0.0)


def _quantized_width(width: int) -> int:
    """The least of ``_WIDTH_QUANTUM * {1, 1.5, 2, 3, 4, 6, ...}`` that holds ``width`` slots.

    Each distinct width of a chunk's lists is one more compilation of ``_compact`` and of the
    padding around it: rounded up to multiples of 32, the 75x75 unicycle's lists (530-1 156
    slots) compiled 70 programs in a cold ``build`` (3.3 of its 7.5 s); in steps of at most 1.5x
    a range of widths takes a handful, for at most half again the slots in the chunk's
    temporaries (the lists are cut to the widest one after)."""
    size = max(_WIDTH_QUANTUM, 2)
    while size < width:
        size = size * 3 // 2 if size & (size - 1) == 0 else size * 4 // 3
    return size


def _regions_per_dim(geometry) -> tuple:
    """Regions per dimension: ``ceil(cells / block)`` (a last partial block counts)."""
    cells, _, block = geometry
    return tuple(-(-c // b) for c, b in zip(cells, block))


def _region_ranges(geometry, boxes: IndexBoxes, d: int):
    """``(first, count)``, each ``(rows, C)`` int32: the first region coordinate (of dimension
    ``d``) a box meets and how many consecutive ones (circularly on a periodic dimension); count 0
    for a box that misses the grid."""
    cells, periodic, block = geometry
    n_d, b_d = cells[d], block[d]
    m = _regions_per_dim(geometry)[d]
    start, length = boxes.start[..., d], boxes.length[..., d]
    first = start // b_d
    end = start + length - 1  # last cell, unwrapped
    if periodic[d]:
        wraps = end >= n_d
        last = jnp.where(wraps, end - n_d, end) // b_d
        count = jnp.where(wraps, m - first + last + 1, last - first + 1)
        full = (length >= n_d) | (count > m) | (wraps & (last >= first))
        count = jnp.where(full, m, count)
    else:
        count = end // b_d - first + 1
    count = jnp.where(length > 0, count, 0)
    return first.astype(jnp.int32), count.astype(jnp.int32)


@functools.partial(jax.jit, static_argnums=0)
def _windows(geometry, boxes: IndexBoxes):
    """Per row and dimension the first region coordinate of its window and the window's extent,
    each ``(rows, n)`` int32."""
    boxes = _flat_rows(boxes)
    periodic = geometry[1]
    anchors, extents = [], []
    for d, m in enumerate(_regions_per_dim(geometry)):
        first, count = _region_ranges(geometry, boxes, d)
        met = count > 0
        any_met = jnp.any(met, axis=-1)
        if periodic[d]:
            # Cheap window: unwrap every range to within half a turn of a reference range; it is
            # valid whenever its extent is below one turn. Otherwise (rare: reachable sets spread
            # over half the circle) the exact circular hull, from each region's coverage.
            ref = jnp.take_along_axis(first, jnp.argmax(met, axis=-1)[:, None], axis=-1)
            shift = jnp.mod(first - ref + m // 2, m) - m // 2  # in [-m/2, m/2)
            low = jnp.min(jnp.where(met, shift, m), axis=-1)
            high = jnp.max(jnp.where(met, shift + count, -m), axis=-1)
            anchor, extent = jnp.mod(ref[:, 0] + low, m), high - low
            anchor, extent = jax.lax.cond(jnp.any(any_met & (extent >= m)), functools.partial(_circular_hull, m=m),
                                          lambda *_: (anchor.astype(jnp.int32), extent.astype(jnp.int32)),
                                          first, count)
        else:
            anchor = jnp.min(jnp.where(met, first, m), axis=-1)
            extent = jnp.max(jnp.where(met, first + count, 0), axis=-1) - anchor
        anchors.append(jnp.where(any_met, anchor, 0).astype(jnp.int32))
        extents.append(jnp.where(any_met, extent, 0).astype(jnp.int32))
    return jnp.stack(anchors, -1), jnp.stack(extents, -1)


def _circular_hull(first, count, m: int):
    """Exact circular hull ``(anchor, extent)`` of each row's ranges on a circle of ``m`` regions:
    it starts just after the longest run of regions no range covers."""
    pos = jnp.arange(m, dtype=jnp.int32)
    offset = pos - first[..., None]  # (rows, C, m)
    offset = jnp.where(offset < 0, offset + m, offset)
    covered = jnp.any((offset < count[..., None]), axis=1)  # (rows, m)
    # gap before covered position x = uncovered regions immediately before it (circularly)
    twice = jnp.concatenate([covered, covered], axis=-1)
    last = jax.lax.cummax(jnp.where(twice, jnp.arange(2 * m, dtype=jnp.int32), -m - 1), axis=1)
    gap = jnp.where(covered, m + pos - 1 - last[:, m - 1:2 * m - 1], -1)
    return jnp.argmax(gap, axis=-1).astype(jnp.int32), (m - jnp.max(gap, axis=-1)).astype(jnp.int32)


def _window_coordinates(geometry, size, anchor, d):
    """``(rows, H_d)`` region coordinates of a row's window in dimension ``d`` (``-1``: off grid)."""
    periodic, m = geometry[1], _regions_per_dim(geometry)[d]
    x = anchor[:, d, None] + jnp.arange(size[d], dtype=jnp.int32)
    return jnp.mod(x, m) if periodic[d] else jnp.where(x < m, x, -1)


def _fixed_point(prob, round_up: bool):
    """P_W as integer multiples of 2^-FRACTION_BITS, rounded outward (exact: a power-of-two scale)."""
    scaled = prob * float(2 ** FRACTION_BITS)
    return (jnp.ceil(scaled) if round_up else jnp.floor(scaled)).astype(jnp.int64)


def _to_float(total, round_up: bool):
    """Integer sums back to probabilities, rounded outward (int64 -> float64 rounds to nearest)."""
    value = total.astype(jnp.float64)
    back = value.astype(jnp.int64)  # exact: |value| < 2^63 and integral
    towards = jnp.inf if round_up else -jnp.inf
    wrong_way = (back < total) if round_up else (back > total)
    value = jnp.where(wrong_way, jnp.nextafter(value, towards), value)
    return value * float(2.0 ** -FRACTION_BITS)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _window_bounds(geometry, size, boxes: IndexBoxes, anchor, prob):
    """``(lower, upper)``, each ``(rows, prod(size) + 1)`` float64: the bounds of the window's
    regions in C order, and of the sink in the last column.

    Sums are exact integer sums of P_W in fixed point (rounded outward once per term and once at
    the end), so a difference array over the window, whose prefix sums cancel terms, loses nothing.
    """
    periodic, turn = geometry[1], _regions_per_dim(geometry)
    n = len(size)
    rows = boxes.sink.shape[0]
    lo, count = [], []
    for d in range(n):
        first, cnt = _region_ranges(geometry, boxes, d)
        offset = first - anchor[:, d, None]
        if periodic[d]:
            offset = jnp.where(offset < 0, offset + turn[d], offset)
            offset = jnp.where(cnt >= turn[d], 0, offset)  # a full turn starts at the window's start
        lo.append(offset)
        count.append(cnt)
    meets = functools.reduce(jnp.logical_and, [c > 0 for c in count])
    inside = functools.reduce(jnp.logical_and, [c == 1 for c in count]) & ~boxes.sink
    # at least one unit: a region met only by boxes of probability 0 is still listed (as the
    # cluster members of the MI-MDP and 2I-MDP expect), with upper 2^-61 (sound: above 0)
    p_up = jnp.broadcast_to(jnp.maximum(_fixed_point(prob, True), 1), boxes.sink.shape)
    p_lo = jnp.broadcast_to(_fixed_point(prob, False), boxes.sink.shape)

    # upper: +-P at the 2^n corners of every box in a (H + 1)-per-dimension difference array,
    # lower: a box inside one region adds P to that region alone. ``MAP_BATCH`` rows at a time,
    # corners expanded inside the loop: the rows' small buffers stay in cache, and the (rows, C 2^n)
    # update arrays are never written out (materialized, they took 5x the time of the scatters).
    ext = tuple(h + 1 for h in size)
    strides = np.cumprod((1,) + ext[::-1])[::-1][1:]
    inner_strides = np.cumprod((1,) + size[::-1])[::-1][1:]
    p_meets = jnp.where(meets, p_up, 0)
    p_inside = jnp.where(inside, p_lo, 0)

    wrap_dims = [d for d in range(n) if periodic[d]]

    def corners(lo_r, count_r, wraps):
        """Per dimension the difference terms (position, sign, mask) of the box's indicator: +1 at
        its start, -1 past its end; a range that wraps past the window's end (only in a window
        that spans the whole circle) is [lo, m) + [0, end - m): -1 at end - m and +1 at 0."""
        terms = []
        for d in range(n):
            end = lo_r[d] + count_r[d]
            if wraps and periodic[d]:
                wrapped = end > turn[d]
                terms.append([(lo_r[d], 1, None), (jnp.where(wrapped, end - turn[d], end), -1, None),
                              (jnp.zeros_like(end), 1, wrapped)])
            else:
                terms.append([(lo_r[d], 1, None), (end, -1, None)])
        return itertools.product(*terms)

    def one_row(row, wraps):
        lo_r, count_r, p_meets_r, p_inside_r = row  # (n, C), (n, C), (C,), (C,)
        total = jnp.zeros(math.prod(ext), jnp.int64)
        for corner in corners(lo_r, count_r, wraps):
            flat = sum(pos * int(strides[d]) for d, (pos, _, _) in enumerate(corner))
            sign = math.prod(sign for _, sign, _ in corner)
            value = p_meets_r if sign > 0 else -p_meets_r
            for _, _, mask in corner:
                value = value if mask is None else jnp.where(mask, value, 0)
            total = total.at[flat].add(value, mode="drop")
        inner = sum(lo_r[d] * int(inner_strides[d]) for d in range(n))
        lower = jnp.zeros(math.prod(size), jnp.int64).at[inner].add(p_inside_r, mode="drop")
        return total, lower

    def each_row(row):
        if not wrap_dims:
            return one_row(row, False)
        lo_r, count_r = row[:2]
        wraps = functools.reduce(jnp.logical_or, [jnp.any(lo_r[d] + count_r[d] > turn[d]) for d in wrap_dims])
        return jax.lax.cond(wraps, functools.partial(one_row, wraps=True), functools.partial(one_row, wraps=False),
                            row)

    total, lower = jax.lax.map(each_row, (jnp.stack(lo, 1), jnp.stack(count, 1), p_meets, p_inside),
                               batch_size=MAP_BATCH)
    total = total.reshape((rows,) + ext)
    for d in range(n):
        total = jnp.cumsum(total, axis=1 + d)
    upper = total[(slice(None),) + tuple(slice(0, h) for h in size)].reshape(rows, -1)

    sink_upper = jnp.sum(jnp.where(boxes.sink, p_up, 0), axis=-1)
    sink_lower = jnp.sum(jnp.where(boxes.misses_grid, p_lo, 0), axis=-1)
    upper = jnp.concatenate([upper, sink_upper[:, None]], -1)
    lower = jnp.concatenate([lower, sink_lower[:, None]], -1)
    return _to_float(lower, False), _to_float(upper, True)


def _factor_axes(varies, sink_factors):
    """Per dimension the one noise axis it varies along (-1: none), or ``None`` where the boxes
    do not factor so, from ``_noise_dependence``."""
    varies, sink_factors = np.asarray(varies), bool(sink_factors)
    if not sink_factors or np.any(varies.sum(axis=1) > 1):
        return None
    return tuple(int(np.argmax(v)) if v.any() else -1 for v in varies)


@functools.partial(jax.jit, static_argnums=1)
def _noise_dependence(boxes: IndexBoxes, noise_shape):
    """``(varies (n, m), sink_factors)``: whether dimension d of the boxes ``(rows, C)`` (start
    or length) changes along noise axis k of the C-order grid ``noise_shape``, and whether every
    box's sink flag is the "or" of per-axis flags (those set for every noise cell of a row
    sharing that axis' index)."""
    boxes = _flat_rows(boxes)
    rows, m = boxes.sink.shape[0], len(noise_shape)
    shape = (rows,) + tuple(noise_shape)
    first = lambda x, k: jax.lax.slice_in_dim(x, 0, 1, axis=1 + k)
    varies = []
    for d in range(boxes.start.shape[-1]):
        start, length = boxes.start[..., d].reshape(shape), boxes.length[..., d].reshape(shape)
        varies.append(jnp.stack([jnp.any((start != first(start, k)) | (length != first(length, k)))
                                 for k in range(m)]))
    sink = boxes.sink.reshape(shape)
    per_axis = _sink_per_axis(sink, keepdims=True)
    return jnp.stack(varies), jnp.all(functools.reduce(jnp.logical_or, per_axis) == sink)


def _sink_per_axis(sink, keepdims: bool = False):
    """Per noise axis k of ``sink (rows, K_1, ..., K_m)``: the flags set for every noise cell of a
    row with a given index along k, ``(rows, K_k)`` (or broadcastable with ``keepdims``)."""
    m = sink.ndim - 1
    return [jnp.all(sink, axis=tuple(1 + j for j in range(m) if j != k), keepdims=keepdims) for k in range(m)]


@functools.partial(jax.jit, static_argnums=(0, 1, 5, 6))
def _factored_window_bounds(geometry, size, boxes: IndexBoxes, anchor, prob, noise_shape, axes):
    """``_window_bounds`` for boxes whose dimension d depends on noise axis ``axes[d]`` alone
    (-1: on none) and whose sink flags are an "or" over the axes (``_noise_dependence``).

    A box meets window region h iff every dimension's range holds h_d, so the upper bounds are
    ``sum_c P(c) prod_d R_d[c_{axes[d]}, h_d]``: one contraction of the ``(K_1, ..., K_m)`` table
    of P_W with the per-dimension indicators, O(prod K * H) per row instead of O(C 2^n)
    scatters. The lower bounds (one region, no sink) and the sink's likewise, with the sink's
    complement ``prod_k (1 - g_k)``. The same fixed-point integers are summed (exactly, in
    another order), so the bounds equal ``_window_bounds``' bit for bit.
    """
    periodic, turn = geometry[1], _regions_per_dim(geometry)
    n, m = len(size), len(noise_shape)
    rows = boxes.sink.shape[0]
    shape = (rows,) + tuple(noise_shape)
    along = lambda x, k: x.reshape(shape)[(slice(None),) + tuple(slice(None) if j == k else 0 for j in range(m))]
    noise_letters, window_letters = "abcdefghijkl"[:m], "nopqstuvwxyz"[:n]
    cell_terms = "".join(noise_letters)
    ranges, singles, nonempty, terms = [], [], [], []
    for d in range(n):
        first, count = _region_ranges(geometry, boxes, d)
        offset = first - anchor[:, d, None]
        h = jnp.arange(size[d], dtype=jnp.int32)
        k = axes[d]
        offset, count = along(offset, k)[..., None], along(count, k)[..., None]  # (rows, K_k or -, 1)
        x = h - offset
        if periodic[d]:
            x = jnp.mod(x, turn[d])  # a range [offset, offset + count) that may wrap past the circle's end
        ranges.append(((x >= 0) & (x < count)).astype(jnp.int64))
        singles.append(((count == 1) & (x == 0)).astype(jnp.int64))
        nonempty.append((along(boxes.length[..., d], k) > 0).astype(jnp.int64))
        terms.append("r" + (noise_letters[k] if k >= 0 else ""))
    no_sink = [(~g).astype(jnp.int64) for g in _sink_per_axis(boxes.sink.reshape(shape))]
    p_up = jnp.maximum(_fixed_point(prob, True), 1).reshape(noise_shape)  # as ``_window_bounds``
    p_lo = _fixed_point(prob, False).reshape(noise_shape)
    window = "r" + window_letters
    dims = [t + window_letters[d] for d, t in enumerate(terms)]
    axis_terms = ["r" + letter for letter in noise_letters]
    upper = jnp.einsum(",".join([cell_terms] + dims) + "->" + window, p_up, *ranges)
    lower = jnp.einsum(",".join([cell_terms] + dims + axis_terms) + "->" + window, p_lo, *singles, *no_sink)
    sink_upper = jnp.sum(p_up) - jnp.einsum(",".join([cell_terms] + axis_terms) + "->r", p_up, *no_sink)
    sink_lower = jnp.sum(p_lo) - jnp.einsum(",".join([cell_terms] + terms) + "->r", p_lo, *nonempty)
    upper = jnp.concatenate([upper.reshape(rows, -1), sink_upper[:, None]], -1)
    lower = jnp.concatenate([lower.reshape(rows, -1), sink_lower[:, None]], -1)
    return _to_float(lower, False), _to_float(upper, True)


@functools.partial(jax.jit, static_argnums=(0, 1, 5))
def _compact(geometry, size, anchor, lower, upper, width):
    """The listed regions (``upper > 0``) of each window as ``(rows, width)`` lists, in increasing
    order (the sink last), which the MI-MDP's slot lookups (a binary search) rely on."""
    periodic, shape = geometry[1], _regions_per_dim(geometry)
    n = len(size)
    sentinel = math.prod(shape) + 1
    rows = anchor.shape[0]
    window = math.prod(size)
    # A window that wraps around a periodic dimension visits its coordinates rotated: put each
    # dimension's window positions in increasing coordinate order (off-grid positions last) and
    # read the window in that order, so the listed regions come out sorted without a sort of the
    # whole window (argsort of the lists cost 3x the rest on the 3-D unicycle).
    coords, orders = [], []
    for d in range(n):
        c = _window_coordinates(geometry, size, anchor, d)  # (rows, H_d)
        order = jnp.argsort(jnp.where(c >= 0, c, shape[d]), axis=-1) if periodic[d] else None
        coords.append(jnp.take_along_axis(c, order, axis=-1) if periodic[d] else c)
        orders.append(order)
    grids = [g.reshape(-1) for g in jnp.meshgrid(*[jnp.arange(h) for h in size], indexing="ij")]
    multi = [coords[d][:, grids[d]] for d in range(n)]  # (rows, prod(size)), sorted C order
    listed = upper > 0
    position = None  # window entry of each sorted position (the identity without periodic dimensions)
    if any(periodic):
        position = sum((orders[d][:, grids[d]] if periodic[d] else grids[d][None]) * int(math.prod(size[d + 1:]))
                       for d in range(n))
        position = jnp.concatenate([position, jnp.full((rows, 1), window, position.dtype)], -1)  # the sink last
        listed = jnp.take_along_axis(listed, position, axis=-1)
    on_grid = functools.reduce(jnp.logical_and, [x >= 0 for x in multi])
    region = jnp.ravel_multi_index(tuple(jnp.maximum(x, 0) for x in multi), shape, mode="clip")
    region = jnp.concatenate([jnp.where(on_grid, region, sentinel), jnp.full((rows, 1), sentinel - 1)], -1)
    # One scatter of the sorted positions into the list slots, then gathers of just ``width``
    # entries per row (scattering the ids and both bounds, and permuting the bounds over the whole
    # window, cost twice as much: 1.13 -> 0.57 s on the 4-room model).
    slot = jnp.where(listed, jnp.cumsum(listed, axis=-1) - 1, width)  # width: dropped
    row = jnp.arange(rows)[:, None]
    source = jnp.broadcast_to(jnp.arange(window + 1, dtype=jnp.int32), slot.shape)
    at = jnp.full((rows, width), window + 1, jnp.int32).at[row, slot].set(source, mode="drop")
    filled = at <= window
    at = jnp.minimum(at, window)
    ids = jnp.where(filled, jnp.take_along_axis(region, at, axis=-1).astype(jnp.int32), sentinel)
    if position is not None:
        at = jnp.take_along_axis(position, at, axis=-1)
    put = lambda t: jnp.where(filled, jnp.take_along_axis(t, at, axis=-1), 0.0)
    return ids, put(lower), put(upper)
