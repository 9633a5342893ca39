"""Labelled regions: each atomic proposition is a union of boxes of the state space.

A region's boxes are closed (``Region(boxes)``, like reach boxes) or open
(``Region(boxes, closed=False)``, like avoid boxes: their faces do not belong to them). On a
``StateGrid`` every cell gets the set of letters its points can carry:

* a cell **inside** a box of the region (the cell's points all lie in it, decided exactly on the
  half-open cell faces) has the proposition;
* a cell that **misses** the region (no point in common) does not;
* a cell that lies **partly** inside (some points in, some out; also a cell covered by a union of
  boxes but by none of them alone) may have it or not: both letters are possible, and the
  product synthesis lets the adversary pick the letter, the worst for p_low and the best for
  p_up. Such cells are counted, and ``labelling`` warns with their number.

So a grid-aligned region (faces on cell faces, written as decimals or not: the tests are exact)
labels every cell exactly, and the guarantees hold for the true regions in every case.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping, Sequence

import jax.numpy as jnp
import numpy as np

from ..errors import as_vector, check_low_high
from ..partition import StateGrid

FACES = ("exact", "interior")


@dataclasses.dataclass(frozen=True, eq=False)
class Region:
    """A union of boxes, closed (default) or open.

    Args:
        boxes: a sequence of ``(low, high)`` pairs of ``(n,)`` corners (as ``StateGrid``'s reach
            and avoid boxes: ``[([0.2, 0.2], [0.4, 0.4])]`` is one box).
        closed: ``True``: every box is closed (its faces belong to the region); ``False``: open
            (an obstacle whose faces are safe, as ``StateGrid``'s avoid boxes).
    """

    low: np.ndarray
    high: np.ndarray
    closed: bool

    def __init__(self, boxes, closed: bool = True):
        boxes = list(zip(boxes.low, boxes.high)) if isinstance(boxes, Region) else list(boxes)
        lows, highs = [], []
        for i, box in enumerate(boxes):
            try:
                lo, hi = box
            except (TypeError, ValueError) as exc:
                raise ValueError(f"box {i} must be a pair (low, high), got {box!r}") from exc
            lo = as_vector(lo, f"box {i} low")
            hi = as_vector(hi, f"box {i} high", dim=lo.shape[0])
            check_low_high(lo, hi, f"box {i}")
            lows.append(lo)
            highs.append(hi)
        if not lows:
            raise ValueError("a region needs at least one box")
        if len({lo.shape[0] for lo in lows}) != 1:
            raise ValueError("all boxes of a region must have the same dimension")
        object.__setattr__(self, "low", np.stack(lows))
        object.__setattr__(self, "high", np.stack(highs))
        object.__setattr__(self, "closed", bool(closed))

    @property
    def n(self) -> int:
        return int(self.low.shape[1])

    def contains(self, x):
        """Whether points ``x: (..., n)`` lie in the region (closed or open boxes), ``(...)`` bool."""
        x = jnp.asarray(x)[..., None, :]
        lo, hi = jnp.asarray(self.low), jnp.asarray(self.high)
        inside = ((x >= lo) & (x <= hi)) if self.closed else ((x > lo) & (x < hi))
        return jnp.any(jnp.all(inside, axis=-1), axis=-1)

    def __repr__(self):
        return f"Region({self.low.shape[0]} {'closed' if self.closed else 'open'} box(es), n={self.n})"


def as_regions(regions: Mapping) -> dict[str, Region]:
    """``{name: Region}`` from ``{name: Region | boxes}`` (boxes are closed)."""
    if not isinstance(regions, Mapping):
        raise TypeError(f"regions must map proposition names to boxes, got {type(regions).__name__}")
    return {str(k): (v if isinstance(v, Region) else Region(v)) for k, v in regions.items()}


def _dimension_tests(c, e, e_incl, a, b, closed: bool):
    """Per dimension: whether the cell interval [c, e) (or [c, e] where ``e_incl``) meets the box
    interval [a, b] (or (a, b) when not ``closed``), and whether it lies inside it. Exact
    comparisons; shapes broadcast (cells x boxes)."""
    a_incl = b_incl = closed
    lo = np.maximum(c, a)
    lo_incl = np.where(c > a, True, a_incl)  # c is always included; at c == a both must be
    hi = np.minimum(e, b)
    hi_incl = np.where(e < b, e_incl, np.where(e > b, b_incl, e_incl & b_incl))
    meets = (lo < hi) | ((lo == hi) & lo_incl & hi_incl)
    inside = ((a < c) | ((a == c) & a_incl)) & ((e < b) | ((e == b) & (b_incl | ~e_incl)))
    return meets, inside


def cell_membership(grid: StateGrid, region: Region, faces: str = "exact") -> tuple[np.ndarray, np.ndarray]:
    """``(inside, meets)``, each ``(N,)`` bool: the cell lies inside one box of the region / has a
    point in common with the region, decided exactly on the half-open cells of ``grid``.

    ``faces="interior"``: the same for the cell's interior and the box's closure (the cell's
    closure lies in the closed box / their interiors overlap), i.e. up to the faces, whatever
    the box's ``closed``."""
    if faces not in FACES:
        raise ValueError(f"faces must be one of {FACES}, got {faces!r}")
    cells = np.arange(grid.num_cells)
    lo, hi = (np.asarray(b) for b in grid.cell_bounds(cells))  # (N, n)
    attained = np.asarray(grid.upper_attained(cells))  # (N, n)
    meets = np.ones((grid.num_cells, region.low.shape[0]), bool)
    inside = np.ones_like(meets)
    for d in range(grid.n):  # a loop over dimensions; cells and boxes are vectorized
        c, e, a, b = lo[:, d, None], hi[:, d, None], region.low[None, :, d], region.high[None, :, d]
        if faces == "exact":
            m, i = _dimension_tests(c, e, attained[:, d, None], a, b, region.closed)
        else:
            m, i = (np.maximum(c, a) < np.minimum(e, b)), (a <= c) & (e <= b)
        meets &= m
        inside &= i
    return np.any(inside, axis=1), np.any(meets, axis=1)


def check_inside_grid(grid: StateGrid, name: str, region: Region) -> None:
    """ValueError unless every box of ``region`` lies in the closed grid box of ``grid``."""
    if region.n != grid.n:
        raise ValueError(f"region {name!r} has boxes of dimension {region.n}, the grid has dimension {grid.n}")
    outside = np.any((region.low < grid.low) | (region.high > grid.high), axis=1)
    if np.any(outside):
        i = int(np.flatnonzero(outside)[0])
        raise ValueError(f"region {name!r}: box {i} ({region.low[i].tolist()}, {region.high[i].tolist()}) is not "
                         f"inside the grid box ({grid.low.tolist()}, {grid.high.tolist()})")


@dataclasses.dataclass(frozen=True, eq=False)
class Labelling:
    """The possible letters of every cell of a grid.

    Attributes:
        propositions: the proposition names, bit ``i`` of a letter is ``propositions[i]``.
        letters: ``(N, L)`` int32 possible letters of every cell (padded by repeating the first);
            ``L = 1`` when no cell is mixed.
        count: ``(N,)`` number of distinct possible letters of each cell (1: labelled exactly).
        mixed: ``(N,)`` bool, the cells that lie partly inside some region (in a set of positive
            volume; a cell that only shares a face with a region can have two letters too).
    """

    propositions: tuple[str, ...]
    letters: np.ndarray
    count: np.ndarray
    mixed: np.ndarray

    @property
    def occurring(self) -> np.ndarray:
        """The distinct letters some cell can carry."""
        return np.unique(self.letters)


def labelling(grid: StateGrid, regions: Mapping[str, Region], propositions: Sequence[str], *,
              faces: str = "exact", warn: bool = True) -> Labelling:
    """The possible letters of every cell of ``grid`` (see the module docstring).

    Args:
        grid: the state grid.
        regions: ``{name: Region}``; every proposition needs one, and every box must lie inside
            the grid box.
        propositions: the alphabet, in bit order.
        faces: ``"exact"`` (the letters of every point of the cell) or ``"interior"`` (of the
            cell's interior points: a face shared by a cell and a region counts as the cell's;
            see ``Specification``).
        warn: warn (``UserWarning``) with the number of cells that lie partly inside a region
            (in a set of positive volume: a cell that only shares a face with a region, exactly
            mixed on that face, is not counted).
    """
    props = tuple(propositions)
    missing = [p for p in props if p not in regions]
    if missing:
        raise ValueError(f"propositions {missing} have no region; regions are given for {sorted(regions)}")
    for name in props:
        check_inside_grid(grid, name, regions[name])
    fixed = np.zeros(grid.num_cells, np.int64)
    uncertain = np.zeros((grid.num_cells, len(props)), bool)
    partly = np.zeros((grid.num_cells, len(props)), bool)  # mixed in a set of positive volume
    for i, name in enumerate(props):  # a loop over propositions; cells are vectorized
        inside, meets = cell_membership(grid, regions[name], faces)
        fixed |= inside.astype(np.int64) << i
        uncertain[:, i] = meets & ~inside
        if faces == "exact":
            inside, meets = cell_membership(grid, regions[name], "interior")
        partly[:, i] = meets & ~inside
    k = uncertain.sum(axis=1)
    width = 1 << int(k.max(initial=0))
    m = np.arange(width)[None, :] % (1 << k)[:, None]  # the subsets of each cell's uncertain bits
    letters = np.repeat(fixed[:, None], width, axis=1)
    seen = np.zeros(grid.num_cells, np.int64)
    for i in range(len(props)):
        take = uncertain[:, i]
        bit = (m >> seen[:, None]) & 1
        letters |= np.where(take[:, None] & (bit == 1), 1 << i, 0)
        seen += take
    mixed = partly.any(axis=1)
    if warn and mixed.any():
        names = [p for i, p in enumerate(props) if partly[:, i].any()]
        warnings.warn(f"{int(mixed.sum())} of {grid.num_cells} cells lie partly inside the region(s) {names}: "
                      f"they are labelled conservatively (the worst of their possible letters for p_low, the "
                      f"best for p_up). Grid-aligned regions, or a finer grid, avoid this.", stacklevel=3)
    return Labelling(propositions=props, letters=letters.astype(np.int32), count=(1 << k).astype(np.int32),
                     mixed=mixed)


def point_letters(regions: Sequence[Region], x):
    """``(...)`` int32 letters of points ``x: (..., n)`` (already wrapped): bit i set when ``x``
    lies in ``regions[i]``. JAX, jittable."""
    letter = jnp.zeros(jnp.shape(x)[:-1], jnp.int32)
    for i, region in enumerate(regions):  # a loop over propositions
        letter = letter | (region.contains(x).astype(jnp.int32) << i)
    return letter
