"""Input validation helpers: every public constructor checks its input before any heavy work."""

from __future__ import annotations

import numpy as np


def as_vector(value, name: str, *, dim: int | None = None, dtype=np.float64) -> np.ndarray:
    """``value`` as a finite 1-D float64 array of length ``dim`` (if given), else ValueError."""
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be array-like of numbers, got {type(value).__name__}") from exc
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array, got shape {arr.shape}")
    if dim is not None and arr.shape[0] != dim:
        raise ValueError(f"{name} must have length {dim}, got {arr.shape[0]}")
    if arr.shape[0] == 0:
        raise ValueError(f"{name} must not be empty")
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


def check_low_high(low: np.ndarray, high: np.ndarray, what: str) -> None:
    if low.shape != high.shape:
        raise ValueError(f"{what}: low and high must have the same shape, got {low.shape} and {high.shape}")
    bad = np.flatnonzero(~(low < high))
    if bad.size:
        raise ValueError(f"{what}: need low < high in every dimension; fails in dimension(s) {bad.tolist()} "
                         f"(low={low.tolist()}, high={high.tolist()})")


def as_cell_counts(cells, dim: int, name: str = "cells") -> np.ndarray:
    """Positive integer cell counts per dimension (a scalar is broadcast)."""
    arr = np.asarray(cells)
    if arr.ndim == 0:
        arr = np.full(dim, arr)
    if arr.shape != (dim,):
        raise ValueError(f"{name} must be an int or have length {dim}, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        if not np.all(np.equal(np.mod(arr, 1), 0)):
            raise TypeError(f"{name} must be integers, got {arr.tolist()}")
        arr = arr.astype(np.int64)
    if np.any(arr <= 0):
        raise ValueError(f"{name} must be positive, got {arr.tolist()}")
    return arr.astype(np.int64)
