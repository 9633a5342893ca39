"""Clusters q_{s,a,c} (Definition 6) on a grid: the cells a reachable box meets.

On a uniform grid the cells that meet a box form an *index box*: per dimension a first cell and a
number of cells (wrapping around on periodic dimensions), plus a flag for "also meets the sink"
(the box leaves the grid box). ``IndexBoxes`` is that compact encoding; ``cluster_members``
expands it to padded member lists, the encoding the Bellman backups gather from.

Padding uses ``sentinel = num_cells + 1``: one past the end of a value vector of length
``num_cells + 1`` (cells + sink), read with ``mode="fill"``. A sentinel of -1 would silently
wrap to the sink.
"""

from __future__ import annotations

import functools
import math
from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass
from ..partition import StateGrid
from ..reach.interval import _subnormal

# Slack, in units of cells, for boxes that wrap around a periodic dimension: their ends are
# compared with the faces after a rounded shift by the period, so the snapping there treats cells
# as closed and grows the box by this slack (it dwarfs the ~1e-13 cells of rounding); it only ever
# adds cells.
INDEX_SLACK = 1e-9


@pytree_dataclass
class IndexBoxes:
    """Cells met by reachable boxes, as index boxes. Leading shape ``B`` is arbitrary.

    Attributes:
        start: ``(*B, n)`` int32 (or the smallest type that holds the grid's cells, see
            ``compute_grid_clusters(..., compact=True)``), first cell index per dimension (in
            ``[0, cells)``).
        length: ``(*B, n)``, same type, number of cells per dimension; 0 when the box misses the
            grid.
        sink: ``(*B,)`` bool, the box also meets the sink (leaves the grid box).
    """

    start: jax.Array
    length: jax.Array
    sink: jax.Array

    @property
    def misses_grid(self):
        """``(*B,)`` the box meets no grid cell (its cluster is the sink alone)."""
        return jnp.any(self.length == 0, axis=-1)

    @property
    def single_cell(self):
        """``(*B,)`` the box lies inside one grid cell (its cluster is one cell, no sink)."""
        return jnp.all(self.length == 1, axis=-1) & ~self.sink

    @property
    def inside_sink(self):
        """``(*B,)`` the box lies outside the grid box (its cluster is the sink alone)."""
        return self.misses_grid


def index_boxes(grid: StateGrid, lo, hi, hi_open=None) -> IndexBoxes:
    """Index boxes of reachable boxes ``lo, hi: (*B, n)`` on ``grid`` (jit-friendly).

    Cells are half-open (``StateGrid``), and a box ``[lo, hi]`` meets the cells that the next
    state can reach with positive probability: a lower end exactly on a face ``e_k`` does not
    reach the cell below it; an upper end exactly on a face reaches the cell above it unless
    ``hi_open`` (``(*B, n)`` bool, default all False: the closed, conservative rule) says the
    value stays below it almost surely. Faces are compared exactly with ``grid.edges``. On a
    periodic dimension a box that does not lie within ``[low, high]`` is shifted by the period
    with rounding, so there cells are taken as closed and grown by ``INDEX_SLACK``.
    """
    return decode_boxes(dimension_codes(grid, lo, hi, hi_open))


# A dimension's (first cell, number of cells, leaves the grid box) packed into one int64.
_LENGTH_SHIFT, _LEAVE_SHIFT = 31, 62


def dimension_codes(grid: StateGrid, lo, hi, hi_open=None, *, normal_ends: bool = False):
    """``(n, *B)`` int64: each dimension's part of `index_boxes`, packed (`decode_boxes` undoes
    it), for ends ``lo, hi, hi_open``: ``(*B, n)`` arrays, or ``(n, *B)`` ones passed as
    sequences of n arrays ``(*B,)`` (the faster layout: each dimension contiguous).

    Entry ``[d]`` depends on dimension d alone, so XLA computes each once; the cross-dimension
    step (a box that misses the grid in one dimension misses it altogether) is left to
    `decode_boxes`. Compiled apart from it, the snapping runs once per box instead of once per
    output (XLA on the CPU fuses a producer into every consumer).

    ``normal_ends=True`` promises that no end is subnormal, which skips their rounding to 0 or
    +-tiny (a third of the cost): true of `reachable_boxes`, whose inputs are made normal and
    whose arithmetic flushes subnormal results to zero where comparisons read them as zero
    (XLA on the CPU; elsewhere subnormals compare exactly and need no rounding anyway)."""
    def by_dimension(x):
        return list(x) if isinstance(x, (list, tuple)) else [x[..., d] for d in range(grid.n)]

    los, his = by_dimension(lo), by_dimension(hi)
    opens = [jnp.zeros(jnp.shape(h), bool) for h in his] if hi_open is None else by_dimension(hi_open)
    codes = []
    for d in range(grid.n):
        ends = (los[d], his[d], jnp.asarray(opens[d], bool))
        args = (grid, d, *(ends if normal_ends else _normal_ends(*ends)))
        if grid.periodic[d]:
            start, length = _periodic_dimension(*args)
            leave = jnp.zeros(jnp.shape(start), bool)
        else:
            start, length, leave = _flat_dimension(*args)
        codes.append(start.astype(jnp.int64) | (length.astype(jnp.int64) << _LENGTH_SHIFT)
                     | (leave.astype(jnp.int64) << _LEAVE_SHIFT))
    return jnp.stack(codes)


def _normal_ends(lo, hi, hi_open):
    """Subnormal ends (compared as 0 by XLA on the CPU) rounded outward to 0 or +-tiny."""
    tiny = float(np.finfo(np.float64).tiny)
    sub_lo, sub_hi = _subnormal(lo), _subnormal(hi)
    lo = jnp.where(sub_lo, jnp.where(jnp.signbit(lo), -tiny, 0.0), lo)
    hi = jnp.where(sub_hi, jnp.where(jnp.signbit(hi), 0.0, tiny), hi)
    return lo, hi, hi_open | sub_hi


def decode_boxes(codes, dtype=jnp.int32) -> IndexBoxes:
    """`IndexBoxes` (leading shape ``B``) from `dimension_codes` ``(n, *B)``, with starts and
    lengths of integer type ``dtype`` (which must hold every cell index and box length)."""
    mask = (1 << _LENGTH_SHIFT) - 1
    lengths = [((c >> _LENGTH_SHIFT) & mask).astype(dtype) for c in codes]
    empty = functools.reduce(jnp.logical_or, [n == 0 for n in lengths])
    sink = functools.reduce(jnp.logical_or, [(c >> _LEAVE_SHIFT) != 0 for c in codes]) | empty
    start = jnp.stack([jnp.where(empty, 0, (c & mask).astype(dtype)) for c in codes], axis=-1)
    return IndexBoxes(start=start, length=jnp.stack([jnp.where(empty, 0, n) for n in lengths], axis=-1), sink=sink)


def decode_dimensions(codes, dtype=jnp.int32):
    """Each dimension's part of `dimension_codes` ``(n, *B)`` on its own, without the
    cross-dimension step of `decode_boxes`: ``(start, length, leave)``, each ``(*B, n)``
    (``leave``: bool, the box leaves the grid box along that dimension)."""
    mask = (1 << _LENGTH_SHIFT) - 1
    start = jnp.stack([(c & mask).astype(dtype) for c in codes], axis=-1)
    length = jnp.stack([((c >> _LENGTH_SHIFT) & mask).astype(dtype) for c in codes], axis=-1)
    leave = jnp.stack([(c >> _LEAVE_SHIFT) != 0 for c in codes], axis=-1)
    return start, length, leave


def small_int(max_value: int):
    """Smallest signed integer type holding ``0 .. max_value``."""
    for dtype in (jnp.int8, jnp.int16, jnp.int32):
        if max_value <= np.iinfo(dtype).max:
            return dtype
    raise ValueError(f"{max_value} cells in one dimension do not fit int32")


def snapping_end(hi, hi_open, high):
    """``(*B, n)`` upper ends that `index_boxes` snaps with the closed rule exactly as it snaps
    ``hi`` with ``hi_open`` on a grid whose box ends at ``high (n,)``: the float below hi where hi
    is open. No face lies strictly between two neighbouring floats, so the values below hi meet
    the same cells as that float; the one exception is hi just above ``high`` (the grid box is
    closed there, the values between reach the sink), where hi is kept, as it is where
    subnormal (`index_boxes` rounds those outward itself).

    Lets the enclosure hand over one array instead of two (XLA on the CPU recomputes the whole
    enclosure once per output). Not for periodic dimensions: their ends are shifted by the
    period, and a face can lie between the shifted neighbours."""
    tiny = float(np.finfo(np.float64).tiny)
    bits = jax.lax.bitcast_convert_type(hi, jnp.int64)
    below = jax.lax.bitcast_convert_type(bits + jnp.where(hi > 0, -1, 1).astype(jnp.int64), jnp.float64)
    # At 0 the float below is subnormal (read as 0 on the CPU): -tiny, and no face lies between.
    below = jnp.where(hi == 0, -tiny, below)
    above_high = jnp.asarray(np.nextafter(np.asarray(high, np.float64), np.inf))
    return jnp.where(hi_open & jnp.isfinite(hi) & (hi != above_high) & ~_subnormal(hi), below, hi)


def _last_cell(grid: StateGrid, d: int, hi, hi_open):
    """Index of the last cell an upper end reaches (the last cell for hi at or above ``high``):
    the cell containing hi, or the one below when hi lies exactly on its lower face and is open."""
    j, on_face = grid.dimension_cell(jnp.clip(hi, grid.low[d], grid.high[d]), d)
    return j - (on_face & hi_open).astype(jnp.int32)


def _flat_dimension(grid: StateGrid, d: int, lo, hi, hi_open):
    """(first cell, number of cells, leaves the grid box) along a non-periodic dimension."""
    low, high = grid.low[d], grid.high[d]
    first = grid.dimension_index(jnp.clip(lo, low, high), d)
    last = _last_cell(grid, d, hi, hi_open)
    # lo inside the grid: the box meets lo's cell whatever the flags say (an open end equal to
    # lo would make the box a null set; counting the cell is the safe side).
    last = jnp.where(lo >= low, jnp.maximum(last, first), last)
    meets = (lo <= high) & (jnp.maximum(hi, lo) >= low) & (last >= first)  # max: `snapping_end` of a null box
    length = jnp.where(meets, last - first + 1, 0)
    return first, length, (lo < low) | (hi > high)


def _periodic_dimension(grid: StateGrid, d: int, lo, hi, hi_open):
    """(first cell, number of cells) along a periodic dimension, wrapping around.

    Each end is brought into ``[low, high]`` by adding -P, 0 or P (P = high - low, when exactly
    representable) with the exact error of that addition (TwoSum), so it is located among the
    faces exactly as an unshifted end would be; ``high`` itself is ``low`` again (cell number
    ``cells`` is cell 0). Ends farther than one period out, or a period that is not a float, fall
    back to closed cells grown by ``INDEX_SLACK``."""
    low, high = float(grid.low[d]), float(grid.high[d])
    cells = int(grid.cells[d])
    period = high - low
    exact_period = Fraction(high) - Fraction(low) == Fraction(period)
    span = hi - lo
    full_turn = ~(span < period * (1 - 8 * np.finfo(np.float64).eps))  # also for inf / NaN spans
    first, ok_lo = _periodic_end(grid, d, lo, jnp.zeros(jnp.shape(lo), bool), period, lower=True)
    last, ok_hi = _periodic_end(grid, d, hi, hi_open, period, lower=False)
    last = jnp.maximum(last, first)
    exact_ok = ok_lo & ok_hi & exact_period
    exact_length = jnp.minimum(last - first + 1, cells)
    exact_start = jnp.mod(first, cells)
    # Fallback: shifted by the period with rounding, closed cells with slack.
    width = grid.width[d]
    t_lo = jnp.mod(lo - low, period) / width
    t_hi = t_lo + span / width
    raw_lo = jnp.ceil(jnp.clip(t_lo, -2.0, cells + 2.0) - INDEX_SLACK).astype(jnp.int32) - 1
    raw_hi = jnp.floor(jnp.clip(t_hi, -2.0, 3.0 * cells + 2.0) + INDEX_SLACK).astype(jnp.int32)
    wrap_length = jnp.minimum(raw_hi - raw_lo + 1, cells)
    wrap_start = jnp.mod(raw_lo, cells)
    start = jnp.where(full_turn, 0, jnp.where(exact_ok, exact_start, wrap_start))
    length = jnp.where(full_turn, cells, jnp.where(exact_ok, exact_length, wrap_length))
    return start, length


def _periodic_end(grid: StateGrid, d: int, x, x_open, period: float, lower: bool):
    """Unwrapped cell index (cell k of period m is ``m * cells + k``) of a box end x along a
    periodic dimension, and whether it was decided exactly."""
    low, high = float(grid.low[d]), float(grid.high[d])
    cells = int(grid.cells[d])
    m = jnp.where(x < low, -1, jnp.where(x > high if not lower else x >= high, 1, 0))
    shift = -m.astype(x.dtype) * period
    s = x + shift
    bb = s - x
    err = (x - (s - bb)) + (shift - bb)  # TwoSum: x + shift = s + err exactly
    decided = (((x == 0) | (jnp.abs(x) >= 2.0 ** -969)) & (s >= low) & (s <= high)
               & ((s == 0) | (jnp.abs(s) >= 2.0 ** -969)))
    at_top = s >= high
    k, on_face = grid.dimension_cell(jnp.clip(s, low, high), d)
    k = jnp.where(at_top, cells, k)
    on_face = jnp.where(at_top, s == high, on_face)
    if lower:
        k = k - (on_face & (err < 0)).astype(jnp.int32)
    else:
        k = k - (on_face & ((err < 0) | ((err == 0) & x_open))).astype(jnp.int32)
    decided = decided & (jnp.abs(m) <= 1) & ~(at_top & (err > 0))
    return m * cells + k, decided


def index_dtype(num_states: int):
    """Smallest signed integer type that holds state indices and the padding ``num_states``."""
    return jnp.int16 if num_states < np.iinfo(np.int16).max else jnp.int32


def max_lengths(boxes: IndexBoxes) -> tuple:
    """Largest length per dimension over all boxes (a static shape for ``cluster_members``)."""
    return lengths_of(jnp.max(boxes.length.reshape(-1, boxes.length.shape[-1]), axis=0))


def lengths_of(longest) -> tuple:
    """``max_lengths`` from the per-dimension maximum ``longest (n,)`` (at least 1 each)."""
    return tuple(max(int(v), 1) for v in np.asarray(longest))


def cluster_members(grid: StateGrid, boxes: IndexBoxes, lengths: tuple):
    """Padded member lists ``(*B, prod(lengths) + 1)`` of the clusters of ``boxes``
    (int16 when the states fit, see ``index_dtype``, else int32).

    Members are flat cell indices, the sink is ``grid.sink``, padding is ``grid.sink + 1``.
    ``lengths`` must bound ``boxes.length`` per dimension (see ``max_lengths``).
    """
    geometry = (tuple(int(c) for c in grid.cells), tuple(bool(p) for p in grid.periodic))
    return _members(geometry, tuple(int(v) for v in lengths), boxes)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _members(geometry, lengths, boxes: IndexBoxes):
    """``cluster_members`` in one fused program (eager, its (rows, C, members, n) temporaries
    took ~10 of the 113 s of the 3-D unicycle's MI-MDP, row 19)."""
    cells, periodic = geometry
    num_cells = math.prod(cells)
    sentinel = num_cells + 1
    offsets = jnp.asarray(np.indices(lengths).reshape(len(lengths), -1).T, jnp.int32)  # (K, n)
    idx = boxes.start[..., None, :] + offsets  # (*B, K, n)
    valid = jnp.all(offsets < boxes.length[..., None, :], axis=-1)
    idx = jnp.where(jnp.asarray(periodic), jnp.mod(idx, jnp.asarray(cells, jnp.int32)), idx)
    flat = jnp.ravel_multi_index(tuple(jnp.moveaxis(idx, -1, 0)), cells, mode="clip")
    grid_members = jnp.where(valid, flat, sentinel).astype(jnp.int32)
    sink_member = jnp.where(boxes.sink, num_cells, sentinel).astype(jnp.int32)[..., None]
    return jnp.concatenate([grid_members, sink_member], axis=-1).astype(index_dtype(num_cells + 1))
