"""Minimum (or maximum) of a grid array over many index boxes, by an n-dimensional sparse table.

A grid array ``A`` has shape ``cells = (c_1, ..., c_n)``. An index box is, per dimension ``d``, a
first cell ``s_d`` and a number of cells ``l_d``: the cells ``s_d, ..., s_d + l_d - 1``, taken
modulo ``c_d`` on a periodic dimension (the box wraps around there).

The sparse table holds, for every level combination ``k = (k_1, ..., k_n)``, the minima of ``A``
over the power-of-two boxes ``[p_d, p_d + 2^{k_d})``:

    T[k][p] = min A[p_1 : p_1 + 2^{k_1}, ..., p_n : p_n + 2^{k_n}].

With ``k_d = floor(log2 l_d)`` the two windows ``[s_d, s_d + 2^{k_d})`` and
``[s_d + l_d - 2^{k_d}, s_d + l_d)`` overlap and together cover exactly the cells of the box in
dimension ``d``; the 2^n products of these windows cover exactly the box. ``min`` is idempotent, so
the minimum of the 2^n table entries *is* the minimum over the box: exact, no rounding, never
larger than any cell's value (the soundness the SMDP backup needs).

Only the levels that the longest box needs are built (``k_d <= floor(log2 max_length_d)``): a table
with all levels up to the grid size was 5x slower on an H100 (it fell out of L2). Periodic
dimensions are extended circularly by ``max_length_d - 1`` cells, so that a box that wraps around is
a contiguous box of the extended array and needs no modular arithmetic per query.

Short dimensions may instead hold a window of *every* length ``1 .. max_length_d``
(``RangeSpec.every_length``): then the box's own extent is one window and that dimension needs one
lookup instead of two. Each such dimension halves the gathers per query (the cost of a backup) and
multiplies the table by ``max_length_d / (floor(log2 max_length_d) + 1)``; by default dimensions
switch while the table stays small enough to stay in cache, and on large grids while the lookups
saved outweigh the larger table's build (``default_every_length``).

Everything is static in shape (``RangeSpec`` is hashable) and jit/vmap friendly; Python loops run
only over dimensions, levels and corners, never over boxes.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np

_OPS = ("min", "max")


# Table entries (8 MB of float64) up to which a dimension switches from power-of-two windows
# (two lookups per query in that dimension) to windows of every length (one lookup). Measured on
# the 3-D friction unicycle (30^3 cells, boxes up to 5x5x3, 8M boxes, 2-core CPU), range minima
# of all boxes: 8 lookups per box (2 MB table) 0.43 s; 4 lookups, every length on the heading
# (6 MB) 0.17-0.19 s; 1 lookup, every length everywhere (17 MB) 0.22 s. Fewer lookups pay until
# the table leaves the cache.
TABLE_BUDGET = 1 << 20
# Past the budget a dimension still switches while a query needs more than this many lookups and
# the table stays within half the boxes queried per rebuild (its build, ~4 ns per entry, then
# costs less than the lookups it saves). 4-D double integrator, boxes 3x3x3x3, greedy backup per
# box (AMD EPYC, 2 cores, 32 MB L3): 32^4 cells (94.6M boxes) 16 lookups 10.8 ns, 8 lookups (25M
# entries) 5.5 ns, 4 (38M) 4.7-5.1 ns, 2 (57M) 8.2-12.9 ns; 18^4 cells 16.0 / 5.8 / 5.5 / 6.5 ns.
# 3-D unicycle at 46^3 (6x6x3 boxes): 8 lookups 4.5 ns, 4 lookups 5.6-5.8 ns. Past 8 lookups the
# gain is small or negative.
MANY_LOOKUPS = 8
# In 3-D and up one lookup per query ran 2-4x slower than two, even with the table in cache (4-D
# 10^4 cells 6.1 vs 1.5 ns per box, 13^4 7.0 vs 2.1; 3-D 22^3 4.6 vs 1.2; 2-D 100^2 2.8 vs 3.1):
# the dimensions stop at two lookups there.
FEWEST_LOOKUPS_3D = 2


@dataclasses.dataclass(frozen=True)
class RangeSpec:
    """Static description of the grid, the longest box and the table (hashable: a jit static argument).

    Attributes:
        cells: ``(n,)`` cells per dimension (the grid array's shape, C order).
        periodic: ``(n,)`` whether dimension d wraps around.
        max_lengths: ``(n,)`` the longest box length per dimension that queries may use (>= 1;
            at most ``cells[d]``). Queries with longer boxes are outside the contract.
        every_length: ``(n,)`` per dimension, True: the table holds windows of every length
            ``1 .. max_length`` and a query reads one window in that dimension; False: windows
            of the lengths ``2^k <= max_length`` and two overlapping windows per query (the
            sparse table proper). ``None``: chosen by ``default_every_length``.
    """

    cells: tuple
    periodic: tuple
    max_lengths: tuple
    every_length: tuple | None = None

    def __post_init__(self):
        cells = tuple(int(c) for c in self.cells)
        periodic = tuple(bool(p) for p in self.periodic)
        lengths = tuple(int(m) for m in self.max_lengths)
        if not (len(cells) == len(periodic) == len(lengths)) or not cells:
            raise ValueError(f"cells, periodic and max_lengths must have one entry per dimension, got "
                             f"{cells}, {periodic}, {lengths}")
        if any(c < 1 for c in cells):
            raise ValueError(f"cells must be >= 1, got {cells}")
        if any(not 1 <= m <= c for m, c in zip(lengths, cells)):
            raise ValueError(f"max_lengths must lie in [1, cells] per dimension, got {lengths} for cells {cells}")
        every = self.every_length
        every = default_every_length(cells, periodic, lengths) if every is None else tuple(bool(e) for e in every)
        if len(every) != len(cells):
            raise ValueError(f"every_length must have one entry per dimension, got {every}")
        object.__setattr__(self, "cells", cells)
        object.__setattr__(self, "periodic", periodic)
        object.__setattr__(self, "max_lengths", lengths)
        object.__setattr__(self, "every_length", every)

    @classmethod
    def for_grid(cls, grid, max_lengths, every_length=None, boxes: int | None = None) -> "RangeSpec":
        """The spec of a ``StateGrid`` (its cells and periodic dimensions); ``every_length=None``:
        ``default_every_length`` for ``boxes`` queries per table build."""
        cells, periodic, lengths = tuple(grid.cells.tolist()), tuple(grid.periodic.tolist()), tuple(max_lengths)
        if every_length is None:
            every_length = default_every_length(cells, periodic, tuple(int(m) for m in lengths), boxes=boxes)
        return cls(cells, periodic, lengths, every_length)

    @property
    def n(self) -> int:
        return len(self.cells)

    @property
    def levels(self) -> tuple:
        """Window lengths per dimension: ``max_length`` (every length) or
        ``floor(log2 max_length) + 1`` (level k covers 2^k cells)."""
        return _levels(self.max_lengths, self.every_length)

    @property
    def extended(self) -> tuple:
        """Shape of the grid array after the circular extension of the periodic dimensions."""
        return _extended(self.cells, self.periodic, self.max_lengths)

    @property
    def table_shape(self) -> tuple:
        """``(*levels, *extended)``: one extended-grid-sized block per level combination."""
        return self.levels + self.extended

    @property
    def corners(self) -> tuple:
        """Windows per dimension a query reads: 1 with every length, or when every length is 1 or
        2 (the two power-of-two windows coincide, since l = 2^floor(log2 l)); else 2."""
        return _corners(self.max_lengths, self.every_length)

    @property
    def index_dtype(self):
        """Integer type of flat table indices."""
        return jnp.int32 if math.prod(self.table_shape) < np.iinfo(np.int32).max else jnp.int64


def _levels(max_lengths, every_length) -> tuple:
    return tuple(m if e else m.bit_length() for m, e in zip(max_lengths, every_length))


def _corners(max_lengths, every_length) -> tuple:
    return tuple(1 if e or m <= 2 else 2 for m, e in zip(max_lengths, every_length))


def _extended(cells, periodic, max_lengths) -> tuple:
    return tuple(c + m - 1 if p else c for c, p, m in zip(cells, periodic, max_lengths))


def default_every_length(cells, periodic, max_lengths, budget: int = TABLE_BUDGET, boxes: int | None = None) -> tuple:
    """Which dimensions get windows of every length: greedily, the dimensions that need two
    power-of-two windows, cheapest (shortest max length) first, while the table stays within
    ``budget`` entries, or, with ``boxes`` (queries per table build) given, while a query needs
    more than ``MANY_LOOKUPS`` lookups and the table stays within ``boxes // 2`` entries. Each
    switch halves the lookups per query; in 3-D and up a query keeps at least two."""
    every = [False] * len(cells)
    size = lambda e: math.prod(_levels(max_lengths, e)) * math.prod(_extended(cells, periodic, max_lengths))
    lookups = lambda e: math.prod(_corners(max_lengths, e))
    fewest = FEWEST_LOOKUPS_3D if len(cells) >= 3 else 1
    for d in sorted(range(len(cells)), key=lambda d: max_lengths[d]):
        if max_lengths[d] <= 2:
            continue  # one power-of-two window already
        trial = every.copy()
        trial[d] = True
        if lookups(trial) < fewest:
            break
        many = boxes is not None and lookups(every) > MANY_LOOKUPS and size(trial) <= boxes // 2
        if size(trial) <= budget or many:
            every = trial
    return tuple(every)


def _combine_and_fill(op: str, dtype):
    """``(elementwise op, identity element)``: the identity is what an empty box yields."""
    if op not in _OPS:
        raise ValueError(f"op must be 'min' or 'max', got {op!r}")
    minimize = op == "min"
    if jnp.issubdtype(dtype, jnp.floating):
        fill = jnp.inf if minimize else -jnp.inf
    else:
        fill = jnp.iinfo(dtype).max if minimize else jnp.iinfo(dtype).min
    return (jnp.minimum if minimize else jnp.maximum), jnp.asarray(fill, dtype)


def build_table(values, spec: RangeSpec, op: str = "min"):
    """The sparse table ``spec.table_shape`` of ``values`` (``(prod(cells),)`` or ``cells``).

    Entry ``[k_1, ..., k_n, p_1, ..., p_n]`` is the ``op`` over the extended array's box
    ``[p_d, p_d + w_d)`` with window length ``w_d = 2^{k_d}`` (or ``k_d + 1`` on an
    ``every_length`` dimension). Entries whose window runs past the extended array are not valid
    (they combine with the identity) and are never read by ``query_table``.
    """
    combine, fill = _combine_and_fill(op, values.dtype)
    table = jnp.reshape(values, spec.cells)
    for d, (c, e) in enumerate(zip(spec.cells, spec.extended)):
        if e > c:  # periodic: cells c .. e-1 repeat cells 0 .. e-c-1 (static indices)
            table = jnp.take(table, np.arange(e) % c, axis=d)
    for d in range(spec.n):
        axis = 2 * d  # the d level axes built so far come first, then the n data axes
        blocks = [table]
        for k in range(1, spec.levels[d]):
            # every length: window k+1 = window k and one more cell; powers of two: window 2^k =
            # two windows 2^(k-1) side by side
            shift, source = (k, table) if spec.every_length[d] else (1 << (k - 1), blocks[-1])
            moved = jax.lax.slice_in_dim(source, shift, source.shape[axis], axis=axis)
            pad = [(0, 0)] * source.ndim
            pad[axis] = (0, shift)
            blocks.append(combine(blocks[-1], jnp.pad(moved, pad, constant_values=fill)))
        # The barrier keeps each dimension's stack in a fusion of its own: XLA:GPU (jax 0.11.2,
        # H100) miscompiled the fused chain of stacks, pads and slices (float64 entries off by
        # ~1e-7, jit only: a torn read); compare jax-ml/jax#40588. It also makes the table a
        # buffer of its own, read by the gathers, instead of something fused into them.
        table = jax.lax.optimization_barrier(jnp.stack(blocks, axis=d))
    return table


def loop_variant_zero(values):
    """0 (int32) computed from ``values`` (any float array), which XLA cannot fold to a constant.

    Added to the index boxes inside a backup, it keeps XLA's loop-invariant code motion from
    hoisting the index arithmetic of every box out of a value-iteration loop, where it would
    stay alive for the whole solve: one int32 per (box, corner), 64 bytes per box in 4-D, 7x
    what the boxes take (``x * 0.0`` is not folded, it is NaN for NaN x; float-to-int conversion
    maps NaN to 0)."""
    return (jnp.ravel(values)[0] * 0.0).astype(jnp.int32)


def query_table(table, start, length, spec: RangeSpec, op: str = "min", anchor=None):
    """``op`` of the grid array over the index boxes ``start, length: (..., n)`` -> ``(...)``
    (or sequences of n arrays ``(...)``, one per dimension).

    ``table`` comes from ``build_table(values, spec, op)``; ``anchor``: an optional int32 0 that
    depends on the values (`loop_variant_zero`), added to the starts. Contract: ``0 <= start < cells`` and
    ``length <= max_lengths`` per dimension, and on non-periodic dimensions
    ``start + length <= cells``. A box with length 0 in some dimension contains no cell and gets
    the identity (``+inf`` for min, ``-inf`` for max). Any integer dtype (int8/int16 included).
    """
    combine, fill = _combine_and_fill(op, table.dtype)
    itype = spec.index_dtype
    by_dimension = lambda x: list(x) if isinstance(x, (list, tuple)) else [x[..., d] for d in range(spec.n)]
    starts, lengths = by_dimension(start), by_dimension(length)
    if anchor is not None:  # in the stored type: a conversion before it would be hoisted
        starts = [s + anchor.astype(s.dtype) for s in starts]
        lengths = [n + anchor.astype(n.dtype) for n in lengths]
    empty = functools.reduce(jnp.logical_or, [n == 0 for n in lengths])
    strides = np.cumprod((spec.table_shape + (1,))[::-1])[::-1][1:]  # C-order strides of the table
    level_strides, data_strides = strides[:spec.n], strides[spec.n:]

    base = jnp.zeros(jnp.shape(starts[0]), itype)
    windows = []  # per dimension: the first cells of its one or two windows
    for d in range(spec.n):
        s, l = starts[d].astype(itype), jnp.maximum(lengths[d].astype(itype), 1)
        if spec.every_length[d]:
            base = base + (l - 1) * int(level_strides[d])  # the window of length l: the box itself
            firsts = (s,)
        else:
            if spec.levels[d] > 1:
                # floor(log2 l) for l >= 1, from the count of leading zeros of an int32
                k = (31 - jax.lax.clz(l.astype(jnp.int32))).astype(itype)
                base = base + k * int(level_strides[d])
                second = s + l - jnp.left_shift(jnp.ones_like(l), k)
            else:
                second = s  # every length is 1: the one window is the box
            firsts = (s, second) if spec.corners[d] == 2 else (s,)
        windows.append([f * int(data_strides[d]) for f in firsts])

    flat = table.reshape(-1)
    result = None
    for corner in itertools.product(*windows):
        # "clip" is XLA's native gather semantics: in-range indices (the contract) cost no check
        value = flat.at[base + sum(corner)].get(mode="clip")
        result = value if result is None else combine(result, value)
    return jnp.where(empty, fill, result)


@functools.partial(jax.jit, static_argnames=("spec", "op"))
def range_extreme(values, start, length, spec: RangeSpec, op: str = "min"):
    """``op`` (``"min"``/``"max"``) of ``values`` (``(prod(cells),)`` or ``cells``) over the index
    boxes ``start, length: (..., n)`` -> ``(...)``; see ``query_table`` for the contract."""
    return query_table(build_table(values, spec, op), start, length, spec, op)


def range_min(values, start, length, spec: RangeSpec):
    """Minimum of ``values`` over each index box ``(..., n)`` -> ``(...)``; ``+inf`` if empty."""
    return range_extreme(values, start, length, spec, "min")


def range_max(values, start, length, spec: RangeSpec):
    """Maximum of ``values`` over each index box ``(..., n)`` -> ``(...)``; ``-inf`` if empty."""
    return range_extreme(values, start, length, spec, "max")
