"""IMDP transition bounds by direct integration of additive noise (``bounds="direct"``).

For a system declared as ``x' = g(x, u) + B w`` (``System.additive``) whose ``B`` has one nonzero
entry per row and per column (a diagonal, or a permutation times a diagonal) and whose noise is
``Gaussian`` (independent components) or ``Uniform`` (a box), the components
``v_i = (B w)_i = b_i w_{pi(i)}`` are independent, so for a grid cell ``s' = prod_i [a_i, b_i)``

    P(s' | x, a) = prod_i f_i(g_i(x, a)),    f_i(c) = P(a_i <= c + v_i < b_i).

Each f_i is the convolution of a log-concave density with an interval, hence quasi-concave in c:
over c in [lo, hi] its minimum is at lo or hi, its maximum at the mode (the interval's midpoint
minus the mean of v_i) clipped into [lo, hi]. With [g_lo, g_hi] a sound box enclosure of g over the
cell s (``reach.enclose``), c ranges over a box, so the minimum over it of the product is the
product of the per-dimension minima and the maximum the product of the maxima. The sink (outside
the closed grid box) has probability ``1 - prod_i (1 - q_i)``, ``q_i(c)`` the mass of v_i outside
``[low_i - c, high_i - c]``; it is increasing in every q_i, so its bounds come from the q_i's.

Floating point (everything rounded outward, so no lower bound exceeds the exact value):

* Every float operation is followed by an outward step (``_dn``/``_up``: 4 eps |x| + 4 tiny,
  as ``reach.interval._nudge``), the noise constants (mean, sigma sqrt 2, half-width) are enclosed
  exactly from rationals on the host, and the CDF arguments t = (e - c) / (sigma sqrt 2) are
  intervals, so the CDF is evaluated at argument bounds (it is monotone).
* The Gaussian CDF is only ever evaluated as a tail, ``G(t) = erfc(t) / 2`` for t >= 0
  (``P(c + v in [a, b))`` is ``G(-x) - G(-y)``, ``G(y) - G(x)`` or ``1 - G(-y) - G(x)`` with y, x the
  scaled faces, chosen by their signs), so tiny probabilities keep their relative accuracy.
  XLA's float64 ``erfc`` is taken to satisfy ``|erfc~(t) - erfc(t)| <= (64 + 2 t^2) u erfc(t)``
  (u = 2^-53) wherever erfc(t) is a normal float, plus 4 tiny absolute below that. Why a t^2
  term: XLA computes exp(-t*t) times a rational function, and the rounding of t*t (at most
  u t^2 relative) becomes a relative error u t^2 of the result. Measured against mpmath (200
  bits) on 236,000 points of [0, 26.5] (jaxlib 0.10, CPU): at most 12.3 u + 1.04 u t^2, the
  bound's half or less everywhere; ``tests/abstraction/test_direct.py`` re-measures it on the
  backend it runs on.
* Products over dimensions: n - 1 roundings of factors in [0, 1], covered by one pad of
  (n + 4) eps relative plus (n + 4) tiny.

Sparse storage: a successor is listed when its upper bound exceeds ``threshold`` (precisely:
along each line of a window in the last dimension, every cell from the first to the last one
above the threshold, which is the same set wherever the factors are unimodal). Per dimension
only a window of cells is computed: those within ``r_i`` of the centre box, with ``r_i`` chosen
so that the Gaussian tail beyond it is at most ``threshold`` (the uniform support for uniform
noise); every cell outside the window has probability at most that tail. The IMDP's scalar
``upper_rest`` (the upper bound of every unlisted state, in every row) is the largest upper bound
of any unlisted window cell or unlisted sink over all rows, or the tail bound if some cell lies
outside a window: at most ``threshold``.

Work per (cell, action) pair: ``O(sum_i W_i)`` erfc evaluations for the per-dimension factors and
``O(prod_i W_i)`` multiplications for the products, ``W_i`` the window length; all of it jitted
and batched over chunks of pairs.
"""

from __future__ import annotations

import functools
import math
from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..noise import Gaussian, Uniform
from ..partition import StateGrid
from ..system import System
from .grid_clusters import policy_actions

_U = 2.0 ** -53
_EPS = 2.0 ** -52
_TINY = float(np.finfo(np.float64).tiny)
# erfc's relative error bound (see the module docstring): ERFC_REL0 + ERFC_REL2 t^2.
ERFC_REL0 = 64 * _U
ERFC_REL2 = 2 * _U
ENTRIES_PER_CHUNK = 1 << 22  # window entries (pairs x prod W_i) per compiled call: ~300 MB of temporaries
_GBOXES_PER_CHUNK = 1 << 16  # (cell, action) enclosures of g per compiled call

SUPPORTED = ("x' = g(x, u) + B w declared with System.additive(g, B, actions=..., noise=...), B a diagonal or a "
             "permutation times a diagonal (one nonzero entry in every row and column, n = d), noise "
             "sj.Gaussian (independent components) or sj.Uniform (a box), a grid without periodic dimensions")


# --------------------------------------------------------------------------- outward rounding

def _dn(x, rel=0.0):
    """A float below every real within ``rel |x|`` of a real x* that rounds to ``x`` (with
    round-to-nearest and flush-to-zero: ``|x - x*| <= u |x| + tiny``). The pad 4 eps |x| + 4 tiny
    also covers its own rounding and that of the subtraction (as ``reach.interval._nudge``)."""
    return x - ((rel + 4 * _EPS) * jnp.abs(x) + 4 * _TINY)


def _up(x, rel=0.0):
    """A float above every real within ``rel |x|`` of a real that rounds to ``x`` (see ``_dn``)."""
    return x + ((rel + 4 * _EPS) * jnp.abs(x) + 4 * _TINY)


def _tail(t):
    """``(lo, hi)`` bounds of ``G(t) = erfc(t) / 2`` for floats ``t >= 0`` (any shape).

    ``erfc(t)/2`` is exact scaling of XLA's erfc, whose relative error is at most
    ``ERFC_REL0 + ERFC_REL2 t^2`` (measured, see the module docstring); relative to the
    computed value that is at most 1 + 1e-12 times as much."""
    e = 0.5 * lax.erfc(t)
    # beyond t = 27 erfc(t) is below the smallest normal float (the 4 tiny of the pad cover it);
    # the cap keeps t * t finite
    t = jnp.minimum(t, 27.0)
    rel = (ERFC_REL0 + ERFC_REL2 * t * t) * (1 + 1e-12)
    return jnp.maximum(_dn(e, rel), 0.0), _up(e, rel)


def _div_dn(d, s_lo, s_hi):
    """A lower bound of ``d* / s`` for every real ``d* >= d`` and ``s in [s_lo, s_hi]``, s_lo > 0."""
    return _dn(d / jnp.where(d >= 0, s_hi, s_lo))


def _div_up(d, s_lo, s_hi):
    """An upper bound of ``d* / s`` for every real ``d* <= d`` and ``s in [s_lo, s_hi]``, s_lo > 0."""
    return _up(d / jnp.where(d >= 0, s_lo, s_hi))


# --------------------------------------------------------------------------- Gaussian factors

def _gauss_args(a, b, c_lo, c_hi, s_lo, s_hi, tight_low: bool):
    """Scaled faces of ``[a, b)`` seen from centres ``c in [c_lo, c_hi]``: ``y = (a - c) / S``,
    ``x = (b - c) / S`` with S = sigma sqrt 2 in ``[s_lo, s_hi]``. ``tight_low``: the endpoints
    that minimize the mass (x low, y high), else those that maximize it (x high, y low)."""
    if tight_low:
        return _div_dn(_dn(b - c_hi), s_lo, s_hi), _div_up(_up(a - c_lo), s_lo, s_hi)
    return _div_up(_up(b - c_lo), s_lo, s_hi), _div_dn(_dn(a - c_hi), s_lo, s_hi)


def _gauss_mass_lower(x, y):
    """Lower bound of ``P(y < Z/sqrt2 < x)`` from a lower bound x and an upper bound y (any
    signs): in the left tail G(-x) - G(-y), in the right one G(y) - G(x), across the mean
    1 - G(-y) - G(x); never 1 - CDF of a tail (cancellation)."""
    gx_lo, gx_hi = _tail(jnp.abs(x))
    gy_lo, gy_hi = _tail(jnp.abs(y))
    left = _dn(gx_lo - gy_hi)
    right = _dn(gy_lo - gx_hi)
    middle = _dn(_dn(1.0 - gy_hi) - gx_hi)
    mass = jnp.where(x <= 0, left, jnp.where(y >= 0, right, middle))
    return jnp.where(y >= x, 0.0, jnp.maximum(mass, 0.0))


def _gauss_mass_upper(x, y):
    """Upper bound of ``P(y < Z/sqrt2 < x)`` from an upper bound x and a lower bound y."""
    gx_lo, gx_hi = _tail(jnp.abs(x))
    gy_lo, gy_hi = _tail(jnp.abs(y))
    left = _up(gx_hi - gy_lo)
    right = _up(gy_hi - gx_lo)
    middle = _up(_up(1.0 - gy_lo) - gx_lo)
    mass = jnp.where(x <= 0, left, jnp.where(y >= 0, right, middle))
    return jnp.clip(mass, 0.0, 1.0)


def _gauss_outside(x, y, upper: bool):
    """Bound of ``P(Z/sqrt2 < y) + P(Z/sqrt2 > x)`` (the mass outside [y, x]); ``upper``: from
    a lower bound x and an upper bound y, else from an upper x and a lower y."""
    gx_lo, gx_hi = _tail(jnp.abs(x))
    gy_lo, gy_hi = _tail(jnp.abs(y))
    if upper:
        below = jnp.where(y <= 0, gy_hi, _up(1.0 - gy_lo))
        above = jnp.where(x >= 0, gx_hi, _up(1.0 - gx_lo))
        return jnp.clip(_up(below + above), 0.0, 1.0)
    below = jnp.where(y <= 0, gy_lo, _dn(1.0 - gy_hi))
    above = jnp.where(x >= 0, gx_lo, _dn(1.0 - gx_hi))
    return jnp.clip(_dn(below + above), 0.0, 1.0)


# --------------------------------------------------------------------------- uniform factors

def _uniform_mass(a, b, c_lo, c_hi, h_lo, h_hi, lower: bool):
    """Bound of ``|[a, b) cap [c - h, c + h]| / 2h`` (v uniform on [-h, h], h in [h_lo, h_hi]):
    ``lower`` at the single centre ``c_lo = c_hi``, else the maximum over c in [c_lo, c_hi]
    (the caller passes the clipped midpoint's interval). The overlap grows with h, 1/2h falls.
    Exactly 1 where the support surely lies in the cell (lower), exactly 0 where it surely
    misses it (upper): the pads would otherwise turn those into 1 - 1e-15 and 1e-308."""
    if lower:
        right = jnp.minimum(b, _dn(c_lo + h_lo))
        left = jnp.maximum(a, _up(c_hi - h_lo))
        value = jnp.maximum(_dn(jnp.maximum(_dn(right - left), 0.0) / (2.0 * h_hi)), 0.0)
        inside = (_dn(c_lo - h_hi) >= a) & (_up(c_hi + h_hi) <= b)
        return jnp.where(inside, 1.0, value)
    right = jnp.minimum(b, _up(c_hi + h_hi))
    left = jnp.maximum(a, _dn(c_lo - h_hi))
    value = jnp.clip(_up(jnp.maximum(_up(right - left), 0.0) / (2.0 * h_lo)), 0.0, 1.0)
    misses = (_up(c_hi + h_hi) <= a) | (_dn(c_lo - h_hi) >= b)
    return jnp.where(misses, 0.0, value)


# --------------------------------------------------------------------------- one dimension

def _clipped_mode(a, b, c_lo, c_hi):
    """Interval ``[k_lo, k_hi]`` holding ``clip((a + b) / 2, c_lo, c_hi)`` (exact midpoint)."""
    m = 0.5 * a + 0.5 * b  # one rounding (the halvings are exact), no overflow
    return jnp.clip(_dn(m), c_lo, c_hi), jnp.clip(_up(m), c_lo, c_hi)


def _factor_bounds(gaussian: bool, faces, c_lo, c_hi, s_lo, s_hi):
    """Per-dimension factors of consecutive cells.

    Args:
        faces: ``(P, W + 1)`` faces of W consecutive cells along this dimension.
        c_lo, c_hi: ``(P,)`` box of centres c (g_i plus the noise mean).
        s_lo, s_hi: enclosure of sigma sqrt 2 (Gaussian) or of the half-width (uniform).
    Returns:
        ``(lower, upper)``, each ``(P, W)``: bounds of min / max over c of P(a <= c + v < b).
    """
    a, b = faces[:, :-1], faces[:, 1:]
    lo_c, hi_c = c_lo[:, None], c_hi[:, None]
    k_lo, k_hi = _clipped_mode(a, b, lo_c, hi_c)
    if gaussian:
        def at(c):
            return _gauss_mass_lower(*_gauss_args(a, b, c, c, s_lo, s_hi, True))
        lower = jnp.minimum(at(lo_c), at(hi_c))
        upper = _gauss_mass_upper(*_gauss_args(a, b, k_lo, k_hi, s_lo, s_hi, False))
    else:
        lower = jnp.minimum(_uniform_mass(a, b, lo_c, lo_c, s_lo, s_hi, True),
                            _uniform_mass(a, b, hi_c, hi_c, s_lo, s_hi, True))
        upper = _uniform_mass(a, b, k_lo, k_hi, s_lo, s_hi, False)
    return lower, upper


def _outside_bounds(gaussian: bool, low, high, c_lo, c_hi, s_lo, s_hi):
    """``(q_lo, q_hi)``, each ``(P,)``: bounds of min / max over c of the mass of c + v outside
    ``[low, high]`` along one dimension (the complement of a unimodal factor: its maximum is at
    an endpoint of the centre box, its minimum at the clipped midpoint)."""
    k_lo, k_hi = _clipped_mode(low, high, c_lo, c_hi)
    if gaussian:
        def at(c):  # upper bound of the outside mass at one centre
            x, y = _gauss_args(low, high, c, c, s_lo, s_hi, True)  # x low, y high: the most mass outside
            return _gauss_outside(x, y, upper=True)
        q_hi = jnp.maximum(at(c_lo), at(c_hi))
        x, y = _gauss_args(low, high, k_lo, k_hi, s_lo, s_hi, False)
        q_lo = _gauss_outside(x, y, upper=False)
    else:
        inside_lo = jnp.minimum(_uniform_mass(low, high, c_lo, c_lo, s_lo, s_hi, True),
                                _uniform_mass(low, high, c_hi, c_hi, s_lo, s_hi, True))
        inside_hi = _uniform_mass(low, high, k_lo, k_hi, s_lo, s_hi, False)
        q_hi = jnp.where(inside_lo == 1.0, 0.0, jnp.clip(_up(1.0 - inside_lo), 0.0, 1.0))  # 1: surely inside
        q_lo = jnp.where(inside_hi == 0.0, 1.0, jnp.clip(_dn(1.0 - inside_hi), 0.0, 1.0))
    return q_lo, q_hi


# --------------------------------------------------------------------------- the kernel

# The work per chunk of (cell, action) pairs is three compiled programs: ``dimension_factors``,
# then ``_count`` (first pass) and ``_combine`` (second pass) on its output. XLA on the CPU fuses
# elementwise producers into their consumers, so in one program every product recomputed its
# factors' erfc calls (6.6x slower on the robot).

@functools.partial(jax.jit, static_argnames=("zeros",))
def _count(uppers, sink_hi, threshold, *, zeros: bool):
    """``(count, rest)``, each ``(P,)``: successors listed per pair, and the largest upper bound
    of an unlisted window cell or sink (the first pass: it sizes the IMDP and ``upper_rest``)."""
    upper = _upper_products(uppers, zeros)
    first, length = _runs(upper > threshold)
    inside = _in_runs(first, length, upper.shape[-1])
    window = tuple(range(1, upper.ndim))
    rest = jnp.max(jnp.where(inside, 0.0, upper), axis=window)
    sink_listed = sink_hi > threshold
    return (jnp.sum(length, axis=tuple(range(1, length.ndim)), dtype=jnp.int32) + sink_listed,
            jnp.maximum(rest, jnp.where(sink_listed, 0.0, sink_hi)))


def _runs(listed):
    """Per line of the window (all indices but the last), the hull of the entries above the
    threshold: ``first, length``, each ``(P, W_0, ..., W_{n-2})`` int32 (length 0: none).

    Every entry of a hull is listed (each has its own sound bounds; the few at or below the
    threshold that a hull may hold cost memory, never soundness). For factors unimodal along the
    last dimension the hull is exactly the entries above the threshold."""
    w = listed.shape[-1]
    any_ = jnp.any(listed, axis=-1)
    first = jnp.argmax(listed, axis=-1).astype(jnp.int32)
    last = (w - 1 - jnp.argmax(listed[..., ::-1], axis=-1)).astype(jnp.int32)
    return first, jnp.where(any_, last - first + 1, 0)


def _in_runs(first, length, w):
    """``(P, W_0, ..., W_{n-1})`` bool: the entry lies in its line's hull."""
    j = jnp.arange(w, dtype=jnp.int32)
    return (j >= first[..., None]) & (j < (first + length)[..., None])


def _outer(factors):
    """``(P, W_0, ..., W_{n-1})`` products of ``n`` factors ``(P, W_i)``."""
    pairs = factors[0].shape[0]
    prod = factors[0]
    for i, f in enumerate(factors[1:], start=1):
        prod = prod[..., None] * f.reshape((pairs,) + (1,) * i + (f.shape[1],))
    return prod


def _lower_products(lowers):
    """Lower bounds of the products: n - 1 roundings (relative u each) and flushed underflows
    (tiny each) of factors in [0, 1]."""
    n, lower = len(lowers), _outer(lowers)
    return jnp.maximum(lower - ((n + 4) * _EPS * lower + (n + 4) * _TINY), 0.0) if n > 1 else lower


def _upper_products(uppers, zeros: bool):
    """Upper bounds of the products (see ``_lower_products``). ``zeros``: keep 0 where a factor
    is 0 (a cell that surely misses the support of uniform noise; an underflowed product of
    positive factors is padded like any other). Gaussian factors are never 0."""
    n, upper = len(uppers), _outer(uppers)
    if n == 1:
        return upper
    padded = upper + ((n + 4) * _EPS * upper + (n + 4) * _TINY)
    if not zeros:
        return padded
    return jnp.where(_outer([(u > 0).astype(upper.dtype) for u in uppers]) > 0, padded, 0.0)


@functools.partial(jax.jit, static_argnames=("gaussian", "shifted", "windows"))
def dimension_factors(g_lo, g_hi, start, edges, mean_lo, mean_hi, scale_lo, scale_hi, *,
                      gaussian: bool, shifted: bool, windows: tuple):
    """Per-dimension factor bounds of a chunk of (cell, action) pairs.

    Args:
        g_lo, g_hi: ``(P, n)`` enclosure of g over each pair's cell.
        start: ``(P, n)`` int32 first window cell per dimension (window length ``windows[i]``).
        edges: tuple of ``n`` arrays ``(cells_i + 1,)``: the grid faces.
        mean_lo, mean_hi, scale_lo, scale_hi: ``(n,)`` enclosures of the mean of v_i and of
            sigma_i sqrt 2 (Gaussian) or of the half-width (uniform).
    Returns:
        ``lowers, uppers``: n arrays ``(P, W_i)``, bounds of the min / max over the centre box of
        each window cell's factor; ``sink_lo, sink_hi (P,)``: bounds of the sink's probability.
    """
    pairs, n = g_lo.shape
    c_lo, c_hi = g_lo, g_hi
    if shifted:  # centres of a zero-mean noise: c = g + E[v] (enclosed)
        c_lo, c_hi = _dn(g_lo + mean_lo), _up(g_hi + mean_hi)
    lowers, uppers = [], []
    sink_lo, sink_hi = jnp.zeros(pairs), jnp.zeros(pairs)
    for i in range(n):
        faces = edges[i][start[:, i:i + 1] + jnp.arange(windows[i] + 1)]
        lo, up = _factor_bounds(gaussian, faces, c_lo[:, i], c_hi[:, i], scale_lo[i], scale_hi[i])
        lowers.append(lo)
        uppers.append(up)
        q_lo, q_hi = _outside_bounds(gaussian, edges[i][0], edges[i][-1], c_lo[:, i], c_hi[:, i],
                                     scale_lo[i], scale_hi[i])
        # the sink: 1 - prod(1 - q_i) is increasing in every q_i; P + q - P q, rounded outward
        # (exactly q where the bound P so far is 0)
        sink_lo = jnp.where(sink_lo == 0, q_lo, jnp.clip(_dn(_dn(sink_lo + q_lo) - _up(sink_lo * q_lo)), 0.0, 1.0))
        sink_hi = jnp.where(sink_hi == 0, q_hi, jnp.clip(_up(_up(sink_hi + q_hi) - _dn(sink_hi * q_hi)), 0.0, 1.0))
    return tuple(lowers), tuple(uppers), sink_lo, sink_hi


@functools.partial(jax.jit, static_argnames=("cells", "width", "zeros"))
def _combine(lowers, uppers, sink_lo, sink_hi, start, threshold, *, cells: tuple, width: int, zeros: bool):
    """The second pass: products over the window boxes, the threshold, and the compaction.

    Args: ``dimension_factors``'s output; ``start (P, n)``; ``width``: K, at least the most
    successors any pair lists (``_count``); ``zeros``: uniform noise (factors may be 0).
    Returns:
        ``succ (P, K)`` int32 (listed grid cells increasing, then the sink ``N``, padding
        ``N + 1``) and ``lower, upper (P, K)`` (0 on padding).
    """
    num_cells = int(np.prod(cells))
    pairs = start.shape[0]
    upper = _upper_products(uppers, zeros)
    last = upper.shape[-1]
    first, length = _runs(upper > threshold)
    first, length = first.reshape(pairs, -1), length.reshape(pairs, -1)  # (P, lines)
    # Compaction without a scatter (XLA's CPU scatter costs ~30 ns an element): the hulls, line
    # after line, fill the first slots; slot k belongs to the line whose hull ends first after k.
    end = jnp.cumsum(length, axis=1, dtype=jnp.int32)
    slots = jnp.arange(width, dtype=jnp.int32)
    method = "compare_all" if end.shape[1] <= 32 else "scan_unrolled"
    line = jax.vmap(lambda e: jnp.searchsorted(e, slots, side="right", method=method))(end)
    line = jnp.minimum(line, end.shape[1] - 1).astype(jnp.int32)
    begin = jnp.take_along_axis(end - length, line, axis=1)
    source = line * last + jnp.take_along_axis(first, line, axis=1) + (slots - begin)
    total = end[:, -1:]
    source = jnp.where(slots < total, source, int(np.prod(upper.shape[1:])))  # past the end: padding
    take = lambda a, fill: jnp.take_along_axis(a.reshape(pairs, -1), source, axis=1, mode="fill", fill_value=fill)
    strides = np.cumprod((1,) + tuple(cells[::-1]))[:-1][::-1]
    succ = take(_flat_ids(start, [f.shape[1] for f in lowers], strides), num_cells + 1)
    low, high = take(_lower_products(lowers), 0.0), take(upper, 0.0)
    # the sink after the listed cells, if listed
    here = (slots == total) & (sink_hi > threshold)[:, None]
    return (jnp.where(here, num_cells, succ), jnp.where(here, sink_lo[:, None], low),
            jnp.where(here, sink_hi[:, None], high))


def _flat_ids(start, windows, strides):
    """``(P, prod W)`` flat grid indices of the window cells, C order over the window."""
    pairs, n = start.shape
    ids = jnp.zeros((pairs,) + (1,) * n, jnp.int32)
    for i in range(n):
        shape = (pairs,) + tuple(windows[i] if k == i else 1 for k in range(n))
        ids = ids + ((start[:, i, None] + jnp.arange(windows[i], dtype=jnp.int32)) * int(strides[i])).reshape(shape)
    return ids.reshape(pairs, -1)


# --------------------------------------------------------------------------- host side

def _round_out(q: Fraction) -> tuple[float, float]:
    """The floats just below and above the rational ``q`` (equal when q is a float)."""
    f = float(q)  # correctly rounded
    lo = f if Fraction(f) <= q else float(np.nextafter(f, -np.inf))
    hi = f if Fraction(f) >= q else float(np.nextafter(f, np.inf))
    return lo, hi


def _sqrt2() -> tuple[Fraction, Fraction]:
    r = float(np.sqrt(2.0))
    lo, hi = Fraction(r), Fraction(r)
    while lo * lo > 2:
        lo = Fraction(float(np.nextafter(float(lo), 0.0)))
    while hi * hi < 2:
        hi = Fraction(float(np.nextafter(float(hi), np.inf)))
    return lo, hi


def additive_structure(system: System, grid: StateGrid):
    """``(perm, scale)``, each ``(n,)``: ``(B w)_i = scale_i w_{perm_i}``, or ValueError naming the
    supported cases."""
    if not isinstance(system, System):
        raise TypeError(f"system must be a smdpjax.System, got {type(system).__name__}")
    if not isinstance(grid, StateGrid):
        raise TypeError(f"state_grid must be a smdpjax.StateGrid, got {type(grid).__name__}")
    if not system.is_additive:
        raise ValueError(f"direct IMDP bounds need an additive-noise system; {system!r} was not declared "
                         f"additive. Supported: {SUPPORTED}.")
    noise = system.noise
    if type(noise) not in (Gaussian, Uniform):
        raise ValueError(f"direct IMDP bounds support Gaussian and Uniform noise, got {noise!r}. "
                         f"Supported: {SUPPORTED}.")
    B = np.asarray(system.B)
    n = grid.n
    nonzero = B != 0
    if B.shape != (n, n) or not (np.all(nonzero.sum(axis=0) == 1) and np.all(nonzero.sum(axis=1) == 1)):
        raise ValueError(f"direct IMDP bounds need B with independent components of B w: a diagonal or a "
                         f"permutation times a diagonal, ({n}, {n}) for this {n}-D grid; got B of shape "
                         f"{B.shape} = {B.tolist()}. Supported: {SUPPORTED}.")
    if np.any(grid.periodic):
        raise ValueError(f"direct IMDP bounds do not support periodic dimensions "
                         f"({np.flatnonzero(grid.periodic).tolist()}). Supported: {SUPPORTED}.")
    perm = np.argmax(nonzero, axis=1)
    return perm, B[np.arange(n), perm]


def noise_constants(noise, perm, scale):
    """Host-side outward enclosures, each ``(n,)`` float64: ``mean_lo, mean_hi`` of E[v_i] and
    ``scale_lo, scale_hi`` of sigma_i sqrt 2 (Gaussian) or of the half-width (uniform), from
    exact rationals (``Fraction`` of the floats)."""
    mean_lo, mean_hi, scale_lo, scale_hi = [], [], [], []
    if isinstance(noise, Gaussian):
        m = np.asarray(noise.mean(), np.float64)
        s = np.asarray(noise.std, np.float64)
        r2_lo, r2_hi = _sqrt2()
        for k, b in zip(perm, scale):
            lo, hi = _round_out(Fraction(float(b)) * Fraction(float(m[k])))
            mean_lo.append(lo)
            mean_hi.append(hi)
            sig = abs(Fraction(float(b))) * Fraction(float(s[k]))
            scale_lo.append(_round_out(sig * r2_lo)[0])
            scale_hi.append(_round_out(sig * r2_hi)[1])
    else:
        low, high = np.asarray(noise.low, np.float64), np.asarray(noise.high, np.float64)
        for k, b in zip(perm, scale):
            bq, lq, hq = Fraction(float(b)), Fraction(float(low[k])), Fraction(float(high[k]))
            lo, hi = _round_out(bq * (lq + hq) / 2)
            mean_lo.append(lo)
            mean_hi.append(hi)
            half = abs(bq) * (hq - lq) / 2
            scale_lo.append(_round_out(half)[0])
            scale_hi.append(_round_out(half)[1])
    return tuple(np.array(v) for v in (mean_lo, mean_hi, scale_lo, scale_hi))


def tail_radius(threshold: float) -> float:
    """A t with ``erfc(t) / 2 <= threshold`` (math.erfc, margin 1e-9 relative), or inf for a
    threshold below 1e-300 (the whole grid is then one window)."""
    if threshold < 1e-300:
        return math.inf
    if threshold >= 0.5:
        return 0.0
    lo, hi = 0.0, 27.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if 0.5 * math.erfc(mid) * (1 + 1e-9) <= threshold:
            hi = mid
        else:
            lo = mid
    return hi


def windows_of(grid: StateGrid, g_lo, g_hi, mean_lo, mean_hi, radius):
    """Per pair and dimension the first cell of the window, ``(P, n)`` int32, and the static
    window lengths ``W (n,)``: every cell that meets ``[c_lo - r_i, c_hi + r_i]`` (the centre box
    widened by the noise radius, rounded outward) lies in its pair's window."""
    starts, widths = [], []
    for i in range(grid.n):
        e = grid.edges[i]
        cells = e.shape[0] - 1
        c_lo = np.nextafter(g_lo[:, i] + mean_lo[i], -np.inf)
        c_hi = np.nextafter(g_hi[:, i] + mean_hi[i], np.inf)
        reach_lo = np.nextafter(c_lo - radius[i], -np.inf)
        reach_hi = np.nextafter(c_hi + radius[i], np.inf)
        first = np.searchsorted(e[1:], reach_lo, side="right")   # cells whose upper face is <= reach_lo lie below
        end = np.searchsorted(e[:-1], reach_hi, side="left")      # cells whose lower face is >= reach_hi lie above
        width = int(min(cells, max(1, np.max(end - first, initial=1))))
        starts.append(np.clip(first, 0, cells - width))
        widths.append(width)
    return np.stack(starts, axis=1).astype(np.int32), tuple(widths)


@functools.lru_cache(maxsize=16)
def _gbox_fn(g, method: str):
    from ..reach import enclose

    def one(xl, xh, u):
        return enclose(g, (xl, u), (xh, u), method)

    over_actions = jax.vmap(one, in_axes=(None, None, 0))
    shared = jax.jit(jax.vmap(over_actions, in_axes=(0, 0, None)))  # actions (A, m)
    per_row = jax.jit(jax.vmap(over_actions, in_axes=(0, 0, 0)))    # actions (R, A, m)
    return shared, per_row


def g_boxes(system: System, grid: StateGrid, rows: np.ndarray, actions: np.ndarray, method: str, progress=False):
    """``(g_lo, g_hi)``, each ``(R, A, n)`` numpy: enclosures of g over every row's cell and
    action (``actions (A, m)`` shared, or ``(R, A, m)`` per row). ValueError where NaN or
    unbounded (the direct bounds need a bounded centre box)."""
    shared, per_row = _gbox_fn(system.g, method)
    num_actions = actions.shape[-2]
    chunk = int(max(1, min(rows.size, _GBOXES_PER_CHUNK // num_actions)))
    lo_parts, hi_parts = [], []
    starts = range(0, rows.size, chunk)
    if progress:
        from tqdm.auto import tqdm
        starts = tqdm(starts, desc="g enclosures", unit="chunk")
    for s in starts:
        idx = rows[s:s + chunk]
        take = np.minimum(np.arange(s, s + chunk), rows.size - 1)
        x_lo, x_hi = grid.cell_bounds(rows[take])
        if actions.ndim == 2:
            lo, hi = shared(jnp.asarray(x_lo), jnp.asarray(x_hi), jnp.asarray(actions))
        else:
            lo, hi = per_row(jnp.asarray(x_lo), jnp.asarray(x_hi), jnp.asarray(actions[take]))
        lo_parts.append(np.asarray(lo)[:idx.size])
        hi_parts.append(np.asarray(hi)[:idx.size])
    g_lo, g_hi = np.concatenate(lo_parts), np.concatenate(hi_parts)
    bad = ~np.all(np.isfinite(g_lo) & np.isfinite(g_hi), axis=(1, 2))
    if np.any(bad):
        r = int(np.flatnonzero(bad)[0])
        lo, hi = (np.asarray(b) for b in grid.cell_bounds(int(rows[r])))
        raise ValueError(f"the enclosure of g over cell {int(rows[r])} (box {lo.tolist()}..{hi.tolist()}) is NaN or "
                         f"unbounded: the direct bounds need g bounded on every non-terminal cell")
    return g_lo, g_hi


def direct_imdp(system: System, grid: StateGrid, *, threshold: float = 1e-12, method: str = "both",
                policy=None, progress: bool = False, entries_per_chunk: int = ENTRIES_PER_CHUNK):
    """The IMDP of ``system`` on ``grid`` with transition bounds by direct integration.

    Args:
        system: declared with ``System.additive`` (see ``SUPPORTED``).
        grid: the state partition (no periodic dimensions).
        threshold: successors whose upper bound exceeds it are listed; every other state has the
            interval ``[0, upper_rest]``, ``upper_rest <= threshold``. Larger: smaller and faster
            IMDPs, looser bounds (the adversary may put ``upper_rest`` on every unlisted state).
        method: enclosure of g over a cell: ``"natural"``, ``"centered"`` or ``"both"``.
        policy: optional ``(N,)`` action per cell: only that action (``|A| = 1``).
        entries_per_chunk: window entries per compiled call (bounds peak memory; a call takes
            whole rows, at least one).
    Returns:
        An ``IMDP`` (``successors, lower, upper (R, A, K)``), ``K`` the most successors listed
        for any pair.
    """
    from .clusters import index_dtype
    from .imdp import IMDP

    perm, scale = additive_structure(system, grid)
    if method not in ("natural", "centered", "both"):
        raise ValueError(f"unknown enclosure method {method!r}; expected 'natural', 'centered' or 'both'")
    try:
        threshold = float(threshold)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"threshold must be a number in [0, 1), got {threshold!r}") from exc
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f"threshold must lie in [0, 1), got {threshold}")
    if int(entries_per_chunk) < 1:
        raise ValueError(f"entries_per_chunk must be positive, got {entries_per_chunk}")
    rows = grid.nonterminal
    if rows.size == 0:
        raise ValueError(f"{grid!r} has no non-terminal cell: every cell is a reach or avoid cell")
    system.check_against(grid.n, np.asarray(grid.cell_centers(rows[np.linspace(0, rows.size - 1,
                                                                                min(rows.size, 64)).astype(int)])))
    out = jax.eval_shape(system.g, jax.ShapeDtypeStruct((grid.n,), jnp.float64),
                         jax.ShapeDtypeStruct(system.actions.shape[1:], jnp.float64))
    if getattr(out, "shape", None) != (grid.n,):  # g + B w may broadcast a wrong shape away
        raise ValueError(f"g(x ({grid.n},), u {system.actions.shape[1:]}) must return shape ({grid.n},), got "
                         f"{getattr(out, 'shape', out)}")
    actions = policy_actions(system, grid, rows, policy)
    gaussian = isinstance(system.noise, Gaussian)
    mean_lo, mean_hi, scale_lo, scale_hi = noise_constants(system.noise, perm, scale)

    g_lo, g_hi = g_boxes(system, grid, rows, actions, method, progress)
    num_rows, num_actions, n = g_lo.shape
    g_lo, g_hi = g_lo.reshape(-1, n), g_hi.reshape(-1, n)
    if gaussian:
        t = tail_radius(threshold)
        radius = np.nextafter(t * scale_hi, np.inf) if np.isfinite(t) else np.full(n, np.inf)
        outside = threshold if np.isfinite(t) else 0.0  # cells beyond the radius: tail <= threshold
    else:
        radius, outside = scale_hi, 0.0  # the support: nothing outside
    if not np.all(np.isfinite(radius)):
        start, windows = np.zeros(g_lo.shape, np.int32), tuple(int(c) for c in grid.cells)
    else:
        start, windows = windows_of(grid, g_lo, g_hi, mean_lo, mean_hi, radius)
    outside_used = any(w < c for w, c in zip(windows, grid.cells))
    per_pair = int(np.prod(windows)) + 1
    # Chunks of whole rows (a slab of the final arrays); the last one ends at the last row and
    # overlaps its predecessor (recomputing a few rows) so that every chunk has one shape.
    chunk = int(max(1, min(num_rows, int(entries_per_chunk) // (per_pair * num_actions))))
    first_rows = sorted({min(r, num_rows - chunk) for r in range(0, num_rows, chunk)})
    constants = dict(edges=tuple(jnp.asarray(e) for e in grid.edges), mean_lo=jnp.asarray(mean_lo),
                     mean_hi=jnp.asarray(mean_hi), scale_lo=jnp.asarray(scale_lo), scale_hi=jnp.asarray(scale_hi),
                     gaussian=gaussian, windows=windows, shifted=bool(np.any(mean_lo != 0) or np.any(mean_hi != 0)))
    if progress:
        from tqdm.auto import tqdm
        first_rows = tqdm(first_rows, desc="direct bounds", unit="chunk")
    # Two passes: the first computes the per-dimension factors (kept: sum_i W_i per pair, small
    # beside the IMDP), sizes the IMDP (the most listed successors of any pair) and finds
    # upper_rest; the second writes the compacted bounds in place into the final arrays.
    kept, width, rest = [], 1, 0.0
    for r in first_rows:
        pairs = slice(r * num_actions, (r + chunk) * num_actions)
        first = jnp.asarray(start[pairs])
        factors = dimension_factors(jnp.asarray(g_lo[pairs]), jnp.asarray(g_hi[pairs]), first, **constants)
        count, unlisted = _count(factors[1], factors[3], threshold, zeros=not gaussian)
        width = max(width, int(jnp.max(count)))
        rest = max(rest, float(jnp.max(unlisted)))
        kept.append((r, factors, first))
    if outside_used:
        rest = max(rest, outside)
    sentinel = grid.num_states
    shape = (num_rows, num_actions, width)
    succ = jnp.full(shape, sentinel, index_dtype(sentinel))
    lower, upper = jnp.zeros(shape), jnp.zeros(shape)
    while kept:
        r, factors, first = kept.pop(0)
        out = _combine(*factors, first, threshold, cells=tuple(int(c) for c in grid.cells), width=width,
                       zeros=not gaussian)
        succ, lower, upper = _put((succ, lower, upper), out, r)
    return IMDP(successors=succ, lower=lower, upper=upper, upper_rest=jnp.asarray(rest),
                rows=jnp.asarray(rows, jnp.int32), labels=jnp.asarray(grid.state_labels))


@functools.partial(jax.jit, donate_argnums=0)
def _put(arrays, parts, row):
    """``arrays`` ``(R, A, K)`` with the rows ``row ..`` replaced by ``parts`` ``(rows * A, K)``,
    in place (donated): no copy of the final arrays, which on the CPU a NumPy round trip made."""
    return tuple(lax.dynamic_update_slice(a, p.reshape((-1,) + a.shape[1:]).astype(a.dtype), (row, 0, 0))
                 for a, p in zip(arrays, parts))
