"""The paper's tightness results (Theorems 2-3) as properties of random small systems."""

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import smdpjax as sj
from smdpjax.abstraction import build, compute_grid_clusters

KINDS = ("imdp", "2imdp", "smdp")


def parametric_dynamics(x, u, w):
    """A nonlinear 2-D system whose coefficients ride along in the input vector
    ``u = (u_0, u_1, a, b, gain, bend, noise_gain)`` (points to the interval arithmetic), so that
    every drawn system shares one compiled reachable-set computation per grid shape."""
    a, b, gain, bend, noise_gain = u[2], u[3], u[4], u[5], u[6]
    return jnp.array([a * x[0] + b * (x[1] - 0.5) + gain * u[0] + bend * jnp.sin(3 * x[1]) + noise_gain * w[0],
                      a * x[1] + gain * u[1] + bend * x[0] * x[1] + noise_gain * w[1]])


@st.composite
def random_problem(draw):
    """A random nonlinear 2-D system, grid, specification and noise partition."""
    a = draw(st.floats(0.6, 1.0))
    b = draw(st.floats(-0.3, 0.3, allow_subnormal=False))  # abstract() refuses subnormal data
    gain = draw(st.floats(0.05, 0.15))
    bend = draw(st.floats(-0.1, 0.1, allow_subnormal=False))
    noise_gain = draw(st.floats(0.02, 0.08))
    gaussian = draw(st.booleans())
    cells = draw(st.sampled_from([6, 8]))
    noise_cells = 3

    inputs = np.array([[1.0, 0.0], [0.0, 1.0], [0.7, 0.7]])
    actions = np.concatenate([inputs, np.tile([a, b, gain, bend, noise_gain], (3, 1))], axis=1)
    if gaussian:
        noise, ngrid = sj.Gaussian([0.0, 0.0], [1.0, 1.0]), sj.NoiseGrid.ball([0.0, 0.0], 2.0, noise_cells)
    else:
        noise, ngrid = sj.Uniform([-1.0, -1.0], [1.0, 1.0]), sj.NoiseGrid.box([-1, -1], [1, 1], noise_cells)
    w = 1.0 / cells
    grid = sj.StateGrid([0, 0], [1, 1], cells, reach=[([1 - 2 * w, 1 - 2 * w], [1, 1])],
                        avoid=[([0.5 - w / 2, 0.2], [0.5 + w / 2, 0.5])])
    return sj.System(parametric_dynamics, actions=actions, noise=noise), grid, ngrid


def assert_nested_under(policy, abstractions, pairs, tol, slack):
    """Evaluate one strategy on every class; each (inner, outer) interval must nest."""
    checked = {k: sj.verify(a, policy, tol=tol) for k, a in abstractions.items()}
    for inner, outer in pairs:
        assert np.all(np.asarray(checked[inner].lower) >= np.asarray(checked[outer].lower) - slack), (inner, outer)
        assert np.all(np.asarray(checked[inner].upper) <= np.asarray(checked[outer].upper) + slack), (inner, outer)


def solve_all(system, grid, ngrid):
    clusters = compute_grid_clusters(system, grid, ngrid)
    abstractions = {kind: build(kind, grid, clusters) for kind in KINDS}
    return abstractions, {kind: sj.synthesize(a, tol=1e-10) for kind, a in abstractions.items()}


@settings(max_examples=5, deadline=None)
@given(random_problem())
def test_bounds_are_ordered_and_nest(problem):
    """Theorem 3. Lower bounds, each class under its own optimal strategy:
    p_low(SMDP) >= p_low(IMDP) and p_low(2I-MDP) >= p_low(IMDP) at every state. Whole intervals,
    under one common strategy (the SMDP's, evaluated with ``verify``): SMDP inside IMDP and
    2I-MDP inside IMDP. (Upper bounds under each class's own strategy are not ordered in general.)
    """
    system, grid, ngrid = problem
    abstractions, sols = solve_all(system, grid, ngrid)
    low = {k: np.asarray(s.lower_optimal) for k, s in sols.items()}
    assert np.all(low["smdp"] >= low["imdp"] - 1e-8)
    assert np.all(low["2imdp"] >= low["imdp"] - 1e-8)

    assert_nested_under(np.asarray(sols["smdp"].policy), abstractions, (("smdp", "imdp"), ("2imdp", "imdp")),
                        tol=1e-10, slack=1e-8)


def test_mimdp_sits_between_imdp_and_smdp():
    """Theorem 3 with the MI-MDP: p_low(SMDP) >= p_low(MI-MDP) >= p_low(IMDP); under the SMDP's
    strategy the intervals nest, SMDP inside MI-MDP inside IMDP. (HiGHS backend for time; both
    backends are checked against reference LPs in tests/abstraction/test_mimdp.py.)"""
    def drift(x, u, w):
        return x + 0.15 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + 0.5 * w)

    system = sj.System(drift, actions=(np.arange(8) * np.pi / 4)[:, None], noise=sj.Gaussian([0, 0], [0.4, 0.4]))
    grid = sj.StateGrid([0, 0], [1, 1], 10, reach=[([0.7, 0.7], [1, 1])], avoid=[([0.4, 0.2], [0.5, 0.6])])
    clusters = compute_grid_clusters(system, grid, sj.NoiseGrid.ball([0, 0], 1.6, 4))
    abstractions = {k: build(k, grid, clusters) for k in ("imdp", "smdp")}
    abstractions["mimdp"] = build("mimdp", grid, clusters, lp_backend="highs")
    sols = {k: sj.synthesize(a, tol=1e-8) for k, a in abstractions.items()}
    low = {k: np.asarray(s.lower_optimal) for k, s in sols.items()}
    assert np.all(low["smdp"] >= low["mimdp"] - 1e-6) and np.all(low["mimdp"] >= low["imdp"] - 1e-6)
    assert low["mimdp"].mean() > low["imdp"].mean() + 0.3  # the clusters do bite here

    assert_nested_under(np.asarray(sols["smdp"].policy), abstractions, (("smdp", "mimdp"), ("mimdp", "imdp")),
                        tol=1e-8, slack=1e-6)
