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

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass
from ..partition import StateGrid

# Slack, in units of cells, by which a box is grown before it is snapped to cell indices. It
# dwarfs the rounding error of (x - low) / width (~1e-13 cells on 10^3-cell axes) and so only ever
# adds cells (never drops one); a box that touches a face meets both cells, as closed cells do.
INDEX_SLACK = 1e-9


@pytree_dataclass
class IndexBoxes:
    """Cells met by reachable boxes, as index boxes. Leading shape ``B`` is arbitrary.

    Attributes:
        start: ``(*B, n)`` int32, first cell index per dimension (in ``[0, cells)``).
        length: ``(*B, n)`` int32, number of cells per dimension; 0 when the box misses the grid.
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


def index_boxes(grid: StateGrid, lo, hi) -> IndexBoxes:
    """Index boxes of reachable boxes ``lo, hi: (*B, n)`` on ``grid`` (jit-friendly)."""
    cells = jnp.asarray(grid.cells, jnp.int32)
    ncell = jnp.asarray(grid.cells, lo.dtype)
    periodic = jnp.asarray(grid.periodic)
    span_cells = (hi - lo) / grid.width
    # Periodic coordinates: move the box's lower end into [low, high), keep its span.
    lo_wrapped = grid.low + jnp.mod(lo - grid.low, grid.high - grid.low)
    lo = jnp.where(periodic, lo_wrapped, lo)
    # Clip before converting to int: infinite bounds (an unbounded enclosure) stay meaningful.
    t_lo = jnp.clip((lo - grid.low) / grid.width, -2.0, ncell + 2.0)
    t_hi = jnp.clip(jnp.where(periodic, t_lo + span_cells, (hi - grid.low) / grid.width), -2.0, 2 * ncell + 2.0)
    raw_lo = jnp.ceil(t_lo - INDEX_SLACK).astype(jnp.int32) - 1  # closed cell i meets [lo, hi] iff i + 1 >= t_lo
    raw_hi = jnp.floor(t_hi + INDEX_SLACK).astype(jnp.int32)  # ... and i <= t_hi

    first = jnp.maximum(raw_lo, 0)
    last = jnp.minimum(raw_hi, cells - 1)
    flat_length = jnp.maximum(last - first + 1, 0)

    full_turn = ~(span_cells + 2 * INDEX_SLACK < ncell)  # also True for an infinite or NaN span
    wrap_length = jnp.where(full_turn, cells, jnp.minimum(raw_hi - raw_lo + 1, cells))
    wrap_start = jnp.where(full_turn, 0, jnp.mod(raw_lo, cells))

    start = jnp.where(periodic, wrap_start, first)
    length = jnp.where(periodic, wrap_length, flat_length)
    leaves = (t_lo < INDEX_SLACK) | (t_hi > ncell - INDEX_SLACK)
    sink = jnp.any(leaves & ~periodic, axis=-1)
    # A box that misses the grid in one dimension misses it altogether.
    empty = jnp.any(length == 0, axis=-1, keepdims=True)
    length = jnp.where(empty, 0, length)
    start = jnp.where(empty, 0, start)
    return IndexBoxes(start=start.astype(jnp.int32), length=length.astype(jnp.int32), sink=sink | empty[..., 0])


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
    sentinel = grid.num_cells + 1
    offsets = jnp.asarray(np.indices(lengths).reshape(len(lengths), -1).T, jnp.int32)  # (K, n)
    cells = jnp.asarray(grid.cells, jnp.int32)
    idx = boxes.start[..., None, :] + offsets  # (*B, K, n)
    valid = jnp.all(offsets < boxes.length[..., None, :], axis=-1)
    idx = jnp.where(jnp.asarray(grid.periodic), jnp.mod(idx, cells), idx)
    flat = jnp.ravel_multi_index(tuple(jnp.moveaxis(idx, -1, 0)), tuple(grid.cells.tolist()), mode="clip")
    grid_members = jnp.where(valid, flat, sentinel).astype(jnp.int32)
    sink_member = jnp.where(boxes.sink, grid.sink, sentinel).astype(jnp.int32)[..., None]
    return jnp.concatenate([grid_members, sink_member], axis=-1).astype(index_dtype(grid.num_states))
