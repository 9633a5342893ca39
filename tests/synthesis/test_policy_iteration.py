"""Policy iteration: the chain's reach values, the adversary's distributions, and synthesis by it."""

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

import smdpjax as sj
from smdpjax.abstraction import compute_grid_clusters
from smdpjax.abstraction.mimdp import MIMDP
from smdpjax.synthesis import policy_iteration

pytest.importorskip("highspy")


def unicycle(x, u, w):
    return x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)


@pytest.fixture(scope="module")
def unicycle_12():
    system = sj.System(unicycle, actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 12, reach=[([0.75, 0.75], [1.0, 1.0])], avoid=[([0.4, 0.25], [0.6, 0.6])])
    return grid, compute_grid_clusters(system, grid, sj.NoiseGrid.ball([0.0, 0.0], 2.1, 6))


@pytest.fixture(scope="module")
def with_remainder():
    """6x6 unicycle with a noise ball of radius 3 sigma: ~5e-3 of mass per unlisted state, so the
    LPs' bucket and remainder variables carry mass."""
    system = sj.System(unicycle, actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 6, reach=[([2 / 3, 2 / 3], [1.0, 1.0])], avoid=[([1 / 3, 1 / 3], [0.5, 0.5])])
    return grid, compute_grid_clusters(system, grid, sj.NoiseGrid.ball([0.0, 0.0], 0.9, 3))


def test_reach_values_of_a_chain_are_its_exact_absorption_probabilities():
    """States 0..3 move, 4 is a reach cell (value 1), 5 an avoid cell, 6 the sink. State 3 loops
    with state 2 and never reaches 4 (value 0 by the graph, not by the solve); state 1 is listed
    twice (a padded row). Hand solution in rationals:
        x0 = 1/2 x1 + 1/4 + 1/4 * 0,  x1 = 1/3 x0 + 1/3 x1 + 1/3  ->  x1 = (1 + x0) / 2,
        x0 = (1 + x0) / 4 + 1/4  ->  x0 = 2/3, x1 = 5/6."""
    half, third, quarter = 0.5, 1 / 3, 0.25
    dense = np.array([[0, half, 0, 0, quarter, quarter, 0],
                      [third, third, 0, 0, third, 0, 0],
                      [0, 0, 0, 1.0, 0, 0, 0],
                      [0, 0, 1.0, 0, 0, 0, 0],
                      [third, third, 0, 0, third, 0, 0]])
    rows = np.array([0, 1, 2, 3, 1])
    terminal = np.array([0.7, 0.7, 0.7, 0.7, 1.0, 0.0, 0.0])  # row entries ignored
    values = policy_iteration.reach_values(sp.csr_matrix(dense), rows, terminal)
    exact = [Fraction(2, 3), Fraction(5, 6), 0, 0, 1, 0, 0]
    np.testing.assert_allclose(values, [float(f) for f in exact], rtol=0, atol=1e-15)  # a few ulps
    assert values[2] == 0.0 and values[3] == 0.0


def test_reach_values_from_a_guess_are_the_direct_solution(monkeypatch):
    """With a guess the chain is solved iteratively: the values of the direct solve to 1e-12, on
    a random chain with slowly leaking states; when the iteration cannot reach the residual
    tolerance (one step allowed), the direct solve's values exactly."""
    rng = np.random.default_rng(3)
    n_rows, n = 300, 303  # states 300 (reach), 301 (avoid), 302 (sink)
    dense = rng.uniform(0, 1, (n_rows, n)) * (rng.uniform(0, 1, (n_rows, n)) < 0.05)
    dense[:, 300:] *= 0.05  # a small leak to the absorbing states per step
    dense[np.arange(n_rows), rng.integers(0, n_rows, n_rows)] += 0.5
    dense /= dense.sum(axis=1, keepdims=True)
    rows = np.arange(n_rows)
    terminal = np.zeros(n)
    terminal[300] = 1.0
    matrix = sp.csr_matrix(dense)
    direct = policy_iteration.reach_values(matrix, rows, terminal)
    assert 0.05 < direct[:300].min() and direct[:300].max() < 0.95
    guess = np.clip(direct + rng.normal(0, 1e-3, n), 0, 1)
    np.testing.assert_allclose(policy_iteration.reach_values(matrix, rows, terminal, guess=guess), direct,
                               rtol=0, atol=1e-12)
    monkeypatch.setattr(policy_iteration, "KRYLOV_STEPS", 1)
    np.testing.assert_array_equal(policy_iteration.reach_values(matrix, rows, terminal, guess=guess), direct)


def test_reach_values_with_nothing_reachable_are_zero():
    dense = np.array([[0.5, 0.0, 0.5], [0.0, 1.0, 0.0]])
    values = policy_iteration.reach_values(sp.csr_matrix(dense), np.array([0, 1]), np.array([0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(values, np.zeros(3))


@pytest.mark.parametrize("adversary", ["min", "max"])
def test_worst_case_transitions_are_feasible_and_attain_the_lp_values(with_remainder, adversary):
    """Every row of ``worst_case_transitions`` is a distribution within the row's listed bounds
    and cluster bounds, whose unlisted mass fits the unlisted states, and whose value at ``v``
    is the row's LP value (the certified q-value, exact with optimal multipliers)."""
    grid, clusters = with_remainder
    mimdp = MIMDP.from_clusters(grid, clusters, lp_backend="highs")
    rng = np.random.default_rng(5)
    v = rng.uniform(0, 1, grid.num_states)
    v[-1] = 0.0
    actions = rng.integers(0, mimdp.num_actions, mimdp.num_rows)
    matrix, solved = mimdp.worst_case_transitions(v, actions, adversary)
    assert solved.all() and matrix.shape == (mimdp.num_rows, grid.num_states)
    gamma = matrix.toarray()
    q = np.asarray(jax.jit(lambda m, x, a: m.q_values(x, adversary, a))(mimdp, jnp.asarray(v), jnp.asarray(actions)))
    np.testing.assert_allclose(gamma @ v, q, rtol=0, atol=1e-8)
    imdp, n = mimdp.relaxation, grid.num_states
    rest = float(imdp.upper_rest)
    unlisted_mass = []
    for r, a in enumerate(actions):
        succ = np.asarray(imdp.successors[r, a])
        listed = succ < n
        g = gamma[r]
        assert abs(g.sum() - 1.0) <= 1e-9 and np.all(g >= -1e-12)
        np.testing.assert_array_less(np.asarray(imdp.lower[r, a])[listed] - 1e-9, g[succ[listed]])
        np.testing.assert_array_less(g[succ[listed]], np.asarray(imdp.upper[r, a])[listed] + 1e-9)
        for slots, clo, cup in zip(np.asarray(mimdp.cluster_slots[r, a]), np.asarray(mimdp.cluster_lower[r, a]),
                                   np.asarray(mimdp.cluster_upper[r, a])):
            members = succ[slots[slots < succ.size]]
            if members.size:
                assert clo - 1e-9 <= g[members].sum() <= cup + 1e-9
        others = np.setdiff1d(np.arange(n), succ[listed])
        unlisted_mass.append(g[others].sum())
        assert g[others].sum() <= others.size * rest + 1e-9
    assert max(unlisted_mass) > 1e-3  # the buckets and the remainder were exercised


def test_policy_iteration_certifies_at_least_value_iterations_bounds(unicycle_12):
    """Policy iteration ends at a strategy whose certified lower bound is value iteration's or
    higher (both within their tolerance of the optimum), in far fewer greedy backups; its
    ``lower`` is the strategy's certified value, as ``verify`` computes it."""
    grid, clusters = unicycle_12
    sols = {}
    for method in ("policy_iteration", "value_iteration"):
        mimdp = MIMDP.from_clusters(grid, clusters, lp_backend="highs")
        sols[method] = sj.synthesize(mimdp, tol=1e-9, method=method)
        assert sols[method].converged
    pi, vi = sols["policy_iteration"], sols["value_iteration"]
    assert np.all(np.asarray(pi.lower) >= np.asarray(vi.lower) - 1e-9)
    assert np.all(np.asarray(pi.lower) <= np.asarray(vi.upper) + 1e-9)
    assert np.all(np.asarray(pi.lower_optimal) >= np.asarray(pi.lower))
    np.testing.assert_allclose(np.asarray(pi.upper), np.asarray(vi.upper), rtol=0, atol=1e-7)
    assert pi.iterations < vi.iterations
    checked = sj.verify(MIMDP.from_clusters(grid, clusters, lp_backend="highs"), np.asarray(pi.policy), tol=1e-9)
    np.testing.assert_allclose(np.asarray(checked.lower), np.asarray(pi.lower), rtol=0, atol=1e-8)


def test_default_method_follows_the_class(unicycle_12, monkeypatch):
    grid, clusters = unicycle_12
    calls = []
    optimize = policy_iteration.optimize
    monkeypatch.setattr(policy_iteration, "optimize", lambda *a, **k: calls.append(1) or optimize(*a, **k))
    sj.synthesize(MIMDP.from_clusters(grid, clusters, lp_backend="highs"), tol=1e-6, upper=False)
    assert calls  # HiGHS vertices: policy iteration
    calls.clear()
    imdp = MIMDP.from_clusters(grid, clusters, lp_backend="highs").relaxation
    sj.synthesize(imdp, tol=1e-6, upper=False)
    assert not calls  # no adversary distributions: value iteration
    pytest.importorskip("clarabel")
    assert not MIMDP.from_clusters(grid, clusters, lp_backend="clarabel").exact_transitions


def test_a_failed_lp_falls_back_to_value_iteration(unicycle_12, monkeypatch):
    """Without a distribution for some row, policy iteration gives up and value iteration runs."""
    grid, clusters = unicycle_12
    mimdp = MIMDP.from_clusters(grid, clusters, lp_backend="highs")
    reference = sj.synthesize(MIMDP.from_clusters(grid, clusters, lp_backend="highs"), tol=1e-8,
                              method="value_iteration")
    original = MIMDP.worst_case_transitions

    def failing(self, v, actions, adversary="min"):
        matrix, solved = original(self, v, actions, adversary)
        return matrix, solved & (np.arange(solved.size) != 3)

    from smdpjax.synthesis import value_iteration

    monkeypatch.setattr(MIMDP, "worst_case_transitions", failing)
    ran = []
    optimize_lower = value_iteration.optimize_lower
    monkeypatch.setattr(value_iteration, "optimize_lower", lambda a, *r, **k: ran.append(a.kind) or optimize_lower(a, *r, **k))
    sol = sj.synthesize(mimdp, tol=1e-8, method="policy_iteration")
    assert ran == ["imdp", "mimdp"]  # the relaxation's warm start, then the MI-MDP's value iteration
    np.testing.assert_allclose(np.asarray(sol.lower), np.asarray(reference.lower), rtol=0, atol=1e-7)


def test_methods_are_checked_before_any_work(unicycle_12):
    grid, clusters = unicycle_12
    mimdp = MIMDP.from_clusters(grid, clusters, lp_backend="highs")
    with pytest.raises(ValueError, match="method must be None or one of"):
        sj.synthesize(mimdp, method="howard")
    with pytest.raises(ValueError, match="worst_case_transitions"):
        sj.synthesize(mimdp.relaxation, method="policy_iteration")
    assert mimdp.lps.stats["calls"] == 0
