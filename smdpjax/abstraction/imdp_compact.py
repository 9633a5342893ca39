"""Interval MDP stored without padding to the widest row: rows bucketed by width, sparse lower bounds.

The IMDP of Lemma 1 (``imdp.IMDP``) keeps every (row, action) pair's successor list padded to the
widest list of the whole abstraction, with a ``lower`` array beside ``upper``. On Table 1 the
lists' widths vary 2-10x between rows (the 2-D unicycle at 75x75: 530 to 1156 successors), and
at most one or two entries per list have a positive lower bound (a reachable box inside one
cell; none at all on the temperature rows), so most of those bytes are padding and zeros.

``CompactIMDP`` stores the same lists:

* rows sorted by their widest list (over actions) and cut into a few *buckets*, each padded only
  to its own widest list (``bucket_edges`` picks the cuts that minimize the padded size);
* only ``successors`` (int16 where the states fit) and ``upper`` per entry, 10 bytes instead of 18;
* the positive lower bounds as ``(slot, value)`` pairs, ``L`` per list (``L`` = the most any list
  has, 0 when none has one).

Inner problem: the greedy of ``imdp.interval_min`` (fill the lower bounds, pour the rest into
states in increasing order of value, unlisted states at ``upper_rest`` each; one global sort of
the values per backup, a bisection over the global rank), run per bucket, with the lower bounds
taken from their sparse pairs: the mass placed after the ``k`` lowest-ranked states are filled,

    M(k) = sum_l lo_l + rest k + sum_{i listed, r_i < k} (u_i - rest) - sum_{l, r_l < k} lo_l,

is ``interval_min``'s ``base + rest k + sum (u_i - lo_i - rest)`` with the same terms grouped
differently, so the value is the same up to the rounding of the sums (``summands_per_backup``
counts the lower pairs too). ``restrict`` keeps the buckets (a row's actions all live in its
bucket), so a strategy's backups cost what its lists hold.

``successors``, ``lower`` and ``upper`` are available as the padded ``(R, A, K)`` arrays of
``IMDP`` (built on access: for tests, exports and small models), and ``padded()`` is the
equivalent ``IMDP``.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass, static_field
from .base import AbstractionMixin, check_adversary
from .clusters import index_dtype

# Explicit column sums up to this many successors per list (see ``imdp.interval_min``).
_EXPLICIT_COLUMNS = 48
# Most buckets ``bucket_edges`` cuts the rows into, and the padded slots one more bucket must
# save (a fraction of the unbucketed size, and at least BUCKET_MIN_SAVING slots, ~40 MB of
# successors and bounds) to be worth its separate loops: on the 144-row temperature model three
# buckets made a backup 1.4x slower, and each bucket adds its own copy of the inner problem to
# every compiled synthesis loop (2-D unicycle 2I-MDP, row 2: cold synthesis 16.8 s with one
# bucket, 26.2 s with two, to save 1.2 MB of 17.9).
MAX_BUCKETS = 6
BUCKET_GAIN = 0.03
BUCKET_MIN_SAVING = 1 << 22


@pytree_dataclass
class CompactIMDP(AbstractionMixin):
    """Attributes (rows in bucket order; bucket b holds ``R_b`` rows with lists of ``K_b`` slots):
        bucket_succ: tuple of ``(R_b, A, K_b)`` int16/int32 successors (cells, sink ``N``), each
            list in increasing order, padded with ``N + 1``.
        bucket_upper: tuple of ``(R_b, A, K_b)`` float64 upper bounds of Lemma 1, ``upper_rest``
            included (0 on padding).
        bucket_lower_slot: tuple of ``(R_b, A, L)`` int16/int32 slots (in ``bucket_succ``) of the
            positive lower bounds, padded with ``K_b``.
        bucket_lower_value: tuple of ``(R_b, A, L)`` float64 those lower bounds (0 on padding).
        order: ``(R,)`` int32 the row (index into ``rows``) at each bucket-ordered position.
        position: ``(R,)`` int32 the bucket-ordered position of each row (``order``'s inverse).
        upper_rest: scalar upper bound of every state not listed (P_W of the remainder cell).
        rows: ``(R,)`` int32 state index of each row (the non-terminal cells).
        labels: ``(N + 1,)`` int8 state labels.
        width: the widest list (``K`` of the padded views).
    """

    bucket_succ: tuple
    bucket_upper: tuple
    bucket_lower_slot: tuple
    bucket_lower_value: tuple
    order: jax.Array
    position: jax.Array
    upper_rest: jax.Array
    rows: jax.Array
    labels: jax.Array
    width: int = static_field(default=1)
    kind: str = static_field(default="imdp")

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_clusters(cls, grid, clusters, *, max_buckets: int = MAX_BUCKETS) -> "CompactIMDP":
        """Lemma 1 from the clusters' index boxes (``box_bounds.region_bounds``, as
        ``IMDP.from_clusters``), stored compactly."""
        from .box_bounds import region_bounds

        succ, lower, upper = region_bounds(grid.cells, grid.periodic, clusters.boxes, clusters.prob)
        rest = jnp.asarray(clusters.prob_rest)
        upper = jnp.where(succ <= grid.num_cells, upper + rest, 0.0)
        return cls.from_lists(succ, lower, upper, rest, clusters.rows, grid.state_labels, max_buckets=max_buckets)

    @classmethod
    def from_imdp(cls, imdp, *, max_buckets: int = MAX_BUCKETS) -> "CompactIMDP":
        """The compact storage of a padded ``IMDP`` (same lists, same bounds)."""
        return cls.from_lists(imdp.successors, imdp.lower, imdp.upper, imdp.upper_rest, imdp.rows, imdp.labels,
                              max_buckets=max_buckets)

    @classmethod
    def from_lists(cls, successors, lower, upper, upper_rest, rows, labels, *,
                   max_buckets: int = MAX_BUCKETS) -> "CompactIMDP":
        """From padded lists ``(R, A, K)`` (padding ``>= N + 1``, anywhere in a list), as an
        ``IMDP`` holds them. Concrete arrays only (the bucket shapes depend on the widths)."""
        labels = jnp.asarray(labels)
        n_states = int(labels.shape[0])
        successors, lower, upper = jnp.asarray(successors), jnp.asarray(lower), jnp.asarray(upper)
        if successors.ndim != 3 or lower.shape != successors.shape or upper.shape != successors.shape:
            raise ValueError(f"successors, lower and upper must share one (R, A, K) shape, got {successors.shape}, "
                             f"{lower.shape}, {upper.shape}")
        listed = successors < n_states
        if bool(jnp.any(listed[..., 1:] & ~listed[..., :-1])):  # padding inside a list: listed entries first
            front = jnp.argsort(~listed, axis=-1, stable=True)
            successors, lower, upper = (jnp.take_along_axis(a, front, axis=-1) for a in (successors, lower, upper))
            listed = successors < n_states
        widths = np.asarray(jnp.sum(listed, axis=-1).max(axis=1))  # (R,) widest list of each row
        edges = bucket_edges(widths, successors.shape[1], max_buckets)
        order = np.argsort(widths, kind="stable").astype(np.int32)
        position = np.empty_like(order)
        position[order] = np.arange(order.size, dtype=np.int32)
        num_lower = int(jnp.max(jnp.sum(lower > 0, axis=-1), initial=0))
        dtype = index_dtype(n_states)
        pieces = []
        for start, stop in zip(edges[:-1], edges[1:]):
            take = jnp.asarray(order[start:stop])
            k_b = max(1, int(widths[order[stop - 1]]))
            pieces.append(_bucket(successors[take, :, :k_b], lower[take, :, :k_b], upper[take, :, :k_b], num_lower,
                                  n_states))
        succ, up, slot, value = (tuple(p[i] for p in pieces) for i in range(4))
        return cls(bucket_succ=tuple(s.astype(dtype) for s in succ), bucket_upper=up, bucket_lower_slot=slot,
                   bucket_lower_value=value,
                   order=jnp.asarray(order), position=jnp.asarray(position), upper_rest=jnp.asarray(upper_rest),
                   rows=jnp.asarray(rows, jnp.int32), labels=labels, width=max(1, int(widths.max(initial=1))))

    # ------------------------------------------------------------------ the abstraction interface

    @property
    def num_actions(self) -> int:
        return int(self.bucket_succ[0].shape[1])

    @property
    def num_lower(self) -> int:
        """``L``: positive lower bounds stored per list."""
        return int(self.bucket_lower_slot[0].shape[2])

    @property
    def buckets(self) -> tuple:
        """``((R_b, K_b), ...)`` rows and list slots of each bucket."""
        return tuple((int(s.shape[0]), int(s.shape[2])) for s in self.bucket_succ)

    @property
    def summands_per_backup(self) -> float:
        # as IMDP: listed successors twice, plus the lower pairs twice, plus the unlisted prefix sum
        return float(2 * (self.width + self.num_lower) + self.num_states * float(self.upper_rest))

    def any_positive_lower(self) -> bool:
        """Whether any transition has a positive lower bound."""
        return any(bool(jnp.any(v > 0)) for v in self.bucket_lower_value)

    def restrict(self, actions) -> "CompactIMDP":
        """The single-action IMDP of a stationary strategy ``actions: (R,)`` (same buckets)."""
        picks = self._bucket_actions(actions)
        pick = lambda arrays: tuple(jnp.take_along_axis(a, act[:, None, None], axis=1) for a, act in zip(arrays, picks))
        return dataclasses.replace(self, bucket_succ=pick(self.bucket_succ), bucket_upper=pick(self.bucket_upper),
                                   bucket_lower_slot=pick(self.bucket_lower_slot),
                                   bucket_lower_value=pick(self.bucket_lower_value))

    def q_values(self, v, adversary: str = "min", actions=None):
        minimize = check_adversary(adversary)
        w = v if minimize else -v  # max_gamma <gamma, v> = -min_gamma <gamma, -v>
        ranking = value_ranking(w)
        arrays = zip(self.bucket_succ, self.bucket_upper, self.bucket_lower_slot, self.bucket_lower_value)
        if actions is None:
            parts = [sparse_interval_min(w, ranking, *a, self.upper_rest) for a in arrays]
        else:
            pick = lambda a, act: jnp.take_along_axis(a, act[:, None, None], axis=1)[:, 0]
            parts = [sparse_interval_min(w, ranking, *(pick(x, act) for x in a), self.upper_rest)
                     for a, act in zip(arrays, self._bucket_actions(actions))]
        value = jnp.concatenate(parts)[self.position]
        return value if minimize else -value

    def _bucket_actions(self, actions):
        """Per bucket, ``actions`` of its rows (``(R,)`` in ``rows`` order -> ``(R_b,)`` each)."""
        picks, start = [], 0
        for s in self.bucket_succ:
            picks.append(actions[self.order[start:start + s.shape[0]]])
            start += s.shape[0]
        return picks

    # ------------------------------------------------------------------ padded views

    def padded(self):
        """The same abstraction as a padded ``IMDP`` (``(R, A, width)`` lists)."""
        from .imdp import IMDP

        return IMDP(successors=self.successors, lower=self.lower, upper=self.upper, upper_rest=self.upper_rest,
                    rows=self.rows, labels=self.labels)

    @property
    def successors(self):
        """``(R, A, width)`` padded successor lists, as ``IMDP.successors`` (built on access)."""
        return self._padded(self.bucket_succ, self.num_states)  # N + 1, one past the sink

    @property
    def upper(self):
        """``(R, A, width)`` padded upper bounds, as ``IMDP.upper`` (built on access)."""
        return self._padded(self.bucket_upper, 0.0)

    @property
    def lower(self):
        """``(R, A, width)`` padded lower bounds, as ``IMDP.lower`` (built on access)."""
        dense = tuple(_dense_lower(slot, value, s.shape[2])
                      for slot, value, s in zip(self.bucket_lower_slot, self.bucket_lower_value, self.bucket_succ))
        return self._padded(dense, 0.0)

    def _padded(self, per_bucket, fill):
        k = self.width
        wide = [jnp.pad(a, ((0, 0), (0, 0), (0, k - a.shape[2])), constant_values=fill) for a in per_bucket]
        return jnp.concatenate(wide)[self.position]

    def __repr__(self):
        r, a = self.num_rows, self.num_actions
        shape = ", ".join(f"{rb}x{kb}" for rb, kb in self.buckets)
        return (f"IMDP(|S|={self.num_states}, rows={r}, |A|={a}, max successors={self.width}, "
                f"buckets rows x slots={shape}, lower pairs per list={self.num_lower}, "
                f"memory={self.nbytes / 1e6:.2f} MB)")


def bucket_edges(widths, num_actions: int = 1, max_buckets: int = MAX_BUCKETS, gain: float = BUCKET_GAIN):
    """Cuts of the rows, sorted by width, into buckets: ``edges`` with bucket b the sorted rows
    ``edges[b]:edges[b + 1]``, padded to the widest of them.

    Minimizes the padded size ``sum_b R_b K_b`` (dynamic programming over the distinct widths,
    O(B D^2) for D distinct widths) with up to ``max_buckets`` buckets, keeping a further bucket
    only where it saves more than ``gain`` of the one-bucket size: each bucket costs its own
    loops, which small problems notice more than a few padded slots.
    """
    w = np.sort(np.maximum(np.asarray(widths, np.int64).reshape(-1), 1))
    if w.size == 0:
        return np.array([0, 0])
    distinct, counts = np.unique(w, return_counts=True)
    ends = np.cumsum(counts)  # rows up to and including each distinct width
    d = distinct.size
    # best[b][j]: least size of the rows up to distinct width j in b + 1 buckets (the last ending at j)
    best = [distinct * ends]
    cuts = [np.full(d, -1)]
    for _ in range(1, max(1, int(max_buckets))):
        prev = best[-1]
        # cost of a last bucket from distinct index i + 1 to j: (ends[j] - ends[i]) * distinct[j]
        cand = prev[:, None] + (ends[None, :] - ends[:, None]) * distinct[None, :]
        cand = np.where(np.arange(d)[:, None] < np.arange(d)[None, :], cand, np.iinfo(np.int64).max)
        arg = np.argmin(cand, axis=0)
        here = cand[arg, np.arange(d)]
        keep = here < prev  # one more bucket must help
        best.append(np.where(keep, here, prev))
        cuts.append(np.where(keep, arg, -2))  # -2: same as with one bucket fewer
    total = float(best[0][-1])
    chosen = 0
    for b in range(1, len(best)):
        if best[chosen][-1] - best[b][-1] > max(gain * total, BUCKET_MIN_SAVING / max(1, num_actions)):
            chosen = b
    edges, j, b = [w.size], d - 1, chosen
    while b > 0:
        i = cuts[b][j]
        if i == -2:
            b -= 1
            continue
        edges.append(int(ends[i]))
        j, b = i, b - 1
    return np.array([0] + edges[::-1])


@functools.partial(jax.jit, static_argnums=(3, 4))
def _bucket(succ, lower, upper, num_lower: int, n_states: int):
    """One bucket's arrays from its padded lists ``(R_b, A, K_b)``: successors, upper bounds, and
    the slots and values of the (at most ``num_lower``) positive lower bounds of each list."""
    positive = (lower > 0) & (succ < n_states)
    count = jnp.cumsum(positive, axis=-1)
    k_b = succ.shape[-1]
    slots = [jnp.where(count[..., -1] > l, jnp.argmax(count > l, axis=-1), k_b) for l in range(num_lower)]
    slot = jnp.stack(slots, -1).astype(index_dtype(k_b + 1)) if slots else \
        jnp.zeros(succ.shape[:2] + (0,), index_dtype(k_b + 1))
    value = jnp.take_along_axis(lower, jnp.minimum(slot.astype(jnp.int32), k_b - 1), axis=-1)
    value = jnp.where(slot < k_b, value, 0.0)
    return succ, jnp.where(succ < n_states, upper, 0.0), slot, value


def _dense_lower(slot, value, width: int):
    """``(..., width)`` lower bounds from their ``(slot, value)`` pairs ``(..., L)``."""
    dense = jnp.zeros(slot.shape[:-1] + (width + 1,), value.dtype)
    lead = jnp.indices(slot.shape[:-1], sparse=True)
    idx = tuple(i[..., None] for i in lead) + (jnp.minimum(slot.astype(jnp.int32), width),)
    return dense.at[idx].add(value)[..., :width]


def value_ranking(w):
    """``(rank (N+1,), w_sorted (N+1,), prefix (N+2,))``: each state's rank in increasing ``w``
    (stable), the sorted values and their prefix sums; one sort per backup, shared by all lists."""
    n_states = w.shape[0]
    order = jnp.argsort(w, stable=True)
    rank = jnp.zeros(n_states, jnp.int32).at[order].set(jnp.arange(n_states, dtype=jnp.int32))
    w_sorted = w[order]
    return rank, w_sorted, jnp.concatenate([jnp.zeros(1, w.dtype), jnp.cumsum(w_sorted)])


def sparse_interval_min(w, ranking, succ, upper, lower_slot, lower_value, upper_rest):
    """``min sum_s' gamma(s') w(s')`` over the interval polytope of every list, its lower bounds
    given sparsely (see the module docstring).

    Args:
        w: ``(N+1,)`` values of all states; ``ranking``: ``value_ranking(w)``.
        succ, upper: ``(..., K)`` listed successors (padding ``>= N+1``) and their upper bounds.
        lower_slot, lower_value: ``(..., L)`` slots in ``succ`` (padding ``>= K``) and values of
            the positive lower bounds.
        upper_rest: upper bound of every unlisted state (their lower bound is 0).
    Returns:
        ``(...)`` the minima.
    """
    rank, w_sorted, prefix = ranking
    n_states = w.shape[0]
    width = succ.shape[-1]
    # Few successors: successor-major columns summed elementwise (one fused loop on the CPU);
    # many: a reduction over the last axis (as ``imdp.interval_min``, measured there).
    if width <= _EXPLICIT_COLUMNS:
        columns = lambda a: jnp.moveaxis(a, -1, 0)
        each = lambda x: x
        column_sum = lambda term: functools.reduce(jnp.add, (term(i) for i in range(width)))
    else:
        columns = lambda a: a
        each = lambda x: x[..., None]
        column_sum = lambda term: jnp.sum(term((Ellipsis, slice(None))), axis=-1)
    succ_k = columns(succ)
    listed = succ_k < n_states
    r = jnp.where(listed, rank.at[succ_k].get(mode="fill", fill_value=n_states), n_states)
    w_i = jnp.where(listed, w.at[succ_k].get(mode="fill", fill_value=0.0), 0.0)
    extra = jnp.where(listed, columns(upper) - upper_rest, 0.0)  # beyond an unlisted state's capacity

    # the lower bounds: (..., L) pairs, their states' ranks and values
    lower_succ = jnp.take_along_axis(succ, jnp.minimum(lower_slot.astype(jnp.int32), width - 1), axis=-1)
    has = (lower_slot < width) & (lower_succ < n_states)
    lo = jnp.where(has, lower_value, 0.0)
    lo_rank = jnp.where(has, rank.at[lower_succ].get(mode="fill", fill_value=n_states), n_states)
    lo_w = jnp.where(has, w.at[lower_succ].get(mode="fill", fill_value=0.0), 0.0)
    lower_sum = lambda term: jnp.sum(term, axis=-1)
    base_mass = lower_sum(lo)

    def mass(k):  # mass placed once the k lowest-ranked states are at their upper bounds
        kk = k[..., None]
        return (base_mass + upper_rest * k + column_sum(lambda i: jnp.where(r[i] < each(k), extra[i], 0.0))
                - lower_sum(jnp.where(lo_rank < kk, lo, 0.0)))

    def bisect(_, bounds):
        lo_k, hi_k = bounds
        mid = (lo_k + hi_k) // 2
        enough = mass(mid) >= 1.0
        return jnp.where(enough, lo_k, mid + 1), jnp.where(enough, mid, hi_k)

    steps = int(n_states).bit_length()  # each step at least halves hi - lo (n_states at first)
    zeros = jnp.zeros(base_mass.shape, jnp.int32)
    _, k_star = jax.lax.fori_loop(0, steps, bisect, (zeros, zeros + n_states))
    j = jnp.maximum(k_star - 1, 0)  # the state that is filled only partly
    full = (upper_rest * prefix[j] + column_sum(lambda i: jnp.where(r[i] < each(j), extra[i] * w_i[i], 0.0))
            - lower_sum(jnp.where(lo_rank < j[..., None], lo * lo_w, 0.0)))
    partial = jnp.where(k_star > 0, (1.0 - mass(j)) * w_sorted[j], 0.0)
    return lower_sum(lo * lo_w) + jnp.where(k_star > 0, full + partial, 0.0)
