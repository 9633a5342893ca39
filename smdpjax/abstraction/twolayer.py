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
The order of the cells inside a block is the block's own (it does not depend on the row): each
call sorts the B blocks' cells, puts every row's capacities in that order and takes their prefix
sums once, so that a bisection step only reads, per block met, the prefix sums at the number of
the block's cells ranked below k (a binary search in the block's sorted ranks).
Blocks that no bounded reachable set meets (only the remainder can put mass there) are handled
in aggregate through a sorted list of the blocks' lowest ranks. Per iteration:
O(N log N + B S log S + R A T S) once, then O(R A T log S) per bisection step (log N steps),
T the blocks a row meets, S the cells per block.

Storage: the fine layer is kept sparse (per row and action the listed successors' slots
``t S + i`` and upper bounds, the positive lower bounds as pairs), rows bucketed by width as in
``imdp_compact``; every backup lays the met blocks' capacities out in rank order (``upper_rest``
on every cell, the listed bounds scattered over it) before the greedy, so only that transient,
not the stored abstraction, has the ``(R, A, T, S)`` shape (row 38: 174 MB stored instead of
2211 MB).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass, static_field
from .base import AbstractionMixin, check_adversary
from .box_bounds import region_bounds
from .clusters import index_dtype
from .grid_clusters import GridClusters
from .imdp_compact import MAX_BUCKETS, _bucket, bucket_edges


def block_layout(grid, block) -> tuple[np.ndarray, np.ndarray]:
    """``(block_of (N+2,), cells_of (B+1, S))``: the block of every state (sentinel -> B+1) and the
    cells of every block (the sink block B holds the sink), padded with ``N + 1``."""
    block = np.broadcast_to(np.asarray(block, np.int64), (grid.n,))
    if np.any(block <= 0):
        raise ValueError(f"block shape must be positive, got {block.tolist()}")
    shape = -(-grid.cells // block)  # blocks per dimension
    multi = np.stack(np.unravel_index(np.arange(grid.num_cells), tuple(grid.cells)), axis=-1)
    block_multi = multi // block
    block_of_cell = np.ravel_multi_index(tuple(block_multi.T), tuple(shape))
    num_blocks = int(np.prod(shape))
    size = int(np.prod(block))
    offset = np.ravel_multi_index(tuple((multi % block).T), tuple(block))
    cells_of = np.full((num_blocks + 1, size), grid.num_cells + 1, np.int32)
    cells_of[block_of_cell, offset] = np.arange(grid.num_cells)
    cells_of[num_blocks, 0] = grid.sink
    block_of = np.concatenate([block_of_cell, [num_blocks, num_blocks + 1]]).astype(np.int32)
    return block_of, cells_of


def default_block(clusters: GridClusters) -> tuple:
    """Block shape = the median extent of the reachable sets per dimension (a block then holds
    about one reachable set), at least 2 cells."""
    lengths = np.asarray(clusters.boxes.length).reshape(-1, clusters.boxes.length.shape[-1])
    lengths = lengths[np.all(lengths > 0, axis=1)]
    if lengths.size == 0:
        return (2,) * clusters.boxes.length.shape[-1]
    return tuple(int(max(2, round(v))) for v in np.median(lengths, axis=0))


@pytree_dataclass
class TwoLayerIMDP(AbstractionMixin):
    """Attributes (T = blocks a row meets, S = cells per block, B = number of blocks; rows in
    bucket order, bucket b holds ``R_b`` rows, ``T_b`` block slots and ``K_b`` fine entries):
        bucket_blocks: tuple of ``(R_b, A, T_b)`` int16/int32 coarse blocks met, in increasing
            order (sink block ``B``), padded with ``B + 1``.
        bucket_block_lower, bucket_block_upper: tuple of ``(R_b, A, T_b)`` coarse bounds L_B, U_B.
        bucket_fine_slot: tuple of ``(R_b, A, K_b)`` int16/int32 slots ``t S + i`` (cell ``i`` of
            block slot ``t``) of the listed fine successors (those a bounded reachable set meets),
            padded with ``T_b S``.
        bucket_fine_upper: tuple of ``(R_b, A, K_b)`` their upper bounds (``upper_rest`` included);
            every other cell of a met block has ``[0, upper_rest]``.
        bucket_lower_slot, bucket_lower_value: tuple of ``(R_b, A, L)`` the positive fine lower
            bounds (slots as ``bucket_fine_slot``, padding ``T_b S``).
        order, position: ``(R,)`` int32 bucket order of the rows and its inverse (as ``CompactIMDP``).
        cells_of: ``(B + 1, S)`` int32 cells of every block, padded with ``N + 1``.
        upper_rest: P_W(remainder): upper bound of every state and every block.
        rows, labels: as in every abstraction.

    ``blocks``, ``block_lower``, ``block_upper`` ``(R, A, T)`` and ``lower``, ``upper``
    ``(R, A, T, S)`` are the padded views (built on access).
    """

    bucket_blocks: tuple
    bucket_block_lower: tuple
    bucket_block_upper: tuple
    bucket_fine_slot: tuple
    bucket_fine_upper: tuple
    bucket_lower_slot: tuple
    bucket_lower_value: tuple
    order: jax.Array
    position: jax.Array
    cells_of: jax.Array
    upper_rest: jax.Array
    rows: jax.Array
    labels: jax.Array
    block_shape: tuple = static_field(default=())
    num_block_slots: int = static_field(default=1)
    kind: str = static_field(default="2imdp")

    @classmethod
    def from_clusters(cls, grid, clusters: GridClusters, block=None, *,
                      max_buckets: int = MAX_BUCKETS) -> "TwoLayerIMDP":
        block = default_block(clusters) if block is None else tuple(np.broadcast_to(np.asarray(block), (grid.n,)))
        block_of, cells_of = block_layout(grid, block)
        num_blocks = cells_of.shape[0] - 1
        blocks, block_lower, block_upper = region_bounds(grid.cells, grid.periodic, clusters.boxes, clusters.prob,
                                                         block=block)
        rest = jnp.asarray(clusters.prob_rest)
        met = blocks <= num_blocks
        block_upper = jnp.where(met, block_upper + rest, 0.0)
        succ, lower, upper = region_bounds(grid.cells, grid.periodic, clusters.boxes, clusters.prob)
        sentinel = grid.num_states  # N + 1 (N cells and the sink)
        upper = jnp.where(succ < sentinel, upper + rest, 0.0)
        size = cells_of.shape[1]
        offset_of = np.zeros(sentinel + 1, np.int32)  # each state's cell slot in its block
        valid = cells_of <= grid.sink
        offset_of[cells_of[valid]] = np.nonzero(valid)[1]
        slot = _fine_slots(succ, blocks, jnp.asarray(block_of), jnp.asarray(offset_of), size)
        listed = succ < sentinel
        widths = np.asarray(jnp.sum(listed, axis=-1).max(axis=1))
        edges = bucket_edges(widths, int(succ.shape[1]), max_buckets)
        order = np.argsort(widths, kind="stable").astype(np.int32)
        position = np.empty_like(order)
        position[order] = np.arange(order.size, dtype=np.int32)
        num_lower = int(jnp.max(jnp.sum((lower > 0) & listed, axis=-1), initial=0))
        met_count = np.asarray(jnp.sum(met, axis=-1).max(axis=1))
        block_dtype = index_dtype(num_blocks + 2)
        pieces = []
        for start, stop in zip(edges[:-1], edges[1:]):
            take = jnp.asarray(order[start:stop])
            k_b = max(1, int(widths[order[stop - 1]]))
            t_b = max(1, int(met_count[order[start:stop]].max()))
            _, fine_upper, l_slot, l_value = _bucket(succ[take, :, :k_b], lower[take, :, :k_b], upper[take, :, :k_b],
                                                     num_lower, sentinel)
            fine_slot = slot[take, :, :k_b]
            # fine slots t S + i of this bucket's T_b block slots; padding (and lower pairs) -> T_b S
            fine_slot = jnp.where(fine_slot < t_b * size, fine_slot, t_b * size)
            l_fine = jnp.take_along_axis(fine_slot, jnp.minimum(l_slot.astype(jnp.int32), k_b - 1), axis=-1)
            l_fine = jnp.where(l_slot < k_b, l_fine, t_b * size)
            dtype = index_dtype(t_b * size + 1)
            pieces.append((blocks[take, :, :t_b].astype(block_dtype), block_lower[take, :, :t_b],
                           block_upper[take, :, :t_b], fine_slot.astype(dtype), fine_upper, l_fine.astype(dtype),
                           l_value))
        fields = [tuple(p[i] for p in pieces) for i in range(7)]
        return cls(*fields, order=jnp.asarray(order), position=jnp.asarray(position), cells_of=jnp.asarray(cells_of),
                   upper_rest=rest, rows=jnp.asarray(clusters.rows, jnp.int32),
                   labels=jnp.asarray(grid.state_labels), block_shape=tuple(int(b) for b in block),
                   num_block_slots=max(1, int(met_count.max(initial=1))))

    @property
    def num_actions(self) -> int:
        return int(self.bucket_blocks[0].shape[1])

    @property
    def buckets(self) -> tuple:
        """``((R_b, T_b, K_b), ...)`` rows, block slots and fine entries of each bucket."""
        return tuple((int(b.shape[0]), int(b.shape[2]), int(f.shape[2]))
                     for b, f in zip(self.bucket_blocks, self.bucket_fine_slot))

    @property
    def summands_per_backup(self) -> float:
        t, s = self.num_block_slots, self.cells_of.shape[1]
        return float(3 * t * s + self.cells_of.shape[0] * float(self.upper_rest))

    def _arrays(self):
        return list(zip(self.bucket_blocks, self.bucket_block_lower, self.bucket_block_upper, self.bucket_fine_slot,
                        self.bucket_fine_upper, self.bucket_lower_slot, self.bucket_lower_value))

    def _bucket_actions(self, actions):
        picks, start = [], 0
        for b in self.bucket_blocks:
            picks.append(actions[self.order[start:start + b.shape[0]]])
            start += b.shape[0]
        return picks

    def restrict(self, actions) -> "TwoLayerIMDP":
        """The single-action 2I-MDP of a stationary strategy ``actions: (R,)`` (same buckets)."""
        picked = [tuple(jnp.take_along_axis(a, act[:, None, None], axis=1) for a in arrays)
                  for arrays, act in zip(self._arrays(), self._bucket_actions(actions))]
        fields = [tuple(p[i] for p in picked) for i in range(7)]
        names = ("bucket_blocks", "bucket_block_lower", "bucket_block_upper", "bucket_fine_slot", "bucket_fine_upper",
                 "bucket_lower_slot", "bucket_lower_value")
        return dataclasses.replace(self, **dict(zip(names, fields)))

    def q_values(self, v, adversary: str = "min", actions=None):
        minimize = check_adversary(adversary)
        w = v if minimize else -v
        ranking = block_ranking(w, self.cells_of)
        parts = []
        acts = [None] * len(self.bucket_blocks) if actions is None else self._bucket_actions(actions)
        for arrays, act in zip(self._arrays(), acts):
            if act is not None:
                arrays = tuple(jnp.take_along_axis(a, act[:, None, None], axis=1)[:, 0] for a in arrays)
            parts.append(_sparse_two_layer_min(w, ranking, *arrays, self.cells_of, self.upper_rest))
        value = jnp.concatenate(parts)[self.position]
        return value if minimize else -value

    # padded views ((R, A, T) and (R, A, T, S), rows in ``rows`` order), built on access

    def _padded(self, per_bucket, fill):
        t = self.num_block_slots
        wide = [jnp.pad(a, ((0, 0), (0, 0), (0, t - a.shape[2])) + ((0, 0),) * (a.ndim - 3), constant_values=fill)
                for a in per_bucket]
        return jnp.concatenate(wide)[self.position]

    @property
    def blocks(self):
        return self._padded(tuple(b.astype(jnp.int32) for b in self.bucket_blocks), self.cells_of.shape[0])

    @property
    def block_lower(self):
        return self._padded(self.bucket_block_lower, 0.0)

    @property
    def block_upper(self):
        return self._padded(self.bucket_block_upper, 0.0)

    def _dense_fine(self, lower: bool):
        size = self.cells_of.shape[1]
        out = []
        for blocks, slot, up, l_slot, l_value in zip(self.bucket_blocks, self.bucket_fine_slot, self.bucket_fine_upper,
                                                     self.bucket_lower_slot, self.bucket_lower_value):
            cells = self.cells_of.at[blocks.astype(jnp.int32)].get(mode="fill", fill_value=self.num_states)
            if lower:
                dense = _scatter_slots(jnp.zeros(cells.shape), l_slot, l_value)
            else:
                dense = _scatter_slots(jnp.where(cells < self.num_states, self.upper_rest, 0.0), slot, up)
            out.append(dense.reshape(cells.shape[:3] + (size,)))
        return self._padded(tuple(out), 0.0)

    @property
    def lower(self):
        return self._dense_fine(True)

    @property
    def upper(self):
        return self._dense_fine(False)

    def __repr__(self):
        r, a = self.num_rows, self.num_actions
        shape = ", ".join(f"{rb}x{tb}x{kb}" for rb, tb, kb in self.buckets)
        return (f"TwoLayerIMDP(|S|={self.num_states}, rows={r}, |A|={a}, block={'x'.join(map(str, self.block_shape))}"
                f" ({self.cells_of.shape[0] - 1} blocks + sink), max blocks met={self.num_block_slots}, buckets rows x "
                f"block slots x fine entries={shape}, memory={self.nbytes / 1e6:.2f} MB)")


@functools.partial(jax.jit, static_argnums=4)
def _fine_slots(succ, blocks, block_of, offset_of, size: int):
    """``(R, A, K)`` slot ``t S + i`` of each listed successor: ``t`` its block's slot in the row's
    sorted ``blocks``, ``i`` its cell's slot in the block; padding ``>= T S``."""
    sentinel = block_of.shape[0] - 1
    succ = succ.astype(jnp.int32)
    succ_block = block_of[jnp.minimum(succ, sentinel)]
    t = jax.vmap(lambda b, q: jnp.searchsorted(b, q))(blocks.reshape(-1, blocks.shape[-1]),
                                                      succ_block.reshape(-1, succ.shape[-1])).reshape(succ.shape)
    t_count = blocks.shape[-1]
    return jnp.where(succ < sentinel, t * size + offset_of[jnp.minimum(succ, sentinel)], t_count * size)


def _scatter_slots(dense, slot, value):
    """``dense (..., T, S)`` with ``value (..., K)`` set at flat slots ``slot`` (out of range: dropped)."""
    shape = dense.shape
    flat = dense.reshape(shape[:-2] + (-1,))
    lead = jnp.indices(slot.shape[:-1], sparse=True)
    idx = tuple(i[..., None] for i in lead) + (slot.astype(jnp.int32),)
    return flat.at[idx].set(value, mode="drop").reshape(shape)


def block_ranking(w, cells_of):
    """What every list's inner problem shares, from one sort of ``w`` per backup: ``(rank,
    w_sorted, within, sorted_rank, sorted_w, inverse, sorted_min_rank, block_prefix)``, every
    block's cells in increasing rank (padding last; one extra all-padding block) and where each
    cell slot lands in that order (``inverse``)."""
    n_states = w.shape[0]
    order = jnp.argsort(w, stable=True)
    rank = jnp.zeros(n_states, jnp.int32).at[order].set(jnp.arange(n_states, dtype=jnp.int32))
    w_sorted = w[order]
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
    return dict(rank=rank, w_sorted=w_sorted, within=within, sorted_rank=sorted_rank, sorted_w=sorted_w,
                inverse=inverse, sorted_min_rank=sorted_min_rank, block_prefix=block_prefix,
                padded_cells=padded_cells)


def _sparse_two_layer_min(w, ranking, blocks, block_lower, block_upper, fine_slot, fine_upper, lower_slot,
                          lower_value, cells_of, upper_rest):
    """``two_layer_min`` on one bucket's sparse fine layer: the capacities ``upper - lower`` of
    the met blocks' cells are laid out in each block's rank order (``upper_rest`` on every cell,
    the listed successors' bounds scattered over it), the lower bounds' sums taken from their
    pairs; then the block greedy of ``_two_layer_sorted``.

    Shapes: ``blocks, block_lower, block_upper (..., T)``, ``fine_slot, fine_upper (..., K)``,
    ``lower_slot, lower_value (..., L)`` (slots ``t S + i``, padding ``>= T S``). Returns ``(...)``.
    """
    n_states = w.shape[0]
    num_blocks, size = cells_of.shape
    t_count = blocks.shape[-1]
    block_row = jnp.minimum(blocks.astype(jnp.int32), num_blocks)  # padding -> the all-padding block
    inverse = ranking["inverse"][block_row]  # (..., T, S): a cell slot's place in rank order

    def sorted_slot(slot):  # flat slot t S + i -> t S + (i's place in block t's rank order)
        slot = slot.astype(jnp.int32)
        t = jnp.minimum(slot // size, t_count - 1)
        i = slot % size
        place = jnp.take_along_axis(inverse.reshape(inverse.shape[:-2] + (-1,)), t * size + i, axis=-1)
        return jnp.where(slot < t_count * size, t * size + place, t_count * size)

    has_lower = lower_slot < t_count * size
    lo = jnp.where(has_lower, lower_value, 0.0)
    lo_sorted = sorted_slot(lower_slot)
    # capacities in rank order: upper_rest on every cell, the listed upper bounds, minus lower bounds
    cap = jnp.where(ranking["sorted_rank"][block_row] < n_states, upper_rest, 0.0)
    cap = _scatter_slots(cap, sorted_slot(fine_slot), fine_upper)
    flat = cap.reshape(cap.shape[:-2] + (-1,))
    lead = jnp.indices(lower_slot.shape[:-1], sparse=True)
    lead = tuple(i[..., None] for i in lead)
    cap = flat.at[lead + (lo_sorted,)].add(-lo, mode="drop").reshape(cap.shape)
    # per block met: sum of lower bounds and their cost
    t_of = jnp.minimum(lower_slot.astype(jnp.int32) // size, t_count - 1)
    lo_cell = ranking["padded_cells"][jnp.take_along_axis(block_row, t_of, axis=-1),
                                      lower_slot.astype(jnp.int32) % size]
    lo_w = w.at[lo_cell].get(mode="fill", fill_value=0.0)
    zeros = jnp.zeros(blocks.shape)
    sum_l = zeros.at[lead + (t_of,)].add(lo)
    base = zeros.at[lead + (t_of,)].add(lo * lo_w)
    return _two_layer_sorted(w, ranking, blocks, block_lower, block_upper, cap, sum_l, base, num_blocks, upper_rest)


def two_layer_min(w, blocks, block_lower, block_upper, lower, upper, cells_of, upper_rest):
    """``min sum gamma w`` over the two-layer polytope for every row (see the module docstring),
    from dense fine bounds.

    Args:
        w: ``(N+1,)`` values.
        blocks, block_lower, block_upper: ``(..., T)``; lower, upper: ``(..., T, S)``.
        cells_of: ``(B+1, S)``; upper_rest: scalar.
    Returns ``(...)``.
    """
    ranking = block_ranking(w, cells_of)
    num_blocks = cells_of.shape[0]
    block_row = jnp.minimum(blocks, num_blocks)  # padding -> the all-padding block
    # Sums over a block do not depend on the order (and padding cells have zero bounds and
    # value); only the capacities are put in rank order, for their prefix sums.
    sum_l = lower.sum(-1)
    base = (lower * w.at[ranking["padded_cells"]].get(mode="fill", fill_value=0.0)[block_row]).sum(-1)
    cap = jnp.take_along_axis(upper - lower, ranking["within"][block_row], -1)  # (..., T, S) in rank order
    return _two_layer_sorted(w, ranking, blocks, block_lower, block_upper, cap, sum_l, base, num_blocks, upper_rest)


def _two_layer_sorted(w, ranking, blocks, block_lower, block_upper, cap, sum_l, base, num_blocks, upper_rest):
    """The block greedy, from each met block's capacities ``cap (..., T, S)`` in the block's rank
    order and its lower bounds' sum and cost ``sum_l, base (..., T)``."""
    n_states = w.shape[0]
    size = cap.shape[-1]
    w_sorted, sorted_rank, sorted_w = ranking["w_sorted"], ranking["sorted_rank"], ranking["sorted_w"]
    sorted_min_rank, block_prefix = ranking["sorted_min_rank"], ranking["block_prefix"]
    blocks = blocks.astype(jnp.int32)
    met = blocks < num_blocks
    block_row = jnp.minimum(blocks, num_blocks)  # padding -> the all-padding block
    w_i = sorted_w[block_row]
    cum_cap = _prefix_sums(cap)
    cum_cost = _prefix_sums(cap * w_i)
    floor = jnp.where(met, jnp.maximum(block_lower, sum_l), 0.0)
    ceil = jnp.where(met, jnp.minimum(block_upper, sum_l + cum_cap[..., -1]), 0.0)

    def prefix_at(prefix, count):  # sum of the first `count` entries
        at = jnp.take_along_axis(prefix, jnp.maximum(count - 1, 0)[..., None], -1)[..., 0]
        return jnp.where(count > 0, at, 0.0)

    def fill_cost(amount):  # pour `amount` into a block's cells in increasing rank
        amount = jnp.maximum(amount, 0.0)  # a rounding below 0 pours nothing
        full = jnp.sum(cum_cap <= amount[..., None], -1)  # cells filled up
        w_next = jnp.take_along_axis(w_i, jnp.minimum(full, size - 1)[..., None], -1)[..., 0]
        partial = jnp.where(full < size, amount - prefix_at(cum_cap, full), 0.0)
        return prefix_at(cum_cost, full) + partial * w_next

    f_floor = base + fill_cost(floor - sum_l)
    f_ceil = base + fill_cost(ceil - sum_l)
    met_min_rank = jnp.where(met, sorted_rank[block_row, 0], n_states)

    search_steps = int(size).bit_length()
    flat_rank = sorted_rank.reshape(-1)
    row_start = block_row * size

    def count_below(k):  # per block met: its cells ranked below k (binary search in sorted_rank)
        k = k[..., None]

        def step(_, bounds):
            lo_i, hi_i = bounds
            mid = (lo_i + hi_i) // 2
            below = (lo_i < hi_i) & (flat_rank[row_start + jnp.minimum(mid, size - 1)] < k)
            return jnp.where(below, mid + 1, lo_i), jnp.where(below | (lo_i >= hi_i), hi_i, mid)

        zeros = jnp.zeros(blocks.shape, jnp.int32)
        return jax.lax.fori_loop(0, search_steps, step, (zeros, zeros + size))[0]

    def mass_and_cost(k):
        count = count_below(k)
        free = sum_l + prefix_at(cum_cap, count)
        m = jnp.clip(free, floor, ceil)
        cost = jnp.where(free < floor, f_floor, jnp.where(free > ceil, f_ceil, base + prefix_at(cum_cost, count)))
        cost = jnp.where(met, cost, 0.0)
        # blocks no bounded reachable set meets: capacity upper_rest each, at their cheapest value
        n_all = jnp.searchsorted(sorted_min_rank, k, side="left")
        met_offered = met_min_rank < k[..., None]
        n_met = jnp.sum(met_offered, -1)
        w_met = jnp.sum(jnp.where(met_offered, w_sorted[jnp.minimum(met_min_rank, n_states - 1)], 0.0), -1)
        mass = m.sum(-1) + upper_rest * (n_all - n_met)
        cost = cost.sum(-1) + upper_rest * (block_prefix[n_all] - w_met)
        return mass, cost

    def bisect(_, bounds):
        lo_k, hi_k = bounds
        mid = (lo_k + hi_k) // 2
        enough = mass_and_cost(mid)[0] >= 1.0
        return jnp.where(enough, lo_k, mid + 1), jnp.where(enough, mid, hi_k)

    steps = int(n_states).bit_length()  # each step at least halves hi - lo (n_states at first)
    zeros = jnp.zeros(blocks.shape[:-1], jnp.int32)
    _, k_star = jax.lax.fori_loop(0, steps, bisect, (zeros, zeros + n_states))
    j = jnp.maximum(k_star - 1, 0)
    mass_j, cost_j = mass_and_cost(j)
    mass_0, cost_0 = mass_and_cost(zeros)
    return jnp.where(k_star > 0, cost_j + (1.0 - mass_j) * w_sorted[j], cost_0)


_MATMUL_PREFIX_MAX = 128


def _prefix_sums(x):
    """Inclusive prefix sums over the last axis. Short axes as a product with a triangular
    matrix of ones: on the CPU, ``cumsum`` over the capacities of the 2I-MDP rows of Table 1
    (9-81 cells per block) took 1.0-1.9x as long (the retired ``benchmarks/two_layer.py``, docs/performance.md), and 3-6x on
    random (R, T, S) arrays with S = 18 and 81; over 256 entries the two cost the same."""
    size = x.shape[-1]
    if size > _MATMUL_PREFIX_MAX:
        return jnp.cumsum(x, -1)
    return jnp.matmul(x, jnp.triu(jnp.ones((size, size), x.dtype)), precision=jax.lax.Precision.HIGHEST)
