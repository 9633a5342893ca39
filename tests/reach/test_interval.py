"""Tests of the natural interval extension (smdpjax.reach.interval)."""
import functools
import math
from fractions import Fraction

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from hypothesis import given, settings, strategies as st  # noqa: E402
from jax import lax  # noqa: E402

from smdpjax.reach.interval import natural_enclosure, supported_primitives  # noqa: E402

SETTINGS = settings(max_examples=50, deadline=None)
RNG_A = np.random.default_rng(7).normal(size=(3, 3))


# ------------------------------------------------------------------ sampling harness

def sample_points(rng, lows, highs, n=2000):
    """n points of the box per argument, (n, *shape): rows 0/1 are the low/high corners, the next
    254 random corners, the rest uniform inside."""
    pts = []
    for lo, hi in zip(lows, highs):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        u = rng.uniform(size=(n,) + lo.shape)
        u[:256] = rng.integers(0, 2, size=(256,) + lo.shape)
        u[0], u[1] = 0.0, 1.0
        p = np.where(u == 0, lo, np.where(u == 1, hi, lo + u * (hi - lo)))
        pts.append(np.clip(p, lo, hi))
    return pts


@functools.lru_cache(maxsize=None)
def batched(fn):
    return jax.jit(jax.vmap(fn))


def assert_encloses(fn, lows, highs, lo, hi, seed=0):
    lo, hi = np.asarray(lo), np.asarray(hi)
    assert not np.any(np.isnan(lo)) and not np.any(np.isnan(hi)), (lo, hi)
    assert np.all(lo <= hi), (lo, hi)
    pts = sample_points(np.random.default_rng(seed), lows, highs)
    ys = np.asarray(batched(fn)(*pts))
    ok = np.isnan(ys) | ((lo <= ys) & (ys <= hi))
    bad = np.argwhere(~ok)
    assert ok.all(), f"{len(bad)} points escape: y={ys[tuple(bad[0])]} box=[{lo}, {hi}]"


def box_strategy(shapes, centre=(-2.0, 2.0), radius=(0.0, 1.5)):
    """Boxes for each argument shape: centres in `centre`, radii mixing 0, tiny and wide."""
    def one(shape):
        size = int(np.prod(shape))
        c = st.lists(st.floats(*centre), min_size=size, max_size=size)
        r = st.lists(st.one_of(st.just(0.0), st.floats(1e-9, 1e-6), st.floats(*radius)),
                     min_size=size, max_size=size)
        return st.tuples(c, r).map(lambda cr: (np.reshape(np.subtract(cr[0], cr[1]), shape),
                                               np.reshape(np.add(cr[0], cr[1]), shape)))
    return st.tuples(*[one(s) for s in shapes]).map(
        lambda bs: (tuple(jnp.asarray(b[0]) for b in bs), tuple(jnp.asarray(b[1]) for b in bs)))


@functools.lru_cache(maxsize=None)
def jitted(name):
    fn = LIBRARY[name][0]
    return jax.jit(lambda lows, highs: natural_enclosure(fn, lows, highs))


def _scan_fn(x):
    def body(c, _):
        return c + 0.1 * jnp.sin(c) * c, c[0]
    c, ys = lax.scan(body, x, None, length=4)
    return c + ys.sum()


def _cond_fn(x):
    return lax.cond(x[0] > 0, lambda v: jnp.cos(v) * v, lambda v: v ** 2, x)


# name -> (fn, argument shapes, centre range, radius range); per-primitive coverage
LIBRARY = {
    "poly_repeated": (lambda x, y: x ** 3 - 2 * x * y + y * y * x - 3.0 * x + 1, [(), ()], (-2, 2), (0, 1.5)),
    "trig_wide": (lambda x: jnp.sin(x) * jnp.cos(2 * x) + jnp.cos(x - 1.0), [(3,)], (-10, 10), (0, 4)),
    "tan": (lambda x: jnp.tan(x), [(2,)], (-1.2, 1.2), (0, 0.3)),
    "monotone": (lambda x: jnp.tanh(x) + jax.nn.sigmoid(x) + jnp.log1p(jnp.exp(x)) + jnp.expm1(x / 3)
                 + jnp.arctan(x) + jnp.arcsinh(x) + jnp.cbrt(x) + jnp.exp2(x / 2), [(3,)], (-3, 3), (0, 1)),
    "positive_domain": (lambda x: jnp.sqrt(x) + jnp.log(x) + x ** 2.5 + lax.rsqrt(x) + x ** x,
                        [(2,)], (1.0, 3.0), (0, 0.9)),
    "int_pows": (lambda x: x ** 2 + x ** 3 - x ** 4 + jnp.square(x) + 0.01 * x ** 5, [(3,)], (-2, 2), (0, 1.5)),
    "neg_pows": (lambda x: x ** -2 + x ** -3 + x ** -1.0 + 1 / x, [(2,)], (0.5, 3), (0, 0.4)),
    "pow_float_int": (lambda x: x ** 2.0 + jnp.power(x, 3.0), [(2,)], (-2, 2), (0, 1.5)),
    "piecewise": (lambda x: jnp.where(x > 0.3, x * 2, -x) + jnp.clip(x, -0.5, 0.5) + jnp.abs(x)
                  + jnp.sign(x) + jnp.maximum(x, 0.1) - jnp.minimum(x, -0.2), [(3,)], (-1, 1), (0, 1)),
    "logic": (lambda x, y: jnp.where(((x > 0) & (y < 0.5)) | ~(x < y) ^ (x == y), x * y, x - y)
              + jnp.where(x != y, 1.0, 0.0), [(3,), (3,)], (-1, 1), (0, 1)),
    "indexing": (lambda x: x[0] * x[1:3].sum() + jnp.take(x, jnp.array([3, 0])).prod()
                 + x.at[1].set(x[2] ** 2).sum() + x.at[0].add(x[3]).max() + jnp.roll(x, 1)[0]
                 + jnp.concatenate([x[:2], -x[2:]]).min() + x[::-1][1]
                 + lax.dynamic_update_slice(x, x[:1] * 2, (2,))[2] + jnp.cumsum(x)[-1],
                 [(4,)], (-2, 2), (0, 1)),
    "matrix": (lambda x, m: (m @ x).sum() + (m.T @ m)[0, 1] + x @ m @ x + jnp.linalg.norm(x)
               + (RNG_A @ x)[2] + jnp.outer(x, x).sum(), [(3,), (3, 3)], (-1, 1), (0, 0.5)),
    "softplus_relu_erf": (lambda x: jax.nn.softplus(x) + jax.nn.relu(x - 0.2) + jax.scipy.special.erf(x)
                          + jnp.sinh(x) + jnp.cosh(x) + jnp.arcsin(x / 3) + jnp.arccos(x / 3) + jnp.arctanh(x / 3),
                          [(3,)], (-2, 2), (0, 0.9)),
    "reductions": (lambda x: jnp.sum(x ** 2, axis=0) + jnp.max(x, axis=1).sum() + jnp.min(x) + jnp.mean(x)
                   + jnp.sort(x.ravel())[2], [(2, 3)], (-2, 2), (0, 1)),
    "control_flow": (lambda x: _scan_fn(x).sum() + _cond_fn(x).sum(), [(2,)], (-1, 1), (0, 0.5)),
    "jit_custom": (lambda x: jax.jit(lambda v: jnp.exp(-v * v))(x).sum() + jax.checkpoint(jnp.sin)(x).sum()
                   + lax.stop_gradient(x[0]) * x[1], [(2,)], (-1, 1), (0, 1)),
}


@pytest.mark.parametrize("name", sorted(LIBRARY))
@SETTINGS
@given(data=st.data())
def test_natural_soundness_by_sampling(name, data):
    fn, shapes, centre, radius = LIBRARY[name]
    lows, highs = data.draw(box_strategy(shapes, centre, radius))
    lo, hi = jitted(name)(lows, highs)
    assert_encloses(fn, lows, highs, lo, hi)


# ------------------------------------------------------------------ tightness

def enc(fn, lo, hi):
    return natural_enclosure(fn, (jnp.asarray(lo, float),), (jnp.asarray(hi, float),))


@pytest.mark.parametrize("fn,a,b", [
    (jnp.exp, -1.3, 2.1), (jnp.log, 0.2, 7.0), (jnp.tanh, -0.7, 0.4), (jax.nn.sigmoid, -3.0, 1.0),
    (jnp.sqrt, 0.5, 3.0), (jnp.arctan, -2.0, 5.0), (jnp.expm1, -1.0, 1.0), (jnp.cbrt, -8.0, 2.0),
    (lambda x: x ** 3, -1.5, 0.5), (lambda x: -x, 1.0, 2.0), (lambda x: 1.0 / x, 0.5, 4.0),
    (lax.rsqrt, 0.5, 2.0)])
def test_monotone_functions_map_endpoints(fn, a, b):
    lo, hi = enc(fn, a, b)
    fa, fb = float(fn(jnp.float64(a))), float(fn(jnp.float64(b)))
    np.testing.assert_allclose([lo, hi], [min(fa, fb), max(fa, fb)], rtol=1e-12, atol=1e-14)
    assert lo <= min(fa, fb) and hi >= max(fa, fb)


def test_sin_over_zero_pi_is_zero_one():
    lo, hi = enc(jnp.sin, 0.0, math.pi)
    assert -1e-14 <= lo <= 0.0 and hi == 1.0


@pytest.mark.parametrize("fn,a,b,expect", [
    (jnp.cos, 0.5, 1.0, (math.cos(1.0), math.cos(0.5))),
    (jnp.cos, -0.5, 1.0, (math.cos(1.0), 1.0)),
    (jnp.cos, 3.0, 3.5, (-1.0, math.cos(3.5))),
    (jnp.sin, 2.0, 2.5, (math.sin(2.5), math.sin(2.0))),
    (jnp.sin, 4.0, 5.0, (-1.0, math.sin(4.0))),
    (jnp.sin, 1.0 + 2 * math.pi * 5, 1.3 + 2 * math.pi * 5, (math.sin(1.0), math.sin(1.3))),
    (jnp.sin, -1.0, 6.0, (-1.0, 1.0)),
    (jnp.cos, 0.0, 7.0, (-1.0, 1.0)),
])
def test_sin_cos_are_tight(fn, a, b, expect):
    lo, hi = enc(fn, a, b)
    np.testing.assert_allclose([lo, hi], expect, rtol=1e-12, atol=1e-14)
    assert lo <= expect[0] + 1e-15 and hi >= expect[1] - 1e-15 and -1 <= lo <= hi <= 1


@pytest.mark.parametrize("fn,a,b,expect", [
    (jnp.square, -1.0, 2.0, (0.0, 4.0)), (lambda x: x ** 4, -2.0, 1.0, (0.0, 16.0)),
    (jnp.abs, -3.0, 2.0, (0.0, 3.0)), (jnp.abs, -3.0, -2.0, (2.0, 3.0)),
    (lambda x: x ** -2, -1.0, 2.0, (0.25, math.inf)), (lambda x: x ** -2, -2.0, -1.0, (0.25, 1.0)),
    (lambda x: x ** -1, -1.0, 2.0, (-math.inf, math.inf)), (lambda x: x ** 3, -2.0, 1.0, (-8.0, 1.0)),
    (lambda x: x ** 2.0, -3.0, 1.0, (0.0, 9.0)), (jnp.cosh, -1.0, 0.5, (1.0, math.cosh(1.0))),
    (lambda x: 1.0 / x, -1.0, 1.0, (-math.inf, math.inf)),
])
def test_even_powers_abs_and_poles(fn, a, b, expect):
    lo, hi = enc(fn, a, b)
    np.testing.assert_allclose([lo, hi], expect, rtol=1e-12, atol=1e-14)


def test_tan_interval_containing_a_pole_is_unbounded():
    lo, hi = enc(jnp.tan, 1.0, 2.0)
    assert lo == -np.inf and hi == np.inf
    lo, hi = enc(jnp.tan, -1.0, 1.0)
    np.testing.assert_allclose([lo, hi], [math.tan(-1.0), math.tan(1.0)], rtol=1e-12)


def test_x_minus_x_natural_has_dependency_width():
    lo, hi = enc(lambda x: x - x, 1.0, 1.5)
    np.testing.assert_allclose([lo, hi], [-0.5, 0.5], rtol=1e-12)


def test_dot_with_point_matrix_is_exact_hull():
    rng = np.random.default_rng(1)
    A, b = rng.normal(size=(4, 3)), rng.normal(size=4)
    zl = rng.normal(size=3)
    zh = zl + rng.uniform(0.01, 1, size=3)
    lo, hi = natural_enclosure(lambda z: A @ z + b, (jnp.asarray(zl),), (jnp.asarray(zh),))
    zc, zr = (zl + zh) / 2, (zh - zl) / 2
    np.testing.assert_allclose(lo, b + A @ zc - np.abs(A) @ zr, rtol=1e-12)
    np.testing.assert_allclose(hi, b + A @ zc + np.abs(A) @ zr, rtol=1e-12)


def test_where_with_undecided_condition_is_hull_and_decided_is_exact():
    # Undecided: hull of both branches, each over the whole box (branches are not refined).
    f = lambda x: jnp.where(x > 0, 10.0 + x, -x)
    np.testing.assert_allclose(enc(f, -1.0, 2.0), (-2.0, 12.0), rtol=1e-12)
    np.testing.assert_allclose(enc(f, 1.0, 2.0), (11.0, 12.0), rtol=1e-12)
    np.testing.assert_allclose(enc(f, -2.0, -1.0), (1.0, 2.0), rtol=1e-12)


def test_domain_is_intersected_and_empty_domain_is_nan():
    np.testing.assert_allclose(enc(jnp.sqrt, -1.0, 4.0), (0.0, 2.0), rtol=1e-12)
    lo, hi = enc(jnp.log, -2.0, -1.0)
    assert np.isnan(lo) and np.isnan(hi)


def test_nan_inputs_propagate():
    for fn in (jnp.sin, jnp.exp, jnp.abs, lambda x: x * 2 + 1, lambda x: jnp.maximum(x, 0.0), jnp.tanh):
        lo, hi = enc(fn, np.nan, 1.0)
        assert np.isnan(lo) or np.isnan(hi)


def test_infinite_bounds_do_not_create_nan():
    # 1/x over a box containing 0 is unbounded; products/dots with it stay unbounded, not NaN.
    f = lambda x: jnp.asarray([[1.0, 0.0], [2.0, -1.0]]) @ (1.0 / x) + 0.0 * (1.0 / x)
    lo, hi = natural_enclosure(f, (jnp.array([-1.0, 1.0]),), (jnp.array([1.0, 2.0]),))
    assert not np.any(np.isnan(lo)) and not np.any(np.isnan(hi))
    assert lo[0] == -np.inf and hi[0] == np.inf


def test_point_arguments_stay_exact():
    u = jnp.array([0.3, -1.2])
    f = lambda x, u: x * u[0] + u[1] + jnp.take(x, jnp.array([1, 0]))[0]
    lo, hi = natural_enclosure(f, (jnp.array([1.0, 2.0]), u), (jnp.array([1.5, 2.5]), u))
    np.testing.assert_allclose([lo, hi], [[0.3 - 1.2 + 2.0, 0.6 - 1.2 + 2.0],
                                          [0.45 - 1.2 + 2.5, 0.75 - 1.2 + 2.5]], rtol=1e-12)


# ------------------------------------------------------------------ outward rounding

def test_point_add_rounds_outward():
    lo, hi = natural_enclosure(lambda a, b: a + b, (jnp.float64(0.1), jnp.float64(0.2)),
                               (jnp.float64(0.1), jnp.float64(0.2)))
    exact = Fraction(0.1) + Fraction(0.2)
    assert float(lo) < float(hi)
    assert Fraction(float(lo)) <= exact <= Fraction(float(hi))


@pytest.mark.parametrize("op,exact", [
    (lambda a, b: a * b, lambda a, b: a * b), (lambda a, b: a / b, lambda a, b: a / b),
    (lambda a, b: a - b, lambda a, b: a - b), (lambda a, b: jnp.sum(jnp.stack([a, b, a])), lambda a, b: 2 * a + b),
    (lambda a, b: jnp.stack([a, b]) @ jnp.stack([b, a]), lambda a, b: 2 * a * b)])
def test_point_ops_contain_exact_rational_result(op, exact):
    a, b = 0.1, 0.3
    lo, hi = natural_enclosure(op, (jnp.float64(a), jnp.float64(b)), (jnp.float64(a), jnp.float64(b)))
    e = exact(Fraction(a), Fraction(b))
    assert Fraction(float(lo)) <= e <= Fraction(float(hi))
    if Fraction(float(e)) != e:  # rounded: the bounds must bracket it strictly
        assert float(lo) < float(hi)


@pytest.mark.parametrize("reduce", ["dot", "sum"])
def test_cancellation_in_sums_is_enclosed(reduce):
    # Float summation of [1e16, 1, -1e16, 3] loses the small terms; the exact sum is 4.
    v = np.array([1e16, 1.0, -1e16, 3.0])
    fn = (lambda x: x @ jnp.ones(4)) if reduce == "dot" else jnp.sum
    for hi_shift in (0.0, 1.0):  # point vector, and an interval in one coordinate
        hi = v + np.array([0, hi_shift, 0, 0])
        lo_b, hi_b = natural_enclosure(fn, (jnp.asarray(v),), (jnp.asarray(v) if not hi_shift else jnp.asarray(hi),))
        assert Fraction(float(lo_b)) <= 4 and 4 + Fraction(hi_shift) <= Fraction(float(hi_b))


def test_flushed_subnormal_products_are_still_enclosed():
    # XLA on CPU flushes subnormals: 1e-300 * -1e-10 evaluates to -0.0; the exact value is -1e-310.
    lo, hi = natural_enclosure(lambda a, b: a * b, (jnp.float64(1e-300), jnp.float64(-1e-10)),
                               (jnp.float64(1e-300), jnp.float64(-1e-10)))
    e = Fraction(1e-300) * Fraction(-1e-10)
    assert Fraction(float(lo)) <= e <= Fraction(float(hi))


def _ulp_neighbourhood(x):
    """Largest |x* - x| over reals x* that round to x, or that XLA could have flushed to x."""
    _, exponent = math.frexp(abs(float(x)))  # |x| = m 2^e, m in [1/2, 1): ulp(x) = 2^(e - 53)
    half_ulp = Fraction(2) ** (exponent - 54) if x != 0 else Fraction(5e-324) / 2
    return half_ulp + Fraction(float(np.finfo(np.float64).tiny))


@pytest.mark.parametrize("rel,abs_", [(0.0, 0.0), (1e-13, 0.0), (0.0, 1e-15), (1e-12, 3e-300)])
def test_outward_step_covers_rounding_and_widening_exactly(rel, abs_):
    """``_nudge`` against exact rational arithmetic on values at binade edges, tiny, zero,
    subnormal and huge: up >= x* + rel|x| + abs_ for every x* that rounds to x (down: mirrored)."""
    from smdpjax.reach.interval import _nudge

    rng = np.random.default_rng(11)
    edges = [2.0 ** k for k in (-1022, -1000, -60, -1, 0, 1, 52, 60, 1000, 1023)]
    values = np.array(edges + [np.nextafter(e, 0.0) for e in edges] + [np.nextafter(e, np.inf) for e in edges]
                      + [0.0, 5e-324, 1e-310, 0.1, 1 / 3, 1e308, np.finfo(np.float64).max]
                      + list(rng.standard_normal(40) * 10.0 ** rng.integers(-300, 300, 40)))
    values = np.concatenate([values, -values])
    up = np.asarray(jax.jit(lambda v: _nudge(v, True, rel, abs_))(jnp.asarray(values)))
    down = np.asarray(jax.jit(lambda v: _nudge(v, False, rel, abs_))(jnp.asarray(values)))
    for x, u, d in zip(values, up, down):
        widen = Fraction(rel) * abs(Fraction(float(x))) + Fraction(abs_) + _ulp_neighbourhood(x)
        if np.isfinite(u):
            assert Fraction(float(u)) >= Fraction(float(x)) + widen, (x, u)
        else:
            assert u == np.inf
        if np.isfinite(d):
            assert Fraction(float(d)) <= Fraction(float(x)) - widen, (x, d)
        else:
            assert d == -np.inf


def test_products_treat_zero_times_infinity_as_zero_and_keep_nan():
    from smdpjax.reach.interval import _mul0

    special = np.array([0.0, -0.0, 1.5, -2.0, np.inf, -np.inf, np.nan])
    x, y = np.meshgrid(special, special)
    got = np.asarray(_mul0(jnp.asarray(x), jnp.asarray(y)))
    with np.errstate(invalid="ignore"):
        want = np.where(np.isnan(x * y) & ~np.isnan(x) & ~np.isnan(y), 0.0, x * y)
    np.testing.assert_array_equal(got, want)


def test_outward_step_of_infinities_and_nan():
    from smdpjax.reach.interval import _nudge

    big = np.finfo(np.float64).max
    v = jnp.array([np.inf, -np.inf, np.nan])
    np.testing.assert_array_equal(np.asarray(_nudge(v, True)), [np.inf, -big, np.nan])
    np.testing.assert_array_equal(np.asarray(_nudge(v, False)), [big, -np.inf, np.nan])
    assert float(jax.grad(lambda t: _nudge(t, True, 1e-13, 1e-15))(2.0)) == 1.0


# ------------------------------------------------------------------ transforms

def unicycle(x, w):
    s = jnp.maximum(1.0 - w[0], 0.0)
    return jnp.stack([x[0] + 0.1 * s * jnp.cos(x[2]), x[1] + 0.1 * s * jnp.sin(x[2]), x[2] + 0.1 * (0.3 + w[1])])


def test_jit_and_vmap_match_unbatched():
    rng = np.random.default_rng(3)
    n = 1000
    xl = rng.uniform(-2, 2, (n, 3))
    xh = xl + rng.uniform(0, 0.5, (n, 3))
    wl = rng.uniform(-0.2, 0.0, (n, 2))
    wh = wl + rng.uniform(0, 0.2, (n, 2))
    one = lambda a, b, c, d: natural_enclosure(unicycle, (a, c), (b, d))
    lo, hi = jax.jit(jax.vmap(one))(xl, xh, wl, wh)
    single = jax.jit(one)
    for i in range(n):
        l, h = single(xl[i], xh[i], wl[i], wh[i])
        np.testing.assert_array_equal(l, lo[i])
        np.testing.assert_array_equal(h, hi[i])
    l, h = one(xl[0], xh[0], wl[0], wh[0])  # eager
    np.testing.assert_array_equal(l, lo[0])
    np.testing.assert_array_equal(h, hi[0])
    assert_encloses(unicycle, (xl[5], wl[5]), (xh[5], wh[5]), lo[5], hi[5])


def test_vmap_with_shared_point_argument():
    f = lambda x, u: x * u + jnp.sin(u)
    us = jnp.linspace(-1, 1, 7)
    out = jax.vmap(lambda u: natural_enclosure(f, (jnp.array(1.0), u), (jnp.array(2.0), u)))(us)
    for k, u in enumerate(np.asarray(us)):
        lo, hi = natural_enclosure(f, (jnp.array(1.0), jnp.float64(u)), (jnp.array(2.0), jnp.float64(u)))
        np.testing.assert_array_equal([out[0][k], out[1][k]], [lo, hi])


def test_gradients_of_width_are_finite():
    def width(xl, xh, wl, wh):
        lo, hi = natural_enclosure(unicycle, (xl, wl), (xh, wh))
        return jnp.sum(hi - lo)
    args = (jnp.array([0.0, 0.0, 0.1]), jnp.array([0.1, 0.2, 0.3]), jnp.array([-0.1, -0.1]), jnp.array([0.1, 0.1]))
    grads = jax.grad(width, argnums=(0, 1, 2, 3))(*args)
    for g in grads:
        assert np.all(np.isfinite(g))
    assert np.any(np.asarray(grads[1]) != 0)  # the widening keeps derivative 1, not 0
    g2 = jax.jit(jax.grad(lambda a, b: jnp.sum(jnp.subtract(*enc(lambda x: jnp.exp(x) * jnp.sin(x), a, b)[::-1]))))(0.1, 0.5)
    assert np.isfinite(g2)


# ------------------------------------------------------------------ unsupported

@pytest.mark.parametrize("fn,name", [
    (lambda x: jnp.arctan2(x, 1.0 + x * x), "atan2"),
    (lambda x: lax.while_loop(lambda c: c < 3.0, lambda c: c + 1.0, x), "while"),
    (lambda x: lax.rem(x, 0.7), "rem"),
])
def test_unsupported_primitive_raises(fn, name):
    with pytest.raises(NotImplementedError, match=repr(name)):
        natural_enclosure(fn, (jnp.float64(0.1),), (jnp.float64(0.2),))


def test_box_dependent_index_raises():
    f = lambda x, i: x[i]
    with pytest.raises(NotImplementedError, match="dynamic_slice|gather"):
        natural_enclosure(f, (jnp.ones(3), jnp.int64(0)), (jnp.ones(3), jnp.int64(1)))


def test_supported_primitives_cover_the_required_list():
    required = """add sub mul div neg integer_pow pow sqrt square exp log log1p expm1 sin cos tan tanh
        logistic abs sign max min clamp select_n lt le gt ge eq ne and or not convert_element_type
        broadcast_in_dim reshape squeeze concatenate slice dynamic_slice gather scatter-add scatter
        dynamic_update_slice transpose reduce_sum reduce_max reduce_min dot_general stop_gradient copy
        copy_p jit pjit custom_jvp_call custom_vjp_call closed_call remat2""".split()
    assert not set(required) - set(supported_primitives())
