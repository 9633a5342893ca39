"""First-order (centred / mean-value) enclosure and its intersection with the natural one.

Mean-value form: for z in the box Z with midpoint zc,
    f(z) in f(zc) + J(Z) (Z - zc) ⊆ [f(zc)] + [-R, R],   R = sum_i |J_i(Z)|max . rad_i,
where J(Z) is the natural interval enclosure of ``jax.jacfwd(f)`` over Z and [f(zc)] the natural
enclosure of f at the point zc (which absorbs the rounding of f(zc)). It is tight when the box is
small (quadratic over-approximation error instead of the natural form's linear one) and removes
the dependency problem (x - x gives [0, 0]).

Soundness caveats handled here:
* The theorem needs f continuous on Z. `interval_eval` flags outputs that may jump inside the box
  (undecided ``where``/``cond`` predicates, ``sign``/``floor`` across a jump, ...); for those the
  centred form is unbounded, so ``"both"`` falls back to the natural enclosure.
* J must be the derivative of what f computes. custom_jvp/custom_vjp rules and stop_gradient can
  make ``jacfwd(fn)`` differ from that, so J is taken of fn's jaxpr with those inlined / removed
  (`_true_function`). Such constructs hidden inside loops/conds disable the centred form.
* The theorem encloses f in exact arithmetic; fn's float evaluation differs from it by rounding.
  We add 2**-30 times the largest finite magnitude of any intermediate over the box. That is a
  generous model of accumulated rounding, not a proof; `"both"` intersects with the natural form,
  which is rigorous for the float evaluation.
"""
from __future__ import annotations

from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import ClosedJaxpr, DropVar, Jaxpr, Literal

from .interval import _CALLS, _nudge, _sub_jaxpr, as_box, interval_eval, mid_rad, natural_enclosure

__all__ = ["centered_enclosure", "enclose"]

_ROUNDING_REL = 2.0 ** -30
_EPS = 2.0 ** -52
_INLINE = set(_CALLS)  # call-like primitives (jit, custom_jvp_call, ...): inlined
_FAKE_DERIVATIVE = {"custom_jvp_call", "custom_vjp_call", "custom_vjp_call_jaxpr", "stop_gradient"}
_inner = _sub_jaxpr


def _sub_jaxprs(params):
    for val in params.values():
        for j in (val if isinstance(val, (tuple, list)) else (val,)):
            if isinstance(j, ClosedJaxpr):
                yield j.jaxpr
            elif isinstance(j, Jaxpr):
                yield j


def _derivative_trustworthy(jaxpr) -> bool:
    """False if a custom derivative rule / stop_gradient sits inside a primitive we cannot inline
    (cond, scan, while): there jacfwd might not differentiate what is computed."""
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name in _INLINE:
            if not _derivative_trustworthy(_inner(eqn.params)[0]):
                return False
            continue
        if any(e.primitive.name in _FAKE_DERIVATIVE
               for sub in _sub_jaxprs(eqn.params) for e in _all_eqns(sub)):
            return False
    return True


def _all_eqns(jaxpr):
    for eqn in jaxpr.eqns:
        yield eqn
        for sub in _sub_jaxprs(eqn.params):
            yield from _all_eqns(sub)


def _true_function(closed: ClosedJaxpr) -> Callable:
    """fn rebuilt from its jaxpr with custom_jvp/vjp calls inlined (their primal) and
    stop_gradient removed, so that jacfwd differentiates exactly what fn computes."""
    def run(jaxpr, consts, args):
        env = dict(zip(jaxpr.constvars, consts))
        env.update(zip(jaxpr.invars, args))
        read = lambda v: v.val if isinstance(v, Literal) else env[v]
        for eqn in jaxpr.eqns:
            ins = [read(v) for v in eqn.invars]
            name = eqn.primitive.name
            if name in _INLINE:
                outs = run(*_inner(eqn.params), ins)
            elif name == "stop_gradient":
                outs = ins
            else:
                outs = eqn.primitive.bind(*ins, **eqn.params)
                outs = outs if eqn.primitive.multiple_results else [outs]
            for v, o in zip(eqn.outvars, outs):
                if not isinstance(v, DropVar):
                    env[v] = o
        return [read(v) for v in jaxpr.outvars]

    return lambda *z: run(closed.jaxpr, closed.consts, z)[0]


def _unbounded_like(x, flag):
    """(-inf, inf) where flag (NaN kept), else x's bounds."""
    nan = jnp.isnan(x[0]) | jnp.isnan(x[1])
    return (jnp.where(flag & ~nan, -jnp.inf, x[0]), jnp.where(flag & ~nan, jnp.inf, x[1]))


def _centered(fn, lows, highs, nat, staged: bool = False):
    """Centred enclosure given `nat`, the natural `interval_eval` of fn over the same box (for
    the continuity flag and the magnitude of intermediates)."""
    closed = jax.make_jaxpr(fn)(*lows)
    if len(closed.jaxpr.outvars) != 1:
        raise ValueError("fn must return exactly one array")
    out_aval = closed.out_avals[0]
    if not jnp.issubdtype(out_aval.dtype, jnp.inexact):
        raise ValueError(f"centered enclosure needs a float output, got {out_aval.dtype}")
    static_point = [lo is hi for lo, hi in zip(lows, highs)]
    is_float = [jnp.issubdtype(lo.dtype, jnp.inexact) for lo in lows]
    diff = [i for i in range(len(lows)) if is_float[i] and not static_point[i]]
    # A box in an integer argument cannot be handled by a derivative: no centred form.
    unbounded = any(not (is_float[i] or static_point[i]) for i in range(len(lows)))
    unbounded = unbounded or not _derivative_trustworthy(closed.jaxpr)

    mids, rads = list(lows), {}
    for i in diff:
        mids[i], rads[i] = mid_rad(lows[i], highs[i])
    zc = tuple(mids)
    f_lo, f_hi = natural_enclosure(fn, zc, zc)  # all-point box: tight, rounding of f(zc) only

    radius = jnp.zeros(out_aval.shape, out_aval.dtype)
    n_terms = 0
    if diff:
        jac = jax.jacfwd(_true_function(closed), argnums=tuple(diff))
        J = interval_eval(jac, lows, highs, staged=staged)
        nd = len(out_aval.shape)
        for i, jl, jh in zip(diff, J.lo, J.hi):
            mag = jnp.maximum(jnp.abs(jl), jnp.abs(jh))
            r = rads[i]
            term = jnp.where(r == 0, jnp.zeros_like(mag), mag * r)  # 0 * inf = 0: exact coordinates
            radius = radius + jnp.sum(term, axis=tuple(range(nd, term.ndim)))
            n_terms += int(np.prod(r.shape))
    # Sum of nonnegative products: computed value >= (1 - n eps) * exact; round the excess up.
    radius = _nudge(radius * (1 + 2 * (n_terms + 2) * _EPS), True)
    if nat.magnitude is not None:
        radius = radius + _ROUNDING_REL * nat.magnitude
    lo = _nudge(f_lo - radius, False)
    hi = _nudge(f_hi + radius, True)
    flag = nat.disc[0] if not unbounded else True
    if flag is False:
        return lo, hi
    return _unbounded_like((lo, hi), jnp.asarray(flag))


def centered_enclosure(fn: Callable, lows: Sequence, highs: Sequence):
    """Mean-value (centred) enclosure: f(z) in f(zc) + J([Z]) (Z - zc).

    fn: callable of positional float64 arrays returning ONE float array of shape S.
    lows, highs: tuples of arrays shaped like fn's arguments (``lows[i] is highs[i]`` = point).
    Returns (lo, hi) of shape S. Unbounded (-inf, inf) where fn may be discontinuous in the box.
    Traceable (jit/vmap/grad)."""
    lows, highs = as_box(lows, highs)
    nat = interval_eval(fn, lows, highs, track_magnitude=True)
    return _centered(fn, lows, highs, nat)


def enclose(fn: Callable, lows: Sequence, highs: Sequence, method: str = "both", open_lows=None,
            open_highs=None, with_open: bool = False, staged: bool = False):
    """Box enclosure of fn over the box by ``method``: "natural" (interval extension),
    "centered" (mean-value form) or "both" (their intersection: never looser than either).

    Same contract as `natural_enclosure`: returns (lo, hi) with fn's output shape. With
    ``with_open``, returns ``(lo, hi, lo_open, hi_open)``: open ends as in `interval_eval`, given
    the inputs' ``open_lows``/``open_highs``. Ends from the centred form are closed (its radius
    is not tracked end by end), so they are open only where the natural bound is the tighter."""
    if method not in ("natural", "centered", "both"):
        raise ValueError(f"unknown enclosure method {method!r}; use 'natural', 'centered' or 'both'")
    lows, highs = as_box(lows, highs)
    nat = interval_eval(fn, lows, highs, track_magnitude=method != "natural", open_lows=open_lows,
                        open_highs=open_highs, staged=staged)
    if len(nat.lo) != 1:
        raise ValueError(f"fn must return exactly one array, got {nat.treedef}")
    n_lo, n_hi, n_lo_open, n_hi_open = nat.lo[0], nat.hi[0], nat.lo_open[0], nat.hi_open[0]
    if method == "natural":
        return (n_lo, n_hi, n_lo_open, n_hi_open) if with_open else (n_lo, n_hi)
    c_lo, c_hi = _centered(fn, lows, highs, nat, staged)
    if method == "centered":
        closed = jnp.zeros(jnp.shape(c_lo), bool)
        return (c_lo, c_hi, closed, closed) if with_open else (c_lo, c_hi)
    # The centred bound is NaN when J is (0*inf); the natural one is then all we have.
    lo = jnp.where(jnp.isnan(c_lo), n_lo, jnp.maximum(n_lo, c_lo))
    hi = jnp.where(jnp.isnan(c_hi), n_hi, jnp.minimum(n_hi, c_hi))
    # Both are enclosures, so they overlap; should that ever fail, keep the hull, not nothing.
    empty = lo > hi
    lo = jnp.where(empty, jnp.minimum(n_lo, c_lo), lo)
    hi = jnp.where(empty, jnp.maximum(n_hi, c_hi), hi)
    if not with_open:
        return lo, hi
    return lo, hi, n_lo_open & (lo == n_lo), n_hi_open & (hi == n_hi)
