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
_TWO_PI = 2.0 * math.pi


class Iv(NamedTuple):
    """Interval of arrays; ``disc`` is a scalar bool (Python False or traced): the value may be a
    discontinuous function of the box variables. ``src`` = ("max"|"min", a, b) records that the
    value is max/min(a, b), so that jvp's tie tests eq(a, max(a, b)) can be decided."""
    lo: Any
    hi: Any
    disc: Any = False
    src: Any = None


class IntervalResult(NamedTuple):
    """Flattened outputs of `interval_eval`: lists of ``lo``, ``hi`` arrays and ``disc`` flags, and
    ``magnitude``: max finite |bound| over all float intermediates (None unless requested)."""
    lo: list
    hi: list
    disc: list
    magnitude: Any
    treedef: Any


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
    return Iv(_nudge(lo, False, rel, abs_), _nudge(hi, True, rel, abs_))


def _clip_range(iv: Iv, rmin=None, rmax=None) -> Iv:
    """Clamp to a function's true range (after widening); jnp.maximum/minimum propagate NaN."""
    lo, hi = iv.lo, iv.hi
    if rmin is not None:
        lo, hi = jnp.maximum(lo, rmin), jnp.maximum(hi, rmin)
    if rmax is not None:
        lo, hi = jnp.minimum(lo, rmax), jnp.minimum(hi, rmax)
    return Iv(lo, hi, iv.disc)


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

@_rule("add", "add_any")
def _add(eqn, a, b):
    return _rounded(a.lo + b.lo, a.hi + b.hi)


@_rule("sub")
def _sub(eqn, a, b):
    return _rounded(a.lo - b.hi, a.hi - b.lo)


@_rule("neg")
def _neg(eqn, a):
    return Iv(-a.hi, -a.lo)


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


@_rule("mul")
def _mul(eqn, a, b):
    ps = [_mul0(x, y) for x in _ends(a) for y in _ends(b)]
    return _rounded(functools.reduce(jnp.minimum, ps), functools.reduce(jnp.maximum, ps))


@_rule("div")
def _div(eqn, a, b):
    # A divisor interval containing 0 makes the quotient unbounded (the safe denominator avoids
    # NaN gradients in the unselected branch).
    has0 = (b.lo <= 0) & (b.hi >= 0)
    one = jnp.ones_like(b.lo)
    qs = [x / y for x in _ends(a) for y in (jnp.where(has0, one, b.lo), jnp.where(has0, one, b.hi))]
    out = _rounded(functools.reduce(jnp.minimum, qs), functools.reduce(jnp.maximum, qs))
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
    """Rule for a monotone elementwise function: map the endpoints, widen, clamp to the range."""
    def rule(eqn, x):
        lo, hi = x.lo, x.hi
        if domain != (None, None):
            lo, hi = _restrict(lo, hi, *domain)
        a = f(eqn, lo)
        b = a if lo is hi else f(eqn, hi)
        if not increasing:
            a, b = b, a
        return _clip_range(_rounded(a, b, rel, abs_), *range_)
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
    return _clip_range(_rounded(_bind(eqn, m), _bind(eqn, big), _LIB_LOOSE), 1.0)


def _hits(lo, hi, offset, period):
    """Does [lo, hi] (slightly enlarged, so rounding can only add extrema) contain offset + k*period?"""
    lo, hi = lax.stop_gradient(lo), lax.stop_gradient(hi)
    s_lo, s_hi = (lo - offset) / period, (hi - offset) / period
    tol = 1e-9 * (1.0 + jnp.maximum(jnp.abs(s_lo), jnp.abs(s_hi)))
    return jnp.floor(s_hi + tol) >= jnp.ceil(s_lo - tol)


def _trig(peak, trough):
    """sin/cos: endpoint images, raised to +-1 where the interval contains a max/min."""
    def rule(eqn, x):
        lo, hi = x.lo, x.hi
        a = _bind(eqn, lo)
        b = a if lo is hi else _bind(eqn, hi)
        full = (hi - lo >= _TWO_PI) | (jnp.maximum(jnp.abs(lo), jnp.abs(hi)) > _TRIG_MAX)
        top = jnp.where(full | _hits(lo, hi, peak, _TWO_PI), 1.0, jnp.maximum(a, b))
        bot = jnp.where(full | _hits(lo, hi, trough, _TWO_PI), -1.0, jnp.minimum(a, b))
        return _clip_range(_rounded(bot, top, _LIB, _BOUNDED_ABS), -1.0, 1.0)
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


def _monotone(index_from=None, index_at=()):
    """Rule for ops non-decreasing in every value operand (structural ops, max, min, clamp, sort,
    reductions by max/min): apply the op to all lows and to all highs. Index operands (positions
    `index_at`, or `index_from` onwards) must be points."""
    def rule(eqn, *ins):
        idx = set(index_at) | (set(range(index_from, len(ins))) if index_from is not None else set())
        for k in idx:
            _require_point(eqn, ins[k], "index operands")
        lo = _bind(eqn, *[i.lo for i in ins])
        hi = _bind(eqn, *[i.hi for i in ins])
        if eqn.primitive.multiple_results:
            return [Iv(l, h) for l, h in zip(lo, hi)]
        return Iv(lo, hi)
    return rule


for _name in ["broadcast_in_dim", "reshape", "squeeze", "expand_dims", "concatenate", "slice",
              "transpose", "rev", "pad", "copy", "copy_p", "stack", "split", "clamp", "reduce_max", "reduce_min", "cummax", "cummin", "optimization_barrier",
              "sharding_constraint", "reshard", "reduce_and", "reduce_or"]:
    _RULES[_name] = _monotone()
_RULES["gather"] = _monotone(index_at=(1,))
_RULES["scatter"] = _RULES["scatter-max"] = _RULES["scatter-min"] = _monotone(index_at=(1,))
_RULES["dynamic_slice"] = _monotone(index_from=1)
_RULES["dynamic_update_slice"] = _monotone(index_from=2)


@_rule("max", "min")
def _max_min(eqn, a, b):
    out = _monotone()(eqn, a, b)
    return Iv(out.lo, out.hi, src=(eqn.primitive.name, a, b))


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


def _select(pred: Iv, cases: Sequence[Iv]) -> Iv:
    """select_n / cond: exact for a point predicate, else the hull of all possibly chosen cases
    (and the result may jump where the predicate flips)."""
    if _is_point(pred):
        p = pred.lo
        lo = lax.select_n(p, *[c.lo for c in cases])
        hi = lo if all(_is_point(c) for c in cases) else lax.select_n(p, *[c.hi for c in cases])
        return Iv(lo, hi)
    plo, phi = pred.lo.astype(jnp.int32), pred.hi.astype(jnp.int32)
    lo = hi = None
    inconsistent = plo > phi  # only from NaN bounds upstream: take every case
    for i, c in enumerate(cases):
        ok = ((plo <= i) & (phi >= i)) | inconsistent
        l = jnp.where(ok, c.lo, _extreme(c.lo.dtype, True))
        h = jnp.where(ok, c.hi, _extreme(c.hi.dtype, False))
        lo = l if lo is None else jnp.minimum(lo, l)
        hi = h if hi is None else jnp.maximum(hi, h)
    return Iv(lo, hi, _any_differs(plo, phi))


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
    return [Iv(o.lo, o.hi, _or(o.disc, in_disc), o.src) for o in out]


def _eval_jaxpr(jaxpr, consts, args, ctx):
    env = {}

    def read(v):
        if isinstance(v, Literal):
            # One object per literal value, so that identity-based reasoning (x OP x, ties in
            # max/min) also recognises repeated literals such as the 0.0 in relu's jvp.
            val = np.asarray(v.val, v.aval.dtype)
            key = (val.dtype.str, val.shape, val.tobytes())
            if key not in ctx.literals:
                ctx.literals[key] = _point(jnp.asarray(val))
            return ctx.literals[key]
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = _point(c)
    env.update(zip(jaxpr.invars, args))
    for eqn in jaxpr.eqns:
        if all(isinstance(v, DropVar) for v in eqn.outvars):
            continue  # dead code (jacfwd keeps unused primal outputs) or output-free callbacks
        outs = _eval_eqn(eqn, [read(v) for v in eqn.invars], ctx)
        ctx.see(outs)
        for v, o in zip(eqn.outvars, outs):
            if not isinstance(v, DropVar):
                env[v] = o
    return [read(v) for v in jaxpr.outvars]


def interval_eval(fn: Callable, lows, highs, track_magnitude: bool = False) -> IntervalResult:
    """Interval-evaluate ``fn`` (any pytree output) over the box; see `natural_enclosure`.

    Returns flattened output bounds, per-output discontinuity flags (scalar bools) and, when
    ``track_magnitude``, the largest finite |bound| seen over all float intermediates."""
    lows, highs = as_box(lows, highs)
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*lows)
    treedef = jax.tree_util.tree_structure(out_shape)
    ctx = _Ctx(track_magnitude)
    args = [Iv(lo, hi) for lo, hi in zip(lows, highs)]
    ctx.see(args)
    outs = _eval_jaxpr(closed.jaxpr, closed.consts, args, ctx)
    dtypes = [v.aval.dtype for v in closed.jaxpr.outvars]
    outs = [Iv(o.lo.astype(d), o.hi.astype(d), o.disc) for o, d in zip(outs, dtypes)]
    return IntervalResult([o.lo for o in outs], [o.hi for o in outs],
                          [o.disc for o in outs], ctx.mag, treedef)


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
