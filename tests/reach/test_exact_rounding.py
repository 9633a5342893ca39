"""Outward rounding only where an operation rounded, and the open-end flags of the interval layer."""

from fractions import Fraction

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest

from smdpjax.reach.interval import interval_eval, natural_enclosure


def enclosure(fn, *args):
    """Enclosure of fn at point arguments (``lo is hi``)."""
    pts = tuple(jnp.float64(a) for a in args)
    return natural_enclosure(fn, pts, pts)


def rd(x: Fraction) -> float:
    """Largest float64 <= x."""
    f = float(x)
    return f if Fraction(f) <= x else float(np.nextafter(f, -np.inf))


def ru(x: Fraction) -> float:
    """Smallest float64 >= x."""
    f = float(x)
    return f if Fraction(f) >= x else float(np.nextafter(f, np.inf))


def test_sums_are_directed_roundings_of_the_exact_sum():
    rng = np.random.default_rng(0)
    a = rng.uniform(-2, 2, 300) * 10.0 ** rng.integers(-3, 4, 300)
    b = rng.uniform(-2, 2, 300) * 10.0 ** rng.integers(-3, 4, 300)
    add = jax.jit(lambda x, y: natural_enclosure(lambda p, q: p + q, (x, y), (x, y)))
    sub = jax.jit(lambda x, y: natural_enclosure(lambda p, q: p - q, (x, y), (x, y)))
    exact_count = 0
    for x, y in zip(a, b):
        for f, exact in ((add, Fraction(x) + Fraction(y)), (sub, Fraction(x) - Fraction(y))):
            lo, hi = (float(v) for v in f(jnp.float64(x), jnp.float64(y)))
            assert (lo, hi) == (rd(exact), ru(exact))  # the tightest float bounds, nothing wider
            exact_count += lo == hi
    assert exact_count > 0  # some sums are exact: then lo == hi == the sum


@pytest.mark.parametrize("x, y", [(0.1, 0.0), (0.1, 1.0), (0.1, 0.5), (3.0, 0.25), (0.75, -6.0), (2.0 ** 600, 2.0 ** -700)])
def test_exact_products_are_not_widened(x, y):
    lo, hi = enclosure(lambda p, q: p * q, x, y)
    assert float(lo) == float(hi) == float(Fraction(x) * Fraction(y))


def test_inexact_products_move_one_float_step_and_quotients_a_few():
    rng = np.random.default_rng(1)
    for x, y in rng.uniform(0.1, 10, size=(200, 2)):
        for op, exact, steps in ((lambda p, q: p * q, Fraction(x) * Fraction(y), 2),
                                 (lambda p, q: p / q, Fraction(x) / Fraction(y), 24)):
            lo, hi = (float(v) for v in enclosure(op, x, y))
            assert Fraction(lo) <= exact <= Fraction(hi)
            if Fraction(float(exact)) == exact:
                assert lo == hi
            else:  # products: round to nearest, then one step outward on each side; quotients
                top = lo  # (not correctly rounded by XLA on the CPU): the generous relative pad
                for _ in range(steps):
                    top = np.nextafter(top, np.inf)
                assert top >= hi


def test_exact_special_values_of_library_functions():
    for fn, x, value in [(jnp.sin, 0.0, 0.0), (jnp.cos, 0.0, 1.0), (jnp.exp, 0.0, 1.0), (jnp.tanh, 0.0, 0.0),
                         (jnp.sqrt, 1.0, 1.0), (jnp.log, 1.0, 0.0)]:
        lo, hi = enclosure(fn, x)
        assert float(lo) == float(hi) == value, fn


def test_a_stopped_vehicle_stays_exactly_on_its_face():
    # x + dt * max(v - w, 0) * cos(th): with friction above v the speed is exactly 0, so the lower end
    # of the reachable x must be exactly the cell's lower face (the 3-D unicycle of Table 1).
    def f(x, th, w):
        return x + 0.1 * jnp.maximum(1.5 - w, 0.0) * jnp.cos(th)

    lows = (jnp.float64(0.3), jnp.float64(0.0), jnp.float64(1.0))
    highs = (jnp.float64(0.4), jnp.float64(0.2), jnp.float64(2.0))
    lo, hi = natural_enclosure(f, lows, highs)
    assert float(lo) == 0.3
    assert float(hi) > 0.4


def test_library_sin_and_cos_are_faithful_here():
    """The assumption behind the one-step trig bounds on the CPU (interval._TRIG_REL): the exact
    value lies strictly between the float neighbours of XLA's result, measured on this machine."""
    if jax.default_backend() != "cpu":
        pytest.skip("the one-step bound is used on the CPU only")
    mpmath.mp.prec = 160
    rng = np.random.default_rng(2)
    k = np.arange(-40, 41) * (np.pi / 4)
    pts = np.concatenate([k, np.nextafter(k, np.inf), np.nextafter(k, -np.inf), rng.uniform(-50, 50, 3000),
                          np.arcsin(np.array([0.5, 0.25, 0.125])), np.arccos(np.array([0.5, 0.25, 0.125]))])
    for jf, mf in ((jnp.sin, mpmath.sin), (jnp.cos, mpmath.cos)):
        ys = np.asarray(jax.jit(jf)(jnp.asarray(pts)))
        for x, y in zip(pts, ys):
            t = mf(mpmath.mpf(float(x)))
            assert mpmath.mpf(float(np.nextafter(y, -np.inf))) < t < mpmath.mpf(float(np.nextafter(y, np.inf))), x


def test_trig_bounds_keep_the_sign_of_tiny_values():
    # cos(fl(pi/2)) = 6.1e-17 > 0 exactly; the bound must not straddle 0 (that would push a box
    # across a face it only approaches).
    lo, hi = enclosure(jnp.cos, np.pi / 2)
    if jax.default_backend() == "cpu":
        assert 0 < float(lo) <= float(mpmath.cos(mpmath.mpf(np.pi / 2))) <= float(hi)


def test_subnormal_inputs_and_constants_are_enclosed():
    tiny_sub = 1e-310
    lo, hi = natural_enclosure(lambda x: x + 1e-310, (jnp.float64(1.0),), (jnp.float64(1.0),))
    assert float(lo) <= 1.0 and float(hi) > 1.0  # 1 + 1e-310 > 1 in real arithmetic
    lo, hi = natural_enclosure(lambda x: x * 3.0, (jnp.float64(tiny_sub),), (jnp.float64(2 * tiny_sub),))
    assert float(lo) <= 3 * tiny_sub and float(hi) >= 6 * tiny_sub


# ------------------------------------------------------------------ open ends

def open_eval(fn, lows, highs, open_lows, open_highs):
    as_f = lambda xs: tuple(jnp.asarray(x, jnp.float64) for x in xs)
    res = interval_eval(fn, as_f(lows), as_f(highs), open_lows=open_lows, open_highs=open_highs)
    return [np.asarray(v) for v in (res.lo[0], res.hi[0], res.lo_open[0], res.hi_open[0])]


def test_open_ends_of_sums_and_the_state_cells_upper_face():
    # x in [0.3, 0.4) (the face 0.4 is not in the cell), w in a noise box with a density.
    lo, hi, lo_open, hi_open = open_eval(lambda x, w: x + 0.125 * w, (0.3, 0.0), (0.4, 0.0), (False, True),
                                         (True, True))
    assert (float(lo), float(hi)) == (0.3, 0.4) and not lo_open and hi_open
    # a closed input end stays closed when the sum is exact
    lo, hi, lo_open, hi_open = open_eval(lambda x, w: x + 0.125 * w, (0.3, 0.0), (0.4, 0.0), (False, False),
                                         (False, False))
    assert not hi_open and not lo_open


def test_a_saturation_makes_an_attained_end():
    # min(x + w, 0.5): the value 0.5 is taken with positive probability (an atom).
    fn = lambda x, w: jnp.minimum(x + w, 0.5)
    lo, hi, lo_open, hi_open = open_eval(fn, (0.4, 0.0), (0.45, 0.1), (False, True), (True, True))
    assert float(hi) == 0.5 and not hi_open
    # below the saturation the open end of the sum survives
    lo, hi, lo_open, hi_open = open_eval(fn, (0.1, 0.0), (0.2, 0.1), (False, True), (True, True))
    assert float(hi) > 0.29 and hi_open


def test_friction_makes_zero_speed_an_attained_lower_end():
    fn = lambda w: jnp.maximum(1.0 - w, 0.0)
    lo, hi, lo_open, hi_open = open_eval(fn, (0.5,), (1.5,), (True,), (True,))
    assert float(lo) == 0.0 and not lo_open and hi_open


def test_products_negation_and_zero():
    lo, hi, lo_open, hi_open = open_eval(lambda x: -2.0 * x, (0.25,), (0.5,), (False,), (True,))
    assert (float(lo), float(hi)) == (-1.0, -0.5) and lo_open and not hi_open
    lo, hi, lo_open, hi_open = open_eval(lambda x: 0.0 * x, (0.25,), (0.5,), (True,), (True,))
    assert float(lo) == float(hi) == 0.0 and not lo_open and not hi_open
    # [0, s] * [-1, -0.5] with 0 attained: the upper end 0 is attained
    lo, hi, lo_open, hi_open = open_eval(lambda s, c: s * c, (0.0, -1.0), (2.0, -0.5), (False, True),
                                         (True, True))
    assert float(hi) == 0.0 and not hi_open


def test_structural_ops_and_point_selects_carry_the_flags():
    fn = lambda x: jnp.concatenate([x[::-1], jnp.where(True, x, 0.0)])
    lo, hi, lo_open, hi_open = open_eval(fn, (np.array([0.0, 1.0]),), (np.array([0.5, 2.0]),),
                                         (np.array([False, True]),), (np.array([True, False]),))
    np.testing.assert_array_equal(hi_open, [False, True, True, False])
    np.testing.assert_array_equal(lo_open, [True, False, False, True])


def test_unknown_rules_close_the_ends():
    lo, hi, lo_open, hi_open = open_eval(lambda x: jnp.sort(x), (np.array([0.0, 1.0]),), (np.array([0.5, 2.0]),),
                                         (np.array([True, True]),), (np.array([True, True]),))
    assert not lo_open.any() and not hi_open.any()


def test_open_flags_agree_with_sampling():
    # Where an end is claimed open, no sample may attain it; where a saturation is hit, samples do.
    fn = lambda x, w: jnp.clip(x + 0.5 * w, 0.0, 0.5)
    lows, highs = (0.2, -0.1), (0.4, 0.2)
    lo, hi, lo_open, hi_open = open_eval(fn, lows, highs, (False, True), (True, True))
    rng = np.random.default_rng(3)
    x = rng.uniform(0.2, 0.4, 100000)
    w = rng.uniform(-0.1, 0.2, 100000)
    y = np.clip(x + 0.5 * w, 0.0, 0.5)
    assert np.all((y >= lo) & (y <= hi))
    if hi_open:
        assert not np.any(y == hi)
    if lo_open:
        assert not np.any(y == lo)


def test_gradients_flow_through_the_directed_roundings():
    # d/da of the upper bound of 0.1 x + sin(x) over [a, a + 0.3] is f'(a + 0.3) (f increasing there)
    def upper(a):
        return natural_enclosure(lambda x: 0.1 * x + jnp.sin(x) + x * x, (a,), (a + 0.3,))[1]
    g = jax.grad(upper)(jnp.float64(0.2))
    np.testing.assert_allclose(float(g), 0.1 + np.cos(0.5) + 2 * 0.5, rtol=1e-12)
