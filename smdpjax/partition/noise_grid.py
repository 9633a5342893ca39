"""The partition C of the disturbance set W.

Bounded W: a grid of axis-aligned cells (``NoiseGrid.box``). Unbounded W: a grid of the
inf-norm ball ``{w : |w - w0|_inf <= r_W}`` plus one *remainder* cell ``W minus the ball``
(``NoiseGrid.ball``). The remainder's reachable set is unbounded: it reaches every state and the
sink, so abstractions treat it as a cluster equal to the whole state space instead of storing it.
Grids need not be uniform (``NoiseGrid.from_edges``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import as_cell_counts, as_vector, check_low_high
from ..noise import Distribution


@jax.jit
def cell_boxes(edges: Sequence) -> tuple:
    """Boxes of the product grid with per-axis ``edges[i]: (k_i + 1,)``, C order.

    Returns ``(low, high)``, each ``(prod k_i, d)``. Works on traced edges (differentiable).
    """
    lows = jnp.meshgrid(*[jnp.asarray(e)[:-1] for e in edges], indexing="ij")
    highs = jnp.meshgrid(*[jnp.asarray(e)[1:] for e in edges], indexing="ij")
    return (jnp.stack([g.reshape(-1) for g in lows], axis=-1),
            jnp.stack([g.reshape(-1) for g in highs], axis=-1))


def cell_probabilities(distribution: Distribution, edges: Sequence, remainder: bool):
    """``(P_W(c) for bounded cells (C_b,), P_W(remainder) scalar)``; differentiable in both inputs.

    Compiled when the distribution is a PyTree (``Gaussian``): one call instead of dozens of
    small dispatched operations, which dominate the abstraction of small systems.
    """
    if jax.tree_util.treedef_is_leaf(jax.tree_util.tree_structure(distribution)):
        return _cell_probabilities(distribution, edges, remainder)
    return _cell_probabilities_jit(distribution, edges, remainder)


def _cell_probabilities(distribution: Distribution, edges: Sequence, remainder: bool):
    low, high = cell_boxes(edges)
    probs = distribution.box_probability(low, high)
    if remainder:
        outer_lo = jnp.stack([jnp.asarray(e)[0] for e in edges])
        outer_hi = jnp.stack([jnp.asarray(e)[-1] for e in edges])
        rest = distribution.outside_probability(outer_lo, outer_hi)
    else:
        rest = jnp.zeros((), probs.dtype)
    return probs, rest


_cell_probabilities_jit = jax.jit(_cell_probabilities, static_argnames="remainder")


def ball_edges(center, radius, cells) -> tuple:
    """Per-axis edges of the uniform grid of the inf-norm ball ``|w - center|_inf <= radius``.

    ``center (d,)``, ``radius`` scalar or ``(d,)``, ``cells`` int or ``(d,)`` ints (static).
    Returns ``d`` arrays ``(k_i + 1,)``, the edges ``NoiseGrid.ball`` uses, as a differentiable
    function of ``center`` and ``radius`` (for gradients and sweeps over the noise partition).
    """
    center = jnp.atleast_1d(jnp.asarray(center, jnp.float64))
    radius = jnp.broadcast_to(jnp.asarray(radius, jnp.float64), center.shape)
    cells = np.broadcast_to(np.asarray(cells, int), center.shape)
    return tuple(center[i] + radius[i] * jnp.linspace(-1.0, 1.0, int(k) + 1) for i, k in enumerate(cells))


def warped_ball_edges(center, radius, logits: Sequence) -> tuple:
    """Per-axis edges of a non-uniform grid of the inf-norm ball, from unconstrained parameters.

    Axis ``i`` has ``k_i = len(logits[i])`` cells whose widths are ``2 radius_i softmax(logits[i])``,
    so the edges are strictly increasing and span ``[center_i - radius_i, center_i + radius_i]``
    for every real ``logits`` (zeros give the uniform ``ball_edges``). Differentiable in all three.
    """
    center = jnp.atleast_1d(jnp.asarray(center, jnp.float64))
    radius = jnp.broadcast_to(jnp.asarray(radius, jnp.float64), center.shape)
    edges = []
    for i, z in enumerate(logits):
        widths = jax.nn.softmax(jnp.asarray(z, jnp.float64))
        unit = jnp.concatenate([jnp.zeros(1), jnp.cumsum(widths)])  # 0 .. 1
        unit = unit.at[-1].set(1.0)  # exactly the ball's face, whatever the rounding of the sum
        edges.append(center[i] + radius[i] * (2.0 * unit - 1.0))
    return tuple(edges)


@dataclasses.dataclass(frozen=True, eq=False)
class NoiseGrid:
    """A partition of W: a product grid given by per-axis edges, and optionally the remainder.

    Attributes:
        edges: tuple of ``d`` increasing arrays ``(k_i + 1,)``.
        remainder: whether the cell ``W minus the grid box`` exists (unbounded W).
    """

    edges: tuple
    remainder: bool

    def __post_init__(self):
        edges = tuple(as_vector(e, f"edges[{i}]") for i, e in enumerate(self.edges))
        for i, e in enumerate(edges):
            if e.shape[0] < 2:
                raise ValueError(f"edges[{i}] needs at least two values (one cell), got {e.shape[0]}")
            if np.any(np.diff(e) <= 0):
                raise ValueError(f"edges[{i}] must be strictly increasing (cells of positive width), got {e}")
        object.__setattr__(self, "edges", edges)

    @classmethod
    def from_edges(cls, edges: Sequence, remainder: bool) -> "NoiseGrid":
        return cls(tuple(edges), bool(remainder))

    @classmethod
    def box(cls, low, high, cells) -> "NoiseGrid":
        """Uniform grid of the bounded set ``W = [low, high]``; ``cells`` per dimension."""
        low = as_vector(low, "NoiseGrid.box low")
        high = as_vector(high, "NoiseGrid.box high", dim=low.shape[0])
        check_low_high(low, high, "NoiseGrid.box")
        cells = as_cell_counts(cells, low.shape[0])
        return cls(tuple(np.linspace(lo, hi, k + 1) for lo, hi, k in zip(low, high, cells)), False)

    @classmethod
    def ball(cls, center, radius, cells) -> "NoiseGrid":
        """Uniform grid of the inf-norm ball of ``radius`` (> 0, scalar or per axis) around
        ``center``, plus the remainder cell ``W minus the ball``."""
        center = as_vector(center, "NoiseGrid.ball center")
        radius = np.broadcast_to(np.asarray(radius, np.float64), center.shape)
        if not np.all(np.isfinite(radius)) or np.any(radius <= 0):
            raise ValueError(f"NoiseGrid.ball radius must be finite and > 0, got {radius}")
        cells = as_cell_counts(cells, center.shape[0])
        return cls(tuple(np.linspace(c - r, c + r, k + 1) for c, r, k in zip(center, radius, cells)), True)

    @property
    def dim(self) -> int:
        return len(self.edges)

    @property
    def shape(self) -> tuple:
        return tuple(e.shape[0] - 1 for e in self.edges)

    @property
    def num_bounded(self) -> int:
        """Number of bounded (grid) cells C_b."""
        return int(np.prod(self.shape))

    @property
    def num_cells(self) -> int:
        """|C| as the paper counts it: grid cells plus the remainder if any."""
        return self.num_bounded + int(self.remainder)

    def boxes(self):
        """``(low, high)`` of the bounded cells, each ``(C_b, d)``."""
        return cell_boxes(self.edges)

    def probabilities(self, distribution: Distribution):
        """``(probs (C_b,), remainder probability)``; they sum to 1 up to rounding.

        Raises ValueError if the grid does not cover the distribution's support and there is
        no remainder cell, since mass would be lost.
        """
        self.check_covers(distribution)
        return cell_probabilities(distribution, self.edges, self.remainder)

    def check_covers(self, distribution: Distribution) -> None:
        if distribution.dim != self.dim:
            raise ValueError(f"noise grid has dimension {self.dim} but the noise distribution has {distribution.dim}")
        if self.remainder:
            return
        s_lo, s_hi = distribution.support()
        lo = np.array([e[0] for e in self.edges])
        hi = np.array([e[-1] for e in self.edges])
        if np.any(s_lo < lo) or np.any(s_hi > hi):
            raise ValueError(
                f"the bounded noise grid [{lo.tolist()}, {hi.tolist()}] does not cover the support "
                f"[{s_lo.tolist()}, {s_hi.tolist()}] of {distribution!r}; use NoiseGrid.ball for unbounded noise")

    def __repr__(self):
        shape = "x".join(map(str, self.shape))
        lo = [float(e[0]) for e in self.edges]
        hi = [float(e[-1]) for e in self.edges]
        rest = " + remainder" if self.remainder else ""
        return f"NoiseGrid(d={self.dim}, cells={shape}{rest}, |C|={self.num_cells}, box={lo}..{hi})"
