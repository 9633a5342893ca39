"""Float arrays stored as small integer codes into a table of their distinct values.

Lemma 1's bounds are sums of noise-cell probabilities over which cells a box meets, so on
regular systems a few values repeat across millions of entries (the 2-room temperature row of
Table 1: 12 distinct upper bounds in 4 800 slots). ``encode`` stores such an array as ``uint8``
or ``uint16`` codes and the sorted table of its values, exactly (no value is rounded: decoding
gives the same floats bit for bit), and only where that takes fewer bytes; ``decoded`` reads
either form. The inner problems decode a block of rows at a time (``imdp_compact.in_row_blocks``),
from a table that stays in the cache.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass

# Distinct values a table may hold (codes in uint16 at most).
MAX_CODES = 1 << 16


@pytree_dataclass
class Coded:
    """Attributes:
        codes: ``(...)`` uint8/uint16 index of each entry's value in ``table``.
        table: ``(U,)`` the distinct values, increasing.
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
    codes narrower than ``x``'s entries), otherwise ``x`` unchanged. Needs a concrete ``x``."""
    host = np.asarray(x)
    if host.size == 0 or host.dtype.kind != "f":
        return x
    table, codes = np.unique(host, return_inverse=True)  # NaN-free: bounds are checked upstream
    if table.size > max_codes:
        return x
    code_dtype = np.uint8 if table.size <= 256 else np.uint16
    coded_bytes = host.size * np.dtype(code_dtype).itemsize + table.nbytes
    if coded_bytes >= host.nbytes:
        return x
    return Coded(codes=jnp.asarray(codes.reshape(host.shape).astype(code_dtype)), table=jnp.asarray(table))


def decoded(x) -> jax.Array:
    """``x`` as a plain array (a ``Coded`` decoded, anything else unchanged)."""
    return x.decode() if isinstance(x, Coded) else x


def map_entries(x, fn):
    """``fn`` (a slice or pick of entries) applied to ``x``, coded or not."""
    return x.map_codes(fn) if isinstance(x, Coded) else fn(x)
