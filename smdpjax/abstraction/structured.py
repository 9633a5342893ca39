"""Structured SMDP clusters for additive noise: one index-box piece per (cell, action, dimension,
cell index along that dimension's noise axis), assembled inside the backup.

For ``x' = g(x, u) + B w`` with one nonzero per row of ``B`` (``System.additive`` with a diagonal,
or a permutation times a diagonal), dimension d of the next state is ``g_d(x, u) + b_d w_j`` with
``j = axis(d)``. So dimension d of the index box of cluster q_{s,a,c} (first cell, number of
cells, leaves the grid box) depends on (s, a) and on the index of c along noise axis ``j`` alone.
Stored per (s, a): ``(K, n)`` pieces, K the most cells along one noise axis, instead of the
``(C, n)`` index boxes of ``C = prod_j K_j`` noise cells; memory O(R A K n) instead of
O(R A C n). The backup spreads dimension d's pieces over the noise cells (a broadcast along the other noise
axes) and applies
the cross-dimension step of `decode_boxes` (a box that misses the grid along one dimension misses
it altogether). The cluster minima are those of the stored index boxes bit for bit: the
enclosure of dimension d reads ``w_j`` alone (``System.additive`` evaluates ``g + b * w[perm]``
element by element), and the snapping of each dimension is the same function.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass, static_field
from ..partition import NoiseGrid, StateGrid
from ..system import System
from .clusters import IndexBoxes, decode_dimensions, lengths_of, small_int
from .grid_clusters import _require_memory, policy_actions, snapped_boxes, validate
from .range_min import RangeSpec, build_table, loop_variant_zero, query_table


def noise_axes(system: System) -> np.ndarray:
    """``(n,)`` the noise axis that enters each state dimension of an additive system.

    Raises ValueError unless ``system`` was declared with ``System.additive`` and every row of
    its ``B`` has exactly one nonzero (what structured clusters need)."""
    if not isinstance(system, System):
        raise TypeError(f"system must be a smdpjax.System, got {type(system).__name__}")
    if not system.is_additive:
        raise ValueError("structured clusters need additive noise declared with System.additive(g, B, ...): "
                         "x' = g(x, u) + B w")
    nonzero = np.asarray(system.B) != 0
    if not np.all(nonzero.sum(axis=1) == 1):
        raise ValueError(f"structured clusters need one nonzero per row of B (a diagonal or a permutation times a "
                         f"diagonal: each state dimension driven by one noise axis), got B =\n{system.B}")
    return np.argmax(nonzero, axis=1)


def pays_off(system: System, grid: StateGrid, noise_grid: NoiseGrid) -> bool:
    """Whether ``encoding="auto"`` picks structured clusters: the system allows them (see
    `noise_axes`) and they take at most half the memory of stored index boxes. Their backup
    costs 1.1-1.4x, their abstraction 4-7x less time (``benchmarks/structured_clusters.py``)."""
    try:
        noise_axes(system)
    except (TypeError, ValueError):  # not for structured clusters (a wrong type is reported later)
        return False
    stored = noise_grid.num_bounded * (2 * grid.n + 1)  # bytes per (cell, action), int8 starts
    structured = max(noise_grid.shape) * 3 * grid.n
    return stored >= 2 * structured


def diagonal_noise_boxes(noise_grid: NoiseGrid):
    """``(w_lo, w_hi)``, each ``(K, d)``: box k is cell ``min(k, K_j - 1)`` along every axis j
    (K the most cells along one axis), so that every cell index of every axis occurs."""
    counts = np.asarray(noise_grid.shape)
    k = np.arange(int(counts.max()))
    index = np.minimum(k[:, None], counts[None, :] - 1)  # (K, d)
    lows = np.stack([np.asarray(e)[index[:, j]] for j, e in enumerate(noise_grid.edges)], axis=-1)
    highs = np.stack([np.asarray(e)[index[:, j] + 1] for j, e in enumerate(noise_grid.edges)], axis=-1)
    return lows, highs


@pytree_dataclass
class StructuredClusters:
    """SMDP clusters of additive noise as per-dimension index-box pieces (module docstring).

    Attributes:
        start: ``(R, A, K, n)`` first cell along dimension d for cell index k of d's noise axis
            (int8/int16/int32: the smallest that holds the grid's cells).
        length: ``(R, A, K, n)`` number of cells along d (same dtype); 0 where the box misses
            the grid along d.
        leave: ``(R, A, K, n)`` bool, the box leaves the grid box along d.
        spec: static grid shape, periodic dimensions and longest box per dimension.
        noise_shape: static cells per noise axis (the bounded noise cells are their product, C order).
        axes: static noise axis of each state dimension.
    """

    start: jax.Array
    length: jax.Array
    leave: jax.Array
    spec: RangeSpec = static_field()
    noise_shape: tuple = static_field()
    axes: tuple = static_field()

    encoding = "structured"

    @property
    def shape(self) -> tuple:
        """``(R, A, C_b)``."""
        return tuple(self.start.shape[:2]) + (int(np.prod(self.noise_shape)),)

    def _spread(self, a, d):
        """Dimension d's pieces ``a[..., d]`` at every noise cell: ``(R, A, C_b)``, by a broadcast
        along the other noise axes (a take with one index per noise cell ran 1.8x slower)."""
        j, k = self.axes[d], self.noise_shape[self.axes[d]]
        one = [1] * len(self.noise_shape)
        one[j] = k
        lead = a.shape[:2]
        piece = a[:, :, :k, d].reshape(lead + tuple(one))
        return jnp.broadcast_to(piece, lead + tuple(self.noise_shape)).reshape(lead + (-1,))

    def pieces(self, anchor=None):
        """Per dimension, the ``(R, A, C_b)`` starts and lengths of every cluster's index box,
        and the ``(R, A, C_b)`` sink flags (as `decode_boxes`: a box that misses the grid along
        one dimension is the sink alone). ``anchor``: see ``range_min.loop_variant_zero``."""
        dims = range(self.spec.n)
        start, length, leave = self.start, self.length, self.leave
        if anchor is not None:
            start, length = start + anchor.astype(start.dtype), length + anchor.astype(length.dtype)
            leave = leave | (anchor != 0)
        starts, lengths = [self._spread(start, d) for d in dims], [self._spread(length, d) for d in dims]
        empty = jnp.any(jnp.stack([n == 0 for n in lengths]), axis=0)
        leave = jnp.any(jnp.stack([self._spread(leave, d) for d in dims]), axis=0)
        return starts, lengths, leave | empty

    def index_boxes(self) -> IndexBoxes:
        """The ``(R, A, C_b)`` index boxes the pieces stand for (int32), equal to those of
        ``compute_grid_clusters``; materialized: memory O(R A C_b n)."""
        starts, lengths, sink = self.pieces()
        empty = jnp.any(jnp.stack([n == 0 for n in lengths]), axis=0)
        start = jnp.stack([jnp.where(empty, 0, s.astype(jnp.int32)) for s in starts], axis=-1)
        length = jnp.stack([jnp.where(empty, 0, n.astype(jnp.int32)) for n in lengths], axis=-1)
        return IndexBoxes(start=start, length=length, sink=sink)

    def take_actions(self, actions) -> "StructuredClusters":
        """The clusters of action ``actions[r]`` in row r: leading shape ``(R, 1, C_b)``."""
        pick = lambda a: jnp.take_along_axis(a, actions.reshape((-1, 1, 1, 1)), axis=1)
        return dataclasses.replace(self, start=pick(self.start), length=pick(self.length), leave=pick(self.leave))

    def extreme(self, v, minimize: bool):
        """min (or max) of ``v (N+1,)`` over every cluster: ``(R, A, C_b)``."""
        op = "min" if minimize else "max"
        starts, lengths, sink = self.pieces(loop_variant_zero(v))
        in_grid = query_table(build_table(v[:-1], self.spec, op), starts, lengths, self.spec, op)
        worse = v[-1] < in_grid if minimize else v[-1] > in_grid
        return jnp.where(sink & worse, v[-1], in_grid)

    def member_lists(self):
        """``(R, A, C_b, K)`` padded member lists (expanded on demand: memory grows with K)."""
        from .smdp import BoxClusters

        boxes = self.index_boxes()
        return BoxClusters(start=boxes.start, length=boxes.length, sink=boxes.sink, spec=self.spec).member_lists()

    def describe(self) -> str:
        lengths = "x".join(map(str, self.spec.max_lengths))
        return f"encoding=structured ({self.start.shape[2]} pieces per dimension), max box={lengths} cells"


def structured_clusters(system: System, grid: StateGrid, noise_grid: NoiseGrid, *, method: str = "both",
                        policy=None, progress: bool = False, mesh=None):
    """``(rows (R,), StructuredClusters, prob (C_b,), prob_rest)`` of an additive system (see
    `noise_axes`): the reachable sets of R x A x K triples (K the most cells along one noise
    axis) instead of R x A x C_b. Arguments as for ``compute_grid_clusters``."""
    axes = noise_axes(system)
    rows = validate(system, grid, noise_grid)
    actions = policy_actions(system, grid, rows, policy)
    prob, prob_rest = noise_grid.probabilities(system.noise)
    w_lo, w_hi = diagonal_noise_boxes(noise_grid)
    dtype = small_int(int(np.max(grid.cells)))
    per_row = (1 if policy is not None else system.num_actions) * w_lo.shape[0]
    _require_memory(grid, rows.size, per_row, np.dtype(dtype).itemsize)
    start, length, leave = snapped_boxes(system, grid, rows, actions, w_lo, w_hi,
                                         lambda codes: _pieces(codes, np.dtype(dtype).name), method=method,
                                         progress=progress, mesh=mesh)
    longest = np.asarray(_longest(length))
    clusters = StructuredClusters(start=start, length=length, leave=leave,
                                  spec=RangeSpec.for_grid(grid, lengths_of(longest), boxes=rows.size * per_row),
                                  noise_shape=tuple(int(k) for k in noise_grid.shape),
                                  axes=tuple(int(j) for j in axes))
    return rows, clusters, prob, prob_rest


def expanded_boxes(clusters: StructuredClusters, dtype: str = "int32") -> IndexBoxes:
    """The ``(R, A, C_b)`` index boxes of ``clusters`` with starts and lengths of type ``dtype``
    (as ``compute_grid_clusters`` returns them), expanded in chunks of rows."""
    from .imdp import row_chunks

    parts = [_expand(chunk, dtype) for chunk in row_chunks(clusters)]
    return parts[0] if len(parts) == 1 else jax.tree.map(lambda *a: jnp.concatenate(a), *parts)


@functools.partial(jax.jit, static_argnames="dtype")
def _expand(clusters: StructuredClusters, dtype: str) -> IndexBoxes:
    boxes = clusters.index_boxes()
    return IndexBoxes(start=boxes.start.astype(dtype), length=boxes.length.astype(dtype), sink=boxes.sink)


@jax.jit
def _longest(length):
    return jnp.max(length.reshape(-1, length.shape[-1]), axis=0)


@functools.partial(jax.jit, static_argnames="dtype")
def _pieces(codes, dtype):
    return decode_dimensions(codes, dtype)
