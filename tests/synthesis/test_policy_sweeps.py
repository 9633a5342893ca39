"""Modified policy iteration in the optimization (``synthesize(policy_sweeps=)``)."""

import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.synthesis import value_iteration


def drift(x, u, w):
    return x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)


@pytest.fixture(scope="module")
def problem():
    system = sj.System(drift, actions=(np.arange(8) * np.pi / 4)[:, None], noise=sj.Gaussian([0, 0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 20, reach=[([0.8, 0.8], [1, 1])], avoid=[([0.4, 0.3], [0.6, 0.7])])
    return system, grid, sj.NoiseGrid.ball([0, 0], 2.1, 12)


@pytest.mark.parametrize("kind", ["imdp", "smdp"])
def test_sweeps_stay_below_the_optimum_and_save_greedy_backups(problem, kind):
    abstraction = sj.abstract(*problem, kind)
    v0 = abstraction.initial_values()
    rows = np.asarray(abstraction.rows)
    # the optimal robust value, by plain value iteration run far past the usual tolerance
    optimum, _, plain_backups, _ = value_iteration.optimize_lower(abstraction, v0, 1e-14, 100_000, policy_sweeps=0)
    optimum = np.asarray(optimum)
    slack = float(abstraction.rounding_per_backup()) * 20_000
    greedy = {}
    for sweeps in (0, 1, 8, 40):
        v, policy, backups, delta = value_iteration.optimize_lower(abstraction, v0, 1e-6, 100_000,
                                                                   policy_sweeps=sweeps, sweep_stop=0.0)
        v = np.asarray(v)
        assert float(delta) <= 1e-6
        assert np.all(v[rows] <= optimum[rows] + slack), sweeps  # every iterate is a lower bound
        assert np.max(optimum[rows] - v[rows]) < 1e-3, sweeps  # and it got close
        # each iteration is one greedy backup, then `sweeps` strategy backups except after the last
        greedy[sweeps] = (int(backups) + sweeps) // (sweeps + 1)
        assert (int(backups) + sweeps) % (sweeps + 1) == 0
        # the strategy found is (near-)optimal: its certified value is close to the optimum
        value = sj.verify(abstraction, np.asarray(jnp.zeros(abstraction.num_states, jnp.int32)
                                                  .at[abstraction.rows].set(policy)), tol=1e-9)
        assert np.max(optimum[rows] - np.asarray(value.lower)[rows]) < 2e-3, sweeps
        assert np.all(np.asarray(value.lower)[rows] <= optimum[rows] + slack)
    assert greedy[8] * 2 < greedy[0]  # the point of it: far fewer maximizations over all actions
    assert greedy[40] <= greedy[8]


@pytest.mark.parametrize("kind", ["imdp", "2imdp"])
def test_sweeps_stop_once_they_change_little_and_are_counted(problem, kind):
    """With ``sweep_stop`` an iteration's sweeps end at the first one that changes no value by
    more than that fraction of the greedy backup's change: fewer backups than running them all,
    each one counted, and the same optimum within the tolerance."""
    abstraction = sj.abstract(*problem, kind)
    v0 = abstraction.initial_values()
    rows = np.asarray(abstraction.rows)
    optimum = np.asarray(value_iteration.optimize_lower(abstraction, v0, 1e-14, 100_000, policy_sweeps=0)[0])
    slack = float(abstraction.rounding_per_backup()) * 20_000
    every, _, every_backups, _ = value_iteration.optimize_lower(abstraction, v0, 1e-6, 100_000, policy_sweeps=40,
                                                                sweep_stop=0.0)
    v, _, backups, delta = value_iteration.optimize_lower(abstraction, v0, 1e-6, 100_000, policy_sweeps=40,
                                                          sweep_stop=0.25)
    v = np.asarray(v)
    assert float(delta) <= 1e-6 and int(backups) < int(every_backups)
    assert (int(every_backups) + 40) % 41 == 0 and (int(backups) + 40) % 41 != 0  # sweeps cut short
    assert np.all(v[rows] <= optimum[rows] + slack) and np.max(optimum[rows] - v[rows]) < 1e-3
    assert np.max(np.abs(v[rows] - np.asarray(every)[rows])) < 1e-3
    # counted one by one: stopping after the first sweep (an infinite ratio) is one sweep each time
    cut = value_iteration.optimize_lower(abstraction, v0, 1e-6, 100_000, policy_sweeps=40, sweep_stop=np.inf)
    one = value_iteration.optimize_lower(abstraction, v0, 1e-6, 100_000, policy_sweeps=1, sweep_stop=0.0)
    assert int(cut[2]) == int(one[2]) and np.array_equal(np.asarray(cut[0]), np.asarray(one[0]))


def test_synthesize_default_sweeps_match_plain_value_iteration_within_tolerance(problem):
    smdp = sj.abstract(*problem, "smdp")
    plain = sj.synthesize(smdp, policy_sweeps=0)
    swept = sj.synthesize(smdp)  # default: |A| = 8 sweeps
    rows = np.asarray(smdp.rows)
    assert swept.converged and plain.converged
    np.testing.assert_allclose(np.asarray(swept.lower)[rows], np.asarray(plain.lower)[rows], atol=2e-4)
    np.testing.assert_allclose(np.asarray(swept.upper)[rows], np.asarray(plain.upper)[rows], atol=2e-4)
    assert np.all(np.asarray(swept.lower) <= np.asarray(swept.upper))


@pytest.mark.parametrize("bad", [-1, 1.5])
def test_bad_sweep_counts_are_refused(problem, bad):
    smdp = sj.abstract(*problem, "smdp")
    with pytest.raises(ValueError, match="policy_sweeps"):
        sj.synthesize(smdp, policy_sweeps=bad)
