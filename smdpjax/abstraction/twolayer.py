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
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass, static_field
from .base import AbstractionMixin, check_adversary
from .box_bounds import region_bounds
from .grid_clusters import GridClusters
from .imdp import IMDP


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
    """Attributes (T = blocks a row meets, S = cells per block, B = number of blocks):
        blocks: ``(R, A, T)`` int32 coarse blocks met (sink block ``B``), padded with ``B + 1``.
        block_lower, block_upper: ``(R, A, T)`` coarse bounds L_B, U_B.
        lower, upper: ``(R, A, T, S)`` fine bounds of the cells of those blocks (cells that no
            bounded reachable set meets have ``[0, upper_rest]``).
        cells_of: ``(B + 1, S)`` int32 cells of every block, padded with ``N + 1``.
        upper_rest: P_W(remainder): upper bound of every state and every block.
        rows, labels: as in every abstraction.
        imdp: the fine-layer IMDP (a relaxation: its ambiguity set contains this one's).
    """

    blocks: jax.Array
    block_lower: jax.Array
    block_upper: jax.Array
    lower: jax.Array
    upper: jax.Array
    cells_of: jax.Array
    upper_rest: jax.Array
    rows: jax.Array
    labels: jax.Array
    block_shape: tuple = static_field(default=())
    kind: str = static_field(default="2imdp")

    @classmethod
    def from_clusters(cls, grid, clusters: GridClusters, block=None) -> "TwoLayerIMDP":
        block = default_block(clusters) if block is None else tuple(np.broadcast_to(np.asarray(block), (grid.n,)))
        block_of, cells_of = block_layout(grid, block)
        num_blocks = cells_of.shape[0] - 1
        block_of_j = jnp.asarray(block_of)
        blocks, block_lower, block_upper = region_bounds(grid.cells, grid.periodic, clusters.boxes, clusters.prob,
                                                         block=block)
        rest = jnp.asarray(clusters.prob_rest)
        met = blocks <= num_blocks
        block_upper = jnp.where(met, block_upper + rest, 0.0)

        fine = IMDP.from_clusters(grid, clusters)
        lower, upper = _fine_bounds_by_block(fine.successors, fine.lower, fine.upper, blocks,
                                             jnp.asarray(cells_of), block_of_j, rest)
        return cls(blocks=blocks, block_lower=block_lower, block_upper=block_upper, lower=lower, upper=upper,
                   cells_of=jnp.asarray(cells_of), upper_rest=rest, rows=fine.rows, labels=fine.labels,
                   block_shape=tuple(int(b) for b in block))

    @property
    def num_actions(self) -> int:
        return int(self.blocks.shape[1])

    @property
    def summands_per_backup(self) -> float:
        t, s = self.lower.shape[2:]
        return float(3 * t * s + self.cells_of.shape[0] * float(self.upper_rest))

    def restrict(self, actions) -> "TwoLayerIMDP":
        """The single-action 2I-MDP of a stationary strategy ``actions: (R,)``."""
        pick = lambda a: jnp.take_along_axis(a, actions.reshape((-1, 1) + (1,) * (a.ndim - 2)), axis=1)
        return dataclasses.replace(self, blocks=pick(self.blocks), block_lower=pick(self.block_lower),
                                   block_upper=pick(self.block_upper), lower=pick(self.lower),
                                   upper=pick(self.upper))

    def q_values(self, v, adversary: str = "min", actions=None):
        minimize = check_adversary(adversary)
        arrays = (self.blocks, self.block_lower, self.block_upper, self.lower, self.upper)
        if actions is not None:
            arrays = tuple(jnp.take_along_axis(a, actions.reshape((-1, 1) + (1,) * (a.ndim - 2)), axis=1)[:, 0]
                           for a in arrays)
        w = v if minimize else -v
        value = two_layer_min(w, *arrays, self.cells_of, self.upper_rest)
        return value if minimize else -value

    def __repr__(self):
        r, a, t, s = self.lower.shape
        return (f"TwoLayerIMDP(|S|={self.num_states}, rows={r}, |A|={a}, block={'x'.join(map(str, self.block_shape))}"
                f" ({self.cells_of.shape[0] - 1} blocks + sink), max blocks met={t}, memory={self.nbytes / 1e6:.2f} MB)")


@jax.jit
def _fine_bounds_by_block(succ, lower, upper, blocks, cells_of, block_of, rest):
    """Scatter the fine IMDP bounds ``(R, A, K)`` into the block layout ``(R, A, T, S)``."""
    sentinel_state = block_of.shape[0] - 1  # N + 1: block_of covers the states and the sentinel
    cells = cells_of.at[blocks].get(mode="fill", fill_value=sentinel_state)  # (R, A, T, S)
    lo = jnp.zeros(cells.shape)
    up = jnp.where(cells < sentinel_state, rest, 0.0)
    # position of each listed successor in the layout: its block's slot in `blocks`, its cell's slot in the block
    succ_block = block_of[jnp.minimum(succ, sentinel_state)]  # (R, A, K)
    t_slot = jnp.argmax(blocks[..., None, :] == succ_block[..., :, None], axis=-1)  # (R, A, K)
    s_slot = jnp.argmax(cells_of.at[succ_block].get(mode="fill", fill_value=-1) == succ[..., None], axis=-1)
    listed = succ < sentinel_state
    r, a, k = succ.shape
    rr, aa = jnp.meshgrid(jnp.arange(r), jnp.arange(a), indexing="ij")
    rr, aa = rr[..., None], aa[..., None]
    t_slot = jnp.where(listed, t_slot, blocks.shape[-1])  # out of range: dropped
    lo = lo.at[rr, aa, t_slot, s_slot].set(lower, mode="drop")
    up = up.at[rr, aa, t_slot, s_slot].set(upper, mode="drop")
    return lo, up


def two_layer_min(w, blocks, block_lower, block_upper, lower, upper, cells_of, upper_rest):
    """``min sum gamma w`` over the two-layer polytope for every row (see the module docstring).

    Args:
        w: ``(N+1,)`` values.
        blocks, block_lower, block_upper: ``(..., T)``; lower, upper: ``(..., T, S)``.
        cells_of: ``(B+1, S)``; upper_rest: scalar.
    Returns ``(...)``.
    """
    n_states = w.shape[0]
    order = jnp.argsort(w, stable=True)
    rank = jnp.zeros(n_states, jnp.int32).at[order].set(jnp.arange(n_states, dtype=jnp.int32))
    w_sorted = w[order]

    # every block's cells in increasing rank (padding last, rank n_states); one extra all-padding
    # block for the padding of `blocks`
    num_blocks, size = cells_of.shape
    padded_cells = jnp.concatenate([cells_of, jnp.full((1, size), n_states, cells_of.dtype)])
    cell_rank = rank.at[padded_cells].get(mode="fill", fill_value=n_states)  # (B+2, S)
    within = jnp.argsort(cell_rank, axis=-1)
    sorted_rank = jnp.take_along_axis(cell_rank, within, -1)  # (B+2, S)
    sorted_w = w.at[jnp.take_along_axis(padded_cells, within, -1)].get(mode="fill", fill_value=0.0)

    # block order by lowest rank, with prefix sums of their cheapest value (for unmet blocks)
    block_min_rank = sorted_rank[:num_blocks, 0]
    sorted_min_rank = jnp.sort(block_min_rank)
    block_prefix = jnp.concatenate([jnp.zeros(1), jnp.cumsum(w_sorted[jnp.minimum(sorted_min_rank, n_states - 1)])])

    met = blocks < num_blocks
    block_row = jnp.minimum(blocks, num_blocks)  # padding -> the all-padding block
    # Sums over a block do not depend on the order (and padding cells have zero bounds and
    # value); only the capacities are put in rank order, for their prefix sums.
    sum_l = lower.sum(-1)
    base = (lower * w.at[padded_cells].get(mode="fill", fill_value=0.0)[block_row]).sum(-1)
    cap = jnp.take_along_axis(upper - lower, within[block_row], -1)  # (..., T, S) in rank order
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
