"""Soundness against the true system, by sampling (not against our own formulas)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.abstraction import compute_grid_clusters, cluster_members
from smdpjax.abstraction.clusters import max_lengths

DT = 0.1


def friction_unicycle(x, u, w):
    """Nonlinear in state and noise; the heading is periodic."""
    speed = jnp.maximum(u[0] - w[0], 0.0)
    return jnp.array([x[0] + DT * speed * jnp.cos(x[2]), x[1] + DT * speed * jnp.sin(x[2]),
                      x[2] + DT * (u[1] + w[1])])


@pytest.fixture(scope="module")
def nonlinear():
    system = sj.System(friction_unicycle, actions=[[0.5, -6.0], [1.5, 3.0], [1.0, 0.0]],
                       noise=sj.Gaussian([0.4, 0.0], [0.5, 0.5]))
    grid = sj.StateGrid([0, 0, 0], [1, 1, 2 * np.pi], [6, 6, 8], periodic=[False, False, True],
                        reach=[([0.7, 0.7, 0], [1, 1, 2 * np.pi])], avoid=[([0.4, 0.3, 0], [0.6, 0.7, 2 * np.pi])])
    noise = sj.NoiseGrid.ball([0.4, 0.0], 2.0, [3, 3])
    return system, grid, noise


def test_every_sampled_successor_lies_in_its_cluster(nonlinear):
    system, grid, noise = nonlinear
    clusters = compute_grid_clusters(system, grid, noise)
    members = np.asarray(cluster_members(grid, clusters.boxes, max_lengths(clusters.boxes)))
    rng = np.random.default_rng(0)
    rows, acts, cells = (rng.integers(0, m, 4000) for m in members.shape[:3])
    x_lo, x_hi = (np.asarray(b) for b in grid.cell_bounds(clusters.rows[rows]))
    w_lo, w_hi = (np.asarray(b)[cells] for b in noise.boxes())
    # corners are where interval bounds are tight, so sample them as often as the inside; cells
    # are half-open, so the upper corner is the last float below an excluded face
    corner = rng.integers(0, 2, x_lo.shape).astype(bool)
    top = np.where(np.asarray(grid.upper_attained(clusters.rows[rows])), x_hi, np.nextafter(x_hi, -np.inf))
    x = np.where(rng.uniform(size=(4000, 1)) < 0.3, np.where(corner, x_lo, top), rng.uniform(x_lo, x_hi))
    w = rng.uniform(w_lo, w_hi)
    nxt = system.step(jnp.asarray(x), jnp.asarray(acts), jnp.asarray(w))
    cell = np.asarray(grid.locate(nxt))
    cell = np.where(cell < 0, grid.sink, cell)
    hit = np.any(members[rows, acts, cells] == cell[:, None], axis=1)
    assert hit.all(), f"{(~hit).sum()} successors outside their cluster"
    # the heading wraps: some clusters must span the 2 pi seam
    heading = members[..., :-1] % grid.cells[2]
    valid = members[..., :-1] <= grid.sink - 1
    seam = np.any(valid & (heading == 0), -1) & np.any(valid & (heading == grid.cells[2] - 1), -1)
    assert seam.any()


def test_empirical_transition_frequencies_lie_in_imdp_intervals(nonlinear):
    system, grid, noise = nonlinear
    imdp = sj.abstract(system, grid, noise, "imdp")
    rng = np.random.default_rng(1)
    samples = 20000
    key = jax.random.PRNGKey(2)
    checked = 0
    for row in rng.choice(imdp.num_rows, 6, replace=False):
        cell = int(imdp.rows[row])
        lo, hi = (np.asarray(b) for b in grid.cell_bounds(cell))
        for action in range(system.num_actions):
            x = rng.uniform(lo, hi)  # the bounds hold for every x in the cell
            key, sub = jax.random.split(key)
            w = system.noise.sample(sub, (samples,))
            nxt = system.step(jnp.broadcast_to(jnp.asarray(x), (samples, 3)), jnp.full(samples, action), w)
            landed = np.asarray(grid.locate(nxt))
            landed = np.where(landed < 0, grid.sink, landed)
            freq = np.bincount(landed, minlength=grid.num_states) / samples
            succ = np.asarray(imdp.successors[row, action])
            listed = succ <= grid.sink
            low = np.zeros(grid.num_states)
            up = np.full(grid.num_states, float(imdp.upper_rest))
            low[succ[listed]] = np.asarray(imdp.lower[row, action])[listed]
            up[succ[listed]] = np.asarray(imdp.upper[row, action])[listed]
            # 4.5 standard deviations of a binomial frequency, plus a floor for p ~ 0
            tol = 4.5 * np.sqrt(np.maximum(freq * (1 - freq), 1e-4) / samples)
            assert np.all(freq >= low - tol), (cell, action)
            assert np.all(freq <= up + tol), (cell, action)
            checked += 1
    assert checked == 6 * system.num_actions
