"""Direct IMDP bounds for additive noise (``abstract(..., bounds="direct")``).

Exact values come from mpmath (160 bits): per dimension the factor P(a <= c + v < b) of a centre
c, its extremes over the exact box of centres (the image of the cell under the affine or
trigonometric g of each test system, in real arithmetic), and their products.
"""

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax import storm
from smdpjax.abstraction import direct
from smdpjax.case_studies import robot_2d
from smdpjax.noise import Distribution

mp.mp.prec = 160
TINY = np.finfo(np.float64).tiny


# ---------------------------------------------------------------- exact reference (mpmath)

def mpf(x):
    return mp.mpf(float(x))


class Exact:
    """Per-dimension law of v_i = (B w)_i: ``("gauss", mean, std)`` or ``("unif", lo, hi)``, mpf."""

    def __init__(self, system):
        B = np.asarray(system.B)
        perm = np.argmax(B != 0, axis=1)
        self.laws = []
        for i, k in enumerate(perm):
            b = mpf(B[i, k])
            if isinstance(system.noise, sj.Gaussian):
                m, s = np.asarray(system.noise.mean())[k], np.asarray(system.noise.std)[k]
                self.laws.append(("gauss", b * mpf(m), abs(b) * mpf(s)))
            else:
                lo, hi = b * mpf(system.noise.low[k]), b * mpf(system.noise.high[k])
                self.laws.append(("unif", min(lo, hi), max(lo, hi)))

    def factor(self, i, a, b, c):
        """P(a <= c + v_i < b)."""
        kind, p, q = self.laws[i]
        if kind == "gauss":
            return mp.ncdf((b - c - p) / q) - mp.ncdf((a - c - p) / q)
        return max(mp.mpf(0), min(b, c + q) - max(a, c + p)) / (q - p)

    def outside(self, i, a, b, c):
        """P(c + v_i outside [a, b]), from the tails (no cancellation)."""
        kind, p, q = self.laws[i]
        if kind == "gauss":
            return mp.ncdf((a - c - p) / q) + mp.ncdf(-(b - c - p) / q)
        return 1 - self.factor(i, a, b, c)

    def mode(self, i, a, b):
        kind, p, q = self.laws[i]
        return (a + b) / 2 - (p if kind == "gauss" else (p + q) / 2)

    def extremes(self, i, a, b, c_lo, c_hi):
        """Exact (min, max) of the factor over c in [c_lo, c_hi] (unimodality)."""
        f = lambda c: self.factor(i, a, b, c)
        return min(f(c_lo), f(c_hi)), f(min(max(self.mode(i, a, b), c_lo), c_hi))

    def outside_extremes(self, i, a, b, c_lo, c_hi):
        """Exact (min, max) of the mass outside [a, b] over c in [c_lo, c_hi]."""
        f = lambda c: self.outside(i, a, b, c)
        return f(min(max(self.mode(i, a, b), c_lo), c_hi)), max(f(c_lo), f(c_hi))


def exact_rows(system, grid, box, pairs):
    """For each pair ``(row index, action)``: exact ``(min, max)`` arrays (mpf objects) over all
    ``N + 1`` states (cells in flat order, then the sink), from ``box(x_lo, x_hi, u)`` the exact
    box of centres g over the cell (lists of mpf ``(lo, hi)`` per dimension)."""
    ex = Exact(system)
    rows = grid.nonterminal
    out = []
    for r, a in pairs:
        lo, hi = grid.cell_bounds(int(rows[r]))
        cbox = box([mpf(v) for v in lo], [mpf(v) for v in hi], np.asarray(system.actions[a]))
        per_dim = []
        inside = []  # (min, max) of the mass outside the grid box along each dimension
        for i in range(grid.n):
            e = [mpf(v) for v in grid.edges[i]]
            per_dim.append([ex.extremes(i, e[j], e[j + 1], *cbox[i]) for j in range(len(e) - 1)])
            inside.append(ex.outside_extremes(i, e[0], e[-1], *cbox[i]))
        mins = np.empty(grid.num_states, object)
        maxs = np.empty(grid.num_states, object)
        for flat, multi in enumerate(np.ndindex(*grid.cells)):
            mins[flat] = mp.fprod(per_dim[i][j][0] for i, j in enumerate(multi))
            maxs[flat] = mp.fprod(per_dim[i][j][1] for i, j in enumerate(multi))
        mins[-1] = maxs[-1] = mp.mpf(0)
        for q_min, q_max in inside:  # 1 - prod(1 - q_i) as P + q - P q: no cancellation
            mins[-1] = mins[-1] + q_min - mins[-1] * q_min
            maxs[-1] = maxs[-1] + q_max - maxs[-1] * q_max
        out.append((mins, maxs))
    return out


def dense_row(imdp, r, a):
    """``(N + 1,)`` lower and upper bounds of every state for one pair (unlisted: [0, upper_rest])."""
    n = imdp.num_states
    lo, up = np.zeros(n), np.full(n, float(imdp.upper_rest))
    succ = np.asarray(imdp.successors[r, a]).astype(np.int64)
    listed = succ < n
    lo[succ[listed]] = np.asarray(imdp.lower[r, a])[listed]
    up[succ[listed]] = np.asarray(imdp.upper[r, a])[listed]
    return lo, up, listed


# ---------------------------------------------------------------- test systems

def affine_box(diag, offset):
    """Exact centre box of g_i(x, u) = diag_i x_i + offset(u)_i (mpf)."""
    def box(lo, hi, u):
        k = offset(u)
        return [(min(d * l, d * h) + c, max(d * l, d * h) + c) for d, l, h, c in zip(map(mpf, diag), lo, hi, k)]
    return box


def line_gauss():
    system = sj.System.additive(lambda x, u: 0.9 * x + u, 0.5, actions=np.array([[-0.3], [0.0], [0.25]]),
                                noise=sj.Gaussian([0.1], [0.4]))
    grid = sj.StateGrid([-2.0], [2.0], 16, reach=[([1.5], [2.0])], avoid=[([-2.0], [-1.5])])
    return system, grid, affine_box([0.9], lambda u: [mpf(u[0])])


def plane_gauss_permuted():
    def g(x, u):
        return jnp.array([x[0] + 0.3 * u[0], -0.7 * x[1] + u[1]])
    B = np.array([[0.0, -0.3], [0.2, 0.0]])  # a permutation times a diagonal, one scale negative
    system = sj.System.additive(g, B, actions=np.array([[1.0, 0.0], [-1.0, 0.2], [0.0, -0.4]]),
                                noise=sj.Gaussian([0.1, -0.2], [0.5, 0.8]))
    grid = sj.StateGrid([-1.0, -1.0], [1.0, 1.0], 10, reach=[([0.6, 0.6], [1.0, 1.0])],
                        avoid=[([-0.2, -0.2], [0.2, 0.2])])
    return system, grid, affine_box([1.0, -0.7], lambda u: [mpf(0.3) * mpf(u[0]), mpf(u[1])])


def plane_uniform():
    def g(x, u):
        return jnp.array([0.5 * x[0] + u[0], x[1] + u[1]])
    system = sj.System.additive(g, [1.0, 0.5], actions=np.array([[0.3, 0.0], [0.0, 0.1], [0.2, -0.1]]),
                                noise=sj.Uniform([-0.3, -0.1], [0.2, 0.4]))
    grid = sj.StateGrid([0.0, 0.0], [1.0, 1.0], [7, 9], reach=[([0.8, 0.8], [1.0, 1.0])])
    return system, grid, affine_box([0.5, 1.0], lambda u: [mpf(u[0]), mpf(u[1])])


def space_gauss():
    system = sj.System.additive(lambda x, u: x + u, 0.3, actions=np.array([[0.2, 0.0, -0.1], [0.0, 0.0, 0.0]]),
                                noise=sj.Gaussian([0.0, 0.0, 0.0], [1.0, 0.5, 0.7]))
    grid = sj.StateGrid([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [5, 4, 3], reach=[([0.8, 0.75, 0.0], [1.0, 1.0, 1.0])])
    return system, grid, affine_box([1.0, 1.0, 1.0], lambda u: [mpf(v) for v in u])


def unicycle_like():
    def g(x, u):
        return x + 0.1 * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])])
    system = sj.System.additive(g, 0.1, actions=(np.arange(8) * np.pi / 4)[:, None],
                                noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 12, reach=[([0.75, 0.75], [1.0, 1.0])])

    def box(lo, hi, u):
        th = mpf(u[0])
        return [(lo[0] + mpf(0.1) * mp.cos(th), hi[0] + mpf(0.1) * mp.cos(th)),
                (lo[1] + mpf(0.1) * mp.sin(th), hi[1] + mpf(0.1) * mp.sin(th))]
    return system, grid, box


SYSTEMS = {"line_gauss": line_gauss, "plane_gauss_permuted": plane_gauss_permuted, "plane_uniform": plane_uniform,
           "space_gauss": space_gauss, "unicycle_like": unicycle_like}


@pytest.fixture(scope="module", params=list(SYSTEMS))
def case(request):
    system, grid, box = SYSTEMS[request.param]()
    imdp = sj.abstract(system, grid, None, "imdp", bounds="direct", method="natural")
    return request.param, system, grid, box, imdp


# ---------------------------------------------------------------- (a) soundness against mpmath

def test_erfc_error_model():
    """The relative error bound of XLA's erfc used for every Gaussian bound, re-measured here on
    the backend that runs the tests (the module docstring has the full measurement)."""
    rng = np.random.default_rng(3)
    t = np.concatenate([rng.uniform(0, 26.5, 4000), 10.0 ** rng.uniform(-12, 0, 500), np.linspace(0, 26.5, 1001)])
    got = np.asarray(jax.jit(jax.lax.erfc)(jnp.asarray(t)))
    worst = 0.0
    for ti, gi in zip(t, got):
        exact = mp.erfc(mpf(ti))
        if exact < TINY:
            continue
        ratio = abs(mpf(gi) - exact) / (exact * (direct.ERFC_REL0 + direct.ERFC_REL2 * ti * ti))
        worst = max(worst, float(ratio))
    assert worst <= 1.0, worst
    assert worst > 0.05  # the model is not vacuous: measured errors use a good part of it


def test_bounds_contain_the_exact_extremes(case):
    """Every state of random pairs: lower <= exact min over the centre box, upper >= exact max;
    listed states within 1e-12 of them (no slack beyond rounding); unlisted ones below upper_rest."""
    name, system, grid, box, imdp = case
    rng = np.random.default_rng(0)
    r_count, a_count = imdp.num_rows, imdp.num_actions
    pairs = [(int(r), int(a)) for r, a in zip(rng.integers(0, r_count, 25), rng.integers(0, a_count, 25))]
    assert float(imdp.upper_rest) <= 1e-12
    for (r, a), (mins, maxs) in zip(pairs, exact_rows(system, grid, box, pairs)):
        lo, up, listed = dense_row(imdp, r, a)
        for s in range(imdp.num_states):
            assert mpf(lo[s]) <= mins[s], (name, r, a, s, lo[s], mins[s])
            assert mpf(up[s]) >= maxs[s], (name, r, a, s, up[s], maxs[s])
        succ = np.asarray(imdp.successors[r, a]).astype(np.int64)[listed]
        for s in succ:
            assert mins[s] - mpf(lo[s]) <= 1e-12 and mpf(up[s]) - maxs[s] <= 1e-12, (name, s, lo[s], up[s])
        assert np.all(np.diff(succ) > 0)  # increasing, the sink last


def test_unimodality_1d():
    """The extremes the bounds rest on: min at an endpoint of the centre box, max at the clipped
    mode, checked against 201 centres on a box wider than the noise (g = 3 x + u)."""
    system = sj.System.additive(lambda x, u: 3.0 * x + u, 1.0, actions=np.array([[0.0], [0.7]]),
                                noise=sj.Gaussian([0.05], [0.3]))
    grid = sj.StateGrid([-1.0], [1.0], 10)
    imdp = sj.abstract(system, grid, None, "imdp", bounds="direct", method="natural", threshold=0.0)
    ex = Exact(system)
    e = [mpf(v) for v in grid.edges[0]]
    checked = 0
    for r in (0, 5):
        for a in (0, 1):
            lo_x, hi_x = (mpf(v[0]) for v in grid.cell_bounds(r))
            c_lo, c_hi = 3 * lo_x + mpf(system.actions[a, 0]), 3 * hi_x + mpf(system.actions[a, 0])
            lo, up, _ = dense_row(imdp, r, a)
            for j in range(10):
                values = [ex.factor(0, e[j], e[j + 1], c_lo + (c_hi - c_lo) * k / 200) for k in range(201)]
                low, high = ex.extremes(0, e[j], e[j + 1], c_lo, c_hi)
                assert min(values) >= low and max(values) <= high * (1 + mpf(1e-30))
                assert mpf(lo[j]) <= min(values) and mpf(up[j]) >= max(values)
                checked += max(values) - min(values) > 0.05  # the box matters
    assert checked > 5


# ---------------------------------------------------------------- (b) tightness

@pytest.mark.parametrize("noise", ["gauss", "unif"])
def test_tight_on_exactly_representable_data(noise):
    """Integer faces, g = x + u with dyadic u, std 1 / the box [-1, 1]: every bound (all cells
    listed, threshold 0) equals the analytic extreme within 1e-12."""
    law = sj.Gaussian([0.0], [1.0]) if noise == "gauss" else sj.Uniform([-1.0], [1.0])
    system = sj.System.additive(lambda x, u: x + u, None, actions=np.array([[0.0], [0.5], [-1.25], [3.0]]), noise=law)
    grid = sj.StateGrid([0.0], [8.0], 8)
    imdp = sj.abstract(system, grid, None, "imdp", bounds="direct", method="natural", threshold=0.0)
    assert float(imdp.upper_rest) == 0.0
    pairs = [(r, a) for r in range(8) for a in range(4)]
    worst = 0.0
    for (r, a), (mins, maxs) in zip(pairs, exact_rows(system, grid, affine_box([1.0], lambda u: [mpf(u[0])]), pairs)):
        lo, up, listed = dense_row(imdp, r, a)
        assert listed.sum() == 9 if noise == "gauss" else True  # every cell and the sink
        for s in range(9):
            assert mpf(lo[s]) <= mins[s] and mpf(up[s]) >= maxs[s]
            worst = max(worst, float(mins[s] - mpf(lo[s])), float(mpf(up[s]) - maxs[s]))
    assert worst <= 1e-12, worst


def test_sink_tail_keeps_relative_accuracy():
    """Far from the grid's faces the sink's probability is ~1e-40: its bounds stay within a
    relative 1e-10 of it (tails are never computed as 1 - CDF)."""
    system = sj.System.additive(lambda x, u: x + u, None, actions=np.array([[0.0]]), noise=sj.Gaussian([0.0], [0.15]))
    grid = sj.StateGrid([-2.0], [2.0], 4)
    imdp = sj.abstract(system, grid, None, "imdp", bounds="direct", method="natural", threshold=0.0)
    (mins, maxs), = exact_rows(system, grid, affine_box([1.0], lambda u: [mpf(u[0])]), [(1, 0)])
    lo, up, _ = dense_row(imdp, 1, 0)
    assert 1e-45 < mins[-1] < 1e-30
    assert mpf(lo[-1]) <= mins[-1] and mins[-1] - mpf(lo[-1]) <= 1e-10 * mins[-1]
    assert mpf(up[-1]) >= maxs[-1] and mpf(up[-1]) - maxs[-1] <= 1e-10 * maxs[-1]


# ---------------------------------------------------------------- structure

def test_chunking_and_policy_do_not_change_the_bounds():
    system, grid, _ = plane_gauss_permuted()
    whole = sj.abstract(system, grid, None, "imdp", bounds="direct")
    small = sj.abstract(system, grid, None, "imdp", bounds="direct", entries_per_chunk=1000)
    for x, y in zip(jax.tree_util.tree_leaves(whole), jax.tree_util.tree_leaves(small)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    policy = np.arange(grid.num_cells) % system.num_actions
    fixed = sj.abstract(system, grid, None, "imdp", bounds="direct", policy=policy)
    assert fixed.num_actions == 1
    picked = whole.restrict(jnp.asarray(policy[grid.nonterminal], jnp.int32))
    k = fixed.successors.shape[-1]
    for x, y in ((fixed.successors, picked.successors), (fixed.lower, picked.lower), (fixed.upper, picked.upper)):
        y = np.asarray(y)
        np.testing.assert_array_equal(np.asarray(x), y[..., :k])
        assert np.all(y[..., k:] == (grid.num_states if y.dtype.kind == "i" else 0))


def test_threshold_trades_size_for_upper_rest():
    system, grid, _ = unicycle_like()
    fine = sj.abstract(system, grid, None, "imdp", bounds="direct")
    coarse = sj.abstract(system, grid, None, "imdp", bounds="direct", threshold=1e-4)
    assert coarse.successors.shape[-1] < fine.successors.shape[-1]
    assert 1e-6 < float(coarse.upper_rest) <= 1e-4
    assert float(fine.upper_rest) <= 1e-12
    a = sj.synthesize(fine)
    b = sj.synthesize(coarse)
    assert np.all(np.asarray(b.lower) <= np.asarray(a.lower) + 1e-9)  # more slack, never more guarantee
    assert float(np.mean(np.asarray(a.lower))) > float(np.mean(np.asarray(b.lower)))


def test_system_additive_declaration():
    g = lambda x, u: 0.5 * x + u
    w = jnp.array([0.3, -0.2])
    x, u = jnp.array([1.0, 2.0]), jnp.array([0.1, 0.0])
    for B, expect in ((None, w), (2.0, 2 * w), ([1.0, -3.0], jnp.array([0.3, 0.6])),
                      ([[0.0, 2.0], [1.0, 0.0]], jnp.array([-0.4, 0.3])),
                      ([[1.0, 1.0], [0.0, 1.0]], jnp.array([0.1, -0.2]))):
        system = sj.System.additive(g, B, actions=np.zeros((1, 2)), noise=sj.Gaussian([0, 0], [1, 1]))
        assert system.is_additive and system.B.shape == (2, 2)
        np.testing.assert_allclose(np.asarray(system.dynamics(x, u, w)), np.asarray(g(x, u) + expect), rtol=1e-15)
    assert not sj.System(lambda x, u, w: x + w, np.zeros((1, 2)), sj.Gaussian([0, 0], [1, 1])).is_additive


# ---------------------------------------------------------------- (c) bad input

class Laplace(Distribution):
    dim = 1

    def box_probability(self, low, high):
        return jnp.zeros(jnp.shape(low)[:-1])

    def support(self):
        return np.full(1, -np.inf), np.full(1, np.inf)

    def sample(self, key, shape=()):
        return jax.random.laplace(key, (*np.atleast_1d(shape), 1))


@pytest.fixture()
def no_work(monkeypatch):
    """Any enclosure of g (the first heavy step) fails the test: errors must come before it."""
    def fail(*args, **kwargs):
        raise AssertionError("the direct bounds started working before rejecting their input")
    monkeypatch.setattr(direct, "g_boxes", fail)


def test_bad_input_raises_before_any_work(no_work):
    grid1 = sj.StateGrid([0.0], [1.0], 4)
    grid2 = sj.StateGrid([0.0, 0.0], [1.0, 1.0], 4)
    gauss1, gauss2 = sj.Gaussian([0.0], [1.0]), sj.Gaussian([0.0, 0.0], [1.0, 1.0])
    plain = sj.System(lambda x, u, w: x + u + w, np.zeros((1, 1)), gauss1)
    with pytest.raises(ValueError, match="not declared additive.*System.additive"):
        sj.abstract(plain, grid1, None, "imdp", bounds="direct")
    additive = sj.System.additive(lambda x, u: x + u, None, actions=np.zeros((1, 1)), noise=gauss1)
    with pytest.raises(ValueError, match="kind='imdp'"):
        sj.abstract(additive, grid1, None, "smdp", bounds="direct")
    with pytest.raises(ValueError, match="unknown bounds"):
        sj.abstract(additive, grid1, None, "imdp", bounds="exact")
    full = sj.System.additive(lambda x, u: x + u, [[1.0, 0.5], [0.0, 1.0]], actions=np.zeros((1, 2)), noise=gauss2)
    with pytest.raises(ValueError, match="permutation times a diagonal"):
        sj.abstract(full, grid2, None, "imdp", bounds="direct")
    laplace = sj.System.additive(lambda x, u: x + u, None, actions=np.zeros((1, 1)), noise=Laplace())
    with pytest.raises(ValueError, match="Gaussian and Uniform"):
        sj.abstract(laplace, grid1, None, "imdp", bounds="direct")
    periodic = sj.StateGrid([0.0], [1.0], 4, periodic=[True])
    with pytest.raises(ValueError, match="periodic"):
        sj.abstract(additive, periodic, None, "imdp", bounds="direct")
    with pytest.raises(ValueError, match="for this 2-D grid"):  # 1-D noise on a 2-D grid
        sj.abstract(additive, grid2, None, "imdp", bounds="direct")
    for bad in (-1e-3, 1.0, float("nan")):
        with pytest.raises(ValueError, match="threshold"):
            sj.abstract(additive, grid1, None, "imdp", bounds="direct", threshold=bad)
    with pytest.raises(ValueError, match="must return shape"):
        wrong = sj.System.additive(lambda x, u: jnp.sum(x + u), None, actions=np.zeros((1, 1)), noise=gauss1)
        sj.abstract(wrong, sj.StateGrid([0.0], [1.0], 4), None, "imdp", bounds="direct")
    with pytest.raises(ValueError, match="policy"):
        sj.abstract(additive, grid1, None, "imdp", bounds="direct", policy=np.zeros(3, int))


def test_bad_declarations():
    gauss = sj.Gaussian([0.0, 0.0], [1.0, 1.0])
    g = lambda x, u: x
    with pytest.raises(ValueError, match="diagonal and must have length d = 2"):
        sj.System.additive(g, [1.0, 2.0, 3.0], actions=np.zeros((1, 1)), noise=gauss)
    with pytest.raises(ValueError, match=r"\(n, 2\) matrix"):
        sj.System.additive(g, np.ones((2, 3)), actions=np.zeros((1, 1)), noise=gauss)
    with pytest.raises(ValueError, match="finite"):
        sj.System.additive(g, [1.0, np.inf], actions=np.zeros((1, 1)), noise=gauss)
    with pytest.raises(TypeError, match="callable"):
        sj.System.additive(1.0, None, actions=np.zeros((1, 1)), noise=gauss)
    with pytest.raises(TypeError, match="Distribution"):
        sj.System.additive(g, None, actions=np.zeros((1, 1)), noise=(0.0, 1.0))


def test_unbounded_enclosure_of_g_is_reported():
    system = sj.System.additive(lambda x, u: 1.0 / x + u, None, actions=np.zeros((1, 1)), noise=sj.Gaussian([0.0], [1.0]))
    with pytest.raises(ValueError, match="cell 1 .*unbounded"):
        sj.abstract(system, sj.StateGrid([-1.0], [1.0], 4), None, "imdp", bounds="direct")


# ---------------------------------------------------------------- (d) Monte Carlo

def test_monte_carlo_lies_in_bounds():
    """Theorem 5 on a small robot (20 x 20 cells of width 1, 25 actions): the closed loop reaches
    the target with a probability in [p_low, p_up] (4.5 binomial standard deviations)."""
    study = robot_2d(cells=20, inputs=5)
    imdp = study.abstract("imdp", bounds="direct")
    sol = sj.synthesize(imdp)
    grid = study.state_grid
    cells = sj.metrics.initial_cells(grid, 6, seed=2)
    per_cell = 2000
    x0 = sj.uniform_in_cells(grid, cells, per_cell, jax.random.PRNGKey(0))
    res = sj.simulate(study.system, sj.Controller(grid, sol.policy), x0, jax.random.PRNGKey(1), max_steps=200)
    sat = np.asarray(res.satisfied).reshape(len(cells), per_cell).mean(axis=1)
    lo, up = np.asarray(sol.lower)[cells], np.asarray(sol.upper)[cells]
    tol = 4.5 * np.sqrt(np.maximum(sat * (1 - sat), 1e-3) / per_cell)
    assert np.all(sat >= lo - tol), (sat, lo)
    assert np.all(sat <= up + tol), (sat, up)
    assert np.max(up - lo) < 0.05  # tight: the check has teeth
    assert res.undecided < 0.01 * x0.shape[0]


# ---------------------------------------------------------------- (e) Storm

@pytest.mark.parametrize("make", [line_gauss, plane_uniform])
def test_storm_robust_values_equal_ours(make, tmp_path):
    pytest.importorskip("stormpy")
    system, grid, _ = make()
    imdp = sj.abstract(system, grid, None, "imdp", bounds="direct", threshold=1e-9)
    path = tmp_path / "direct.drn"
    storm.to_drn(imdp, path)
    model = storm.storm_model(path)
    nontrivial = False
    for horizon in (1, 5, 20):
        lower = np.asarray(sj.synthesize(imdp, horizon=horizon).lower)
        robust = storm.storm_values(model, horizon)
        nontrivial |= bool(np.any((lower > 0.01) & (lower < 0.99)))
        assert np.max(np.abs(robust - lower)) <= 1e-9
        assert np.all(lower <= robust + 1e-12)
    assert nontrivial


def test_benchmark_script_runs(tmp_path):
    """``benchmarks/direct_imdp.py`` at its smallest: one problem, the direct class, a few runs."""
    from benchmarks import direct_imdp

    out = tmp_path / "direct.json"
    rows = direct_imdp.main(["--problems", "unicycle", "--kinds", "direct", "--initial", "5",
                             "--trajectories", "50", "--out", str(out)])
    assert [r["kind"] for r in rows] == ["direct"] and rows[0]["mc_in_bounds"]
    assert rows[0]["e_avg"] < 0.02 and rows[0]["bounds_per_s"] > 0 and out.exists()
