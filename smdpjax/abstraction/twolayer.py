"""Two-layer IMDP (2I-MDP, the paper's reference [gracia2024temporal]).

The fine layer is the state grid with the IMDP bounds of Lemma 1. The coarse layer partitions
the grid into non-overlapping *blocks* of ``block`` cells per dimension (the sink is a block of
its own), and Lemma 1 bounds the probability of landing in each block:

    L_B = sum_c P_W(c) 1(Reach(s,a,c) inside B),   U_B = sum_c P_W(c) 1(Reach(s,a,c) meets B) (+ P_W(rest)).

Inner problem, exact and without an LP: with the block masses m_B fixed, the cheapest placement
inside a block is the interval greedy, a convex piecewise-linear f_B(m_B) whose slopes are the
values of the block's states in increasing order. Minimizing sum_B f_B(m_B) subject to
sum m_B = 1 and m_B in [lo_B, hi_B] is then a greedy over all pieces in increasing value, each
block clipped to its range. With one global sort of the values per iteration, the mass placed
once every state of rank < k has been offered is

    M(k) = sum_B clip(sum_{i in B} l_i + sum_{i in B, rank_i < k} (u_i - l_i), lo_B, hi_B),

monotone in k; a bisection finds where it reaches 1, and the state of rank k* - 1 takes the rest.
The bisection reads masses only; the cost of the placement it finds is computed once, after it,
by pouring each block's mass beyond its lower bounds into the block's cells in rank order.
The order of the cells inside a block is the block's own (it does not depend on the row): each
call sorts the B blocks' cells, puts every row's capacities in that order and takes their prefix
sums once, so that a bisection step only reads, per block met, the prefix sums at the number of
the block's cells ranked below k (one read of a count table ``(N + 1, B + 2)`` built from the
sort, or a binary search in the block's sorted ranks where the table would be large or read
little: ``wants_count_table``).
Blocks that no bounded reachable set meets (only the remainder can put mass there) are handled
in aggregate through a sorted list of the blocks' lowest ranks. Per iteration:
O(N log N + B S log S + P S) once, then O(R A T) (count table) or O(R A T log S) per bisection
step (log N steps), T the most blocks a row meets, S the cells per block, P the met pairs.

Storage: the fine layer is kept sparse (per row and action the listed successors' slots
``t S + i`` and upper bounds, in fixed-width chunks as in ``imdp_compact``, the positive lower
bounds as pairs); every backup lays the met blocks' capacities out in rank order (``upper_rest``
on every cell, the listed bounds scattered over it) before the greedy, one row of ``S`` per met
(list, block) pair (``block_pairs``: rows meet 30 of the T = 81 block slots on average on the
4-room temperature row), so only that transient, not the stored abstraction, has ``S`` entries
per met block (row 38: 75 MB stored, the upper bounds ``coded``, instead of 2211 MB). On the CPU
the rows are solved a block at a time (``imdp_compact.in_row_blocks``, ``BLOCK_SLOTS``), so that
transient is a block's.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass, static_field
from .base import AbstractionMixin, check_adversary
from .box_bounds import region_bounds
from .clusters import index_dtype
from .coded import decoded, encode, map_entries
from .grid_clusters import GridClusters
from .imdp import value_ranking
from .imdp_compact import block_fields, chunk_lists, in_row_blocks, most_per_block

# Slots (T S plus the fine entries, per row and action) per block of rows on the CPU: 4x the
# IMDP's ``imdp_compact.BLOCK_SLOTS``. Each block pays ~0.4 ms of fixed cost (the layout's
# programs and 15 bisection steps of small programs), which outweighed keeping its capacities
# in L2: one backup, ms, at 2^19 -> 2^21 slots: 4-room temperature 440 -> 375, 3-D unicycle
# (37 noise cells) 1180 -> 1030-1100, (101) 995 -> 945, 2-D unicycle 60x60 217 -> 193; 2^20
# and 2^22 in between or equal, 2^23 slower (docs/performance.md).
BLOCK_SLOTS = 1 << 21


def block_layout(grid, block) -> tuple[np.ndarray, np.ndarray]:
    """``(block_of (N+2,), cells_of (B+1, S))``: the block of every state (sentinel -> B+1) and the
    cells of every block (the sink block B holds the sink), padded with ``N + 1``. Read-only
    (kept for the next model of the same grid and block shape)."""
    return _grid_layout(grid, block)[:2]


def _grid_layout(grid, block) -> tuple:
    """``_layout`` of ``grid`` with ``block`` cells per block and dimension (checked)."""
    block = np.broadcast_to(np.asarray(block, np.int64), (grid.n,))
    if np.any(block <= 0):
        raise ValueError(f"block shape must be positive, got {block.tolist()}")
    return _layout(tuple(int(c) for c in grid.cells), tuple(int(b) for b in block))


@functools.lru_cache(maxsize=16)
def _layout(cells: tuple, block: tuple):
    """``block_layout``'s arrays, then ``offset_of (N+2,)`` (each state's cell slot in its block,
    0 for the sentinel) and the three on the device."""
    cells, block = np.array(cells), np.array(block)
    num_cells = int(np.prod(cells))
    shape = -(-cells // block)  # blocks per dimension
    multi = np.stack(np.unravel_index(np.arange(num_cells), tuple(cells)), axis=-1)
    block_multi = multi // block
    block_of_cell = np.ravel_multi_index(tuple(block_multi.T), tuple(shape))
    num_blocks = int(np.prod(shape))
    size = int(np.prod(block))
    offset = np.ravel_multi_index(tuple((multi % block).T), tuple(block))
    cells_of = np.full((num_blocks + 1, size), num_cells + 1, np.int32)
    cells_of[block_of_cell, offset] = np.arange(num_cells)
    cells_of[num_blocks, 0] = num_cells  # the sink
    block_of = np.concatenate([block_of_cell, [num_blocks, num_blocks + 1]]).astype(np.int32)
    offset_of = np.zeros(num_cells + 2, np.int32)
    valid = cells_of <= num_cells
    offset_of[cells_of[valid]] = np.nonzero(valid)[1]
    host = (block_of, cells_of, offset_of)
    for a in host:
        a.flags.writeable = False
    return host + tuple(jnp.asarray(a) for a in host)


def default_block(clusters: GridClusters) -> tuple:
    """Block shape = the median extent of the reachable sets per dimension (a block then holds
    about one reachable set), at least 2 cells."""
    lengths = clusters.boxes.length
    n = lengths.shape[-1]
    counts = np.array(_extent_counts(lengths, EXTENT_BINS))  # extents from EXTENT_BINS - 1 on in one bin
    counts[:, 0] = 0  # boxes empty in some dimension (counted there in every dimension)
    if not counts.any():
        return (2,) * n
    middle = counts.sum(axis=1, keepdims=True) // 2  # the upper middle order statistic's index
    if np.any(np.cumsum(counts, axis=1)[:, -2] <= middle[:, 0]):  # a middle extent is in the last bin
        bins = 1 << (int(_longest_extent(lengths)) + 1).bit_length()
        counts = np.array(_extent_counts(lengths, bins))
        counts[:, 0] = 0
    return tuple(int(max(2, round(_median_count(c)))) for c in counts)


# Extents counted one by one when the block shape is chosen (longer ones share the last bin and
# are counted again only where a median falls among them).
EXTENT_BINS = 64


@jax.jit
def _longest_extent(lengths):
    return jnp.max(lengths, initial=0)


@functools.partial(jax.jit, static_argnums=1)
def _extent_counts(lengths, bins: int):
    """``(n, bins)`` per dimension how many boxes of ``lengths (..., n)`` have each extent (at
    least ``bins - 1`` in the last bin), the boxes empty in any dimension counted as extent 0 (in
    one pass: numpy's mask and bincounts took 0.7 s of the 3-D unicycle's 2I-MDP build, 14M
    boxes)."""
    lengths = lengths.reshape(-1, lengths.shape[-1])
    empty = jnp.any(lengths <= 0, axis=1)
    return jnp.stack([jnp.bincount(jnp.where(empty, 0, jnp.minimum(lengths[:, d], bins - 1)), length=bins)
                      for d in range(lengths.shape[1])])


def _median_count(counts) -> float:
    """``np.median`` of the integers that ``counts`` counts (``counts[v]`` copies of ``v``): the
    mean of the two middle order statistics, found in the cumulative counts (``np.median`` of the
    3-D unicycle's 8M boxes, a partition per column, took 0.5 s of the 2I-MDP build)."""
    cumulative = np.cumsum(counts)
    total = int(cumulative[-1])
    low, high = (int(np.searchsorted(cumulative, k, side="right")) for k in ((total - 1) // 2, total // 2))
    return (low + high) / 2


@pytree_dataclass
class TwoLayerIMDP(AbstractionMixin):
    """Attributes (T = blocks a row meets, S = cells per block, B = number of blocks; the fine
    entries in ``C`` chunks of ``W`` slots, row ``r`` owning ``ceil(entries_r / W)`` consecutive
    ones, as in ``imdp_compact``):
        blocks: ``(R, A, T)`` int16/int32 coarse blocks met, in increasing order (sink block
            ``B``), padded with ``B + 1``.
        block_lower, block_upper: ``(R, A, T)`` coarse bounds L_B, U_B.
        chunk_slot: ``(C, A, W)`` int16/int32 slots ``t S + i`` (cell ``i`` of block slot ``t``)
            of the listed fine successors (those a bounded reachable set meets), padded with ``T S``.
        chunk_upper: ``(C, A, W)`` their upper bounds (``upper_rest`` included; a ``coded.Coded``
            array where that is smaller); every other cell of a met block has ``[0, upper_rest]``.
        chunk_row: ``(C,)`` int32 the row of each chunk, nondecreasing.
        lower_slot, lower_value: ``(R, A, L)`` the positive fine lower bounds (slots as
            ``chunk_slot``, padding ``T S``).
        cells_of: ``(B + 1, S)`` int32 cells of every block, padded with ``N + 1``.
        upper_rest: P_W(remainder): upper bound of every state and every block.
        rows, labels: as in every abstraction.
        list_rows: rows that own chunks (``R`` until sharding pads the row arrays).
        block_rows, block_chunks, strategy_blocks: the inner problem a block of rows at a time
            (every action; one action per row), as ``CompactIMDP``'s (``imdp_compact.inner_blocks``).
        block_pairs: the most (row, action, met block) pairs any such block of rows has (every
            action; one action per row, whatever the action): the capacities are laid out for
            that many pairs instead of ``T`` per list (``imdp_compact.most_per_block``); 0: ``T``
            per list.

    ``lower``, ``upper`` ``(R, A, T, S)`` are the dense fine bounds (built on access).
    """

    blocks: jax.Array
    block_lower: jax.Array
    block_upper: jax.Array
    chunk_slot: jax.Array
    chunk_upper: jax.Array
    chunk_row: jax.Array
    lower_slot: jax.Array
    lower_value: jax.Array
    cells_of: jax.Array
    upper_rest: jax.Array
    rows: jax.Array
    labels: jax.Array
    block_shape: tuple = static_field(default=())
    list_rows: int = static_field(default=0)
    block_rows: int = static_field(default=0)
    block_chunks: int = static_field(default=0)
    strategy_blocks: tuple = static_field(default=(0, 0))
    block_pairs: tuple = static_field(default=(0, 0))
    kind: str = static_field(default="2imdp")

    @classmethod
    def from_clusters(cls, grid, clusters: GridClusters, block=None, *, chunk: int | None = None) -> "TwoLayerIMDP":
        """Lemma 1 on both layers from the clusters' index boxes; ``block``: cells per block and
        dimension (default ``default_block``), ``chunk``: slots per chunk of the fine entries
        (default ``imdp_compact.chunk_width`` of their counts)."""
        block = default_block(clusters) if block is None else tuple(np.broadcast_to(np.asarray(block), (grid.n,)))
        _, cells_of, _, block_of, cells_of_device, offset_of = _grid_layout(grid, block)
        num_blocks = cells_of.shape[0] - 1
        blocks, block_lower, block_upper = region_bounds(grid.cells, grid.periodic, clusters.boxes, clusters.prob,
                                                         block=block, noise_shape=clusters.noise_shape)
        rest = jnp.asarray(clusters.prob_rest)
        blocks, block_upper, met_per_list = _coarse_layer(blocks, block_upper, rest, num_blocks,
                                                          index_dtype(num_blocks + 2))
        met_per_list = np.asarray(met_per_list)  # (R, A), the sink block B included
        met_count = max(1, int(met_per_list.max(initial=1)))
        if met_count < blocks.shape[-1]:
            blocks, block_lower, block_upper = (x[..., :met_count] for x in (blocks, block_lower, block_upper))
        succ, lower, upper, (widths, num_lower) = region_bounds(grid.cells, grid.periodic, clusters.boxes,
                                                                clusters.prob, noise_shape=clusters.noise_shape,
                                                                counts=True)
        sentinel = grid.num_states  # N + 1 (N cells and the sink)
        size = cells_of.shape[1]
        slot = _fine_slots(succ, blocks, block_of, offset_of, size)
        widths, num_lower = np.maximum(np.asarray(widths), 1), int(num_lower)
        c_slot, c_upper, chunk_row, l_slot, l_value = chunk_lists(slot, lower, upper, succ, sentinel, widths, chunk,
                                                                  num_lower, met_count * size, upper_add=rest,
                                                                  id_dtype=index_dtype(met_count * size + 1))
        blocking = _blocking(chunk_row, met_per_list, met_count * size, c_slot.shape[0] * c_slot.shape[2], BLOCK_SLOTS)
        return cls(blocks=blocks, block_lower=block_lower, block_upper=block_upper,
                   chunk_slot=c_slot, chunk_upper=encode(c_upper), chunk_row=jnp.asarray(chunk_row), lower_slot=l_slot,
                   lower_value=l_value,
                   cells_of=cells_of_device, upper_rest=rest, rows=jnp.asarray(clusters.rows, jnp.int32),
                   labels=jnp.asarray(grid.state_labels), block_shape=tuple(int(b) for b in block),
                   list_rows=int(widths.size), **blocking)

    def with_block_budget(self, budget: int) -> "TwoLayerIMDP":
        """The same abstraction, its rows solved in blocks of about ``budget`` slots on the CPU (0:
        all rows at once); the default is ``BLOCK_SLOTS``. The same values."""
        rows = self.list_rows or self.num_rows
        met_per_list = np.asarray(self.blocks[:rows] < self.cells_of.shape[0]).sum(-1)
        return dataclasses.replace(self, **_blocking(np.asarray(self.chunk_row), met_per_list,
                                                     self.num_block_slots * self.cells_of.shape[1],
                                                     self.num_chunks * self.chunk, budget))

    @property
    def num_actions(self) -> int:
        return int(self.blocks.shape[1])

    @property
    def num_block_slots(self) -> int:
        """``T``: block slots per list."""
        return int(self.blocks.shape[2])

    @property
    def chunk(self) -> int:
        """``W``: fine entries per chunk."""
        return int(self.chunk_slot.shape[2])

    @property
    def num_chunks(self) -> int:
        return int(self.chunk_slot.shape[0])

    @property
    def summands_per_backup(self) -> float:
        t, s = self.num_block_slots, self.cells_of.shape[1]
        return float(3 * t * s + self.cells_of.shape[0] * float(self.upper_rest))

    def restrict(self, actions) -> "TwoLayerIMDP":
        """The single-action 2I-MDP of a stationary strategy ``actions: (R,)``."""
        by_row, by_chunk = actions[:, None, None], actions[self.chunk_row][:, None, None]
        pick = lambda a, act: jnp.take_along_axis(a, act, axis=1)
        return dataclasses.replace(self, blocks=pick(self.blocks, by_row), block_lower=pick(self.block_lower, by_row),
                                   block_upper=pick(self.block_upper, by_row),
                                   chunk_slot=pick(self.chunk_slot, by_chunk),
                                   chunk_upper=map_entries(self.chunk_upper, lambda a: pick(a, by_chunk)),
                                   lower_slot=pick(self.lower_slot, by_row), lower_value=pick(self.lower_value, by_row),
                                   block_rows=self.strategy_blocks[0], block_chunks=self.strategy_blocks[1],
                                   block_pairs=(self.block_pairs[1],) * 2)

    def q_values(self, v, adversary: str = "min", actions=None):
        minimize = check_adversary(adversary)
        w = v if minimize else -v
        rows = self.list_rows or self.num_rows
        by_row = (self.blocks, self.block_lower, self.block_upper, self.lower_slot, self.lower_value)
        by_chunk = (self.chunk_slot, self.chunk_upper)
        row_blocks, num_pairs = (self.block_rows, self.block_chunks), self.block_pairs[0]
        if actions is not None:
            row_blocks, num_pairs = self.strategy_blocks, self.block_pairs[1]
            pick = lambda a, act: jnp.take_along_axis(a, act[:, None, None], axis=1)[:, 0]
            by_row = tuple(pick(a, actions) for a in by_row)
            by_chunk = tuple(map_entries(a, lambda x: pick(x, actions[self.chunk_row])) for a in by_chunk)
        lists = rows * (self.num_actions if actions is None else 1)
        ranking = block_ranking(w, self.cells_of, wants_count_table(self.num_states, self.cells_of.shape[0],
                                                                    lists * self.num_block_slots))

        def solve(row_arrays, chunk_arrays, chunk_row):
            blocks, block_lower, block_upper, lower_slot, lower_value = row_arrays
            return _sparse_two_layer_min(w, ranking, blocks, block_lower, block_upper, *chunk_arrays, chunk_row,
                                         lower_slot, lower_value, self.cells_of, self.upper_rest, num_pairs)

        padding = self.num_block_slots * self.cells_of.shape[1]  # T S: no fine entry
        value = in_row_blocks(solve, tuple(a[:rows] for a in by_row), by_chunk, (padding, 0.0), self.chunk_row,
                              row_blocks)
        if self.num_rows > rows:  # rows padded by sharding repeat the last row
            value = value[jnp.minimum(jnp.arange(self.num_rows), rows - 1)]
        return value if minimize else -value

    def _dense_fine(self, lower: bool):
        """``(R, A, T, S)`` dense fine bounds (``upper_rest`` on every cell of a met block for the
        upper ones)."""
        size = self.cells_of.shape[1]
        rows = self.list_rows or self.num_rows
        blocks = self.blocks[:rows].astype(jnp.int32)
        cells = self.cells_of.at[blocks].get(mode="fill", fill_value=self.num_states)  # (R, A, T, S)
        if lower:
            return _scatter_slots(jnp.zeros(cells.shape), self.lower_slot[:rows], self.lower_value[:rows])
        dense = jnp.where(cells < self.num_states, self.upper_rest, 0.0)
        return _scatter_slots(dense, self.chunk_slot, decoded(self.chunk_upper), lead_rows=self.chunk_row)

    @property
    def lower(self):
        return self._dense_fine(True)

    @property
    def upper(self):
        return self._dense_fine(False)

    def __repr__(self):
        r, a = self.num_rows, self.num_actions
        return (f"TwoLayerIMDP(|S|={self.num_states}, rows={r}, |A|={a}, block={'x'.join(map(str, self.block_shape))}"
                f" ({self.cells_of.shape[0] - 1} blocks + sink), max blocks met={self.num_block_slots}, fine entries="
                f"{self.num_chunks}x{self.chunk} slots, memory={self.nbytes / 1e6:.2f} MB)")


def _blocking(chunk_row, met_per_list, capacities: int, entries: int, budget: int) -> dict:
    """``block_rows``, ``block_chunks``, ``strategy_blocks`` (``imdp_compact.block_fields``) and
    ``block_pairs`` of rows ``met_per_list (R, A)`` (met blocks per list); a row and action costs
    its ``capacities`` (T S, laid out in every backup) and its share of the ``entries`` (C W)."""
    rows = met_per_list.shape[0]
    blocking = block_fields(chunk_row, rows, met_per_list.shape[1], capacities + entries / rows, budget)
    blocking["block_pairs"] = (most_per_block(met_per_list.sum(1), blocking["block_rows"]),
                               most_per_block(met_per_list.max(1), blocking["strategy_blocks"][0]))
    return blocking


@functools.partial(jax.jit, static_argnums=(3, 4))
def _coarse_layer(blocks, block_upper, rest, num_blocks: int, dtype):
    """The coarse lists as stored: ``(blocks as dtype, block_upper with the remainder's
    ``rest`` on every met block, blocks met per list (R, A))``."""
    met = blocks <= num_blocks
    return blocks.astype(dtype), jnp.where(met, block_upper + rest, 0.0), jnp.sum(met, axis=-1)


@functools.partial(jax.jit, static_argnums=4)
def _fine_slots(succ, blocks, block_of, offset_of, size: int):
    """``(R, A, K)`` slot ``t S + i`` of each listed successor: ``t`` its block's slot in the row's
    sorted ``blocks``, ``i`` its cell's slot in the block; padding ``>= T S``."""
    sentinel = block_of.shape[0] - 1
    succ = succ.astype(jnp.int32)
    succ_block = block_of[jnp.minimum(succ, sentinel)]
    # unrolled binary search: 1.07 -> 0.63 s on the 3-D unicycle's 22 410 x 10 lists of 212 slots
    t = jax.vmap(lambda b, q: jnp.searchsorted(b, q, method="scan_unrolled"))(
        blocks.reshape(-1, blocks.shape[-1]), succ_block.reshape(-1, succ.shape[-1])).reshape(succ.shape)
    t_count = blocks.shape[-1]
    return jnp.where(succ < sentinel, t * size + offset_of[jnp.minimum(succ, sentinel)], t_count * size)


def _lead(shape, rows=None):
    """Index arrays of the leading axes of entries ``(..., K)``, shaped to broadcast against the
    last axis; with ``rows (C,)``, the first axis indexes through it (chunks -> their rows)."""
    lead = list(jnp.indices(shape[:-1], sparse=True))
    if rows is not None:
        lead[0] = rows.reshape(lead[0].shape)
    return tuple(i[..., None] for i in lead)


def _scatter_slots(dense, slot, value, lead_rows=None):
    """``dense (R, ..., T, S)`` with ``value (..., K)`` set at flat slots ``slot`` (out of range:
    dropped); ``lead_rows (C,)``: the entries are chunks, ``slot``'s first axis maps to these rows."""
    shape = dense.shape
    flat = dense.reshape(shape[:-2] + (-1,))
    idx = _lead(slot.shape, lead_rows) + (slot.astype(jnp.int32),)
    return flat.at[idx].set(value, mode="drop").reshape(shape)


# Largest count table ``(N + 1) x (B + 2)`` (entries) ``block_ranking`` builds; beyond it, or
# where the bisection reads it fewer than ``COUNT_TABLE_READS`` times per entry, the inner problem
# counts a block's cells ranked below k by a binary search in the block's ranks. (The 3-D unicycle
# 2I-MDP, 1 502 blocks, table built in 32 ms: with every action one backup 3.5 -> 1.9 s with the
# table, with one action per row (0.32 reads per entry) 0.35 -> 0.20 s; the 4-D temperature, 257
# blocks: 1.76 -> 1.06 s. When the table took 0.25 s to build, the single-action backup lost.)
COUNT_TABLE_MAX = 1 << 26
COUNT_TABLE_READS = 0.125


def wants_count_table(n_states: int, num_blocks: int, block_slots: int) -> bool:
    """Whether a backup over ``block_slots`` (list, block slot) pairs builds the count table
    (``num_blocks`` = B + 1 with the sink block)."""
    entries = (n_states + 1) * (num_blocks + 1)
    return entries <= COUNT_TABLE_MAX and block_slots * int(n_states).bit_length() >= COUNT_TABLE_READS * entries


def block_ranking(w, cells_of, count_table: bool = False):
    """What every list's inner problem shares, from one sort of ``w`` per backup: ``(rank,
    w_sorted, within, sorted_rank, sorted_w, inverse, blocks_below, prefix_below,
    padded_cells, cell_count)``, every block's cells in increasing rank (padding last; one extra
    all-padding block), where each cell slot lands in that order (``inverse``), per ``k`` in
    ``0..N+1`` the blocks with a cell ranked below ``k`` and the sum of those blocks' lowest
    values, and each block's number of cells ``(B + 2,)``; with ``count_table``, ``count (N + 1,
    B + 2)``: the cells of each block ranked below each ``k``."""
    n_states = w.shape[0]
    rank, w_sorted, _ = value_ranking(w)
    num_blocks, size = cells_of.shape
    padded_cells = jnp.concatenate([cells_of, jnp.full((1, size), n_states, cells_of.dtype)])
    cell_rank = rank.at[padded_cells].get(mode="fill", fill_value=n_states)  # (B+2, S)
    within = jnp.argsort(cell_rank, axis=-1)
    sorted_rank = jnp.take_along_axis(cell_rank, within, -1)
    sorted_w = w.at[jnp.take_along_axis(padded_cells, within, -1)].get(mode="fill", fill_value=0.0)
    inverse = jnp.zeros_like(within).at[jnp.arange(within.shape[0])[:, None], within].set(
        jnp.broadcast_to(jnp.arange(size, dtype=within.dtype), within.shape))
    sorted_min_rank = jnp.sort(sorted_rank[:num_blocks, 0])
    block_prefix = jnp.concatenate([jnp.zeros(1), jnp.cumsum(w_sorted[jnp.minimum(sorted_min_rank, n_states - 1)])])
    # per k in 0..N+1: the blocks whose lowest rank is below k, and their lowest values' sum (a
    # read each in every bisection step; a binary search per step made the 3-D unicycle's greedy
    # backup ~2% slower)
    blocks_below = jnp.cumsum(jnp.zeros(n_states + 1, jnp.int32).at[sorted_min_rank + 1].add(1, mode="drop"))
    ranking = dict(rank=rank, w_sorted=w_sorted, within=within, sorted_rank=sorted_rank, sorted_w=sorted_w,
                   inverse=inverse, blocks_below=blocks_below, prefix_below=block_prefix[blocks_below],
                   padded_cells=padded_cells, cell_count=jnp.sum(padded_cells < n_states, -1))
    if count_table:
        ranking["count"] = _count_table(rank, padded_cells)
    return ranking


def _on_cpu() -> bool:
    return jax.default_backend() == "cpu"


def _count_table(rank, padded_cells):
    """``(N + 1, B + 2)``: entry ``[k, b]`` the cells of block ``b`` ranked below ``k`` (a row per
    ``k``, so the blocks of one list read one row)."""
    n_states = rank.shape[0]
    num_blocks, size = padded_cells.shape
    dtype = jnp.uint8 if size < 256 else jnp.int32
    block_of_rank = jnp.full(n_states, num_blocks, jnp.int32).at[
        rank.at[padded_cells].get(mode="fill", fill_value=n_states)].set(
        jnp.broadcast_to(jnp.arange(num_blocks, dtype=jnp.int32)[:, None], padded_cells.shape), mode="drop")
    if _on_cpu():
        # one pass down the ranks, each row the last plus one: the table written once (XLA's
        # cumulative sum over the leading axis, a log-depth scan, took 7x longer on the 3-D unicycle)
        def next_row(row, block):
            row = row.at[block].add(jnp.ones((), dtype), mode="drop")
            return row, row

        counts = jax.lax.scan(next_row, jnp.zeros(num_blocks, dtype), block_of_rank)[1]
    else:  # 27 000 sequential steps would not pay on an accelerator (not measured there)
        one_hot = (block_of_rank[:, None] == jnp.arange(num_blocks, dtype=jnp.int32)).astype(dtype)
        counts = jnp.cumsum(one_hot, 0, dtype=dtype)
    return jnp.concatenate([jnp.zeros((1, num_blocks), dtype), counts])


def _pairs(met, num_pairs: int):
    """``(pair (..., T), count P)``: the row of every (list, block slot) in a ``(P, S)`` layout of
    the met blocks. ``num_pairs`` > 0: the met slots in order, every other slot on row
    ``num_pairs`` (all zero capacity), ``P = num_pairs + 1``; 0: a row per slot."""
    if num_pairs == 0:
        return jnp.arange(met.size, dtype=jnp.int32).reshape(met.shape), met.size
    flat = met.reshape(-1)
    pair = jnp.where(flat, jnp.cumsum(flat, dtype=jnp.int32) - 1, num_pairs)
    return pair.reshape(met.shape), num_pairs + 1


def _sparse_two_layer_min(w, ranking, blocks, block_lower, block_upper, fine_slot, fine_upper, chunk_row,
                          lower_slot, lower_value, cells_of, upper_rest, num_pairs=0):
    """``two_layer_min`` on the sparse, chunked fine layer: the capacities ``upper - lower`` of
    the met blocks' cells are laid out in each block's rank order (``upper_rest`` on every cell,
    the listed successors' bounds scattered over it), one row per met (list, block) pair when
    ``num_pairs`` (at least the met pairs of these rows) is given, the lower bounds' sums taken
    from their pairs; then the block greedy of ``_two_layer_sorted``.

    Shapes: ``blocks, block_lower, block_upper (R, ..., T)``, ``fine_slot, fine_upper (C, ...,
    W)`` chunks of the rows ``chunk_row (C,)``, ``lower_slot, lower_value (R, ..., L)`` (slots
    ``t S + i``, padding ``>= T S``). Returns ``(R, ...)``.
    """
    n_states = w.shape[0]
    num_blocks, size = cells_of.shape
    t_count = blocks.shape[-1]
    block_row = jnp.minimum(blocks.astype(jnp.int32), num_blocks)  # padding -> the all-padding block
    pair, count = _pairs(blocks < num_blocks, num_pairs)
    pair_block = jnp.full(count, num_blocks, jnp.int32).at[
        jnp.where(blocks < num_blocks, pair, count)].set(block_row, mode="drop")

    def sorted_slot(slot, rows=None):  # flat slot t S + i -> (pair of t) S + (i's place in its rank order)
        slot = slot.astype(jnp.int32)
        t = jnp.minimum(slot // size, t_count - 1)
        at = _lead(slot.shape, rows) + (t,)
        place = ranking["inverse"][block_row[at], slot % size]
        return jnp.where(slot < t_count * size, pair[at] * size + place, count * size)

    has_lower = lower_slot < t_count * size
    lo = jnp.where(has_lower, lower_value, 0.0)
    # capacities in rank order: upper_rest on every cell, the listed upper bounds, minus lower bounds
    # a block's cells come first in its rank order, its padding last
    cells = ranking["cell_count"][pair_block][:, None]
    cap = jnp.where(jnp.arange(size, dtype=cells.dtype) < cells, upper_rest, 0.0).reshape(-1)
    cap = cap.at[sorted_slot(fine_slot, chunk_row)].set(fine_upper, mode="drop")
    cap = cap.at[sorted_slot(lower_slot)].add(-lo, mode="drop").reshape(count, size)
    # per block met: sum of lower bounds and their cost
    lead = _lead(lower_slot.shape)
    t_of = jnp.minimum(lower_slot.astype(jnp.int32) // size, t_count - 1)
    lo_cell = ranking["padded_cells"][jnp.take_along_axis(block_row, t_of, axis=-1),
                                      lower_slot.astype(jnp.int32) % size]
    lo_w = w.at[lo_cell].get(mode="fill", fill_value=0.0)
    zeros = jnp.zeros(blocks.shape)
    sum_l = zeros.at[lead + (t_of,)].add(lo)
    base = zeros.at[lead + (t_of,)].add(lo * lo_w)
    return _two_layer_sorted(w, ranking, blocks, block_lower, block_upper, cap, pair, pair_block, sum_l, base,
                             num_blocks, upper_rest)


def two_layer_min(w, blocks, block_lower, block_upper, lower, upper, cells_of, upper_rest):
    """``min sum gamma w`` over the two-layer polytope for every row (see the module docstring),
    from dense fine bounds.

    Args:
        w: ``(N+1,)`` values.
        blocks, block_lower, block_upper: ``(..., T)``; lower, upper: ``(..., T, S)``.
        cells_of: ``(B+1, S)``; upper_rest: scalar.
    Returns ``(...)``.
    """
    num_blocks, size = cells_of.shape
    ranking = block_ranking(w, cells_of, wants_count_table(w.shape[0], num_blocks, blocks.size))
    block_row = jnp.minimum(blocks, num_blocks)  # padding -> the all-padding block
    # Sums over a block do not depend on the order (and padding cells have zero bounds and
    # value); only the capacities are put in rank order, for their prefix sums.
    sum_l = lower.sum(-1)
    base = (lower * w.at[ranking["padded_cells"]].get(mode="fill", fill_value=0.0)[block_row]).sum(-1)
    cap = jnp.take_along_axis(upper - lower, ranking["within"][block_row], -1)  # (..., T, S) in rank order
    pair, _ = _pairs(blocks < num_blocks, 0)
    return _two_layer_sorted(w, ranking, blocks, block_lower, block_upper, cap.reshape(-1, size), pair,
                             block_row.reshape(-1), sum_l, base, num_blocks, upper_rest)


def _two_layer_sorted(w, ranking, blocks, block_lower, block_upper, cap, pair, pair_block, sum_l, base, num_blocks,
                      upper_rest):
    """The block greedy, from the capacities ``cap (P, S)`` of the met blocks' cells in each
    block's rank order (row ``pair (..., T)`` for each list's block slot, of block ``pair_block
    (P,)``; unmet slots on all-zero rows) and each met block's lower bounds' sum and cost ``sum_l,
    base (..., T)``."""
    n_states = w.shape[0]
    size = cap.shape[-1]
    count = cap.shape[0]
    w_sorted, sorted_rank, sorted_w = ranking["w_sorted"], ranking["sorted_rank"], ranking["sorted_w"]
    blocks = blocks.astype(jnp.int32)
    met = blocks < num_blocks
    block_row = jnp.minimum(blocks, num_blocks)  # padding -> the all-padding block
    cum_cap = _prefix_sums(cap)
    flat_cap = cum_cap.reshape(-1)
    floor = jnp.where(met, jnp.maximum(block_lower, sum_l), 0.0)
    ceil = jnp.where(met, jnp.minimum(block_upper, sum_l + cum_cap[pair, -1]), 0.0)

    if "count" in ranking:  # one read of the count table per block slot
        table = ranking["count"]
        flat_table, table_width = table.reshape(-1), table.shape[1]

        def count_below(k):  # per block met: its cells ranked below k
            return flat_table[k[..., None] * table_width + block_row].astype(jnp.int32)
    else:
        search_steps = int(size).bit_length()
        flat_rank = sorted_rank.reshape(-1)
        row_start = block_row * size

        def count_below(k):  # a binary search in the block's sorted ranks
            k = k[..., None]

            def step(_, bounds):
                lo_i, hi_i = bounds
                mid = (lo_i + hi_i) // 2
                below = (lo_i < hi_i) & (flat_rank[row_start + jnp.minimum(mid, size - 1)] < k)
                return jnp.where(below, mid + 1, lo_i), jnp.where(below | (lo_i >= hi_i), hi_i, mid)

            zeros = jnp.zeros(blocks.shape, jnp.int32)
            return jax.lax.fori_loop(0, search_steps, step, (zeros, zeros + size))[0]

    met_min_rank = jnp.where(met, sorted_rank[block_row, 0], n_states)

    def masses(k):
        """Per list: the met blocks' masses ``(..., T)`` once every state of rank < k is offered
        (each block's lower bounds plus its cells ranked below k filled up, clipped to the block's
        range), the total mass with the blocks no bounded reachable set meets (capacity
        ``upper_rest`` each), and which met blocks have a cell ranked below k."""
        count_of = count_below(k)
        at = flat_cap[pair * size + jnp.maximum(count_of - 1, 0)]
        m = jnp.clip(sum_l + jnp.where(count_of > 0, at, 0.0), floor, ceil)
        met_offered = met_min_rank < k[..., None]
        unmet = ranking["blocks_below"][k] - jnp.sum(met_offered, -1)
        return m, m.sum(-1) + upper_rest * unmet, met_offered

    def bisect(_, bounds):
        lo_k, hi_k = bounds
        mid = (lo_k + hi_k) // 2
        enough = masses(mid)[1] >= 1.0
        return jnp.where(enough, lo_k, mid + 1), jnp.where(enough, mid, hi_k)

    steps = int(n_states).bit_length()  # each step at least halves hi - lo (n_states at first)
    zeros = jnp.zeros(blocks.shape[:-1], jnp.int32)
    _, k_star = jax.lax.fori_loop(0, steps, bisect, (zeros, zeros + n_states))
    # The greedy's placement once the states of rank < j are offered (j = k* - 1; k* = 0: the
    # blocks' floors alone hold all the mass), then the state of rank j takes the rest. Its cost
    # is computed once, here, by pouring each block's mass beyond its lower bounds into its cells
    # in rank order (a block's mass is its floor, its ceiling, or its cells ranked below j filled
    # up, and pouring gives each its cost): one pass over the capacities, where prefix sums of
    # their costs, read in every bisection step, took a third of the 4-room model's backup.
    j = jnp.maximum(k_star - 1, 0)
    m, mass_j, met_offered = masses(j)
    amount = jnp.zeros(count).at[jnp.where(met, pair, count)].set(m - sum_l, mode="drop")
    poured = jnp.clip(amount[:, None] - (cum_cap - cap), 0.0, cap)  # (P, S): capacity before each cell
    fill = jnp.sum(poured * sorted_w[pair_block], -1)
    cost = jnp.sum(jnp.where(met, base + fill[pair], 0.0), -1)
    w_met = jnp.sum(jnp.where(met_offered, w_sorted[jnp.minimum(met_min_rank, n_states - 1)], 0.0), -1)
    cost = cost + upper_rest * (ranking["prefix_below"][j] - w_met)
    return jnp.where(k_star > 0, cost + (1.0 - mass_j) * w_sorted[j], cost)


_MATMUL_PREFIX_MAX = 128
# Up to this many entries, one product with a triangular matrix; longer (up to
# ``_MATMUL_PREFIX_MAX``), two levels of them: blocks of ``q ~ sqrt(S)`` entries, then the
# blocks' totals (about ``2 sqrt(S)`` instead of ``S`` multiply-adds per entry).
_ONE_LEVEL_MAX = 16


def _triangle(size, dtype, strict=False):
    return jnp.triu(jnp.ones((size, size), dtype), 1 if strict else 0)


def _prefix_sums(x):
    """Inclusive prefix sums over the last axis. Short axes as products with triangular
    matrices of ones: on the CPU, ``cumsum`` over the capacities of the 2I-MDP rows of Table 1
    (9-81 cells per block) took 1.0-1.9x as long (docs/performance.md), and 3-6x on random
    (R, T, S) arrays with S = 18 and 81; over 256 entries the two cost the same. Every prefix is
    still a sum of the same terms (in another order), so the rounding bound is unchanged."""
    size = x.shape[-1]
    if size > _MATMUL_PREFIX_MAX:
        return jnp.cumsum(x, -1)
    dot = functools.partial(jnp.matmul, precision=jax.lax.Precision.HIGHEST)
    if size <= _ONE_LEVEL_MAX:
        return dot(x, _triangle(size, x.dtype))
    q = math.isqrt(size - 1) + 1
    m = -(-size // q)
    y = jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, m * q - size)]).reshape(x.shape[:-1] + (m, q))
    inner = dot(y, _triangle(q, x.dtype))  # prefix sums inside each group of q
    before = dot(inner[..., -1], _triangle(m, x.dtype, strict=True))  # totals of the groups before
    return (inner + before[..., None]).reshape(x.shape[:-1] + (m * q,))[..., :size]
