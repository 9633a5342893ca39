"""Tests of the centred (mean-value) enclosure and of `enclose` (smdpjax.reach.centered)."""
import functools

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from hypothesis import given, settings, strategies as st  # noqa: E402

from smdpjax.reach.centered import centered_enclosure, enclose  # noqa: E402
from smdpjax.reach.interval import natural_enclosure  # noqa: E402

SETTINGS = settings(max_examples=50, deadline=None)
METHODS = ("natural", "centered", "both")
A_RANDOM = np.random.default_rng(11).normal(size=(4, 4))
U_UNICYCLE = jnp.array([1.0, 0.3])
U_ROOM = jnp.array([0.0, 1.0, 0.5, 0.2])


def unicycle(x, u, w, dt=0.1):
    px, py, th = x[0], x[1], x[2]
    v, om = u[0], u[1]
    s = jnp.maximum(v - w[0], 0.0)
    return jnp.stack([px + dt * s * jnp.cos(th), py + dt * s * jnp.sin(th), th + dt * (om + w[1])])


def room(x, u, w, a=0.05, b=0.1, c=0.2, xa=15.0):
    return (x + b * (xa - x) + a * (jnp.roll(x, 1) - x) + c * u) * (1 + w)


@jax.custom_jvp
def cube_with_wrong_derivative(x):
    return x ** 3


cube_with_wrong_derivative.defjvp(lambda p, t: (p[0] ** 3, jnp.zeros_like(t[0])))


# name -> (fn, [(shape, centre range, radius range) per argument])
LIBRARY = {
    "poly_repeated": (lambda x, y: x * x * y - 3 * x * y * y + x ** 4 - 2 * x + y,
                      [((), (-2, 2), (0, 1)), ((), (-2, 2), (0, 1))]),
    "x_sin_y_exp": (lambda x, y: x * jnp.sin(y) + jnp.exp(-x ** 2),
                    [((), (-2, 2), (0, 1)), ((), (-4, 4), (0, 2))]),
    "unicycle": (lambda x, w: unicycle(x, U_UNICYCLE, w),
                 [((3,), (-2, 2), (0, 0.5)), ((2,), (-0.5, 0.5), (0, 0.5))]),
    "unicycle_saturating": (lambda x, w: unicycle(x, jnp.array([0.2, 0.3]), w),
                            [((3,), (-2, 2), (0, 0.5)), ((2,), (-0.5, 0.5), (0, 0.5))]),
    "room": (lambda x, w: room(x, U_ROOM, w),
             [((4,), (17, 23), (0, 0.5)), ((4,), (-0.02, 0.02), (0, 0.02))]),
    "piecewise": (lambda x: jnp.where(x > 0, x ** 2, -x) + jnp.clip(x, -0.3, 0.4) + jnp.abs(x) * jnp.sign(x)
                  + jnp.tanh(3 * x), [((3,), (-1, 1), (0, 1))]),
    "matvec": (lambda x: A_RANDOM @ x + jnp.tanh(A_RANDOM @ x), [((4,), (-2, 2), (0, 1))]),
    "cancellation": (lambda x: (x + 0.1) - x + 1e3 * ((x * 3.0) - 2.0 * x - x), [((2,), (-1e3, 1e3), (0, 1e3))]),
    "fake_derivatives": (lambda x: cube_with_wrong_derivative(x) + jax.lax.stop_gradient(x) * x
                         + jax.nn.softplus(x), [((2,), (-2, 2), (0, 1))]),
}


def box_strategy(specs):
    def one(shape, centre, radius):
        size = int(np.prod(shape))
        c = st.lists(st.floats(*centre), min_size=size, max_size=size)
        r = st.lists(st.one_of(st.just(0.0), st.floats(1e-9, 1e-6), st.floats(*radius)),
                     min_size=size, max_size=size)
        return st.tuples(c, r).map(lambda cr: (np.reshape(np.subtract(cr[0], cr[1]), shape),
                                               np.reshape(np.add(cr[0], cr[1]), shape)))
    return st.tuples(*[one(*s) for s in specs]).map(
        lambda bs: (tuple(jnp.asarray(b[0]) for b in bs), tuple(jnp.asarray(b[1]) for b in bs)))


def sample_points(rng, lows, highs, n=2000):
    """Rows 0/1: the low/high corners; the next 254: random corners; the rest uniform."""
    pts = []
    for lo, hi in zip(lows, highs):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        u = rng.uniform(size=(n,) + lo.shape)
        u[:256] = rng.integers(0, 2, size=(256,) + lo.shape)
        u[0], u[1] = 0.0, 1.0
        pts.append(np.clip(np.where(u == 0, lo, np.where(u == 1, hi, lo + u * (hi - lo))), lo, hi))
    return pts


@functools.lru_cache(maxsize=None)
def batched(fn):
    return jax.jit(jax.vmap(fn))


@functools.lru_cache(maxsize=None)
def jitted(name, method):
    fn = LIBRARY[name][0]
    return jax.jit(lambda lows, highs: enclose(fn, lows, highs, method))


def assert_encloses(fn, lows, highs, lo, hi, seed=0):
    lo, hi = np.asarray(lo), np.asarray(hi)
    assert not np.any(np.isnan(lo)) and not np.any(np.isnan(hi)), (lo, hi)
    assert np.all(lo <= hi), (lo, hi)
    ys = np.asarray(batched(fn)(*sample_points(np.random.default_rng(seed), lows, highs)))
    ok = np.isnan(ys) | ((lo <= ys) & (ys <= hi))
    bad = np.argwhere(~ok)
    assert ok.all(), f"{len(bad)} points escape: y={ys[tuple(bad[0])]} box=[{lo}, {hi}]"


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", sorted(LIBRARY))
@SETTINGS
@given(data=st.data())
def test_soundness_by_sampling(name, method, data):
    fn, specs = LIBRARY[name]
    lows, highs = data.draw(box_strategy(specs))
    lo, hi = jitted(name, method)(lows, highs)
    assert_encloses(fn, lows, highs, lo, hi)
    if method == "both":  # never looser than either method
        for m in ("natural", "centered"):
            l, h = jitted(name, m)(lows, highs)
            assert np.all(np.asarray(lo) >= np.asarray(l)) and np.all(np.asarray(hi) <= np.asarray(h))


# ------------------------------------------------------------------ tightness

def test_affine_both_is_exact_interval_hull():
    rng = np.random.default_rng(2)
    A, b = rng.normal(size=(5, 3)), rng.normal(size=5)
    zl = rng.normal(size=3)
    zh = zl + rng.uniform(0.01, 2.0, size=3)
    zc, zr = (zl + zh) / 2, (zh - zl) / 2
    expect_lo, expect_hi = b + A @ zc - np.abs(A) @ zr, b + A @ zc + np.abs(A) @ zr
    for method in ("both", "centered"):
        lo, hi = enclose(lambda z: A @ z + b, (jnp.asarray(zl),), (jnp.asarray(zh),), method)
        # the centred form alone carries a 2**-30 * magnitude allowance for float rounding
        tol = dict(rtol=1e-12) if method == "both" else dict(rtol=1e-12, atol=1e-7)
        np.testing.assert_allclose(lo, expect_lo, **tol)
        np.testing.assert_allclose(hi, expect_hi, **tol)
        assert np.all(lo <= expect_lo + 1e-12) and np.all(hi >= expect_hi - 1e-12)


def test_x_minus_x_centered_removes_dependency():
    box = ((jnp.array(1.0),), (jnp.array(1.5),))
    lo, hi = enclose(lambda x: x - x, *box, method="natural")
    np.testing.assert_allclose([lo, hi], [-0.5, 0.5], rtol=1e-12)
    for method in ("centered", "both"):
        lo, hi = enclose(lambda x: x - x, *box, method=method)
        assert lo <= 0.0 <= hi and hi - lo < 1e-8


@pytest.mark.parametrize("method", ["centered", "both"])
def test_float_rounding_of_fn_is_covered(method):
    # J of (x + 0.1) - x is exactly 0, so the mean-value form alone would give [f(zc)] only; the
    # float values at other points differ by rounding (this box was found escaping without the
    # rounding allowance).
    f = lambda x: (x + 0.1) - x
    a, b = -3.4053656700181563, 4.838859498797342
    lo, hi = enclose(f, (jnp.float64(a),), (jnp.float64(b),), method)
    ys = np.asarray(jax.jit(jax.vmap(f))(np.concatenate([np.linspace(a, b, 200001), [a, b]])))
    assert lo <= ys.min() and ys.max() <= hi and hi - lo < 1e-7


def test_centered_beats_natural_on_small_boxes_quadratically():
    f = lambda x: x * (1 - x) + jnp.sin(x) * jnp.cos(x) - x * x * x
    true_width = []
    excess = {"natural": [], "both": []}
    for r in (1e-2, 1e-3):
        box = ((jnp.array(0.4 - r),), (jnp.array(0.4 + r),))
        ys = f(jnp.linspace(0.4 - r, 0.4 + r, 20001))
        tw = float(ys.max() - ys.min())
        true_width.append(tw)
        for m in excess:
            lo, hi = enclose(f, *box, method=m)
            excess[m].append(float(hi - lo) - tw)
    assert excess["both"][0] < 0.2 * excess["natural"][0]
    # natural excess shrinks linearly (x10), the centred one quadratically (~x100)
    assert excess["both"][1] < excess["both"][0] / 50


def test_discontinuous_functions_fall_back_to_natural():
    for f in (jnp.sign, lambda x: jnp.where(x > 0.0, 1.0, 0.0) + x, jnp.floor,
              lambda x: (x > 0).astype(jnp.float64)):
        box = ((jnp.array(-0.5),), (jnp.array(0.7),))
        c_lo, c_hi = centered_enclosure(f, *box)
        assert c_lo == -np.inf and c_hi == np.inf
        np.testing.assert_array_equal(enclose(f, *box), natural_enclosure(f, *box))
        assert_encloses(f, *box, *enclose(f, *box))
    # ... but continuous piecewise functions keep the centred form
    lo, hi = centered_enclosure(lambda x: jnp.maximum(x, 0.0) + jnp.clip(x, -1.0, 1.0) + jnp.abs(x),
                                (jnp.array(-0.5),), (jnp.array(0.7),))
    assert np.isfinite(lo) and np.isfinite(hi)


def test_wrong_custom_derivatives_are_not_trusted():
    # jacfwd(cube_with_wrong_derivative) = 0 would give a point; the true derivative is used.
    box = ((jnp.array(1.0),), (jnp.array(2.0),))
    lo, hi = centered_enclosure(cube_with_wrong_derivative, *box)
    assert lo <= 1.0 and hi >= 8.0
    lo, hi = centered_enclosure(lambda x: jax.lax.stop_gradient(x) * x, *box)
    assert lo <= 1.0 and hi >= 4.0


def test_unknown_method_raises():
    with pytest.raises(ValueError, match="method"):
        enclose(jnp.sin, (jnp.array(0.0),), (jnp.array(1.0),), method="taylor")


def test_unsupported_primitive_raises_through_enclose():
    for method in METHODS:
        with pytest.raises(NotImplementedError, match="'atan2'"):
            enclose(lambda x: jnp.arctan2(x, 2.0), (jnp.array(0.0),), (jnp.array(1.0),), method)


# ------------------------------------------------------------------ transforms

@pytest.mark.parametrize("method", ["centered", "both"])
def test_jit_vmap_1000_boxes_match_unbatched(method):
    rng = np.random.default_rng(5)
    n = 1000
    xl = rng.uniform(18, 22, (n, 4))
    xh = xl + rng.uniform(0, 0.5, (n, 4))
    wl = rng.uniform(-0.02, 0.0, (n, 4))
    wh = wl + rng.uniform(0, 0.02, (n, 4))
    one = lambda a, b, c, d: enclose(lambda x, w: room(x, U_ROOM, w), (a, c), (b, d), method)
    lo, hi = jax.jit(jax.vmap(one))(xl, xh, wl, wh)
    single = jax.jit(one)
    for i in range(n):
        l, h = single(xl[i], xh[i], wl[i], wh[i])
        np.testing.assert_array_equal(l, lo[i])
        np.testing.assert_array_equal(h, hi[i])
    assert_encloses(lambda x, w: room(x, U_ROOM, w), (xl[3], wl[3]), (xh[3], wh[3]), lo[3], hi[3])


def test_vmap_over_actions_with_point_argument():
    # The reachable-set pattern: u enters as the same object in lows and highs (a point).
    us = jnp.stack([jnp.linspace(0.5, 1.5, 6), jnp.linspace(-0.3, 0.3, 6)], axis=1)
    xl, xh = jnp.array([0.0, 0.0, 0.1]), jnp.array([0.1, 0.1, 0.3])
    wl, wh = jnp.array([-0.1, -0.1]), jnp.array([0.1, 0.1])
    lo, hi = jax.jit(jax.vmap(lambda u: enclose(unicycle, (xl, u, wl), (xh, u, wh))))(us)
    single = jax.jit(lambda u: enclose(unicycle, (xl, u, wl), (xh, u, wh)))
    for k in range(us.shape[0]):
        l, h = single(us[k])
        np.testing.assert_allclose(l, lo[k], rtol=1e-15)
        np.testing.assert_allclose(h, hi[k], rtol=1e-15)
        u = us[k]
        assert_encloses(lambda x, w: unicycle(x, u, w), (xl, wl), (xh, wh), lo[k], hi[k])


@pytest.mark.parametrize("method", METHODS)
def test_gradients_of_width_are_finite(method):
    f = LIBRARY["x_sin_y_exp"][0]

    def width(xl, xh, yl, yh):
        lo, hi = enclose(f, (xl, yl), (xh, yh), method)
        return jnp.sum(hi - lo)
    args = (jnp.array(0.3), jnp.array(0.5), jnp.array(-0.2), jnp.array(0.4))
    grads = jax.grad(width, argnums=(0, 1, 2, 3))(*args)  # eager: XLA compiles this graph slowly
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))
    assert np.any(np.asarray(grads[1]) != 0)
