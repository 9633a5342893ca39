"""Interval MDP abstraction (Lemma 1) and its inner problem.

For each (s, a) and successor s', Lemma 1 gives

    P_low(s, a, s') = sum_c 1(Reach(s,a,c) inside s') P_W(c),
    P_up(s, a, s')  = sum_c 1(Reach(s,a,c) meets s')  P_W(c).

Successors are stored as padded lists (never a dense |S| x |S| matrix). The remainder noise cell
of unbounded W reaches every state, so *every* state s' has ``P_up >= P_W(rest)``: listed
successors include it in ``upper``, and every unlisted state has the interval ``[0, upper_rest]``.

Inner problem (``q_values``): the classic O(N log N) greedy (fill the lower bounds, then pour the
remaining mass into states in increasing order of value up to their upper bounds), made exact in
the presence of the unlisted states: one global sort of ``v`` per Bellman iteration gives every
state's rank; with ``M(k)`` the mass placed after the ``k`` lowest-ranked states are filled up,
a bisection over ``k`` finds where the mass reaches 1, and prefix sums of the sorted values give
the unlisted states' contribution in O(1). Cost per iteration: O(N log N + R A K log N).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from .._pytree import pytree_dataclass, static_field
from .base import AbstractionMixin, check_adversary
from .box_bounds import region_bounds
from .clusters import index_dtype
from .grid_clusters import GridClusters

_ROWS_PER_CHUNK = 1 << 12
_EXPLICIT_COLUMNS = 48


@pytree_dataclass
class IMDP(AbstractionMixin):
    """Attributes:
        successors: ``(R, A, K)`` int16/int32 successor states (cells, sink ``N``), padded with ``N + 1``.
        lower, upper: ``(R, A, K)`` float64 transition bounds of Lemma 1 (0 on padding).
        upper_rest: scalar upper bound of every state not listed (P_W of the remainder cell).
        rows: ``(R,)`` int32 state index of each row (the non-terminal cells).
        labels: ``(N + 1,)`` int8 state labels.
    """

    successors: jax.Array
    lower: jax.Array
    upper: jax.Array
    upper_rest: jax.Array
    rows: jax.Array
    labels: jax.Array
    kind: str = static_field(default="imdp")

    @classmethod
    def from_clusters(cls, grid, clusters: GridClusters) -> "IMDP":
        """Lemma 1 from the clusters' index boxes (``box_bounds.region_bounds``: exact sums,
        rounded outward); successors in increasing order."""
        succ, lower, upper = region_bounds(grid.cells, grid.periodic, clusters.boxes, clusters.prob,
                                           noise_shape=clusters.noise_shape)
        succ = succ.astype(index_dtype(grid.num_states))
        rest = jnp.asarray(clusters.prob_rest)
        return cls(successors=succ, lower=lower, upper=jnp.where(succ <= grid.num_cells, upper + rest, 0.0),
                   upper_rest=rest, rows=jnp.asarray(clusters.rows, jnp.int32),
                   labels=jnp.asarray(grid.state_labels))

    @classmethod
    def from_members(cls, members, prob, prob_rest, rows, labels, width: int | None = None) -> "IMDP":
        """An IMDP from a frozen cluster structure and noise-cell probabilities (Lemma 1 again).

        ``members (R, A, C_b, K)`` are the SMDP's padded cluster member lists (padding
        ``N + 1``); a cluster with exactly one member lies inside one state. The bounds are sums of
        ``prob (C_b,)`` (plus ``prob_rest`` on the upper ones), so they are linear and
        differentiable in the probabilities, which may be traced (``jax.grad``, ``jax.vmap``).
        ``width``: successors per row (static); computed from ``members`` when omitted, which
        needs concrete members. Equal to ``from_clusters`` on the same clusters.
        """
        labels = jnp.asarray(labels)
        sentinel = int(labels.shape[0])
        members = jnp.asarray(members)
        if width is None:
            width = successor_width(members, sentinel)
        prob = jnp.asarray(prob)
        pieces = [_interval_bounds(ids, prob, jnp.sum(ids < sentinel, axis=-1) == 1, sentinel, int(width))
                  for ids in row_chunks(members)]
        succ, lower, upper = (jnp.concatenate(p) for p in zip(*pieces))
        succ = succ.astype(index_dtype(sentinel))
        rest = jnp.asarray(prob_rest)
        return cls(successors=succ, lower=lower, upper=jnp.where(succ < sentinel, upper + rest, 0.0),
                   upper_rest=rest, rows=jnp.asarray(rows, jnp.int32), labels=labels)

    def with_bounds(self, lower, upper, upper_rest) -> "IMDP":
        """The same successor lists with other bounds (e.g. rebuilt from new probabilities)."""
        return dataclasses.replace(self, lower=lower, upper=upper, upper_rest=jnp.asarray(upper_rest))

    @property
    def num_actions(self) -> int:
        return int(self.successors.shape[1])

    def any_positive_lower(self) -> bool:
        """Whether any transition has a positive lower bound."""
        return bool(jnp.any(self.lower > 0))

    def compact(self):
        """The same abstraction stored without padding (``imdp_compact.CompactIMDP``)."""
        from .imdp_compact import CompactIMDP

        return CompactIMDP.from_imdp(self)

    @property
    def summands_per_backup(self) -> float:
        # listed successors twice (lower-bound part and fill), plus the unlisted states' prefix sum
        return float(2 * self.successors.shape[2] + self.num_states * float(self.upper_rest))

    def restrict(self, actions) -> "IMDP":
        """The single-action IMDP of a stationary strategy ``actions: (R,)``."""
        pick = lambda a: jnp.take_along_axis(a, actions[:, None, None], axis=1)
        return dataclasses.replace(self, successors=pick(self.successors), lower=pick(self.lower),
                                   upper=pick(self.upper))

    def q_values(self, v, adversary: str = "min", actions=None):
        minimize = check_adversary(adversary)
        succ, lower, upper = self.successors, self.lower, self.upper
        if actions is not None:
            pick = lambda a: jnp.take_along_axis(a, actions[:, None, None], axis=1)[:, 0]
            succ, lower, upper = pick(succ), pick(lower), pick(upper)
        w = v if minimize else -v  # max_gamma <gamma, v> = -min_gamma <gamma, -v>
        value = interval_min(w, succ, lower, upper, self.upper_rest)
        return value if minimize else -value

    def __repr__(self):
        r, a, k = self.successors.shape
        return (f"IMDP(|S|={self.num_states}, rows={r}, |A|={a}, max successors={k}, "
                f"memory={self.nbytes / 1e6:.2f} MB)")


def value_ranking(w):
    """``(rank (N+1,), w_sorted (N+1,), prefix (N+2,))``: each state's rank in increasing ``w``
    (stable), the sorted values and their prefix sums; one sort per backup, shared by all lists."""
    n_states = w.shape[0]
    order = jnp.argsort(w, stable=True)
    rank = jnp.zeros(n_states, jnp.int32).at[order].set(jnp.arange(n_states, dtype=jnp.int32))
    w_sorted = w[order]
    return rank, w_sorted, jnp.concatenate([jnp.zeros(1, w.dtype), jnp.cumsum(w_sorted)])


def interval_min(w, succ, lower, upper, upper_rest):
    """``min sum_s' gamma(s') w(s')`` over ``gamma`` in the interval polytope, for every row.

    Args:
        w: ``(N+1,)`` values of all states.
        succ, lower, upper: ``(..., K)`` listed successors (padding ``>= N+1``) and their bounds.
        upper_rest: upper bound of every unlisted state (their lower bound is 0).
    Returns:
        ``(...)`` the minima.
    """
    n_states = w.shape[0]
    rank, w_sorted, prefix = value_ranking(w)

    # Few successors (the sparse rows of bounded noise): successor-major (K, ...) columns,
    # combined by explicit elementwise sums, which XLA on the CPU fuses into one vectorized
    # loop; a reduction over a short K axis ran 1.5-1.7x slower. Many successors: the reduction
    # over the last axis (explicit sums of hundreds of columns ran 1.5-2.9x slower there, a
    # reduction over a leading axis 2.5x). Measured with the retired benchmarks/cpu_layouts.py (docs/performance.md). The order of
    # the sums does not matter for soundness (the allowance counts summands, see
    # ``summands_per_backup``).
    width = succ.shape[-1]
    if width <= _EXPLICIT_COLUMNS:
        columns = lambda a: jnp.moveaxis(a, -1, 0)
        each = lambda x: x  # a per-row quantity against column i
        column_sum = lambda term: functools.reduce(jnp.add, (term(i) for i in range(width)))
    else:
        columns = lambda a: a
        each = lambda x: x[..., None]
        column_sum = lambda term: jnp.sum(term((Ellipsis, slice(None))), axis=-1)
    succ_k = columns(succ)
    listed = succ_k < n_states
    r = jnp.where(listed, rank.at[succ_k].get(mode="fill", fill_value=n_states), n_states)
    w_i = jnp.where(listed, w.at[succ_k].get(mode="fill", fill_value=0.0), 0.0)
    lo = jnp.where(listed, columns(lower), 0.0)
    extra = jnp.where(listed, columns(upper) - columns(lower) - upper_rest, 0.0)  # beyond an unlisted state's
    base_mass = column_sum(lambda i: lo[i])

    def mass(k):  # mass placed once the k lowest-ranked states are at their upper bounds
        return base_mass + upper_rest * k + column_sum(lambda i: jnp.where(r[i] < each(k), extra[i], 0.0))

    k_star = first_rank_filling(mass, base_mass.shape, n_states)
    j = jnp.maximum(k_star - 1, 0)  # the state that is filled only partly
    full = upper_rest * prefix[j] + column_sum(lambda i: jnp.where(r[i] < each(j), extra[i] * w_i[i], 0.0))
    partial = jnp.where(k_star > 0, (1.0 - mass(j)) * w_sorted[j], 0.0)
    return column_sum(lambda i: lo[i] * w_i[i]) + jnp.where(k_star > 0, full + partial, 0.0)


def first_rank_filling(mass, shape, n_states: int):
    """``(shape)`` int32 the least ``k`` in ``0..n_states`` with ``mass(k) >= 1`` (``n_states``
    if none), by bisection; ``mass`` is nondecreasing in ``k``, maps ``shape`` to ``shape``."""
    def bisect(_, bounds):
        lo_k, hi_k = bounds
        mid = (lo_k + hi_k) // 2
        enough = mass(mid) >= 1.0
        return jnp.where(enough, lo_k, mid + 1), jnp.where(enough, mid, hi_k)

    steps = int(n_states).bit_length()  # each step at least halves hi - lo (n_states at first)
    zeros = jnp.zeros(shape, jnp.int32)
    return jax.lax.fori_loop(0, steps, bisect, (zeros, zeros + n_states))[1]


def row_chunks(tree, size: int = _ROWS_PER_CHUNK):
    """Slices of a PyTree of row-major arrays, ``size`` rows at a time (bounds peak memory)."""
    rows = jax.tree_util.tree_leaves(tree)[0].shape[0]
    for start in range(0, rows, size):
        yield jax.tree.map(lambda a: a[start:start + size], tree)


def successor_width(members, sentinel: int) -> int:
    """Most distinct regions any row's clusters meet: the successor-list width of Lemma 1."""
    return max(int(_count_distinct(ids, sentinel).max()) for ids in row_chunks(jnp.asarray(members)))


@functools.partial(jax.jit, static_argnums=1)
def _count_distinct(members, sentinel):
    ids = jnp.sort(members.reshape(members.shape[0], members.shape[1], -1), axis=-1)
    first = jnp.concatenate([jnp.ones_like(ids[..., :1], bool), ids[..., 1:] != ids[..., :-1]], axis=-1)
    return jnp.sum(first & (ids < sentinel), axis=-1)


@functools.partial(jax.jit, static_argnums=(3, 4))
def _interval_bounds(members, prob, single, sentinel, width):
    """Lemma 1 bounds from cluster members ``(R, A, C, K)`` -> region lists ``(R, A, width)``."""
    r, a, c, k = members.shape
    ids = members.reshape(r, a, c * k)
    w_up = jnp.broadcast_to(prob[:, None], (c, k)).reshape(c * k)
    w_lo = jnp.where(single[..., None], prob[:, None], 0.0)  # (R, A, C, 1): a single-region cluster
    w_lo = jnp.broadcast_to(w_lo, (r, a, c, k)).reshape(r, a, c * k)
    order = jnp.argsort(ids, axis=-1)
    ids = jnp.take_along_axis(ids, order, axis=-1)
    up = jnp.where(ids < sentinel, w_up[order], 0.0)
    lo = jnp.where(ids < sentinel, jnp.take_along_axis(w_lo, order, axis=-1), 0.0)
    first = jnp.concatenate([jnp.ones_like(ids[..., :1], bool), ids[..., 1:] != ids[..., :-1]], axis=-1)
    slot = jnp.clip(jnp.cumsum(first, axis=-1) - 1, 0, width - 1)
    rr, aa = jnp.meshgrid(jnp.arange(r), jnp.arange(a), indexing="ij")
    rr, aa = rr[..., None], aa[..., None]
    succ = jnp.full((r, a, width), sentinel, jnp.int32).at[rr, aa, slot].min(ids)
    lower = jnp.zeros((r, a, width)).at[rr, aa, slot].add(lo)
    upper = jnp.zeros((r, a, width)).at[rr, aa, slot].add(up)
    return succ, lower, upper
