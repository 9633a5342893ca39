"""Natural interval extension of JAX functions, by interpreting their jaxpr.

`natural_enclosure(fn, lows, highs)` traces `fn` to a jaxpr and re-evaluates it with every variable
replaced by an interval ``(lo, hi)`` of arrays of the variable's shape. Each primitive has a rule
that maps input intervals to an output interval containing every value the primitive can take,
both in exact real arithmetic and in the float evaluation of `fn`. Rules round outward (see
`_nudge`), so the result is sound under floating-point rounding. Everything is ordinary jnp/lax
work on (possibly traced) arrays, so the enclosure itself runs under `jax.jit`, `jax.vmap` and
`jax.grad` (gradients of the bounds flow through; the rounding steps are constants to autodiff).

Conventions
* A *point* interval is one whose ``lo`` and ``hi`` are the same Python object (literals, jaxpr
  constants, arguments passed with ``lows[i] is highs[i]``, and exact structural results of
  points). Non-float work on points (indices, iota, integer arithmetic) is evaluated exactly.
* Boolean intervals: ``lo`` = definitely true, ``hi`` = possibly true.
* Domain errors are handled as in standard interval arithmetic: the input is intersected with
  the domain (``sqrt`` of ``[-1, 4]`` is ``[0, 2]``); points where `fn` is NaN have no value to
  enclose. An interval lying entirely outside the domain gives NaN bounds; NaN inputs give NaN.
* Input boxes are assumed finite. XLA on CPU flushes subnormals to zero, so outward rounding
  always adds at least the smallest normal number.
* Every variable also carries a flag "possibly discontinuous in the box variables" (set by
  ``select_n``/``cond`` with an undecided predicate, ``sign``/``floor``/... across a jump, bool to
  number conversions, float narrowing). `centered.py` uses it: a mean-value form needs continuity.
* Outward rounding only where an operation rounded. ``add``/``sub`` find the sign of their
  rounding error exactly (TwoSum) and keep the float result when it already lies on the safe
  side; ``mul``/``div`` keep it when the product is exact (significand bit counts); ``sin(0) = 0``,
  ``cos(0) = 1``, ``exp(0) = 1`` and the other exact special values of library functions are
  kept. So an exactly representable bound (``x + 0.1 * 0 * cos(t) = x``) stays exactly where it is,
  which is what lets a reachable box end exactly on a cell face. Every other rule widens.
* Open ends: ``lo_open``/``hi_open`` (bool arrays or Python False) state that the value never
  attains the bound with positive probability: for every state in the (half-open) state box,
  the set of noise values with ``value >= hi`` has probability zero (noise with a density). A
  widened bound is open (the value lies strictly inside); the rules for add, sub, neg, mul,
  max, min, clamp, select and structural ops propagate the flags exactly; every other rule
  returns closed ends (False), the conservative answer. Cell snapping uses ``hi_open`` to decide
  whether an upper bound exactly on a face reaches the cell above it.
* Subnormal inputs and constants (flushed to zero by XLA on the CPU) are replaced by intervals
  around them, so the exactness tests only ever see zeros and normal numbers.
"""
from __future__ import annotations

import functools
import math
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend.core import ClosedJaxpr, DropVar, Jaxpr, Literal

__all__ = ["natural_enclosure", "interval_eval", "IntervalResult", "mid_rad", "as_box",
           "supported_primitives"]

_EPS = 2.0 ** -52  # twice the float64 unit roundoff: generous per-operation relative error
_LIB = 1e-13       # relative widening for library functions (not correctly rounded in XLA)
_LIB_LOOSE = 1e-12  # ... for the ones measured at ~1e-14 relative error (exp2, log1p, sinh, ...)
_BOUNDED_ABS = 1e-15  # extra absolute widening for bounded functions (sin, tanh, erf, ...)
_TRIG_MAX = 1e8    # beyond this |x| argument reduction is not trusted: sin/cos give [-1, 1]
# sin/cos accuracy. On the CPU XLA's float64 sin and cos are faithful (the exact value lies strictly
# between the result's two float neighbours; measured max error 0.56 ulp against mpmath at 45 000
# points including the neighbours of every multiple of pi/4 in [-10 pi, 10 pi], where an absolute
# error model would lose the sign of cos(fl(pi/2))), so one float step bounds them;
# tests/reach/test_exact_rounding.py re-measures this wherever the suite runs. Elsewhere (CUDA
# documents 2 ulp) a relative 2^-48 (16 ulp), chosen per platform by lax.platform_dependent.
_TRIG_REL = 2.0 ** -48
_TWO_PI = 2.0 * math.pi


class Iv(NamedTuple):
    """Interval of arrays; ``disc`` is a scalar bool (Python False or traced): the value may be a
    discontinuous function of the box variables. ``src`` = ("max"|"min", a, b) records that the
    value is max/min(a, b), so that jvp's tie tests eq(a, max(a, b)) can be decided.
    ``lo_open``/``hi_open``: the bound is almost surely not attained (module docstring)."""
    lo: Any
    hi: Any
    disc: Any = False
    src: Any = None
    lo_open: Any = False
    hi_open: Any = False


class IntervalResult(NamedTuple):
    """Flattened outputs of `interval_eval`: lists of ``lo``, ``hi`` arrays and ``disc`` flags,
    ``magnitude``: max finite |bound| over all float intermediates (None unless requested), and
    lists of bool arrays ``lo_open``, ``hi_open`` (the bound is almost surely not attained)."""
    lo: list
    hi: list
    disc: list
    magnitude: Any
    treedef: Any
    lo_open: list = ()
    hi_open: list = ()


# --------------------------------------------------------------------------- helpers

def _is_point(iv: Iv) -> bool:
    return iv.lo is iv.hi


def _point(x) -> Iv:
    x = jnp.asarray(x)
    return Iv(x, x)


def _inexact(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


def _or(a, b):
    if a is False:
        return b
    if b is False:
        return a
    return jnp.logical_or(a, b)


def _nudge(x, up: bool, rel=0.0, abs_=0.0):
    """Move float ``x`` outward past ``x* + rel*|x| + abs_``, where x* is any real that rounds to
    ``x`` (the exact result of the operation that produced it).

    ``rel`` is a static float in [0, 1/4); ``abs_`` a float or an array >= 0. The result is
    ``x +- ((rel + 4 eps) |x| + (1 + 8 eps) abs_ + 4 tiny)`` evaluated in float (eps = 2^-52):
    with round-to-nearest and flush-to-zero, the computed pad is at least (1 - 2^-50) times its
    exact value, and the final addition loses at most 2^-53 (|x| + pad) + tiny, so the extra
    4 eps |x| + 8 eps abs_ + 4 tiny cover both roundings and x's own (<= 2^-53 |x| + tiny). One
    multiply-add and a select, instead of a ``nextafter`` (which cost half of the centred form).

    Infinite ``x``: +inf as a lower bound becomes the largest float (the exact value overflowed,
    it is at least that), -inf as an upper bound the most negative one; the outward infinities
    stay. NaN stays NaN. The derivative is 1 (the pad is a constant to autodiff), so gradients
    of the bounds still flow."""
    if not _inexact(x):
        return x
    if not 0.0 <= rel < 0.25:
        raise ValueError(f"relative widening must lie in [0, 1/4), got {rel}")
    return _outward(x, abs_, bool(up), float(rel))


@functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3))
def _outward(x, abs_, up, rel):
    info = jnp.finfo(x.dtype)
    eps, tiny, big = float(info.eps), float(info.tiny), float(info.max)
    pad = (rel + 4 * eps) * jnp.abs(x) + 4 * tiny
    if not (isinstance(abs_, (int, float)) and abs_ == 0):
        pad = pad + (1 + 8 * eps) * abs_
    moved = x + pad if up else x - pad
    inward = jnp.maximum(x, -big) if up else jnp.minimum(x, big)  # -inf up / +inf down: finite
    return jnp.where(jnp.isinf(x), inward, moved).astype(x.dtype)


@_outward.defjvp
def _outward_jvp(up, rel, primals, tangents):
    x, abs_ = primals
    return _outward(x, abs_, up, rel), tangents[0]


def _rounded(lo, hi, rel=0.0, abs_=0.0) -> Iv:
    """Widened outward: the value lies strictly inside, so both ends are open."""
    return Iv(_nudge(lo, False, rel, abs_), _nudge(hi, True, rel, abs_), lo_open=True, hi_open=True)


# --------------------------------------------------------------------------- exact rounding

_SMALL = 2.0 ** -969  # below this a float's last bit may be subnormal: exactness is not decided


def _float64(*xs) -> bool:
    return all(jnp.result_type(x) == jnp.float64 for x in xs)


def _decidable(x):
    """Zero or large enough that every bit of x and of an error against it is a normal number
    (infinities pass here; the sum's finiteness is tested once)."""
    return (x == 0) | (jnp.abs(x) >= _SMALL)


def _sum_error(a, b, s):
    """(a + b) - s exactly for s = fl(a + b) (TwoSum, no multiplication, so contraction into an
    FMA cannot change it) and whether it is decided (see `_decidable`)."""
    bb = s - a
    err = (a - (s - bb)) + (b - bb)
    return err, _decidable(a) & _decidable(b) & jnp.isfinite(s)


def _directed(s, err, ok, up: bool):
    """Bound from a float result s with exact error err: s itself where it already lies on the
    safe side of the exact value, else its float neighbour on that side (the exact value lies
    strictly between the two), so the bound is the directed rounding of the exact value.
    Undecided errors widen. Returns (bound, strictly beyond the exact value)."""
    # With decided operands a rounded sum is at least 2^-970 in magnitude: its neighbour is normal.
    safe = (err <= 0) if up else (err >= 0)
    bound = jnp.where(ok, jnp.where(safe, s, _neighbour(s, up)), _nudge(s, up))
    return bound, ~(ok & (err == 0))


def _faithful(y, up: bool):
    """Bound on the exact value of a faithfully rounded library result y (the exact value lies
    strictly between y's two float neighbours): the neighbour on the safe side."""
    return jnp.where(jnp.abs(y) >= _SMALL, _neighbour(y, up), _nudge(y, up))


def _trig_bound(y, up: bool):
    """Bound on the exact sin/cos value computed as y, on the platform the program is compiled
    for (see _TRIG_REL)."""
    return lax.platform_dependent(y, cpu=lambda v: _faithful(v, up),
                                  default=lambda v: _nudge(v, up, _TRIG_REL))


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _neighbour(s, up: bool):
    """The next float64 above (up) or below s, for finite nonzero s (one step of its bits).
    Derivative 1, like `_outward`: the step is a constant to autodiff."""
    bits = lax.bitcast_convert_type(s, jnp.int64)
    return lax.bitcast_convert_type(bits + jnp.where((s > 0) == up, 1, -1).astype(jnp.int64), jnp.float64)


@_neighbour.defjvp
def _neighbour_jvp(up, primals, tangents):
    return _neighbour(primals[0], up), tangents[0]


_MANTISSA = (1 << 52) - 1


def _product_exact(x, y, p):
    """fl(x * y) = p equals x * y exactly (0 * inf counts as the exact 0 of the convention).

    A sufficient test that is cheap enough to run on every corner product: a factor is zero or a
    power of two, or the significands are short (26 and 27 bits: their product fits 53 bits);
    and the product neither underflowed nor overflowed. It decides every product of the
    dynamics' constants and exact values met in practice (0.1 * 1, 0.125 * 3, x * 0); a product
    it misses is widened by one float step, which only costs an ulp of tightness."""
    if not _float64(x, y, p):
        return jnp.zeros(jnp.shape(p), bool)
    mx = lax.bitcast_convert_type(x, jnp.int64) & _MANTISSA
    my = lax.bitcast_convert_type(y, jnp.int64) & _MANTISSA
    short = (((mx & _LOW27) == 0) & ((my & _LOW26) == 0)) | (((mx & _LOW26) == 0) & ((my & _LOW27) == 0))
    fits = (mx == 0) | (my == 0) | short
    info = jnp.finfo(jnp.float64)
    normal = (jnp.abs(p) >= float(info.tiny)) & (jnp.abs(p) <= float(info.max))
    return (x == 0) | (y == 0) | (fits & normal)


_LOW26 = (1 << 26) - 1
_LOW27 = (1 << 27) - 1


def _special_exact(fn_name, x, fx):
    """fx = f(x) is exact at the function's special points (f(0) = 0, exp(0) = 1, ...)."""
    pairs = _SPECIAL.get(fn_name, ())
    exact = jnp.zeros(jnp.shape(fx), bool)
    for a, b in pairs:
        exact = exact | ((x == a) & (fx == b))
    return exact


_SPECIAL = {  # exact values of library functions, where IEEE results are exact in any libm
    "exp": ((0.0, 1.0),), "exp2": ((0.0, 1.0),), "expm1": ((0.0, 0.0),), "log": ((1.0, 0.0),),
    "log1p": ((0.0, 0.0),), "sqrt": ((0.0, 0.0), (1.0, 1.0)), "rsqrt": ((1.0, 1.0),),
    "cbrt": ((0.0, 0.0),), "tanh": ((0.0, 0.0),), "logistic": ((0.0, 0.5),), "erf": ((0.0, 0.0),),
    "atan": ((0.0, 0.0),), "asinh": ((0.0, 0.0),), "sinh": ((0.0, 0.0),), "asin": ((0.0, 0.0),),
    "acos": ((1.0, 0.0),), "atanh": ((0.0, 0.0),), "cosh": ((0.0, 1.0),), "sin": ((0.0, 0.0),),
    "cos": ((0.0, 1.0),), "tan": ((0.0, 0.0),),
}


def _keep_exact(exact, value, widened):
    """value where exact, the widened bound elsewhere; plus 'widened here' (an open end)."""
    return jnp.where(exact, value, widened), ~exact


def _subnormal(x):
    """Subnormal entries, by their bits (XLA's CPU code compares them as 0)."""
    bits = lax.bitcast_convert_type(x, jnp.int64)
    return ((bits & (0x7FF << 52)) == 0) & ((bits & _MANTISSA) != 0)


def _sanitize(iv: Iv) -> Iv:
    """Subnormal entries as intervals around them: [0, tiny] or [-tiny, 0]."""
    if not _float64(iv.lo):
        return iv
    if not isinstance(iv.lo, jax.core.Tracer) and not isinstance(iv.hi, jax.core.Tracer):
        lo_np, hi_np = np.asarray(iv.lo), np.asarray(iv.hi)
        if not (np.any(_subnormal_np(lo_np)) or np.any(_subnormal_np(hi_np))):
            return iv
    tiny = float(jnp.finfo(jnp.float64).tiny)
    sub_lo, sub_hi = _subnormal(iv.lo), _subnormal(iv.hi)
    neg_lo = lax.bitcast_convert_type(iv.lo, jnp.int64) < 0
    neg_hi = lax.bitcast_convert_type(iv.hi, jnp.int64) < 0
    lo = jnp.where(sub_lo, jnp.where(neg_lo, -tiny, 0.0), iv.lo)
    hi = jnp.where(sub_hi, jnp.where(neg_hi, 0.0, tiny), iv.hi)
    return Iv(lo, hi, iv.disc, None, _or(iv.lo_open, sub_lo), _or(iv.hi_open, sub_hi))


def _constant(value) -> Iv:
    """A concrete constant: a point, or an interval around its subnormal entries."""
    if isinstance(value, jax.core.Tracer):
        return _point(value)
    host = np.asarray(value)
    if host.dtype == np.float64 and np.any(_subnormal_np(host)):
        return _sanitize(Iv(jnp.asarray(host), jnp.asarray(host.copy())))
    return _point(jnp.asarray(value))


def _subnormal_np(x):
    return (x != 0) & (np.abs(x) < np.finfo(np.float64).tiny)


def _clip_range(iv: Iv, rmin=None, rmax=None) -> Iv:
    """Clamp to a function's true range (after widening); jnp.maximum/minimum propagate NaN.
    A clamped end is closed (the range's bound may be attained)."""
    lo, hi = iv.lo, iv.hi
    lo_open, hi_open = iv.lo_open, iv.hi_open
    if rmin is not None:
        lo_open, hi_open = lo_open & ~(lo < rmin), hi_open & ~(hi < rmin)
        lo, hi = jnp.maximum(lo, rmin), jnp.maximum(hi, rmin)
    if rmax is not None:
        lo_open, hi_open = lo_open & ~(lo > rmax), hi_open & ~(hi > rmax)
        lo, hi = jnp.minimum(lo, rmax), jnp.minimum(hi, rmax)
    return Iv(lo, hi, iv.disc, None, lo_open, hi_open)


def _restrict(lo, hi, dmin=None, dmax=None):
    """Intersect [lo, hi] with the domain [dmin, dmax]; NaN if the intersection is empty."""
    outside = jnp.zeros(jnp.shape(lo), bool)
    if dmin is not None:
        outside = outside | (hi < dmin)
        lo, hi = jnp.maximum(lo, dmin), jnp.maximum(hi, dmin)
    if dmax is not None:
        outside = outside | (lo > dmax)
        lo, hi = jnp.minimum(lo, dmax), jnp.minimum(hi, dmax)
    return jnp.where(outside, jnp.nan, lo), jnp.where(outside, jnp.nan, hi)


def _abs_range(lo, hi):
    """(min |x|, max |x|) over [lo, hi]; NaN-propagating."""
    return jnp.maximum(jnp.maximum(lo, -hi), 0), jnp.maximum(-lo, hi)


def _extreme(dtype, upper: bool):
    dtype = np.dtype(dtype)
    if dtype == np.bool_:
        return np.bool_(upper)
    if jnp.issubdtype(dtype, jnp.inexact):
        return np.array(np.inf if upper else -np.inf, dtype)
    info = np.iinfo(dtype)
    return np.array(info.max if upper else info.min, dtype)


def _any_differs(a, b):
    return jnp.any(a != b)


def _bind(eqn, *args):
    return eqn.primitive.bind(*args, **eqn.params)


def mid_rad(lo, hi):
    """Midpoint and radius of [lo, hi] (same shapes) with [mid - rad, mid + rad] ⊇ [lo, hi]
    exactly; mid lies in [lo, hi] (so it can serve as an expansion point)."""
    mid = jnp.clip(0.5 * lo + 0.5 * hi, lo, hi)  # 0.5*lo + 0.5*hi cannot overflow
    rad = _nudge(jnp.maximum(hi - mid, mid - lo), True)
    return mid, jnp.where((lo == mid) & (hi == mid), jnp.zeros_like(rad), rad)


def as_box(lows, highs):
    """Convert to tuples of jnp arrays, keeping ``lo is hi`` identity (point arguments)."""
    lows, highs = tuple(lows), tuple(highs)
    if len(lows) != len(highs):
        raise ValueError(f"lows and highs differ in length: {len(lows)} != {len(highs)}")
    out_lo, out_hi = [], []
    for lo, hi in zip(lows, highs):
        a = jnp.asarray(lo)
        b = a if hi is lo else jnp.asarray(hi)
        if jnp.shape(a) != jnp.shape(b) or a.dtype != b.dtype:
            raise ValueError(f"box bounds differ in shape/dtype: {a.shape} {a.dtype} vs {b.shape} {b.dtype}")
        out_lo.append(a)
        out_hi.append(b)
    return tuple(out_lo), tuple(out_hi)


# --------------------------------------------------------------------------- rule registry

_RULES: dict[str, Callable] = {}
# Primitives whose float result on point inputs is exact (no rounding), so points stay points.
_EXACT = {"broadcast_in_dim", "reshape", "squeeze", "expand_dims", "concatenate", "slice",
          "transpose", "rev", "pad", "copy", "copy_p", "stack", "split", "iota", "gather",
          "dynamic_slice", "dynamic_update_slice", "scatter", "scatter-max", "scatter-min",
          "select_n", "max", "min", "clamp", "neg", "abs", "sign", "floor", "ceil", "round",
          "reduce_max", "reduce_min", "cummax", "cummin", "sort", "stop_gradient",
          "convert_element_type", "optimization_barrier", "sharding_constraint", "reshard",
          "reduce_and", "reduce_or"}
# Rules that are also valid for non-point integer/bool intervals (no float-only tricks).
_INT_OK = {"broadcast_in_dim", "reshape", "squeeze", "expand_dims", "concatenate", "slice",
           "transpose", "rev", "pad", "copy", "copy_p", "stack", "split", "gather",
           "dynamic_slice", "dynamic_update_slice", "scatter", "scatter-max", "scatter-min",
           "select_n", "max", "min", "clamp", "neg", "abs", "sign", "reduce_max", "reduce_min",
           "cummax", "cummin", "sort", "stop_gradient", "convert_element_type",
           "optimization_barrier", "sharding_constraint", "reshard", "add", "add_any", "sub", "mul",
           "lt", "le", "gt", "ge", "eq", "ne", "and", "or", "not", "xor", "reduce_and",
           "reduce_or", "reduce_sum", "cumsum", "scatter-add", "is_finite"}


def _rule(*names):
    def register(f):
        for n in names:
            _RULES[n] = f
        return f
    return register


def supported_primitives() -> list[str]:
    """Names of the primitives with an interval rule (plus the nested-jaxpr ones)."""
    return sorted(set(_RULES) | set(_CALLS) | {"cond", "scan"})


# --------------------------------------------------------------------------- arithmetic

def _sum_bounds(x, y):
    """Directed bounds (down, up) of x + y, and whether the exact sum lies strictly inside each."""
    s = x + y
    if not _float64(s):
        return (_nudge(s, False), True), (_nudge(s, True), True)
    err, ok = _sum_error(x, y, s)
    return _directed(s, err, ok, False), _directed(s, err, ok, True)


def _add_ends(a: Iv, b: Iv) -> Iv:
    """[a] + [b] (b already negated for a subtraction)."""
    (lo, lo_strict), up = _sum_bounds(a.lo, b.lo)
    hi, hi_strict = up if _is_point(a) and _is_point(b) else _sum_bounds(a.hi, b.hi)[1]
    return Iv(lo, hi, lo_open=_or(lo_strict, _or(a.lo_open, b.lo_open)),
              hi_open=_or(hi_strict, _or(a.hi_open, b.hi_open)))


def _negated(a: Iv) -> Iv:
    if _is_point(a):
        return _point(-a.lo)
    return Iv(-a.hi, -a.lo, a.disc, None, a.hi_open, a.lo_open)


@_rule("add", "add_any")
def _add(eqn, a, b):
    return _add_ends(a, b)


@_rule("sub")
def _sub(eqn, a, b):
    return _add_ends(a, _negated(b))


@_rule("neg")
def _neg(eqn, a):
    return _negated(a)


def _mul0(x, y):
    """x*y with 0*inf = 0: interval products treat infinite bounds as limits."""
    p = x * y
    if not _inexact(p):
        return p
    # A NaN product of non-NaN factors is 0 * inf; then x + y is +-inf, not NaN (x + y is NaN for
    # inf + -inf only, whose product -inf is no NaN): one test instead of one per factor.
    return jnp.where(jnp.isnan(p) & ~jnp.isnan(x + y), jnp.zeros_like(p), p)


def _ends(iv):
    return (iv.lo,) if _is_point(iv) else (iv.lo, iv.hi)


def _open_ends(iv):
    return (False,) if _is_point(iv) else (iv.lo_open, iv.hi_open)


def _extreme_of(values, exact, opens, up: bool):
    """Bound max (up) or min of candidate ``values`` (each attained where its ``opens`` is False
    and only at its corner): kept where every candidate equal to it is exact, else widened. Open
    where it was widened, or where no closed candidate attains it and it is not 0 (a product is
    then extreme only at corners; at 0 it may be attained along an edge)."""
    best = functools.reduce(jnp.maximum if up else jnp.minimum, values)
    all_exact, closed_hit = True, False
    for v, e, o in zip(values, exact, opens):
        hit = v == best
        all_exact = all_exact & (~hit | e)
        closed_hit = closed_hit | (hit & ~jnp.asarray(o, bool))
    # An inexact IEEE result is within half a unit of the exact one: one float step is safe.
    step = jnp.where(jnp.abs(best) >= _SMALL, _neighbour(best, up), _nudge(best, up))
    bound, widened = _keep_exact(all_exact, best, step)
    return bound, widened | (~closed_hit & (best != 0))


@_rule("mul")
def _mul(eqn, a, b):
    pairs = [(x, y, _or(ox, oy)) for x, ox in zip(_ends(a), _open_ends(a)) for y, oy in zip(_ends(b), _open_ends(b))]
    ps = [_mul0(x, y) for x, y, _ in pairs]
    exact = [_product_exact(x, y, p) for (x, y, _), p in zip(pairs, ps)]
    opens = [o for _, _, o in pairs]
    lo, lo_open = _extreme_of(ps, exact, opens, False)
    hi, hi_open = _extreme_of(ps, exact, opens, True)
    return Iv(lo, hi, lo_open=lo_open, hi_open=hi_open)


@_rule("div")
def _div(eqn, a, b):
    # A divisor interval containing 0 makes the quotient unbounded (the safe denominator avoids
    # NaN gradients in the unselected branch).
    has0 = (b.lo <= 0) & (b.hi >= 0)
    one = jnp.ones_like(b.lo)
    pairs = [(x, y) for x in _ends(a) for y in (jnp.where(has0, one, b.lo), jnp.where(has0, one, b.hi))]
    qs = [x / y for x, y in pairs]
    # x / y = q exactly iff q * y is an exact product equal to x.
    exact = [_product_exact(q, y, q * y) & (q * y == x) & jnp.isfinite(q) for (x, y), q in zip(pairs, qs)]
    # XLA's float division is not correctly rounded on the CPU (it may multiply by a rounded
    # reciprocal), so an inexact quotient is widened by the generous `_nudge`, not one float step.
    lo = functools.reduce(jnp.minimum, qs)
    hi = functools.reduce(jnp.maximum, qs)
    lo_exact = functools.reduce(jnp.logical_and, [~(q == lo) | e for q, e in zip(qs, exact)])
    hi_exact = functools.reduce(jnp.logical_and, [~(q == hi) | e for q, e in zip(qs, exact)])
    lo, lo_w = _keep_exact(lo_exact, lo, _nudge(lo, False))
    hi, hi_w = _keep_exact(hi_exact, hi, _nudge(hi, True))
    out = Iv(lo, hi, lo_open=lo_w, hi_open=hi_w)
    nan_a = jnp.isnan(a.lo) | jnp.isnan(a.hi)
    return Iv(jnp.where(has0, jnp.where(nan_a, jnp.nan, -jnp.inf), out.lo),
              jnp.where(has0, jnp.where(nan_a, jnp.nan, jnp.inf), out.hi))


def _int_pow(lo, hi, n, p, rel):
    """Enclosure of x**n over [lo, hi] for integer-valued n (Python int or array); p(x) = x**n."""
    where = (lambda c, u, v: u if c else v) if isinstance(n, (int, np.integer)) else jnp.where
    even = (n % 2) == 0
    neg = n < 0
    m, big = _abs_range(lo, hi)
    pm, pM = p(m), p(big)
    contains0 = (lo <= 0) & (hi >= 0)
    inf = jnp.asarray(jnp.inf, pm.dtype)
    odd_lo = where(neg, jnp.where(contains0, -inf, p(hi)), p(lo))
    odd_hi = where(neg, jnp.where(contains0, inf, p(lo)), p(hi))
    out = _rounded(where(even, where(neg, pM, pm), odd_lo), where(even, where(neg, pm, pM), odd_hi), rel)
    return jnp.where(even, jnp.maximum(out.lo, 0), out.lo), out.hi  # even powers are >= 0


@_rule("integer_pow")
def _integer_pow(eqn, x):
    n = eqn.params["y"]
    return Iv(*_int_pow(x.lo, x.hi, n, lambda v: _bind(eqn, v), _LIB + abs(n) * _EPS))


@_rule("square")
def _square(eqn, x):
    return Iv(*_int_pow(x.lo, x.hi, 2, lambda v: _bind(eqn, v), 0.0))


@_rule("pow")
def _pow(eqn, x, y):
    # x**y for x >= 0 is monotone in each argument (direction set by the other's sign / side of
    # 1), so the corners hold the extremes; 0**negative = inf falls out of the corners too.
    xl, xh = _restrict(x.lo, x.hi, 0.0, None)
    cs = [_bind(eqn, a, b) for a in (xl, xh) for b in _ends(y)]
    out = _clip_range(_rounded(functools.reduce(jnp.minimum, cs), functools.reduce(jnp.maximum, cs),
                               _LIB_LOOSE), 0.0)
    if not _is_point(y):
        return out
    # A negative base is only meaningful for an integer-valued (point) exponent, e.g. x ** 2.0.
    n = y.lo
    ilo, ihi = _int_pow(x.lo, x.hi, n, lambda v: _bind(eqn, v, n), _LIB_LOOSE)
    use_int = (n == jnp.round(n)) & (x.lo < 0)
    return Iv(jnp.where(use_int, ilo, out.lo), jnp.where(use_int, ihi, out.hi))


def _unary(f, increasing=True, rel=_LIB, abs_=0.0, domain=(None, None), range_=(None, None)):
    """Rule for a strictly monotone elementwise function: map the endpoints, widen except at
    exact special values (`_SPECIAL`), clamp to the range. An unwidened end keeps its operand
    end's open flag (strict monotonicity), unless the domain clamped it."""
    def rule(eqn, x):
        lo, hi = x.lo, x.hi
        lo_open, hi_open = x.lo_open, x.hi_open
        if domain != (None, None):
            r_lo, r_hi = _restrict(lo, hi, *domain)
            lo_open, hi_open = lo_open & (r_lo == lo), hi_open & (r_hi == hi)
            lo, hi = r_lo, r_hi
        a = f(eqn, lo)
        b = a if lo is hi else f(eqn, hi)
        name = eqn.primitive.name
        ea, eb = _special_exact(name, lo, a), _special_exact(name, hi, b)
        if not increasing:
            a, b, ea, eb, lo_open, hi_open = b, a, eb, ea, hi_open, lo_open
        wide = _rounded(a, b, rel, abs_)
        new_lo, w_lo = _keep_exact(ea, a, wide.lo)
        new_hi, w_hi = _keep_exact(eb, b, wide.hi)
        return _clip_range(Iv(new_lo, new_hi, lo_open=w_lo | lo_open, hi_open=w_hi | hi_open), *range_)
    return rule


for _name, _kw in {
    "exp": dict(range_=(0.0, None)),
    "exp2": dict(rel=_LIB_LOOSE, range_=(0.0, None)),
    "expm1": dict(range_=(-1.0, None)),
    "log": dict(domain=(0.0, None)),
    "log1p": dict(rel=_LIB_LOOSE, domain=(-1.0, None)),
    "sqrt": dict(rel=0.0, domain=(0.0, None), range_=(0.0, None)),
    "rsqrt": dict(increasing=False, domain=(0.0, None), range_=(0.0, None)),
    "cbrt": dict(),
    "tanh": dict(abs_=_BOUNDED_ABS, range_=(-1.0, 1.0)),
    "logistic": dict(abs_=_BOUNDED_ABS, range_=(0.0, 1.0)),
    "erf": dict(rel=_LIB_LOOSE, abs_=_BOUNDED_ABS, range_=(-1.0, 1.0)),
    "atan": dict(abs_=_BOUNDED_ABS),
    "asinh": dict(),
    "sinh": dict(rel=_LIB_LOOSE),
    "asin": dict(abs_=_BOUNDED_ABS, domain=(-1.0, 1.0)),
    "acos": dict(increasing=False, abs_=_BOUNDED_ABS, domain=(-1.0, 1.0), range_=(0.0, None)),
    "atanh": dict(rel=_LIB_LOOSE, domain=(-1.0, 1.0)),
}.items():
    _RULES[_name] = _unary(_bind, **_kw)


@_rule("cosh")
def _cosh(eqn, x):
    m, big = _abs_range(x.lo, x.hi)
    c_m = _bind(eqn, m)
    wide = _rounded(c_m, _bind(eqn, big), _LIB_LOOSE)
    lo, w_lo = _keep_exact(_special_exact("cosh", m, c_m), c_m, wide.lo)
    return _clip_range(Iv(lo, wide.hi, lo_open=w_lo, hi_open=True), 1.0)


def _hits(lo, hi, offset, period):
    """Does [lo, hi] (slightly enlarged, so rounding can only add extrema) contain offset + k*period?"""
    lo, hi = lax.stop_gradient(lo), lax.stop_gradient(hi)
    s_lo, s_hi = (lo - offset) / period, (hi - offset) / period
    tol = 1e-9 * (1.0 + jnp.maximum(jnp.abs(s_lo), jnp.abs(s_hi)))
    return jnp.floor(s_hi + tol) >= jnp.ceil(s_lo - tol)


def _trig(peak, trough):
    """sin/cos: endpoint images, raised to +-1 where the interval contains a max/min. An end
    equal to an exact special value (sin 0 = 0, cos 0 = 1) is kept, closed; others widen."""
    def rule(eqn, x):
        lo, hi = x.lo, x.hi
        a = _bind(eqn, lo)
        b = a if lo is hi else _bind(eqn, hi)
        name = eqn.primitive.name
        ea, eb = _special_exact(name, lo, a), _special_exact(name, hi, b)
        full = (hi - lo >= _TWO_PI) | (jnp.maximum(jnp.abs(lo), jnp.abs(hi)) > _TRIG_MAX)
        top_hit, bot_hit = full | _hits(lo, hi, peak, _TWO_PI), full | _hits(lo, hi, trough, _TWO_PI)
        top = jnp.where(top_hit, 1.0, jnp.maximum(a, b))
        bot = jnp.where(bot_hit, -1.0, jnp.minimum(a, b))
        exact_top = ~top_hit & (((top == a) & ea & ((top != b) | eb)) | ((top == b) & eb & ((top != a) | ea)))
        exact_bot = ~bot_hit & (((bot == a) & ea & ((bot != b) | eb)) | ((bot == b) & eb & ((bot != a) | ea)))
        new_lo, w_lo = _keep_exact(exact_bot, bot, _trig_bound(bot, False))
        new_hi, w_hi = _keep_exact(exact_top, top, _trig_bound(top, True))
        return _clip_range(Iv(new_lo, new_hi, lo_open=w_lo, hi_open=w_hi), -1.0, 1.0)
    return rule


_RULES["sin"] = _trig(math.pi / 2, -math.pi / 2)
_RULES["cos"] = _trig(0.0, math.pi)


@_rule("tan")
def _tan(eqn, x):
    # Poles cannot raise under tracing: an interval containing one gets (-inf, inf).
    lo, hi = x.lo, x.hi
    pole = ((hi - lo >= math.pi) | _hits(lo, hi, math.pi / 2, math.pi)
            | (jnp.maximum(jnp.abs(lo), jnp.abs(hi)) > _TRIG_MAX))
    out = _rounded(_bind(eqn, lo), _bind(eqn, hi), _LIB)
    return Iv(jnp.where(pole, -jnp.inf, out.lo), jnp.where(pole, jnp.inf, out.hi))


@_rule("abs")
def _abs(eqn, x):
    return Iv(*_abs_range(x.lo, x.hi))


@_rule("sign", "floor", "ceil", "round")
def _step(eqn, x):
    """Monotone step functions: exact endpoint images; a jump inside the box is a discontinuity."""
    lo, hi = _bind(eqn, x.lo), _bind(eqn, x.hi)
    return Iv(lo, hi, _any_differs(lo, hi))


# --------------------------------------------------------------------------- reductions, dot

def _reduced_size(shape, axes):
    return int(np.prod([shape[a] for a in axes], dtype=np.int64))


def _sum_like(eqn, x, n, *extra):
    """Monotone summation (reduce_sum, cumsum, scatter-add): bounds of the sum, widened by the
    worst-case accumulated rounding n*eps*sum|terms| in any summation order."""
    los, his = [i.lo for i in (x,) + extra], [i.hi for i in (x,) + extra]
    lo, hi = _bind(eqn, *los), _bind(eqn, *his)
    if not _inexact(lo):
        return Iv(lo, hi)
    mags = [jnp.maximum(jnp.abs(l), jnp.abs(h)) if _inexact(l) else l for l, h in zip(los, his)]
    err = _bind(eqn, *mags) * ((n + 1) * _EPS) + n * jnp.finfo(lo.dtype).tiny
    return _rounded(lo, hi, 0.0, err)


@_rule("reduce_sum")
def _reduce_sum(eqn, x):
    return _sum_like(eqn, x, _reduced_size(x.lo.shape, eqn.params["axes"]))


@_rule("reduce_prod")
def _reduce_prod(eqn, x):
    """Product along the reduced axes as a chain of interval multiplications."""
    axes = tuple(eqn.params["axes"])
    keep = [d for d in range(x.lo.ndim) if d not in axes]
    perm = list(axes) + keep
    shape = (-1,) + tuple(x.lo.shape[d] for d in keep)
    lo, hi = (jnp.transpose(b, perm).reshape(shape) for b in (x.lo, x.hi))
    if lo.shape[0] == 0:
        one = jnp.ones(shape[1:], lo.dtype)
        return Iv(one, one)
    acc = Iv(lo[0], hi[0])
    for k in range(1, lo.shape[0]):
        acc = _mul(eqn, acc, Iv(lo[k], hi[k]))
    return acc


@_rule("cumsum")
def _cumsum(eqn, x):
    return _sum_like(eqn, x, x.lo.shape[eqn.params["axis"]])


@_rule("scatter-add")
def _scatter_add(eqn, x, idx, upd):
    _require_point(eqn, idx, "scatter indices")
    return _sum_like(eqn, x, int(np.prod(upd.lo.shape)), idx, upd)


def _finite_mid_rad(iv):
    """mid/rad with infinite bounds replaced by 0, plus the mask of infinite entries."""
    inf = jnp.isinf(iv.lo) | jnp.isinf(iv.hi)
    zero = jnp.zeros_like(iv.lo)
    mid, rad = mid_rad(jnp.where(inf, zero, iv.lo), jnp.where(inf, zero, iv.hi))
    return mid, rad, inf.astype(iv.lo.dtype)


def _nonzero(iv):
    nz = (iv.lo != 0) if _is_point(iv) else ~((iv.lo == 0) & (iv.hi == 0))
    return nz.astype(iv.lo.dtype)


@_rule("dot_general")
def _dot_general(eqn, a, b):
    """Midpoint-radius product: c = ac.bc, r = |ac|.br + ar.|bc| + ar.br (exact hull when one
    operand is a point), plus a rigorous bound gamma_n (|ac|.|bc| + r) on the float rounding."""
    if not (_inexact(a.lo) and _inexact(b.lo)):
        raise NotImplementedError("no interval rule for primitive 'dot_general' on non-float intervals")
    dot = functools.partial(_bind, eqn)
    (ca, _), _ = eqn.params["dimension_numbers"]
    n = _reduced_size(a.lo.shape, ca)
    ac, ar, ainf = (a.lo, None, None) if _is_point(a) else _finite_mid_rad(a)
    bc, br, binf = (b.lo, None, None) if _is_point(b) else _finite_mid_rad(b)
    c = dot(ac, bc)
    mag = dot(jnp.abs(ac), jnp.abs(bc))
    r = jnp.zeros_like(c)
    if ar is not None:
        r = r + dot(ar, jnp.abs(bc))
    if br is not None:
        r = r + dot(jnp.abs(ac), br)
    if ar is not None and br is not None:
        r = r + dot(ar, br)
    gam = 2 * (n + 2) * _EPS
    rad = r * (1 + gam) + gam * mag + (n + 1) * jnp.finfo(c.dtype).tiny
    out = _rounded(c - rad, c + rad)
    unbounded = jnp.zeros(c.shape, bool)
    if ainf is not None:
        unbounded = unbounded | (dot(ainf, _nonzero(b)) > 0)
    if binf is not None:
        unbounded = unbounded | (dot(_nonzero(a), binf) > 0)
    return Iv(jnp.where(unbounded, -jnp.inf, out.lo), jnp.where(unbounded, jnp.inf, out.hi))


# --------------------------------------------------------------------------- structural / monotone

def _require_point(eqn, iv, what):
    if not _is_point(iv):
        raise NotImplementedError(
            f"interval rule for primitive {eqn.primitive.name!r} needs {what} that do not depend "
            f"on the box (constant indices); got an interval")


def _monotone(index_from=None, index_at=(), moves_flags=False):
    """Rule for ops non-decreasing in every value operand (structural ops, max, min, clamp, sort,
    reductions by max/min): apply the op to all lows and to all highs. Index operands (positions
    `index_at`, or `index_from` onwards) must be points. ``moves_flags``: the op only moves
    elements around, so it is applied to the open flags too (else the ends are closed)."""
    def rule(eqn, *ins):
        idx = set(index_at) | (set(range(index_from, len(ins))) if index_from is not None else set())
        for k in idx:
            _require_point(eqn, ins[k], "index operands")
        lo = _bind(eqn, *[i.lo for i in ins])
        hi = _bind(eqn, *[i.hi for i in ins])
        flagged = moves_flags and any(i.lo_open is not False or i.hi_open is not False
                                      for k, i in enumerate(ins) if k not in idx)
        if flagged:
            def flags(which):
                return _bind(eqn, *[i.lo if k in idx else _flag_array(getattr(i, which), i.lo)
                                    for k, i in enumerate(ins)])
            lo_open, hi_open = flags("lo_open"), flags("hi_open")
        if eqn.primitive.multiple_results:
            if flagged:
                return [Iv(l, h, lo_open=lf, hi_open=hf) for l, h, lf, hf in zip(lo, hi, lo_open, hi_open)]
            return [Iv(l, h) for l, h in zip(lo, hi)]
        if flagged:
            return Iv(lo, hi, lo_open=lo_open, hi_open=hi_open)
        return Iv(lo, hi)
    return rule


for _name in ["reduce_max", "reduce_min", "cummax", "cummin", "reduce_and", "reduce_or"]:
    _RULES[_name] = _monotone()
for _name in ["broadcast_in_dim", "reshape", "squeeze", "expand_dims", "concatenate", "slice",
              "transpose", "rev", "pad", "copy", "copy_p", "stack", "split", "optimization_barrier",
              "sharding_constraint", "reshard"]:
    _RULES[_name] = _monotone(moves_flags=True)
_RULES["gather"] = _monotone(index_at=(1,), moves_flags=True)
_RULES["scatter"] = _monotone(index_at=(1,), moves_flags=True)
_RULES["scatter-max"] = _RULES["scatter-min"] = _monotone(index_at=(1,))
_RULES["dynamic_slice"] = _monotone(index_from=1, moves_flags=True)
_RULES["dynamic_update_slice"] = _monotone(index_from=2, moves_flags=True)


def _max_flags(a: Iv, b: Iv, lo, hi, is_max: bool):
    """Open flags of max(a, b) (is_max) or min(a, b) with bounds lo, hi. For max, the upper end
    is attained only if an operand reaching it attains it, the lower end only if both operands
    can sit at it; min is the mirror image."""
    def any_attains(bound, x_end, x_open, y_end, y_open):  # open iff each operand misses it
        return ((x_end != bound) | jnp.asarray(x_open, bool)) & ((y_end != bound) | jnp.asarray(y_open, bool))

    def one_misses(bound, x_end, x_open, y_end, y_open):  # open iff one operand misses it
        return ((x_end == bound) & jnp.asarray(x_open, bool)) | ((y_end == bound) & jnp.asarray(y_open, bool))

    if is_max:
        return (one_misses(lo, a.lo, a.lo_open, b.lo, b.lo_open),
                any_attains(hi, a.hi, a.hi_open, b.hi, b.hi_open))
    return (any_attains(lo, a.lo, a.lo_open, b.lo, b.lo_open),
            one_misses(hi, a.hi, a.hi_open, b.hi, b.hi_open))


@_rule("max", "min")
def _max_min(eqn, a, b):
    out = _monotone()(eqn, a, b)
    if all(x.lo_open is False and x.hi_open is False for x in (a, b)):
        return Iv(out.lo, out.hi, src=(eqn.primitive.name, a, b))
    lo_open, hi_open = _max_flags(a, b, out.lo, out.hi, eqn.primitive.name == "max")
    return Iv(out.lo, out.hi, src=(eqn.primitive.name, a, b), lo_open=lo_open, hi_open=hi_open)


@_rule("clamp")
def _clamp(eqn, low, x, high):
    """clamp(low, x, high) = min(max(x, low), high), flags by the max and min rules."""
    out = _monotone()(eqn, low, x, high)
    if x.lo_open is False and x.hi_open is False:
        return out
    m_lo, m_hi = jnp.maximum(x.lo, low.lo), jnp.maximum(x.hi, low.hi)
    m_lo_open, m_hi_open = _max_flags(x, low, m_lo, m_hi, True)
    m = Iv(m_lo, m_hi, lo_open=m_lo_open, hi_open=m_hi_open)
    lo_open, hi_open = _max_flags(m, high, out.lo, out.hi, False)
    return Iv(out.lo, out.hi, lo_open=lo_open, hi_open=hi_open)


def _decide_tie(name, x, y):
    """eq(x, m) for m = max(x, y) (name "max") or min(x, y): holds where x >= y (resp. <=)."""
    if name == "max":
        return Iv(x.lo >= y.hi, x.hi >= y.lo)
    return Iv(x.hi <= y.lo, x.lo <= y.hi)


@_rule("sort")
def _sort(eqn, *ins):
    # Sorting one array is monotone (componentwise order); with payload operands it is not.
    if len(ins) != 1:
        raise NotImplementedError("no interval rule for primitive 'sort' with several operands (argsort)")
    return _monotone()(eqn, *ins)


@_rule("stop_gradient")
def _identity(eqn, x):
    return x


@_rule("convert_element_type")
def _convert(eqn, x):
    new, old = np.dtype(eqn.params["new_dtype"]), np.dtype(x.lo.dtype)
    if new == np.bool_ and old != np.bool_:
        return Iv((x.lo > 0) | (x.hi < 0), ~((x.lo == 0) & (x.hi == 0)))
    lo, hi = _bind(eqn, x.lo), _bind(eqn, x.hi)
    new_f, old_f = jnp.issubdtype(new, jnp.inexact), jnp.issubdtype(old, jnp.inexact)
    if old == np.bool_ or (old_f and not new_f):
        return Iv(lo, hi, _any_differs(lo, hi))  # bool->number, float->int: steps
    if new_f and (not old_f or np.finfo(new).bits < np.finfo(old).bits):
        # int->float and float narrowing round; narrowing is a staircase (a discontinuity).
        out = _rounded(lo, hi)
        return Iv(out.lo, out.hi, old_f)
    return Iv(lo, hi)


# --------------------------------------------------------------------------- booleans, select

def _same(a, b):
    return a is b


@_rule("lt", "le", "gt", "ge", "eq", "ne")
def _compare(eqn, a, b):
    name = eqn.primitive.name
    if _same(a, b):
        # x OP x for the same variable (e.g. the NaN test x != x): decided unless bounds are NaN.
        maybe_nan = jnp.isnan(a.lo) | jnp.isnan(a.hi) if _inexact(a.lo) else jnp.zeros(a.lo.shape, bool)
        yes = jnp.ones(a.lo.shape, bool)
        if name in ("eq", "le", "ge"):
            return Iv(~maybe_nan, yes)
        return Iv(~yes, maybe_nan)
    if name in ("eq", "ne"):
        for x, m in ((a, b), (b, a)):
            if m.src is not None and any(x is v for v in m.src[1:]):
                y = m.src[2] if x is m.src[1] else m.src[1]
                tie = _decide_tie(m.src[0], x, y)
                return tie if name == "eq" else Iv(~tie.hi, ~tie.lo)
    if name in ("gt", "ge"):
        a, b, name = b, a, {"gt": "lt", "ge": "le"}[name]
    if name == "lt":
        return Iv(a.hi < b.lo, a.lo < b.hi)
    if name == "le":
        return Iv(a.hi <= b.lo, a.lo <= b.hi)
    sure = (a.lo == a.hi) & (b.lo == b.hi) & (a.lo == b.lo)
    maybe = (a.lo <= b.hi) & (b.lo <= a.hi)
    return Iv(sure, maybe) if name == "eq" else Iv(~maybe, ~sure)


def _require_bool(eqn, *ivs):
    if any(np.dtype(iv.lo.dtype) != np.bool_ for iv in ivs):
        raise NotImplementedError(
            f"no interval rule for primitive {eqn.primitive.name!r} on non-point integer intervals "
            "(bitwise ops are not monotone)")


@_rule("is_finite")
def _is_finite(eqn, x):
    return Iv((x.lo > -jnp.inf) & (x.hi < jnp.inf), (x.lo < jnp.inf) & (x.hi > -jnp.inf))


@_rule("and")
def _and(eqn, a, b):
    _require_bool(eqn, a, b)
    return Iv(a.lo & b.lo, a.hi & b.hi)


@_rule("or")
def _or_rule(eqn, a, b):
    _require_bool(eqn, a, b)
    return Iv(a.lo | b.lo, a.hi | b.hi)


@_rule("not")
def _not(eqn, a):
    _require_bool(eqn, a)
    return Iv(~a.hi, ~a.lo)


@_rule("xor")
def _xor(eqn, a, b):
    _require_bool(eqn, a, b)
    return Iv((a.lo & ~b.hi) | (~a.hi & b.lo), (a.hi & ~b.lo) | (~a.lo & b.hi))


def _flag_array(flag, like):
    return jnp.broadcast_to(jnp.asarray(flag, bool), jnp.shape(like))


def _select(pred: Iv, cases: Sequence[Iv]) -> Iv:
    """select_n / cond: exact for a point predicate, else the hull of all possibly chosen cases
    (and the result may jump where the predicate flips). An end of the hull is open where every
    possibly chosen case either misses it or has it open."""
    flagged = any(c.lo_open is not False or c.hi_open is not False for c in cases)
    if _is_point(pred):
        p = pred.lo
        lo = lax.select_n(p, *[c.lo for c in cases])
        hi = lo if all(_is_point(c) for c in cases) else lax.select_n(p, *[c.hi for c in cases])
        if not flagged:
            return Iv(lo, hi)
        return Iv(lo, hi, lo_open=lax.select_n(p, *[_flag_array(c.lo_open, lo) for c in cases]),
                  hi_open=lax.select_n(p, *[_flag_array(c.hi_open, hi) for c in cases]))
    plo, phi = pred.lo.astype(jnp.int32), pred.hi.astype(jnp.int32)
    lo = hi = None
    inconsistent = plo > phi  # only from NaN bounds upstream: take every case
    oks = []
    for i, c in enumerate(cases):
        ok = ((plo <= i) & (phi >= i)) | inconsistent
        oks.append(ok)
        l = jnp.where(ok, c.lo, _extreme(c.lo.dtype, True))
        h = jnp.where(ok, c.hi, _extreme(c.hi.dtype, False))
        lo = l if lo is None else jnp.minimum(lo, l)
        hi = h if hi is None else jnp.maximum(hi, h)
    if not flagged or not _inexact(lo):
        return Iv(lo, hi, _any_differs(plo, phi))
    lo_open = hi_open = True
    for ok, c in zip(oks, cases):
        lo_open = lo_open & (~ok | (c.lo > lo) | jnp.asarray(c.lo_open, bool))
        hi_open = hi_open & (~ok | (c.hi < hi) | jnp.asarray(c.hi_open, bool))
    return Iv(lo, hi, _any_differs(plo, phi), None, lo_open, hi_open)


@_rule("select_n")
def _select_n(eqn, pred, *cases):
    return _select(pred, cases)


# --------------------------------------------------------------------------- the interpreter

class _Ctx:
    """Per-evaluation state: running max of finite |bounds| (None when not tracked)."""
    def __init__(self, track):
        self.track = track
        self.mag = None
        self.literals = {}

    def see(self, ivs):
        if not self.track:
            return
        for iv in ivs:
            if not _inexact(iv.lo):
                continue
            for x in _ends(iv):
                x = lax.stop_gradient(x)
                m = jnp.max(jnp.where(jnp.isfinite(x), jnp.abs(x), 0), initial=0.0)
                self.mag = m if self.mag is None else jnp.maximum(self.mag, m)


def _sub_jaxpr(params):
    for key in ("jaxpr", "call_jaxpr", "fun_jaxpr"):
        j = params.get(key)
        if isinstance(j, ClosedJaxpr):
            return j.jaxpr, j.consts
        if isinstance(j, Jaxpr):
            return j, ()
    raise NotImplementedError(f"cannot find the inner jaxpr in params {sorted(params)}")


def _call(eqn, ins, ctx):
    jaxpr, consts = _sub_jaxpr(eqn.params)
    return _eval_jaxpr(jaxpr, consts, ins, ctx)


# Primitives that just call an inner jaxpr. For custom_jvp/custom_vjp only the primal matters.
_CALLS = {n: _call for n in ("jit", "pjit", "closed_call", "core_call", "custom_jvp_call",
                             "custom_vjp_call", "custom_vjp_call_jaxpr", "remat", "remat2",
                             "checkpoint")}


def _cond(eqn, ins, ctx):
    branches = eqn.params["branches"]
    index, ops = ins[0], ins[1:]
    outs = [_eval_jaxpr(b.jaxpr, b.consts, ops, ctx) for b in branches]
    last = len(branches) - 1
    if _is_point(index):
        p = jnp.clip(index.lo, 0, last)
        pred = Iv(p, p)
    else:
        pred = Iv(jnp.clip(index.lo, 0, last), jnp.clip(index.hi, 0, last))
    return [_select(pred, [o[k] for o in outs]) for k in range(len(eqn.outvars))]


def _slice0(iv, i):
    lo = iv.lo[i]
    return Iv(lo, lo if _is_point(iv) else iv.hi[i])


def _stack0(ivs, aval):
    if not ivs:
        z = jnp.zeros(aval.shape, aval.dtype)
        return Iv(z, z)
    lo = jnp.stack([iv.lo for iv in ivs])
    hi = lo if all(_is_point(iv) for iv in ivs) else jnp.stack([iv.hi for iv in ivs])
    return Iv(lo, hi, functools.reduce(_or, [iv.disc for iv in ivs], False))


def _scan(eqn, ins, ctx):
    """Unrolled: the trip count of a scan is static."""
    p = eqn.params
    body, nc, ncarry, length = p["jaxpr"], p["num_consts"], p["num_carry"], p["length"]
    consts, carry, xs = ins[:nc], list(ins[nc:nc + ncarry]), ins[nc + ncarry:]
    ys = []
    steps = range(length - 1, -1, -1) if p["reverse"] else range(length)
    for i in steps:
        out = _eval_jaxpr(body.jaxpr, body.consts, list(consts) + carry + [_slice0(x, i) for x in xs], ctx)
        carry, y = out[:ncarry], out[ncarry:]
        ys.append(y)
    if p["reverse"]:
        ys = ys[::-1]
    y_avals = [v.aval for v in eqn.outvars[ncarry:]]
    return carry + [_stack0([y[k] for y in ys], y_avals[k]) for k in range(len(y_avals))]


_HIGHER = dict(_CALLS, cond=_cond, scan=_scan)


def _eval_eqn(eqn, ins, ctx):
    name = eqn.primitive.name
    if name in _HIGHER:
        return _HIGHER[name](eqn, ins, ctx)
    in_disc = functools.reduce(_or, [iv.disc for iv in ins], False)
    float_out = any(_inexact(v.aval.dtype) for v in eqn.outvars)
    if all(_is_point(iv) for iv in ins) and (name in _EXACT or not float_out):
        vals = _bind(eqn, *[iv.lo for iv in ins])
        vals = vals if eqn.primitive.multiple_results else [vals]
        return [Iv(v, v) for v in vals]
    rule = _RULES.get(name)
    if rule is None:
        raise NotImplementedError(
            f"no interval rule for primitive {name!r}; see "
            "smdpjax.reach.interval.supported_primitives() for what the natural interval extension "
            "handles. Rewrite fn with supported operations or add a rule to that module.")
    if not float_out and name not in _INT_OK:
        raise NotImplementedError(
            f"no interval rule for primitive {name!r} on non-point integer/bool intervals")
    out = rule(eqn, *ins)
    out = out if isinstance(out, list) else [out]
    return [o._replace(disc=_or(o.disc, in_disc)) for o in out]


def _materialized(iv: Iv) -> Iv:
    """The same interval, computed into memory before its consumers run (`_stored`)."""
    fields = ("lo", "hi", "disc", "lo_open", "hi_open")
    arrays = {f: getattr(iv, f) for f in fields
              if isinstance(getattr(iv, f), (jax.Array, jax.core.Tracer)) and not (f == "hi" and _is_point(iv))}
    if not arrays:
        return iv
    stored = _stored(arrays)
    if _is_point(iv):
        stored["hi"] = stored["lo"]
    return iv._replace(**stored)


@jax.custom_jvp
def _stored(arrays: dict) -> dict:
    """``arrays`` unchanged, behind a fusion boundary that XLA keeps: a while loop whose trip
    count it cannot know (1, or 0 for a NaN first entry; either returns the input) and whose
    body it cannot prove to be the identity. An optimization barrier, a scan of length 1 or a
    pass-through loop body are all optimized away on the CPU. Identity to autodiff."""
    first = jnp.ravel(next(iter(arrays.values())))[0]
    trips = (first == first).astype(jnp.int32)

    def body(c):  # c[0] < trips here, so the select always keeps a
        return c[0] + 1, jax.tree.map(lambda a: jnp.where(c[0] > trips, ~a if a.dtype == bool else -a, a), c[1])

    return lax.while_loop(lambda c: c[0] < trips, body, (jnp.int32(0), arrays))[1]


@_stored.defjvp
def _stored_jvp(primals, tangents):
    return _stored(*primals), tangents[0]


def _eval_jaxpr(jaxpr, consts, args, ctx, staged: bool = False):
    """Interval values of ``jaxpr``'s outputs. ``staged``: each argument varies along its own
    batch axes (``reachable_boxes`` vmaps states, actions and noise cells separately), so a value
    that depends on fewer arguments than its consumer is stored before the consumer reads it
    (`_materialized`); otherwise XLA's CPU fusion recomputes e.g. the cos of a state interval for
    every (action, noise cell) pair."""
    env = {}
    deps = {v: frozenset([i]) for i, v in enumerate(jaxpr.invars)} if staged else {}
    stored = {}

    def read(v):
        if isinstance(v, Literal):
            # One object per literal value, so that identity-based reasoning (x OP x, ties in
            # max/min) also recognises repeated literals such as the 0.0 in relu's jvp.
            val = np.asarray(v.val, v.aval.dtype)
            key = (val.dtype.str, val.shape, val.tobytes())
            if key not in ctx.literals:
                ctx.literals[key] = _constant(val)
            return ctx.literals[key]
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = _constant(c)
    env.update(zip(jaxpr.invars, args))
    for eqn in jaxpr.eqns:
        if all(isinstance(v, DropVar) for v in eqn.outvars):
            continue  # dead code (jacfwd keeps unused primal outputs) or output-free callbacks
        ins = [read(v) for v in eqn.invars]
        if staged:
            in_deps = [deps.get(v, frozenset()) if not isinstance(v, Literal) else frozenset() for v in eqn.invars]
            out_deps = frozenset().union(*in_deps)
            for k, (v, d) in enumerate(zip(eqn.invars, in_deps)):
                if d and d < out_deps:
                    if v not in stored:
                        stored[v] = _materialized(ins[k])
                    ins[k] = stored[v]
            deps.update((v, out_deps) for v in eqn.outvars)
        outs = _eval_eqn(eqn, ins, ctx)
        ctx.see(outs)
        for v, o in zip(eqn.outvars, outs):
            if not isinstance(v, DropVar):
                env[v] = o
    return [read(v) for v in jaxpr.outvars]


def interval_eval(fn: Callable, lows, highs, track_magnitude: bool = False, open_lows=None,
                  open_highs=None, staged: bool = False) -> IntervalResult:
    """Interval-evaluate ``fn`` (any pytree output) over the box; see `natural_enclosure`.

    ``open_lows``/``open_highs``: optional per-argument bool arrays (or None / False): that end of
    the argument's interval is almost surely not attained (a half-open state cell's upper face,
    a noise box of a distribution with a density). Points (``lows[i] is highs[i]``) are closed
    and must not be subnormal when traced (callers check their data).

    Returns flattened output bounds, per-output discontinuity flags (scalar bools), when
    ``track_magnitude`` the largest finite |bound| seen over all float intermediates, and the
    outputs' open flags.

    ``staged``: the arguments vary along separate vmapped axes; store each intermediate that a
    consumer broadcasts over more of them (see `_eval_jaxpr`; the same values, faster on the CPU)."""
    lows, highs = as_box(lows, highs)
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*lows)
    treedef = jax.tree_util.tree_structure(out_shape)
    ctx = _Ctx(track_magnitude)
    k = len(lows)
    open_lows = [False] * k if open_lows is None else list(open_lows)
    open_highs = [False] * k if open_highs is None else list(open_highs)
    args = []
    for lo, hi, lo_open, hi_open in zip(lows, highs, open_lows, open_highs):
        if lo is hi:
            iv = _point(lo) if isinstance(lo, jax.core.Tracer) else _constant(lo)
        else:
            flag = lambda f: False if f is None or f is False else jnp.asarray(f, bool)
            iv = _sanitize(Iv(lo, hi, lo_open=flag(lo_open), hi_open=flag(hi_open)))
        args.append(iv)
    ctx.see(args)
    outs = _eval_jaxpr(closed.jaxpr, closed.consts, args, ctx, staged)
    dtypes = [v.aval.dtype for v in closed.jaxpr.outvars]
    outs = [Iv(o.lo.astype(d), o.hi.astype(d), o.disc, None,
               _flag_array(o.lo_open, o.lo) & jnp.issubdtype(d, jnp.inexact),
               _flag_array(o.hi_open, o.hi) & jnp.issubdtype(d, jnp.inexact)) for o, d in zip(outs, dtypes)]
    return IntervalResult([o.lo for o in outs], [o.hi for o in outs],
                          [o.disc for o in outs], ctx.mag, treedef,
                          [o.lo_open for o in outs], [o.hi_open for o in outs])


def natural_enclosure(fn: Callable, lows: Sequence, highs: Sequence):
    """Natural interval extension of ``fn`` over a box.

    fn: callable taking positional jnp arrays (float64), returning ONE array of shape S.
    lows, highs: tuples of arrays with the shapes/dtypes of fn's arguments; an argument passed as
        the same object in both (``lows[i] is highs[i]``) is a point and is handled exactly.
    Returns (lo, hi), arrays of shape S with fn(z) in [lo, hi] for every z in the box, in real
    arithmetic and in fn's float64 evaluation. Traceable (jit/vmap/grad).
    Raises NotImplementedError naming any primitive without an interval rule."""
    res = interval_eval(fn, lows, highs)
    if len(res.lo) != 1:
        raise ValueError(f"fn must return exactly one array, got {res.treedef}")
    return res.lo[0], res.hi[0]
