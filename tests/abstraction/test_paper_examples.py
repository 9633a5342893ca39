"""The paper's Examples 1 and 2, reconstructed.

x' = [[0.5, 0.2], [0, 0.5]] x + [0.25, 0.7] u + [0, 2.4] w, u = 1, w ~ U[-1, 1] split into 5 cells.
The state grid has one column ([-2, 0]) and six rows of height 0.96 starting at y = -4, so that
Reach(s1, a, c_i) meets exactly rows i and i+1: the SMDP clusters from s1 are {s_i, s_{i+1}}.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj

A = jnp.array([[0.5, 0.2], [0.0, 0.5]])
B = jnp.array([0.25, 0.7])
G = jnp.array([0.0, 2.4])


def lti(x, u, w):
    return A @ x + B * u[0] + G * w[0]


@pytest.fixture(scope="module")
def example():
    system = sj.System(lti, actions=[[1.0]], noise=sj.Uniform([-1.0], [1.0]))
    grid = sj.StateGrid([-2.0, -4.0], [0.0, -4.0 + 6 * 0.96], [1, 6])
    noise = sj.NoiseGrid.box([-1.0], [1.0], 5)
    return system, grid, sj.abstract(system, grid, noise, "imdp"), sj.abstract(system, grid, noise, "smdp")


def test_smdp_clusters_from_s1(example):
    _, grid, _, smdp = example
    members = np.asarray(smdp.members)[0, 0]  # row of s1, the only action
    clusters = [sorted(int(m) for m in row if m <= grid.sink) for row in members]
    assert clusters == [[0, 1], [1, 2], [2, 3], [3, 4], [4, 5]]
    np.testing.assert_allclose(np.asarray(smdp.prob), 0.2, rtol=1e-14)
    assert float(smdp.prob_rest) == 0.0


def test_imdp_bounds_from_s1(example):
    _, grid, imdp, _ = example
    succ = np.asarray(imdp.successors)[0, 0]
    lower = dict(zip(succ.tolist(), np.asarray(imdp.lower)[0, 0].tolist()))
    upper = dict(zip(succ.tolist(), np.asarray(imdp.upper)[0, 0].tolist()))
    assert sorted(s for s in lower if s <= grid.sink) == [0, 1, 2, 3, 4, 5]
    assert all(lower[s] == 0.0 for s in range(6))  # no reachable set fits inside one region
    np.testing.assert_allclose([upper[s] for s in range(6)], [0.2, 0.4, 0.4, 0.4, 0.4, 0.2], rtol=1e-14)


def test_gamma_imdp_is_feasible_for_imdp_but_not_smdp(example):
    _, grid, imdp, smdp = example
    gamma = np.array([0.2, 0.4, 0.4, 0.0, 0.0, 0.0])  # Example 1's spurious distribution
    succ = np.asarray(imdp.successors)[0, 0]
    lo = np.zeros(7)
    up = np.zeros(7)
    keep = succ <= grid.sink
    lo[succ[keep]] = np.asarray(imdp.lower)[0, 0][keep]
    up[succ[keep]] = np.asarray(imdp.upper)[0, 0][keep]
    assert np.all(gamma >= lo[:6]) and np.all(gamma <= up[:6]) and gamma.sum() == pytest.approx(1.0)
    # Every SMDP distribution puts at least P(c5) = 1/5 on {s5, s6}; gamma puts 0 there.
    v = jnp.zeros(grid.num_states).at[jnp.array([4, 5])].set(1.0)
    smdp_min = float(smdp.q_values(v, "min")[0, 0])
    imdp_min = float(imdp.q_values(v, "min")[0, 0])
    assert smdp_min == pytest.approx(0.2)
    assert imdp_min == pytest.approx(0.0)
    assert gamma[4] + gamma[5] < smdp_min
