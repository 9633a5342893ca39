"""Verification of a fixed look-up-table controller for finite-horizon safety (the paper's third
case study, at two rooms): bounds for every class, nested, and containing the Monte Carlo estimate."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.abstraction import build, compute_grid_clusters

B, A, XA, C = 0.0334, 0.044, 6.0, 1.6
HORIZON = 15


def rooms(x, u, w):
    neighbours = jnp.roll(x, 1) + jnp.roll(x, -1) - 2 * x  # a ring of two rooms: each is the other's neighbour
    return (x + B * (XA - x) + A * neighbours / 2 + 0.8 * C * u) * (1 + w)


@pytest.fixture(scope="module")
def setup():
    heaters = np.array([[0, 0], [0, 1], [1, 0], [1, 1]], float)
    system = sj.System(rooms, actions=heaters, noise=sj.Gaussian([0, 0], [0.0075, 0.0075]))
    grid = sj.StateGrid([17.5, 17.5], [22.0, 22.0], 12)
    noise = sj.NoiseGrid.ball([0, 0], 0.0295, 4)
    centers = np.asarray(grid.cell_centers())
    on = (centers < 19.75).astype(int)  # u_i = 1 below the middle of the band
    table = on[:, 0] * 2 + on[:, 1]  # index into `heaters`
    clusters = compute_grid_clusters(system, grid, noise)
    return system, grid, table, {k: build(k, grid, clusters) for k in ("imdp", "2imdp", "smdp")}


def test_safety_bounds_nest_and_contain_monte_carlo(setup):
    system, grid, table, abstractions = setup
    sols = {k: sj.verify(a, table, horizon=HORIZON, objective="safety") for k, a in abstractions.items()}
    lo = {k: np.asarray(s.lower) for k, s in sols.items()}
    up = {k: np.asarray(s.upper) for k, s in sols.items()}
    for inner in ("smdp", "2imdp"):
        assert np.all(lo[inner] >= lo["imdp"] - 1e-10) and np.all(up[inner] <= up["imdp"] + 1e-10)
    assert lo["smdp"][:-1].mean() > 0.5  # the heater keeps most rooms in the band

    cells = np.array([0, 30, 66, 77, 100, 143])
    per_cell = 2000
    x0 = sj.uniform_in_cells(grid, cells, per_cell, jax.random.PRNGKey(0))
    res = sj.simulate(system, sj.Controller(grid, np.append(table, 0)), x0, jax.random.PRNGKey(1),
                      max_steps=HORIZON, objective="safety")
    sat = np.asarray(res.satisfied).reshape(len(cells), per_cell).mean(axis=1)
    tol = 4.5 * np.sqrt(np.maximum(sat * (1 - sat), 1e-3) / per_cell)
    for k in sols:
        assert np.all(sat >= lo[k][cells] - tol), k
        assert np.all(sat <= up[k][cells] + tol), k


def test_safety_with_one_step_is_the_one_step_bound(setup):
    _, grid, table, abstractions = setup
    smdp = abstractions["smdp"]
    sol = sj.verify(smdp, table, horizon=1, objective="safety")
    v0 = smdp.initial_values("safety")
    expect = smdp.q_values(v0, "min", jnp.asarray(table[np.asarray(smdp.rows)]))
    np.testing.assert_allclose(np.asarray(sol.lower)[np.asarray(smdp.rows)], np.asarray(expect), atol=1e-9)


def test_abstracting_only_the_table_action_gives_the_same_bounds(setup):
    """abstract(..., policy=table) keeps |A| = 1 (as the paper does) and loses nothing."""
    system, grid, table, abstractions = setup
    noise = sj.NoiseGrid.ball([0, 0], 0.0295, 4)
    single = sj.abstract(system, grid, noise, "smdp", policy=table)
    assert single.num_actions == 1
    assert single.nbytes < abstractions["smdp"].nbytes / 3
    a = sj.verify(single, horizon=HORIZON, objective="safety")
    b = sj.verify(abstractions["smdp"], table, horizon=HORIZON, objective="safety")
    np.testing.assert_allclose(np.asarray(a.lower), np.asarray(b.lower), atol=1e-12)
    np.testing.assert_allclose(np.asarray(a.upper), np.asarray(b.upper), atol=1e-12)
    with pytest.raises(ValueError, match="pass the policy"):
        sj.verify(abstractions["smdp"], horizon=3, objective="safety")
    with pytest.raises(ValueError, match="policy entries"):
        sj.abstract(system, grid, noise, "smdp", policy=np.full(grid.num_cells, 4))


def test_a_settled_bound_is_not_backed_up_again(setup):
    """A stationary strategy's bounds once a backup leaves them unchanged (the 2I-MDP's and
    SMDP's optimistic bounds here settle at once): the same values as the same strategy given
    per time step, which backs up every step."""
    from smdpjax.synthesis import value_iteration

    _, grid, table, abstractions = setup
    settled = 0
    for kind, ab in abstractions.items():
        rows_policy = jnp.asarray(table[np.asarray(ab.rows)], jnp.int32)
        v0 = ab.initial_values("safety")
        lo, up, policy = value_iteration.finite_horizon(ab, v0, HORIZON, rows_policy)
        lo_t, up_t, _ = value_iteration.finite_horizon(ab, v0, HORIZON, jnp.tile(rows_policy, (HORIZON, 1)))
        np.testing.assert_allclose(np.asarray(lo), np.asarray(lo_t), rtol=0, atol=1e-14)
        np.testing.assert_allclose(np.asarray(up), np.asarray(up_t), rtol=0, atol=1e-14)
        assert policy.shape == (HORIZON, ab.rows.shape[0]) and np.all(np.asarray(policy) == np.asarray(rows_policy))
        once = ab.q_values(v0, "max", rows_policy)
        settled += bool(jnp.all(v0.at[ab.rows].set(once) == v0))
    assert settled >= 1  # the skip is exercised


def test_optimistic_bound_as_a_complement_and_its_rounding(setup):
    """A stationary strategy's optimistic backup is ``1 - min <gamma, 1 - v>``: within the two
    backups' rounding bounds of the maximizing one, exactly 1 where the mass can stay on safe
    states, and its two extra roundings are added to the upper bound's allowance only."""
    from smdpjax.synthesis import value_iteration

    _, grid, table, abstractions = setup
    for kind, ab in abstractions.items():
        rows_policy = jnp.asarray(table[np.asarray(ab.rows)], jnp.int32)
        v0 = ab.initial_values("safety")
        _, up, _ = value_iteration.finite_horizon(ab, v0, HORIZON, rows_policy)
        _, up_max, _ = value_iteration.finite_horizon(ab, v0, HORIZON, jnp.tile(rows_policy, (HORIZON, 1)))
        per_step = 2 * ab.rounding_per_backup() + value_iteration.COMPLEMENT_ROUNDING
        assert np.max(np.abs(np.asarray(up) - np.asarray(up_max))) <= HORIZON * per_step
        once = np.asarray(1.0 - ab.q_values(1.0 - v0, "min", rows_policy))
        assert np.all(once <= 1.0) and np.sum(once == 1.0) > 0.9 * once.size
        stationary = sj.verify(ab, table, horizon=HORIZON, objective="safety")
        per_time = sj.verify(ab, np.tile(table, (HORIZON, 1)), horizon=HORIZON, objective="safety")
        extra = HORIZON * value_iteration.COMPLEMENT_ROUNDING
        assert stationary.rounding_allowance == pytest.approx(per_time.rounding_allowance + extra, rel=1e-12, abs=0)
        assert extra > 1e-6 * per_time.rounding_allowance  # the test can tell the two apart
        # the same backups, the stationary strategy's actions picked once instead of per step
        # (other fusions of the same sums: the last bits may differ)
        np.testing.assert_allclose(np.asarray(stationary.lower), np.asarray(per_time.lower), rtol=0,
                                   atol=HORIZON * 2 * ab.rounding_per_backup())
