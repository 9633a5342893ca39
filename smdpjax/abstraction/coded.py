"""Float arrays stored as small integer codes into a table of their distinct values.

Lemma 1's bounds are sums of noise-cell probabilities over which cells a box meets, so on
regular systems a few values repeat across millions of entries (the 2-room temperature row of
Table 1: 12 distinct upper bounds in 4 800 slots). ``encode`` stores such an array as ``uint8``
(or, on request, ``uint16``) codes and the table of its values, exactly (no value is rounded:
decoding gives the same floats bit for bit), and only where that takes fewer bytes; ``decoded``
reads either form. The inner problems decode a block of rows at a time
(``imdp_compact.in_row_blocks``), from a table that stays in the cache.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass

# Distinct values a table holds by default: uint8 codes, hashes that stay in the cache. Up to
# 2^16 (uint16 codes) on request: 45 M entries took 1.0 s to look up among 20 000 values (a
# table that leaves the cache) against 0.2 s among 39.
MAX_CODES = 1 << 8
# Entries of the strided samples ``encode`` builds its table from before it looks up every entry.
_SAMPLES = (1 << 16, 1 << 20)
# Up to this many entries the look-up runs in NumPy (no compilation for each new size).
_HOST_LOOKUP = 1 << 20
# The look-up hashes into at most 2^_HASH_BITS slots per level (8 MB of uint16).
_HASH_BITS = 22


@pytree_dataclass
class Coded:
    """Attributes:
        codes: ``(...)`` uint8/uint16 index of each entry's value in ``table``.
        table: ``(U,)`` the distinct values (ordered by their bit patterns).
    """

    codes: jax.Array
    table: jax.Array

    @property
    def shape(self) -> tuple:
        return tuple(self.codes.shape)

    @property
    def ndim(self) -> int:
        return len(self.codes.shape)

    @property
    def dtype(self):
        return self.table.dtype

    def decode(self) -> jax.Array:
        """The array itself: ``table[codes]``."""
        return self.table[self.codes.astype(jnp.int32)]

    def map_codes(self, fn) -> "Coded":
        """The coded array of ``fn`` applied to the array, for ``fn`` that only moves or picks
        entries (slices, ``take_along_axis``): applied to the codes, the table kept."""
        return Coded(codes=fn(self.codes), table=self.table)

    def __repr__(self):
        return f"Coded(shape={self.shape}, {self.table.shape[0]} values, codes {self.codes.dtype})"


def encode(x, max_codes: int = MAX_CODES):
    """``x`` as a ``Coded`` array where that is smaller (at most ``max_codes`` distinct values,
    at most 2^16; codes narrower than ``x``'s entries), otherwise ``x`` unchanged. Needs a
    concrete float64 ``x``.

    Values are told apart by their bits (decoding returns every entry bit for bit). The table is
    found from a strided sample of the entries and completed with the values the sample missed,
    so a large array is never sorted whole: each entry is looked up through a few levels of
    multiplicative hashes that together separate the table's values (``_hash_levels``)."""
    if max_codes > 1 << 16:
        raise ValueError(f"max_codes must be at most 65536 (uint16 codes), got {max_codes}")
    if not hasattr(x, "dtype") or x.dtype != jnp.float64 or x.size == 0 or isinstance(x, jax.core.Tracer):
        return x  # not a concrete float64 array (traced: under jit the values are unknown)
    x = jnp.asarray(x)
    host_bits = np.asarray(x).reshape(-1).view(np.uint64)  # no copy on the CPU
    if x.size <= _SAMPLES[0]:  # small: one sort of all entries
        table, codes = np.unique(host_bits, return_inverse=True)
        return _coded(x, table, codes) if table.size <= max_codes else x
    table = np.zeros(0, np.uint64)
    for sample in _SAMPLES + (x.size, x.size):  # ever larger strided samples, then all entries
        whole = sample >= x.size
        bits = host_bits if whole else host_bits[::max(1, x.size // sample)]
        codes, missed, any_missed = _lookup(bits, x if whole else None, table)
        if not any_missed:
            if whole:
                break
            continue
        table = np.union1d(table, bits[np.asarray(missed).reshape(-1)])
        if table.size > max_codes:
            return x
    else:  # pragma: no cover - the second pass over all entries finds every value in the table
        return x
    return _coded(x, table, codes)


def _coded(x, table_bits, codes):
    """``x`` as codes ``(n,)`` (host or device) into ``table_bits`` (sorted), where smaller."""
    code_dtype = np.uint8 if table_bits.size <= 256 else np.uint16
    if x.size * np.dtype(code_dtype).itemsize + table_bits.nbytes >= x.nbytes:
        return x
    values = jnp.asarray(table_bits.view(np.float64))
    if isinstance(codes, np.ndarray):  # converted and shaped on the host: no device programs
        return Coded(codes=jnp.asarray(codes.astype(code_dtype).reshape(x.shape)), table=values)
    return Coded(codes=jnp.asarray(codes, code_dtype).reshape(x.shape), table=values)


# Odd 64-bit multipliers tried for a hash that separates a table's values (splitmix64's, golden ratio).
_MULTIPLIERS = (0x9E3779B97F4A7C15, 0xBF58476D1CE4E5B9, 0x94D049BB133111EB, 0xC2B2AE3D27D4EB4F,
                0xFF51AFD7ED558CCD, 0xC4CEB9FE1A85EC53, 0x165667B19E3779F9, 0xD6E8FEB86659FD93)


def _lookup(bits, flat, table_bits):
    """``(codes (n,), missed (n,), any missed)``: the index of each of the bit patterns ``bits
    (n,)`` (host) in ``table_bits`` (sorted) and which are not in the table. Large arrays
    (``flat``, the same entries as a device array) are looked up in one compiled pass through the
    hashes of ``_hash_levels``, else by a binary search."""
    size = int(table_bits.size)
    if size == 0:
        return None, np.ones(bits.shape, bool), True
    if flat is None or bits.size <= _HOST_LOOKUP:
        bits = bits.reshape(-1)
        codes = np.minimum(np.searchsorted(table_bits, bits), size - 1)
        missed = table_bits[codes] != bits
        return codes, missed, bool(missed.any())
    levels = _hash_levels(table_bits)
    if levels is None:
        codes, missed, any_missed = _search_codes(flat, jnp.asarray(table_bits))
    else:
        mults, luts = zip(*levels)
        shift = 64 - int(np.log2(luts[0].size))
        codes, missed, any_missed = _hash_codes(flat, jnp.asarray(table_bits), tuple(jnp.asarray(lut) for lut in luts),
                                                tuple(np.uint64(m) for m in mults), shift)
    return codes, missed, bool(any_missed)


def _hash_levels(table_bits):
    """``[(multiplier, lut)]``: each value of ``table_bits`` in the slot of exactly one level's
    table ``lut`` (its code there), where no other value still unplaced at that level hashes
    (``(bits * multiplier) >> shift``); ``None`` if ``_MULTIPLIERS`` run out first."""
    size = table_bits.size
    bits = min(_HASH_BITS, 2 * max(size - 1, 1).bit_length() + 1)
    shift = np.uint64(64 - bits)
    left = np.arange(size)
    levels = []
    for mult in _MULTIPLIERS:
        slots = (table_bits[left] * np.uint64(mult)) >> shift
        _, first, counts = np.unique(slots, return_index=True, return_counts=True)
        alone = first[counts == 1]
        lut = np.zeros(1 << bits, np.uint16)
        lut[slots[alone]] = left[alone]
        levels.append((mult, lut))
        left = np.delete(left, alone)
        if left.size == 0:
            return levels
    return None


@functools.partial(jax.jit, static_argnums=4)
def _hash_codes(flat, table_bits, luts, mults, shift: int):
    bits = jax.lax.bitcast_convert_type(flat, jnp.uint64)
    codes = jnp.zeros(bits.shape, jnp.int32)
    found = jnp.zeros(bits.shape, bool)
    for lut, mult in zip(luts, mults):  # the first level whose slot holds the entry's value
        code = lut[((bits * mult) >> np.uint64(shift)).astype(jnp.int32)].astype(jnp.int32)
        hit = ~found & (table_bits[code] == bits)
        codes, found = jnp.where(hit, code, codes), found | hit
    return codes, ~found, ~jnp.all(found)


@jax.jit
def _search_codes(flat, table_bits):
    bits = jax.lax.bitcast_convert_type(flat, jnp.uint64)
    codes = jnp.minimum(jnp.searchsorted(table_bits, bits), table_bits.shape[0] - 1).astype(jnp.int32)
    missed = table_bits[codes] != bits
    return codes, missed, jnp.any(missed)


def decoded(x) -> jax.Array:
    """``x`` as a plain array (a ``Coded`` decoded, anything else unchanged)."""
    return x.decode() if isinstance(x, Coded) else x


def map_entries(x, fn):
    """``fn`` (a slice or pick of entries) applied to ``x``, coded or not."""
    return x.map_codes(fn) if isinstance(x, Coded) else fn(x)
