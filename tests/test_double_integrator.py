"""The 4-D double integrator case study: its B, its dynamics, its box sizes, and its bounds
against Monte Carlo."""

import importlib

import jax
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.case_studies import double_integrator_4d
from smdpjax.reach import reachable_boxes

model = importlib.import_module("smdpjax.case_studies.double_integrator_4d")


def test_declared_additive_with_one_nonzero_per_row_of_B():
    study = double_integrator_4d(8)
    system = study.system
    assert system.is_additive and system.B.shape == (4, 2)
    np.testing.assert_array_equal(np.count_nonzero(system.B, axis=1), [1, 1, 1, 1])
    dt = model.DT
    np.testing.assert_array_equal(system.B, [[dt ** 2 / 2, 0], [0, dt ** 2 / 2], [dt, 0], [0, dt]])
    assert system.num_actions == 25 and sorted(set(system.actions.ravel())) == [-1.0, -0.5, 0.0, 0.5, 1.0]
    assert study.noise_grid.num_cells == 5 and study.state_grid.num_cells == 8 ** 4
    assert study.reach_method == "natural" and study.objective == "reach_avoid"


def test_dynamics_is_the_zero_order_hold_discretization():
    study = double_integrator_4d(8)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    low, high = study.state_grid.low, study.state_grid.high
    x = np.asarray(jax.random.uniform(keys[0], (1000, 4), minval=low, maxval=high))
    actions = np.asarray(jax.random.randint(keys[1], (1000,), 0, study.system.num_actions))
    w = np.asarray(0.5 * jax.random.normal(keys[2], (1000, 2)))
    dt = model.DT
    A = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    B = np.array([[dt ** 2 / 2, 0], [0, dt ** 2 / 2], [dt, 0], [0, dt]])
    u = study.system.actions[actions]
    expected = x @ A.T + (u + w) @ B.T
    np.testing.assert_allclose(study.system.step(x, actions, w), expected, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(model.zoh_step(x, u, w), expected, rtol=1e-14, atol=1e-14)


def test_default_grid_has_a_million_cells_and_bad_input_is_refused():
    study = double_integrator_4d()
    assert study.state_grid.num_cells == 32 ** 4 >= 10 ** 6
    assert double_integrator_4d((16, 16, 8, 8)).state_grid.num_cells == 16 * 16 * 8 * 8
    for bad in (0, 1.5, True, "2"):
        with pytest.raises(ValueError, match="noise_cells"):
            double_integrator_4d(8, noise_cells=bad)
    with pytest.raises(ValueError):
        double_integrator_4d(0)


def test_reachable_boxes_span_at_most_three_cells_at_the_default_size():
    """Every reachable box of 500 random cells of the 32^4 grid (all actions, noise cells) is
    narrower than two cells in every dimension, so it meets at most three."""
    study = double_integrator_4d()
    grid, noise = study.state_grid, study.noise_grid
    cells = np.random.default_rng(0).choice(grid.num_cells, 500, replace=False)
    x_lo, x_hi = grid.cell_bounds(cells)
    w_lo, w_hi = noise.boxes()
    enclose = jax.jit(reachable_boxes, static_argnums=0, static_argnames="method")
    lo, hi = enclose(study.system.dynamics, x_lo, x_hi, study.system.actions, w_lo, w_hi, method="natural")
    width = np.asarray(hi - lo).reshape(-1, 4).max(axis=0)
    cell = (grid.high - grid.low) / grid.cells
    assert np.all(width < 2 * cell), (width, cell)
    assert np.all(width > cell)  # and wider than one cell: the bound is not vacuous


@pytest.fixture(scope="module")
def solved():
    """16^4 cells: the smallest uniform grid on which the SMDP certifies the task (p_low is 0 on
    12^4)."""
    study = double_integrator_4d(16)
    smdp = study.abstract("smdp")
    return study, smdp, study.solve(smdp, tol=1e-5)


def test_small_grid_bounds_are_ordered_and_nontrivial(solved):
    study, smdp, solution = solved
    assert smdp.kind == "smdp" and smdp.num_actions == 25
    assert tuple(smdp.clusters.spec.max_lengths) == (3, 3, 3, 3)
    lower, upper = np.asarray(solution.lower), np.asarray(solution.upper)
    assert solution.converged and np.all(lower <= upper) and np.all((lower >= 0) & (upper <= 1))
    start = int(study.state_grid.locate(np.array([[1.0, 1.0, 0.01, 0.01]]))[0])
    assert lower[start] > 0.4  # from rest at (1, 1): the task is certified with a useful probability
    rows = np.asarray(smdp.rows)
    assert np.mean(lower[rows] > 0.5) > 0.25


def test_monte_carlo_lies_within_the_bounds(solved):
    study, _, solution = solved
    grid = study.state_grid
    lower, upper = np.asarray(solution.lower), np.asarray(solution.upper)
    start = int(grid.locate(np.array([[1.0, 1.0, 0.01, 0.01]]))[0])
    rows = np.asarray(grid.nonterminal)
    rng = np.random.default_rng(1)
    middling = rows[(lower[rows] > 0.2) & (lower[rows] < 0.9)]
    hopeless = rows[lower[rows] < 0.05]
    cells = np.concatenate([[start], rng.choice(middling, 4, replace=False), rng.choice(hopeless, 2, replace=False)])
    per_cell = 400
    x0 = sj.uniform_in_cells(grid, cells, per_cell, jax.random.PRNGKey(2))
    controller = sj.Controller(grid, solution.policy)
    result = sj.simulate(study.system, controller, x0, jax.random.PRNGKey(3), max_steps=study.max_steps)
    assert result.undecided == 0
    p_mc = np.asarray(result.satisfied).reshape(len(cells), per_cell).mean(axis=1)
    # 4.5 binomial standard deviations (floor at p(1-p) = 1e-4): a sound bound fails this ~1e-5 times
    tol = 4.5 * np.sqrt(np.maximum(p_mc * (1 - p_mc), 1e-4) / per_cell)
    assert np.all(p_mc >= lower[cells] - tol), (cells, p_mc, lower[cells])
    assert np.all(p_mc <= upper[cells] + tol), (cells, p_mc, upper[cells])
