"""The phi-conservative state partition: a uniform grid of boxes over the safe box plus a sink.

Flat cell indices are C order over ``cells``; index ``num_cells`` is the sink state s_avoid
(everything outside the grid box). Every grid cell carries a label:

* ``REACH``: the cell lies inside a reach box (it is in S_reach, absorbing with value 1);
* ``AVOID``: the cell overlaps an avoid box in a set of positive volume (absorbing, value 0);
* ``NONTERMINAL``: every other cell (S_nt in the paper).

Cells are half-open boxes: along dimension i, cell k is ``[e_k, e_{k+1})`` with the faces
``e = edges[i]`` held as explicit float64 arrays (``e_k`` is the float nearest to
``low + k (high - low) / cells``, computed with exact rationals), except that the last cell is
closed at ``high`` (periodic dimensions: ``high`` is ``low`` again, in cell 0). So the cells
partition the grid box exactly and "a point lies on a face" is decided by exact comparison with
``edges``; a face at a decimal such as 0.4 (30 cells over [0, 1]) is the float a user types.
(Jitted code reads the faces from the table: XLA's float division is not correctly rounded on
the CPU, so a face recomputed as ``k * span / cells`` may differ from it by an ulp.)

Regions: reach boxes are closed, avoid boxes are open (their faces are safe), the grid box is
closed. A cell is a reach cell iff its closure lies inside a reach box, an avoid cell iff it meets
the interior of an avoid box; both tests are exact comparisons with the edges, so a grid-aligned
region written as decimal literals (0.4 on a grid of 30 cells over [0, 1]) labels exactly the
cells it covers.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from fractions import Fraction

import jax.numpy as jnp
import numpy as np

from ..errors import as_cell_counts, as_vector, check_low_high

NONTERMINAL, REACH, AVOID = 0, 1, 2


def _as_boxes(boxes, n: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """A sequence of ``(low, high)`` pairs as two arrays ``(k, n)``."""
    if boxes is None:
        boxes = ()
    lows, highs = [], []
    for i, box in enumerate(boxes):
        try:
            low, high = box
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{what}[{i}] must be a pair (low, high)") from exc
        low = as_vector(low, f"{what}[{i}] low", dim=n)
        high = as_vector(high, f"{what}[{i}] high", dim=n)
        check_low_high(low, high, f"{what}[{i}]")
        lows.append(low)
        highs.append(high)
    shape = (len(lows), n)
    return (np.array(lows).reshape(shape), np.array(highs).reshape(shape))


def _edges(low: float, high: float, cells: int, dim: int) -> np.ndarray:
    """``(cells + 1,)`` faces: the float nearest to ``low + k (high - low) / cells`` (exact
    rationals, so ``edges[0] = low``, ``edges[-1] = high`` and grid-aligned decimals match)."""
    a, span = Fraction(low), Fraction(high) - Fraction(low)
    e = np.array([float(a + span * k / cells) for k in range(cells + 1)])
    if not np.all(np.diff(e) > 0):
        raise ValueError(f"StateGrid: {cells} cells over [{low}, {high}] in dimension {dim} are narrower than "
                         f"float64 can separate; use fewer cells")
    return e


def _require_labels_memory(cells: np.ndarray, regions: int) -> None:
    """Refuse a grid whose per-cell arrays (faces of every cell, region tests, labels) would not
    fit, before computing them."""
    from ..memory import require

    count, n = float(np.prod(cells.astype(np.float64))), int(cells.size)
    per_cell = 2 * 8 * n + 8 + 1 + 2 * max(regions, 1) * n  # faces, index, label, region tests
    require(count * per_cell, f"StateGrid with {count:.3g} cells ({' x '.join(str(int(c)) for c in cells)})",
            "use fewer cells per dimension")


@dataclasses.dataclass(frozen=True, eq=False)
class StateGrid:
    """Uniform grid over the safe box ``[low, high]`` with reach and avoid boxes.

    Args:
        low, high: ``(n,)`` corners of the grid box (the safe set before obstacles).
        cells: cells per dimension, an int or ``(n,)`` positive ints.
        reach: sequence of ``(low, high)`` boxes making up X_reach; must lie inside the grid box.
        avoid: sequence of ``(low, high)`` boxes of obstacles inside the grid box (everything
            outside the grid box is avoided anyway: it is the sink state).
        periodic: ``(n,)`` bools (or None): dimension i wraps around with period
            ``high[i] - low[i]`` (a heading in [0, 2 pi), say). Points are taken modulo the period
            and reachable boxes that cross the seam meet the cells on both sides.
    """

    low: np.ndarray
    high: np.ndarray
    cells: np.ndarray
    reach_boxes: tuple[np.ndarray, np.ndarray]
    avoid_boxes: tuple[np.ndarray, np.ndarray]
    periodic: np.ndarray
    labels: np.ndarray
    edges: tuple

    def __init__(self, low, high, cells, reach: Sequence = (), avoid: Sequence = (), periodic=None):
        low = as_vector(low, "StateGrid low")
        n = low.shape[0]
        high = as_vector(high, "StateGrid high", dim=n)
        check_low_high(low, high, "StateGrid")
        cells = as_cell_counts(cells, n)
        periodic = np.zeros(n, bool) if periodic is None else np.asarray(periodic, bool).reshape(-1)
        if periodic.shape != (n,):
            raise ValueError(f"periodic must have length {n}, got {periodic.shape}")
        reach_boxes = _as_boxes(reach, n, "reach")
        avoid_boxes = _as_boxes(avoid, n, "avoid")
        edges = tuple(_edges(float(a), float(b), int(k), i) for i, (a, b, k) in enumerate(zip(low, high, cells)))
        r_lo, r_hi = reach_boxes
        outside = np.any((r_lo < low) | (r_hi > high), axis=1)
        if np.any(outside):
            i = int(np.flatnonzero(outside)[0])
            raise ValueError(f"reach box {i} ({r_lo[i].tolist()}, {r_hi[i].tolist()}) is not inside the safe "
                             f"grid box ({low.tolist()}, {high.tolist()}): X_reach must be a subset of X_safe")
        a_lo, a_hi = avoid_boxes
        overlap = np.all((r_lo[:, None] < a_hi[None]) & (r_hi[:, None] > a_lo[None]), axis=2)
        if np.any(overlap):
            i, j = map(int, np.argwhere(overlap)[0])
            raise ValueError(f"reach box {i} overlaps avoid box {j}: X_reach must be a subset of X_safe")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)
        object.__setattr__(self, "cells", cells)
        object.__setattr__(self, "reach_boxes", reach_boxes)
        object.__setattr__(self, "avoid_boxes", avoid_boxes)
        object.__setattr__(self, "periodic", periodic)
        object.__setattr__(self, "edges", edges)
        _require_labels_memory(cells, len(r_lo) + len(a_lo))
        object.__setattr__(self, "labels", self._compute_labels())

    # -- geometry ---------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return int(self.low.shape[0])

    @property
    def num_cells(self) -> int:
        """Number of grid cells; the sink has index ``num_cells``."""
        return int(np.prod(self.cells))

    @property
    def num_states(self) -> int:
        """|S| as the paper counts it: grid cells plus the sink."""
        return self.num_cells + 1

    @property
    def sink(self) -> int:
        return self.num_cells

    @property
    def width(self) -> np.ndarray:
        """``(n,)`` nominal cell widths ``(high - low) / cells`` (the faces are ``edges``)."""
        return (self.high - self.low) / self.cells

    def cell_bounds(self, index):
        """Boxes of flat cell indices ``index: (...)``: returns ``(low, high)``, each ``(..., n)``,
        the faces ``edges`` of the half-open cells (``high`` excluded except on the last cell of a
        non-periodic dimension).

        NumPy arrays for concrete (NumPy / Python) indices, JAX arrays for JAX ones (traced
        included), with identical values."""
        xp = np if isinstance(index, (np.ndarray, np.integer, int, list, tuple)) else jnp
        multi = xp.unravel_index(xp.asarray(index), tuple(self.cells.tolist()))
        lo = xp.stack([xp.asarray(e)[m] for e, m in zip(self.edges, multi)], axis=-1)
        hi = xp.stack([xp.asarray(e)[m + 1] for e, m in zip(self.edges, multi)], axis=-1)
        return lo, hi

    def upper_attained(self, index):
        """``(..., n)`` bool: the cell's upper face belongs to it (last cell of a non-periodic
        dimension), so ``cell_bounds(index)[1]`` is a maximum rather than a supremum."""
        xp = np if isinstance(index, (np.ndarray, np.integer, int, list, tuple)) else jnp
        multi = xp.stack(xp.unravel_index(xp.asarray(index), tuple(self.cells.tolist())), axis=-1)
        return (multi + 1 == self.cells) & ~self.periodic

    def face(self, d: int, k):
        """``edges[d][k]`` for integer arrays ``k`` in ``[0, cells[d]]`` (jit-friendly)."""
        return jnp.asarray(self.edges[d])[k]

    def dimension_index(self, x, d: int):
        """Cell index along dimension ``d`` of coordinates ``x: (...)`` already wrapped and inside
        ``[low[d], high[d]]``: the k with ``edges[d][k] <= x < edges[d][k + 1]`` (k = cells - 1 at
        ``high``). Exact (see `dimension_cell`)."""
        return self.dimension_cell(x, d)[0]

    def dimension_cell(self, x, d: int):
        """``(k, x == edges[d][k])`` for coordinates ``x: (...)`` inside ``[low[d], high[d]]``:
        the cell index of `dimension_index` and whether x lies on that cell's lower face.

        An estimate from the nominal width (off by at most one cell) corrected by exact comparison
        with the faces around it."""
        last = int(self.cells[d]) - 1
        guess = jnp.clip(jnp.floor((x - self.low[d]) * (1.0 / self.width[d])), 0, last).astype(jnp.int32)
        faces = jnp.asarray(self._face_windows[d])  # e_{k-1}, e_k, e_{k+1} at k + 0, 1, 2
        below, at, above = faces[guess], faces[guess + 1], faces[guess + 2]
        down = x < at
        up = (x >= above) & (guess < last)
        k = guess - down.astype(jnp.int32) + up.astype(jnp.int32)
        face = jnp.where(down, below, jnp.where(up, above, at))
        return k, x == face

    @functools.cached_property
    def _face_windows(self) -> tuple:
        """Per dimension the faces with -inf in front: ``(cells + 2,)``."""
        return tuple(np.concatenate([[-np.inf], e]) for e in self.edges)

    def wrap(self, x):
        """Points ``(..., n)`` with periodic coordinates brought into ``[low, high)``."""
        x = jnp.asarray(x)
        period = self.high - self.low
        wrapped = self.low + jnp.mod(x - self.low, period)
        wrapped = jnp.where(wrapped >= self.high, self.low, wrapped)  # rounded up to high: that is low
        return jnp.where(self.periodic, wrapped, x)

    def locate(self, x):
        """Flat cell index of each point ``x: (..., n)``, -1 outside the grid box (or NaN).

        Returns ``(...)`` int32. A point on a face shared by two cells belongs to the upper one
        (half-open cells); a point on the grid box's upper boundary to the last cell.
        """
        x = jnp.asarray(x)
        if x.ndim == 0 or x.shape[-1] != self.n:
            raise ValueError(f"locate: points must have shape (..., {self.n}), got {x.shape}")
        x = self.wrap(x)
        inside = jnp.all((x >= self.low) & (x <= self.high), axis=-1)
        multi = [self.dimension_index(x[..., d], d) for d in range(self.n)]
        flat = jnp.ravel_multi_index(tuple(multi), tuple(self.cells.tolist()), mode="clip")
        return jnp.where(inside, flat, -1).astype(jnp.int32)

    def cell_centers(self, index=None):
        """Centres ``(k, n)`` of the given flat cells (all cells by default)."""
        index = np.arange(self.num_cells) if index is None else index
        lo, hi = self.cell_bounds(index)
        return (lo + hi) / 2

    # -- specification ----------------------------------------------------------------------
    def _compute_labels(self) -> np.ndarray:
        lo, hi = (np.asarray(b) for b in self.cell_bounds(np.arange(self.num_cells)))
        labels = np.full(self.num_cells, NONTERMINAL, np.int8)
        r_lo, r_hi = self.reach_boxes
        inside_reach = np.all((lo[:, None] >= r_lo[None]) & (hi[:, None] <= r_hi[None]), axis=2)
        labels[np.any(inside_reach, axis=1)] = REACH
        a_lo, a_hi = self.avoid_boxes
        meets_avoid = np.all((lo[:, None] < a_hi[None]) & (hi[:, None] > a_lo[None]), axis=2)
        labels[np.any(meets_avoid, axis=1)] = AVOID
        return labels

    @property
    def state_labels(self) -> np.ndarray:
        """``(num_cells + 1,)`` labels including the sink (``AVOID``)."""
        return np.append(self.labels, np.int8(AVOID))

    @property
    def nonterminal(self) -> np.ndarray:
        """Flat indices of S_nt (safe, not reach), ascending."""
        return np.flatnonzero(self.labels == NONTERMINAL)

    def in_reach(self, x):
        """Whether points ``x: (..., n)`` lie in X_reach (the closed reach boxes; the true sets,
        not the cells)."""
        return self._in_boxes(self.wrap(x), self.reach_boxes, closed=True)

    def in_avoid(self, x):
        """Whether points ``x: (..., n)`` lie in X_avoid: outside the (closed) grid box, NaN, or in
        the interior of an avoid box."""
        x = self.wrap(x)
        outside = ~jnp.all((x >= self.low) & (x <= self.high), axis=-1) | jnp.any(jnp.isnan(x), axis=-1)
        return outside | self._in_boxes(x, self.avoid_boxes, closed=False)

    @staticmethod
    def _in_boxes(x, boxes, closed: bool):
        lo, hi = boxes
        if lo.shape[0] == 0:
            return jnp.zeros(x.shape[:-1], bool)
        x = x[..., None, :]
        inside = (x >= lo) & (x <= hi) if closed else (x > lo) & (x < hi)
        return jnp.any(jnp.all(inside, axis=-1), axis=-1)

    def __repr__(self):
        counts = np.bincount(self.labels, minlength=3)
        per = "x".join(map(str, self.cells.tolist()))
        wrap = f", periodic={np.flatnonzero(self.periodic).tolist()}" if self.periodic.any() else ""
        return (f"StateGrid(n={self.n}, cells={per}, |S|={self.num_states} "
                f"(nonterminal={counts[NONTERMINAL]}, reach={counts[REACH]}, avoid={counts[AVOID]} + sink){wrap})")
