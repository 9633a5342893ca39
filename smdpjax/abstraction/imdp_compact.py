"""Interval MDP stored without padding to the widest row: lists in fixed-width chunks, sparse lower bounds.

The IMDP of Lemma 1 (``imdp.IMDP``) keeps every (row, action) pair's successor list padded to the
widest list of the whole abstraction, with a ``lower`` array beside ``upper``. On Table 1 the
lists' widths vary 2-10x between rows (the 2-D unicycle at 75x75: 530 to 1156 successors), and
at most one or two entries per list have a positive lower bound (a reachable box inside one
cell; none at all on the temperature rows), so most of those bytes are padding and zeros.

``CompactIMDP`` stores the same lists:

* each row's lists cut into ``ceil(width_r / W)`` *chunks* of one width ``W`` (``list_chunk_width``
  picks it), all chunks in one ``(C, A, W)`` array with the row of each chunk beside it, so the
  padding is at most ``W - 1`` slots per row and every backup is one program whatever the widths;
* only ``successors`` (int16 where the states fit) and ``upper`` per entry, 10 bytes instead of 18
  (3 or 4 where the upper bounds take at most 65 536 distinct values: ``coded``);
* the positive lower bounds as ``(state, value)`` pairs, ``L`` per list (``L`` = the most any
  list has, 0 when none has one).

Inner problem: the greedy of ``imdp.interval_min`` (fill the lower bounds, pour the rest into
states in increasing order of value, unlisted states at ``upper_rest`` each; one global sort of
the values per backup, a bisection over the global rank). Each bisection step sums every chunk's
terms and adds the chunks of a row (a sorted segment sum); the lower bounds enter from their
pairs: the mass placed after the ``k`` lowest-ranked states are filled,

    M(k) = sum_l lo_l + rest k + sum_{i listed, r_i < k} (u_i - rest) - sum_{l, r_l < k} lo_l,

is ``interval_min``'s ``base + rest k + sum (u_i - lo_i - rest)`` with the same terms grouped
differently, so the value is the same up to the rounding of the sums (``summands_per_backup``
counts the lower pairs too).

On the CPU the rows are solved a block at a time (``inner_blocks``, ``in_row_blocks``): every
bisection step passes over all slots of its rows, so all rows at once stream the whole storage
from memory ``log2(N + 1)`` times per backup, while a block of about ``BLOCK_SLOTS`` slots is read
from the cache after its first pass. Same values (a row's sums are the same sums); measured in
``benchmarks/imdp_blocks.py``. On an accelerator all rows run at once.

``successors``, ``lower`` and ``upper`` are available as the padded ``(R, A, K)`` arrays of
``IMDP`` (built on access: for tests, exports and small models), and ``padded()`` is the
equivalent ``IMDP``. Sharding (``smdpjax.sharding``) splits the rows' lower pairs and replicates
the chunks.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass, static_field
from .base import AbstractionMixin, check_adversary
from .box_bounds import list_counts, region_bounds
from .clusters import index_dtype
from .coded import decoded, encode, map_entries
from .imdp import first_rank_filling, value_ranking

# Explicit column sums up to this many slots per chunk (see ``imdp.interval_min``).
_EXPLICIT_COLUMNS = 48
# What a chunk costs beyond its slots, in slots: the gather of its row's bisection point and the
# segment sum of its partial sums in every bisection step.
CHUNK_OVERHEAD = 8
# Chunk widths ``chunk_width`` considers (besides the widest list itself).
CHUNK_WIDTHS = (4, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024)
# The IMDP's lists wider than ``_EXPLICIT_COLUMNS`` are cut into chunks of at most this many slots
# (``list_chunk_width``), summed as explicit columns, which cost less per slot than a reduction
# over a wide chunk. Greedy backup, ms, as ``chunk_width`` chose -> 32 slots (48 / 24): 2-D
# unicycle 45x45 50.5 -> 36.3 (45.8 / 34.3), 60x60 152 -> 111 (137), 75x75 388 -> 277 (270);
# 3-D unicycle 373 -> 345 (379 / 345); 3-D temperature 2.6 -> 2.2; 4-D 182 -> 149 (168 / 153).
WIDE_LIST_CHUNK = 32
# Slots (chunk entries times actions) the inner problem reads per block of rows (``inner_blocks``):
# a block's ranks and capacities (12 bytes a slot) stay in a core's L2 cache through the bisection.
BLOCK_SLOTS = 1 << 19


@pytree_dataclass
class CompactIMDP(AbstractionMixin):
    """Attributes (``C`` chunks of ``W`` slots; row ``r`` owns ``ceil(width_r / W)`` consecutive ones):
        chunk_succ: ``(C, A, W)`` int16/int32 successors (cells, sink ``N``); a row's chunks hold
            its lists in increasing order, padded with ``N + 1``.
        chunk_upper: ``(C, A, W)`` float64 upper bounds of Lemma 1, ``upper_rest`` included (0 on
            padding); a ``coded.Coded`` array (codes into a table of the distinct values) where
            that is smaller.
        chunk_row: ``(C,)`` int32 the row (index into ``rows``) of each chunk, nondecreasing.
        lower_succ: ``(R, A, L)`` int16/int32 the states with a positive lower bound, padded with
            ``N + 1``.
        lower_value: ``(R, A, L)`` float64 those lower bounds (0 on padding).
        upper_rest: scalar upper bound of every state not listed (P_W of the remainder cell).
        rows: ``(R,)`` int32 state index of each row (the non-terminal cells).
        labels: ``(N + 1,)`` int8 state labels.
        width: the widest list (``K`` of the padded views).
        list_rows: rows that own chunks (``R`` until sharding pads the row arrays).
        block_rows, block_chunks: the inner problem runs ``block_rows`` rows at a time, each block
            reading ``block_chunks`` consecutive chunks (``inner_blocks``); 0: all rows at once.
        strategy_blocks: the same for one action per row (``q_values(..., actions)``, ``restrict``).
    """

    chunk_succ: jax.Array
    chunk_upper: jax.Array
    chunk_row: jax.Array
    lower_succ: jax.Array
    lower_value: jax.Array
    upper_rest: jax.Array
    rows: jax.Array
    labels: jax.Array
    width: int = static_field(default=1)
    list_rows: int = static_field(default=0)
    block_rows: int = static_field(default=0)
    block_chunks: int = static_field(default=0)
    strategy_blocks: tuple = static_field(default=(0, 0))
    kind: str = static_field(default="imdp")

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_clusters(cls, grid, clusters, *, chunk: int | None = None) -> "CompactIMDP":
        """Lemma 1 from the clusters' index boxes (``box_bounds.region_bounds``, as
        ``IMDP.from_clusters``), stored compactly; ``chunk``: the chunk width (default
        ``list_chunk_width`` of the lists' widths)."""
        succ, lower, upper, counts = region_bounds(grid.cells, grid.periodic, clusters.boxes, clusters.prob,
                                                   noise_shape=clusters.noise_shape, counts=True)
        rest = jnp.asarray(clusters.prob_rest)
        return cls.from_lists(succ, lower, upper, rest, clusters.rows, grid.state_labels, chunk=chunk, upper_add=rest,
                              counts=counts)

    @classmethod
    def from_imdp(cls, imdp, *, chunk: int | None = None) -> "CompactIMDP":
        """The compact storage of a padded ``IMDP`` (same lists, same bounds)."""
        return cls.from_lists(imdp.successors, imdp.lower, imdp.upper, imdp.upper_rest, imdp.rows, imdp.labels,
                              chunk=chunk)

    @classmethod
    def from_lists(cls, successors, lower, upper, upper_rest, rows, labels, *,
                   chunk: int | None = None, upper_add=None, counts=None) -> "CompactIMDP":
        """From padded lists ``(R, A, K)`` (padding ``>= N + 1``, anywhere in a list), as an
        ``IMDP`` holds them (``upper_add``: a scalar the listed ``upper`` bounds do not include yet,
        added to them; ``counts``: where the listed entries are known to come first, their
        ``box_bounds.list_counts``). Concrete arrays only (the number of chunks depends on the
        widths)."""
        labels = jnp.asarray(labels)
        n_states = int(labels.shape[0])
        successors, lower, upper = jnp.asarray(successors), jnp.asarray(lower), jnp.asarray(upper)
        if successors.ndim != 3 or lower.shape != successors.shape or upper.shape != successors.shape:
            raise ValueError(f"successors, lower and upper must share one (R, A, K) shape, got {successors.shape}, "
                             f"{lower.shape}, {upper.shape}")
        num_rows = int(successors.shape[0])
        if num_rows == 0:
            raise ValueError("an IMDP needs at least one row (non-terminal cell)")
        gaps, widths, num_lower = (False, *counts) if counts is not None else list_stats(successors, lower, n_states)
        if bool(gaps):  # padding inside a list: listed entries first
            front = jnp.argsort(successors >= n_states, axis=-1, stable=True)
            successors, lower, upper = (jnp.take_along_axis(a, front, axis=-1) for a in (successors, lower, upper))
        widths, num_lower = np.maximum(np.asarray(widths), 1), int(num_lower)  # (R,) widest list of each row
        chunk = list_chunk_width(widths) if chunk is None else chunk
        c_succ, c_upper, chunk_row, l_succ, l_value = chunk_lists(successors, lower, upper, successors, n_states,
                                                                  widths, chunk, num_lower, n_states,
                                                                  upper_add=upper_add, id_dtype=index_dtype(n_states))
        slots = c_succ.shape[0] * c_succ.shape[2] / num_rows  # per row and action
        return cls(chunk_succ=c_succ, chunk_upper=encode(c_upper), chunk_row=jnp.asarray(chunk_row),
                   lower_succ=l_succ, lower_value=l_value, upper_rest=jnp.asarray(upper_rest), rows=jnp.asarray(rows, jnp.int32),
                   labels=labels, width=int(widths.max()), list_rows=num_rows,
                   **block_fields(chunk_row, num_rows, c_succ.shape[1], slots))

    # ------------------------------------------------------------------ the abstraction interface

    @property
    def num_actions(self) -> int:
        return int(self.chunk_succ.shape[1])

    @property
    def num_lower(self) -> int:
        """``L``: positive lower bounds stored per list."""
        return int(self.lower_succ.shape[2])

    @property
    def chunk(self) -> int:
        """``W``: slots per chunk."""
        return int(self.chunk_succ.shape[2])

    @property
    def num_chunks(self) -> int:
        return int(self.chunk_succ.shape[0])

    @property
    def summands_per_backup(self) -> float:
        # as IMDP: listed successors twice, plus the lower pairs twice, plus the unlisted prefix sum
        return float(2 * (self.width + self.num_lower) + self.num_states * float(self.upper_rest))

    def any_positive_lower(self) -> bool:
        """Whether any transition has a positive lower bound."""
        return bool(jnp.any(self.lower_value > 0))

    def restrict(self, actions) -> "CompactIMDP":
        """The single-action IMDP of a stationary strategy ``actions: (R,)``."""
        by_chunk = actions[self.chunk_row][:, None, None]
        by_row = actions[:, None, None]
        pick = lambda a, act: jnp.take_along_axis(a, act, axis=1)
        return dataclasses.replace(self, chunk_succ=pick(self.chunk_succ, by_chunk),
                                   chunk_upper=map_entries(self.chunk_upper, lambda a: pick(a, by_chunk)),
                                   lower_succ=pick(self.lower_succ, by_row), lower_value=pick(self.lower_value, by_row),
                                   block_rows=self.strategy_blocks[0], block_chunks=self.strategy_blocks[1])

    def q_values(self, v, adversary: str = "min", actions=None):
        minimize = check_adversary(adversary)
        w = v if minimize else -v  # max_gamma <gamma, v> = -min_gamma <gamma, -v>
        arrays = (self.chunk_succ, self.chunk_upper, self.lower_succ, self.lower_value)
        blocks = (self.block_rows, self.block_chunks)
        if actions is not None:
            blocks = self.strategy_blocks
            pick = lambda a, act: jnp.take_along_axis(a, act[:, None, None], axis=1)[:, 0]
            by_chunk = actions[self.chunk_row]
            arrays = (pick(arrays[0], by_chunk), map_entries(arrays[1], lambda a: pick(a, by_chunk)),
                      pick(arrays[2], actions), pick(arrays[3], actions))
        succ, upper, lower_succ, lower_value = arrays
        rows = self.list_rows or self.num_rows
        value = chunked_interval_min(w, value_ranking(w), succ, upper, self.chunk_row, lower_succ[:rows],
                                     lower_value[:rows], self.upper_rest, blocks=blocks)
        if self.num_rows > rows:  # rows padded by sharding repeat the last row
            value = value[jnp.minimum(jnp.arange(self.num_rows), rows - 1)]
        return value if minimize else -value

    # ------------------------------------------------------------------ padded views

    def padded(self):
        """The same abstraction as a padded ``IMDP`` (``(R, A, width)`` lists)."""
        from .imdp import IMDP

        return IMDP(successors=self.successors, lower=self.lower, upper=self.upper, upper_rest=self.upper_rest,
                    rows=self.rows, labels=self.labels)

    @property
    def successors(self):
        """``(R, A, width)`` padded successor lists, as ``IMDP.successors`` (built on access)."""
        return self._padded(self.chunk_succ, self.num_states)  # N + 1, one past the sink

    @property
    def upper(self):
        """``(R, A, width)`` padded upper bounds, as ``IMDP.upper`` (built on access)."""
        return self._padded(decoded(self.chunk_upper), 0.0)

    @property
    def lower(self):
        """``(R, A, width)`` padded lower bounds, as ``IMDP.lower`` (built on access)."""
        succ = self.successors[..., :, None]
        pairs = (self.lower_succ[:, :, None, :] == succ) & (self.lower_succ[:, :, None, :] < self.num_states)
        return jnp.sum(jnp.where(pairs, self.lower_value[:, :, None, :], 0.0), axis=-1)

    def _padded(self, chunks, fill):
        rows = self.list_rows or self.num_rows
        first = jnp.searchsorted(self.chunk_row, self.chunk_row, side="left")
        within = jnp.arange(self.num_chunks) - first
        most = -(-self.width // self.chunk)
        out = jnp.full((rows, most) + chunks.shape[1:], fill, chunks.dtype)
        out = out.at[self.chunk_row, within].set(chunks)  # (R, chunks per row, A, W)
        out = jnp.moveaxis(out, 1, 2).reshape(rows, chunks.shape[1], most * self.chunk)[..., :self.width]
        if self.num_rows > rows:  # rows padded by sharding repeat the last row
            out = out[jnp.minimum(jnp.arange(self.num_rows), rows - 1)]
        return out

    def __repr__(self):
        return (f"IMDP(|S|={self.num_states}, rows={self.num_rows}, |A|={self.num_actions}, max successors="
                f"{self.width}, chunks={self.num_chunks}x{self.chunk} slots, lower pairs per list={self.num_lower}, "
                f"memory={self.nbytes / 1e6:.2f} MB)")


@functools.partial(jax.jit, static_argnums=2)
def list_stats(successors, lower, n_states: int):
    """Of padded lists ``(R, A, K)`` (padding ``>= n_states``) in one pass: whether padding comes
    before a listed entry anywhere, the widest list of each row ``(R,)`` and the most positive
    lower bounds of any list."""
    listed = successors < n_states
    return jnp.any(listed[..., 1:] & ~listed[..., :-1]), *list_counts(successors, lower, n_states)


def chunk_width(widths, overhead: int = CHUNK_OVERHEAD, candidates=CHUNK_WIDTHS, one_per_row: bool = True) -> int:
    """The chunk width ``W`` that minimizes ``sum_r ceil(w_r / W) (W + overhead)`` over
    ``candidates`` below the widest list and (``one_per_row``) the widest list itself (one chunk
    per row).

    Args:
        widths: ``(R,)`` widest list of each row (over actions).
        overhead: a chunk's cost beyond its slots, in slots.
    """
    w = np.maximum(np.asarray(widths, np.int64).reshape(-1), 1)
    widest = int(w.max(initial=1))
    options = [c for c in candidates if c < widest] + ([widest] if one_per_row or widest <= min(candidates) else [])
    cost = [int(np.sum(-(-w // c) * (c + overhead))) for c in options]
    return int(options[int(np.argmin(cost))])


def list_chunk_width(widths) -> int:
    """The IMDP's chunk width: ``chunk_width`` where every list fits in ``_EXPLICIT_COLUMNS``
    slots, else ``chunk_width`` over the candidates up to ``WIDE_LIST_CHUNK`` (not one chunk per
    row), so that every chunk is summed as explicit columns."""
    if int(np.max(widths, initial=1)) <= _EXPLICIT_COLUMNS:
        return chunk_width(widths)
    return chunk_width(widths, candidates=tuple(c for c in CHUNK_WIDTHS if c <= WIDE_LIST_CHUNK), one_per_row=False)


def chunk_layout(widths, chunk: int | None = None):
    """``(chunk_row (C,), within (C,), W, most)``: rows of widest lists ``widths (R,)`` cut into
    ``ceil(width_r / W)`` chunks of ``W`` slots (``chunk``, default ``chunk_width(widths)``); each
    chunk's row and its place among the row's chunks, and the most chunks any row has."""
    widths = np.maximum(np.asarray(widths, np.int64).reshape(-1), 1)
    w = chunk_width(widths) if chunk is None else int(chunk)
    if w < 1:
        raise ValueError(f"chunk width must be at least 1, got {chunk}")
    counts = -(-widths // w)
    chunk_row = np.repeat(np.arange(widths.size, dtype=np.int32), counts)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    within = (np.arange(chunk_row.size) - first[chunk_row]).astype(np.int32)
    return chunk_row, within, w, int(counts.max(initial=1))


def _to_chunks(x, chunk_row, within, width: int, most: int, fill):
    """``(C, A, W)`` chunks of padded lists ``x (R, A, K)`` (listed entries first; ``fill`` past
    ``K``), in the layout of ``chunk_layout``."""
    r, a, k = x.shape
    x = jnp.pad(x, ((0, 0), (0, 0), (0, max(most * width - k, 0))), constant_values=fill)
    return x[..., :most * width].reshape(r, a, most, width)[chunk_row, :, within]


def _lower_slots(positive, num_lower: int):
    """``(R, A, L)`` slots of the (at most ``L = num_lower``) True entries of ``positive (R, A,
    K)`` in each list, padded with ``K``."""
    r, a, k = positive.shape
    count = jnp.cumsum(positive, axis=-1)
    slots = [jnp.where(count[..., -1] > l, jnp.argmax(count > l, axis=-1), k) for l in range(num_lower)]
    return jnp.stack(slots, -1).astype(jnp.int32) if slots else jnp.zeros((r, a, 0), jnp.int32)


def chunk_lists(ids, lower, upper, keys, limit: int, widths, chunk, num_lower: int, fill, upper_add=None,
                id_dtype=None):
    """Chunked storage of padded lists ``(R, A, K)`` (listed entries first): ``(chunk_ids (C, A,
    W), chunk_upper (C, A, W), chunk_row (C,) (host), lower_ids (R, A, L), lower_value (R, A, L))``.

    ``ids`` is what an entry stores (a state, or the 2I-MDP's fine slot), as ``id_dtype`` (default
    its own), ``fill`` its padding; an entry is listed where ``keys < limit``; ``widths (R,)`` the widest
    list of each row; ``upper_add``: a scalar added to the listed upper bounds (``upper_rest``);
    the lower bounds keep only their ``num_lower`` positive entries per list, as (id, value)
    pairs. The layout is computed on the host, the arrays in one compiled pass (the dozen eager
    operations it replaces cost more than the work on the 2-room rows of Table 1)."""
    chunk_row, within, w, most = chunk_layout(widths, chunk)
    add = jnp.zeros((), upper.dtype) if upper_add is None else jnp.asarray(upper_add, upper.dtype)
    dtype = np.dtype(ids.dtype if id_dtype is None else id_dtype)
    arrays = _chunk_arrays(ids, lower, upper, keys, add, chunk_row, within, int(limit), w, most, int(num_lower),
                           fill, dtype)
    return arrays[0], arrays[1], chunk_row, arrays[2], arrays[3]


@functools.partial(jax.jit, static_argnums=(7, 8, 9, 10, 11, 12))
def _chunk_arrays(ids, lower, upper, keys, add, chunk_row, within, limit: int, w: int, most: int, num_lower: int,
                  fill, dtype):
    listed = keys < limit
    ids = ids.astype(dtype)
    c_ids = _to_chunks(jnp.where(listed, ids, fill), chunk_row, within, w, most, fill)
    c_upper = _to_chunks(jnp.where(listed, upper + add, 0.0), chunk_row, within, w, most, 0.0)
    slot = _lower_slots((lower > 0) & listed, num_lower)
    k = ids.shape[-1]
    has = slot < k
    safe = jnp.minimum(slot, k - 1)
    l_ids = jnp.where(has, jnp.take_along_axis(ids, safe, axis=-1), fill).astype(dtype)
    l_value = jnp.where(has, jnp.take_along_axis(lower, safe, axis=-1), 0.0)
    return c_ids, c_upper, l_ids, l_value


def inner_blocks(chunk_row, num_rows: int, slots_per_row: float, budget: int = BLOCK_SLOTS) -> tuple[int, int]:
    """``(block_rows, block_chunks)``: rows per block of an inner problem, so that a block reads
    about ``budget`` slots, and the most chunks any block's rows own (``(0, 0)``: one block).

    Each bisection step of the inner problem passes over every slot of its rows; blocked, a
    block's slots are read from the cache in every step but the first. The last block is the
    last ``block_rows`` rows (it overlaps the one before it).

    Args:
        chunk_row: ``(C,)`` the row of each chunk, nondecreasing (concrete).
        num_rows: ``R``.
        slots_per_row: what a row costs on average, in slots (the compact IMDP: ``C A W / R``).
    """
    block_rows = max(1, int(budget // max(float(slots_per_row), 1.0)))
    if block_rows >= num_rows:
        return 0, 0
    counts = np.bincount(np.asarray(chunk_row, np.int64), minlength=num_rows)[:num_rows]
    return block_rows, most_per_block(counts, block_rows)


def most_per_block(per_row, block_rows: int) -> int:
    """The largest sum of ``per_row (R,)`` over a block of ``block_rows`` consecutive rows as
    ``in_row_blocks`` cuts them (the last block is the last ``block_rows`` rows; 0: all rows):
    the chunks a block reads, or the 2I-MDP's met (list, block) pairs."""
    per_row = np.asarray(per_row, np.int64)
    num_rows = per_row.size
    if not 0 < block_rows < num_rows:
        return int(per_row.sum())
    start = np.concatenate([[0], np.cumsum(per_row)])
    first = np.minimum(np.arange(0, num_rows, block_rows), num_rows - block_rows)
    return int(np.max(start[first + block_rows] - start[first]))


def block_fields(chunk_row, num_rows: int, num_actions: int, slots_per_row: float, budget: int = BLOCK_SLOTS,
                 backend: str | None = None) -> dict:
    """``block_rows``, ``block_chunks`` (every action) and ``strategy_blocks`` (one action per
    row) of a class that solves its rows in blocks (``inner_blocks``; ``slots_per_row``: per row
    and action). All 0 (all rows at once) off the CPU (``backend``, default JAX's), where an
    accelerator wants all rows at once, or with ``budget=0``."""
    if budget == 0 or (backend or jax.default_backend()) != "cpu":
        return dict(block_rows=0, block_chunks=0, strategy_blocks=(0, 0))
    block_rows, block_chunks = inner_blocks(chunk_row, num_rows, num_actions * slots_per_row, budget)
    return dict(block_rows=block_rows, block_chunks=block_chunks,
                strategy_blocks=inner_blocks(chunk_row, num_rows, slots_per_row, budget))


def in_row_blocks(solve, by_row, by_chunk, fills, chunk_row, blocks):
    """``solve(by_row, by_chunk, chunk_row) -> (R, ...)`` a block of rows at a time.

    Args:
        solve: an inner problem over rows ``by_row`` (arrays ``(R, ...)``) whose lists are the
            chunks ``by_chunk`` (arrays ``(C, ...)``, or ``coded.Coded`` ones, which ``solve``
            receives decoded) of the rows ``chunk_row (C,)``.
        fills: per chunk array, the entry that stands for no entry (padding).
        blocks: ``(block_rows, block_chunks)`` from ``inner_blocks``; ``(0, 0)``: all rows at once.

    Each block is ``block_rows`` consecutive rows and the ``block_chunks`` chunks from its first
    row's first (one size for all blocks: the slice may reach other rows' chunks, which become
    padding). The same values as ``solve`` on all rows, up to the order of sums over chunks.
    """
    block_rows, block_chunks = blocks
    num_rows, num_chunks = by_row[0].shape[0], chunk_row.shape[0]
    if not 0 < block_rows < num_rows:
        return solve(by_row, tuple(decoded(a) for a in by_chunk), chunk_row)
    block_chunks = min(block_chunks, num_chunks)
    n_blocks = -(-num_rows // block_rows)
    row_start = np.minimum(np.arange(n_blocks) * block_rows, num_rows - block_rows)
    chunk_start = jnp.minimum(jnp.searchsorted(chunk_row, jnp.asarray(row_start, chunk_row.dtype), side="left"),
                              num_chunks - block_chunks).astype(jnp.int32)

    def take(a, at, size):  # a coded array is decoded a block at a time
        return decoded(map_entries(a, lambda x: jax.lax.dynamic_slice_in_dim(x, at, size, axis=0)))

    def one(start):
        r0, c0 = start
        local = take(chunk_row, c0, block_chunks) - r0
        mine = (local >= 0) & (local < block_rows)
        chunks = tuple(jnp.where(mine.reshape((-1,) + (1,) * (a.ndim - 1)), take(a, c0, block_chunks),
                                 jnp.asarray(fill, a.dtype)) for a, fill in zip(by_chunk, fills))
        return solve(tuple(take(a, r0, block_rows) for a in by_row), chunks, jnp.clip(local, 0, block_rows - 1))

    values = jax.lax.map(one, (jnp.asarray(row_start, jnp.int32), chunk_start))  # (blocks, block_rows, ...)
    head = values[:-1].reshape((-1,) + values.shape[2:])
    return jnp.concatenate([head, values[-1, head.shape[0] - int(row_start[-1]):]])


def chunked_interval_min(w, ranking, succ, upper, chunk_row, lower_succ, lower_value, upper_rest, blocks=(0, 0)):
    """``min sum_s' gamma(s') w(s')`` over the interval polytope of every list, the lists in
    chunks and their lower bounds given as pairs (see the module docstring).

    Args:
        w: ``(N+1,)`` values of all states; ``ranking``: ``value_ranking(w)``.
        succ, upper: ``(C, ..., W)`` chunks of the listed successors (padding ``>= N+1``) and
            their upper bounds.
        chunk_row: ``(C,)`` the row of each chunk, nondecreasing, every row in ``0..R-1`` owning
            at least one.
        lower_succ, lower_value: ``(R, ..., L)`` states (padding ``>= N+1``) and values of the
            positive lower bounds, all of them listed in the row's chunks.
        upper_rest: upper bound of every unlisted state (their lower bound is 0).
        blocks: ``(block_rows, block_chunks)`` from ``inner_blocks``: the rows are solved that
            many at a time (``in_row_blocks``); ``(0, 0)``: all at once.
    Returns:
        ``(R, ...)`` the minima.
    """
    def solve(by_row, by_chunk, rows_of_chunks):
        return _chunks_min(w, ranking, *by_chunk, rows_of_chunks, *by_row, upper_rest)

    return in_row_blocks(solve, (lower_succ, lower_value), (succ, upper), (w.shape[0], 0.0), chunk_row, blocks)


def _chunks_min(w, ranking, succ, upper, chunk_row, lower_succ, lower_value, upper_rest):
    """``chunked_interval_min`` of all rows at once."""
    rank, w_sorted, prefix = ranking
    n_states = w.shape[0]
    num_rows = lower_succ.shape[0]
    width = succ.shape[-1]
    # Few slots per chunk: slot-major columns summed elementwise (one fused loop on the CPU);
    # many: a reduction over the last axis (as ``imdp.interval_min``, measured there).
    if width <= _EXPLICIT_COLUMNS:
        columns = lambda a: jnp.moveaxis(a, -1, 0)
        each = lambda x: x
        column_sum = lambda term: functools.reduce(jnp.add, (term(i) for i in range(width)))
    else:
        columns = lambda a: a
        each = lambda x: x[..., None]
        column_sum = lambda term: jnp.sum(term((Ellipsis, slice(None))), axis=-1)
    per_row = lambda x: jax.ops.segment_sum(x, chunk_row, num_segments=num_rows, indices_are_sorted=True)
    succ_k = columns(succ)
    listed = succ_k < n_states
    r = jnp.where(listed, rank.at[succ_k].get(mode="fill", fill_value=n_states), n_states)
    w_i = jnp.where(listed, w.at[succ_k].get(mode="fill", fill_value=0.0), 0.0)
    extra = jnp.where(listed, columns(upper) - upper_rest, 0.0)  # beyond an unlisted state's capacity

    has = lower_succ < n_states
    lo = jnp.where(has, lower_value, 0.0)
    lo_rank = jnp.where(has, rank.at[lower_succ].get(mode="fill", fill_value=n_states), n_states)
    lo_w = jnp.where(has, w.at[lower_succ].get(mode="fill", fill_value=0.0), 0.0)
    lower_sum = lambda term: jnp.sum(term, axis=-1)
    base_mass = lower_sum(lo)

    def mass(k):  # mass placed once the k lowest-ranked states are at their upper bounds
        k_chunk = k[chunk_row]
        return (base_mass + upper_rest * k + per_row(column_sum(lambda i: jnp.where(r[i] < each(k_chunk), extra[i], 0.0)))
                - lower_sum(jnp.where(lo_rank < k[..., None], lo, 0.0)))

    k_star = first_rank_filling(mass, base_mass.shape, n_states)
    j = jnp.maximum(k_star - 1, 0)  # the state that is filled only partly
    j_chunk = j[chunk_row]
    full = (upper_rest * prefix[j] + per_row(column_sum(lambda i: jnp.where(r[i] < each(j_chunk), extra[i] * w_i[i], 0.0)))
            - lower_sum(jnp.where(lo_rank < j[..., None], lo * lo_w, 0.0)))
    partial = jnp.where(k_star > 0, (1.0 - mass(j)) * w_sorted[j], 0.0)
    return lower_sum(lo * lo_w) + jnp.where(k_star > 0, full + partial, 0.0)
