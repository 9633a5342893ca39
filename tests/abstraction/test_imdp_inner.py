"""The IMDP inner problem against a general LP solver, on random interval polytopes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linprog

from smdpjax.abstraction import imdp as imdp_module
from smdpjax.abstraction import interval_min


def random_instance(rng, n_states, k, rest):
    succ = rng.choice(n_states, size=k, replace=False)
    lower = rng.uniform(0, 1, k) * rng.integers(0, 2, k)
    lower *= rng.uniform(0.2, 0.9) / max(lower.sum(), 1e-12)
    upper = lower + rng.uniform(0, 0.6, k) + rest
    unlisted = n_states - k
    if upper.sum() + unlisted * rest < 1:  # make it feasible
        upper *= (1 - unlisted * rest) / upper.sum() + 0.05
    values = rng.choice([0.0, 0.25, 0.5, 1.0], size=n_states) if rng.uniform() < 0.3 else rng.uniform(0, 1, n_states)
    return succ, lower, upper, values


def lp_min(succ, lower, upper, rest, values):
    n = values.size
    lo = np.zeros(n)
    hi = np.full(n, rest)
    lo[succ], hi[succ] = lower, upper
    res = linprog(values, A_eq=np.ones((1, n)), b_eq=[1.0], bounds=list(zip(lo, hi)), method="highs")
    assert res.status == 0
    return res.fun


@pytest.mark.parametrize("explicit_columns", [0, 48], ids=["reduction", "columns"])
@pytest.mark.parametrize("rest", [0.0, 1e-3, 0.02])
def test_interval_min_matches_lp(rest, explicit_columns, monkeypatch):
    # both ways of summing over successors (chosen by K) must solve the same problem exactly
    monkeypatch.setattr(imdp_module, "_EXPLICIT_COLUMNS", explicit_columns)
    rng = np.random.default_rng(int(rest * 1e4))
    n_states, k = 40, 9
    inst = [random_instance(rng, n_states, k, rest) for _ in range(300)]
    pad = np.full((len(inst), 3), n_states + 1)
    succ = jnp.asarray(np.c_[np.stack([i[0] for i in inst]), pad])[:, None]
    lower = jnp.asarray(np.c_[np.stack([i[1] for i in inst]), 0 * pad])[:, None]
    upper = jnp.asarray(np.c_[np.stack([i[2] for i in inst]), 0 * pad])[:, None]
    values = jnp.asarray(np.stack([i[3] for i in inst]))
    solve = jax.vmap(interval_min, in_axes=(0, 0, 0, 0, None))  # traced afresh: the monkeypatch applies
    got_min = np.asarray(solve(values, succ, lower, upper, rest))[:, 0]
    got_max = -np.asarray(solve(-values, succ, lower, upper, rest))[:, 0]
    expect_min = [lp_min(i[0], i[1], i[2], rest, i[3]) for i in inst]
    expect_max = [-lp_min(i[0], i[1], i[2], rest, -i[3]) for i in inst]
    np.testing.assert_allclose(got_min, expect_min, atol=1e-9)
    np.testing.assert_allclose(got_max, expect_max, atol=1e-9)


def test_interval_min_batched_rows_are_independent():
    rng = np.random.default_rng(7)
    n_states, k, rest = 30, 6, 0.01
    inst = [random_instance(rng, n_states, k, rest) for _ in range(20)]
    values = inst[0][3]
    succ = np.stack([i[0] for i in inst])
    lower = np.stack([i[1] for i in inst])
    upper = np.stack([i[2] for i in inst])
    got = np.asarray(interval_min(jnp.asarray(values), jnp.asarray(succ), jnp.asarray(lower),
                                  jnp.asarray(upper), rest))
    expect = [lp_min(s, l, u, rest, values) for s, l, u in zip(succ, lower, upper)]
    np.testing.assert_allclose(got, expect, atol=1e-9)
