import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj


def drift(x, u, w):
    return x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)


@pytest.fixture(scope="module")
def solved():
    system = sj.System(drift, actions=(np.arange(8) * np.pi / 4)[:, None], noise=sj.Gaussian([0, 0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 20, reach=[([0.8, 0.8], [1, 1])], avoid=[([0.4, 0.3], [0.6, 0.7])])
    noise = sj.NoiseGrid.ball([0, 0], 2.1, 12)
    sols = {k: sj.synthesize(sj.abstract(system, grid, noise, k)) for k in ("imdp", "smdp")}
    # the MI-MDP's strategy sweeps iterate frozen LP multipliers (the default): checked here too
    sols["mimdp"] = sj.synthesize(sj.abstract(system, grid, noise, "mimdp", lp_backend="highs"))
    return system, grid, sols


@pytest.mark.parametrize("kind", ["smdp", "imdp", "mimdp"])
def test_monte_carlo_lies_in_bounds(solved, kind):
    """Theorem 5: the closed loop satisfies the specification with a probability in [p_low, p_up].

    Tolerance: 4.5 binomial standard deviations (n = 2000 per cell), so a correct implementation
    fails this with probability < 1e-5 per cell.
    """
    system, grid, sols = solved
    sol = sols[kind]
    controller = sj.Controller(grid, sol.policy)
    cells = sj.metrics.initial_cells(grid, 6, seed=1)
    per_cell = 2000
    x0 = sj.uniform_in_cells(grid, cells, per_cell, jax.random.PRNGKey(0))
    res = sj.simulate(system, controller, x0, jax.random.PRNGKey(1), max_steps=400)
    sat = np.asarray(res.satisfied).reshape(len(cells), per_cell).mean(axis=1)
    lo = np.asarray(sol.lower)[cells]
    up = np.asarray(sol.upper)[cells]
    tol = 4.5 * np.sqrt(np.maximum(sat * (1 - sat), 1e-3) / per_cell)
    assert np.all(sat >= lo - tol), (sat, lo)
    assert np.all(sat <= up + tol), (sat, up)
    assert res.undecided < 0.01 * x0.shape[0]


def test_controller_maps_points_to_cell_actions(solved):
    _, grid, sols = solved
    policy = np.asarray(sols["smdp"].policy)
    controller = sj.Controller(grid, policy)
    centers = np.asarray(grid.cell_centers())
    np.testing.assert_array_equal(np.asarray(controller(centers)), policy[:-1])
    assert int(controller(jnp.array([5.0, 5.0]))) == policy[-1]  # outside: the sink's entry


def test_trajectories_stop_when_decided(solved):
    system, grid, sols = solved
    controller = sj.Controller(grid, sols["smdp"].policy)
    x0 = jnp.array([[0.1, 0.1], [0.9, 0.9], [0.5, 0.5]])  # running, already in reach, in an obstacle
    res = sj.simulate(system, controller, x0, jax.random.PRNGKey(4), max_steps=50, return_trajectories=True)
    traj = np.asarray(res.trajectories)
    assert traj.shape == (51, 3, 2)
    assert bool(res.satisfied[1]) and int(res.steps[1]) == 0 and np.all(traj[:, 1] == traj[0, 1])
    assert bool(res.failed[2]) and int(res.steps[2]) == 0
    s = int(res.steps[0])
    if s < 50:
        assert np.all(traj[s:, 0] == traj[s, 0])  # frozen once decided


def test_safety_objective_counts_survivors(solved):
    system, grid, _ = solved
    stay = sj.Controller(grid, np.zeros(grid.num_states, int))  # always drive east
    x0 = jnp.tile(jnp.array([[0.05, 0.15]]), (200, 1))
    res = sj.simulate(system, stay, x0, jax.random.PRNGKey(5), max_steps=3, objective="safety")
    assert res.probability > 0.9  # three steps of 0.1 from x = 0.05 stay inside
    res = sj.simulate(system, stay, x0, jax.random.PRNGKey(5), max_steps=30, objective="safety")
    assert res.probability < 0.1  # thirty steps east leave the box


def test_bad_simulation_input(solved):
    system, grid, sols = solved
    controller = sj.Controller(grid, sols["smdp"].policy)
    with pytest.raises(ValueError, match="x0"):
        sj.simulate(system, controller, jnp.zeros((3, 3)), jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="objective"):
        sj.simulate(system, controller, jnp.zeros((3, 2)), jax.random.PRNGKey(0), objective="x")
    with pytest.raises(ValueError, match="policy"):
        sj.Controller(grid, np.zeros(5, int))
