import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.partition import AVOID, NONTERMINAL, REACH


def drift(x, u, w):
    return x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)


@pytest.fixture(scope="module")
def small_problem():
    system = sj.System(drift, actions=(np.arange(8) * np.pi / 4)[:, None], noise=sj.Gaussian([0, 0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 20, reach=[([0.8, 0.8], [1, 1])], avoid=[([0.4, 0.3], [0.6, 0.7])])
    noise = sj.NoiseGrid.ball([0, 0], 2.1, 12)
    return system, grid, noise


@pytest.fixture(scope="module")
def solutions(small_problem):
    system, grid, noise = small_problem
    return {kind: sj.synthesize(sj.abstract(system, grid, noise, kind), tol=1e-9) for kind in ("imdp", "smdp")}


def test_terminal_states_and_range(small_problem, solutions):
    _, grid, _ = small_problem
    for sol in solutions.values():
        lo, up = np.asarray(sol.lower), np.asarray(sol.upper)
        labels = grid.state_labels
        assert np.all(lo[labels == REACH] == 1) and np.all(up[labels == REACH] == 1)
        assert np.all(lo[labels == AVOID] == 0) and np.all(up[labels == AVOID] == 0)
        assert np.all((0 <= lo) & (lo <= up + 1e-12) & (up <= 1))
        assert sol.converged
        assert lo.shape == (grid.num_states,) and sol.policy.shape == (grid.num_states,)


def test_smdp_lower_bound_dominates_imdp(solutions):
    """Theorem 3 (lower bounds): p_low(SMDP) >= p_low(IMDP) at every state."""
    smdp, imdp = solutions["smdp"], solutions["imdp"]
    assert np.all(np.asarray(smdp.lower_optimal) >= np.asarray(imdp.lower_optimal) - 1e-8)
    assert np.mean(np.asarray(smdp.lower_optimal)) > np.mean(np.asarray(imdp.lower_optimal)) + 0.05
    assert smdp.iterations > 10


def test_lower_is_certified_value_of_policy(small_problem, solutions):
    """The reported lower bound is the policy's own worst case, never above the optimum."""
    system, grid, noise = small_problem
    abstraction = sj.abstract(system, grid, noise, "smdp")
    sol = solutions["smdp"]
    again = sj.verify(abstraction, np.asarray(sol.policy), tol=1e-9)
    np.testing.assert_allclose(np.asarray(again.lower), np.asarray(sol.lower), atol=1e-8)
    assert np.all(np.asarray(sol.lower) <= np.asarray(sol.lower_optimal) + 1e-12)
    assert np.max(np.asarray(sol.lower_optimal - sol.lower)) < 1e-6


def test_finite_horizon_is_exact_number_of_backups(small_problem):
    system, grid, noise = small_problem
    abstraction = sj.abstract(system, grid, noise, "smdp")
    v = abstraction.initial_values()
    for _ in range(3):  # three robust backups by hand
        q = abstraction.q_values(v, "min")
        v = v.at[abstraction.rows].set(q.max(axis=1))
    sol = sj.synthesize(abstraction, horizon=3)
    np.testing.assert_allclose(np.asarray(sol.lower), np.asarray(v), atol=1e-12)
    assert sol.policy.shape == (3, grid.num_states)
    longer = sj.synthesize(abstraction, horizon=6)
    assert np.all(np.asarray(longer.lower) >= np.asarray(sol.lower) - 1e-12)  # more time, more reach


def test_upper_dominates_lower_and_policy_values(small_problem, solutions):
    _, grid, _ = small_problem
    for sol in solutions.values():
        nt = grid.state_labels == NONTERMINAL
        assert np.all(np.asarray(sol.upper)[nt] >= np.asarray(sol.lower)[nt])


def test_rejects_bad_arguments(small_problem):
    system, grid, noise = small_problem
    abstraction = sj.abstract(system, grid, noise, "smdp")
    with pytest.raises(ValueError, match="tol"):
        sj.synthesize(abstraction, tol=0.0)
    with pytest.raises(ValueError, match="horizon"):
        sj.synthesize(abstraction, horizon=-1)
    with pytest.raises(ValueError, match="objective"):
        sj.synthesize(abstraction, horizon=3, objective="liveness")
    with pytest.raises(ValueError, match="finite horizon"):
        sj.synthesize(abstraction, objective="safety")
    with pytest.raises(TypeError, match="abstraction"):
        sj.synthesize(np.zeros(3))
    with pytest.raises(ValueError, match="policy entries"):
        sj.verify(abstraction, np.full(grid.num_cells, 99))
    with pytest.raises(ValueError, match="shape"):
        sj.verify(abstraction, np.zeros(5, int))


def test_jit_of_q_values_matches_eager(small_problem):
    system, grid, noise = small_problem
    for kind in ("imdp", "smdp"):
        abstraction = sj.abstract(system, grid, noise, kind)
        v = jax.random.uniform(jax.random.PRNGKey(3), (grid.num_states,), dtype=jnp.float64)
        eager = abstraction.q_values(v, "max")
        jitted = jax.jit(lambda a, v: a.q_values(v, "max"))(abstraction, v)
        np.testing.assert_allclose(np.asarray(eager), np.asarray(jitted), atol=1e-14)


@pytest.mark.parametrize("kind", ["imdp", "smdp"])
def test_early_stopping_only_loosens_the_bounds(small_problem, kind):
    """A loose tolerance must give bounds that contain the tight ones at every state: lower is
    iterated from below, upper from above. (Iterating upper from below, as a warm start from the
    lower bound would, under-estimates it when stopped early: checked, so the test has teeth.)"""
    system, grid, noise = small_problem
    abstraction = sj.abstract(system, grid, noise, kind)
    west = np.full(grid.num_cells, 4)  # drive into the left wall: p_up well below 1 on most cells
    loose, tight = (sj.verify(abstraction, west, tol=tol) for tol in (3e-2, 1e-10))
    slack = loose.rounding_allowance + tight.rounding_allowance  # each widened by its own allowance
    assert np.all(np.asarray(loose.lower) <= np.asarray(tight.lower) + slack)
    assert np.all(np.asarray(loose.upper) >= np.asarray(tight.upper) - slack)
    nt = grid.state_labels == NONTERMINAL
    assert np.mean(np.asarray(tight.upper)[nt]) < 0.9
    assert loose.gap >= tight.gap and loose.evaluation_iterations < tight.evaluation_iterations

    from smdpjax.synthesis import value_iteration
    fixed = abstraction.restrict(jnp.asarray(west[np.asarray(abstraction.rows)], jnp.int32))
    from_below, _, _ = value_iteration.evaluate(fixed, tight.lower, "max", 3e-2, 100_000)
    assert np.any(np.asarray(from_below) < np.asarray(tight.upper) - 1e-6)


@pytest.mark.parametrize("horizon", [None, 7])
@pytest.mark.parametrize("kind", ["imdp", "smdp"])
def test_lower_only_matches_full_synthesis(small_problem, kind, horizon):
    """``upper=False`` gives the same guarantee and strategy and only the trivial upper bound."""
    system, grid, noise = small_problem
    abstraction = sj.abstract(system, grid, noise, kind)
    full = sj.synthesize(abstraction, horizon=horizon, tol=1e-9)
    lean = sj.synthesize(abstraction, horizon=horizon, tol=1e-9, upper=False)
    np.testing.assert_array_equal(np.asarray(lean.policy), np.asarray(full.policy))
    np.testing.assert_allclose(np.asarray(lean.lower), np.asarray(full.lower), rtol=0, atol=1e-12)
    labels = grid.state_labels
    up = np.asarray(lean.upper)
    assert np.all(up[labels != AVOID] == 1) and np.all(up[labels == AVOID] == 0)
    assert np.all(np.asarray(full.upper) <= up)
