"""The IMDP inner problem against a general LP solver, on random interval polytopes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linprog

from smdpjax.abstraction import imdp as imdp_module
from smdpjax.abstraction import interval_min
import smdpjax as sj


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


def random_padded_imdp(rng, n_states, rows, actions, rest, max_k=12, pad=3):
    """A padded IMDP with lists of varying width (so that rows fall into several buckets) and up
    to three positive lower bounds per list, listed entries in increasing order."""
    from smdpjax.partition import NONTERMINAL

    k = max_k + pad
    succ = np.full((rows, actions, k), n_states, np.int64)
    lower, upper = np.zeros((rows, actions, k)), np.zeros((rows, actions, k))
    for r in range(rows):
        width = rng.integers(2, max_k + 1) if r % 3 else max_k  # row widths differ; each row has its own
        for a in range(actions):
            s, lo, up, _ = random_instance(rng, n_states, int(rng.integers(1, width + 1)), rest)
            keep = np.argsort(s)
            lo = lo[keep] * (rng.uniform(size=s.size) < 0.4)  # sparse lower bounds
            succ[r, a, :s.size], lower[r, a, :s.size], upper[r, a, :s.size] = s[keep], lo, up[keep]
    labels = np.full(n_states, NONTERMINAL, np.int8)
    return sj.IMDP(successors=jnp.asarray(succ, jnp.int16), lower=jnp.asarray(lower), upper=jnp.asarray(upper),
                   upper_rest=jnp.asarray(rest), rows=jnp.arange(rows, dtype=jnp.int32), labels=jnp.asarray(labels))


@pytest.mark.parametrize("explicit_columns", [0, 48], ids=["reduction", "columns"])
@pytest.mark.parametrize("rest", [0.0, 1e-3, 0.02])
def test_compact_imdp_equals_padded_and_lp(rest, explicit_columns, monkeypatch):
    """Buckets and sparse lower bounds solve the padded IMDP's inner problem: against the LP and
    against ``interval_min`` on the padded lists, every action, a fixed strategy, ``restrict``."""
    from smdpjax.abstraction import imdp_compact

    monkeypatch.setattr(imdp_compact, "_EXPLICIT_COLUMNS", explicit_columns)
    monkeypatch.setattr(imdp_compact, "BUCKET_MIN_SAVING", 0)
    rng = np.random.default_rng(int(rest * 1e4) + 5)
    n_states, rows, actions = 40, 30, 3
    padded = random_padded_imdp(rng, n_states, rows, actions, rest)
    compact = imdp_compact.CompactIMDP.from_imdp(padded, max_buckets=4)
    assert len(compact.buckets) >= 2 and compact.num_lower >= 2  # the bucketed, sparse path
    assert compact.nbytes < padded.nbytes
    for name in ("successors", "lower", "upper"):  # the padded views give the lists back (widest list's width)
        np.testing.assert_array_equal(np.asarray(getattr(compact, name)),
                                      np.asarray(getattr(padded, name))[..., :compact.width])
    strategy = jnp.asarray(rng.integers(0, actions, rows), jnp.int32)
    for trial in range(4):
        values = rng.uniform(0, 1, n_states) if trial % 2 else rng.choice([0.0, 0.25, 0.5, 1.0], n_states)
        v = jnp.asarray(values)
        for adversary in ("min", "max"):
            got = np.asarray(compact.q_values(v, adversary))
            np.testing.assert_allclose(got, np.asarray(padded.q_values(v, adversary)), rtol=0, atol=1e-15)
            fixed = np.asarray(compact.q_values(v, adversary, strategy))
            np.testing.assert_array_equal(fixed, got[np.arange(rows), np.asarray(strategy)])
            np.testing.assert_array_equal(np.asarray(compact.restrict(strategy).q_values(v, adversary))[:, 0], fixed)
        succ, lo, up = (np.asarray(x) for x in (padded.successors, padded.lower, padded.upper))
        for r in range(0, rows, 4):
            for a in range(actions):
                keep = succ[r, a] < n_states
                expect = lp_min(succ[r, a][keep], lo[r, a][keep], up[r, a][keep], rest, values)
                assert np.asarray(compact.q_values(v, "min"))[r, a] == pytest.approx(expect, abs=1e-9)


def test_bucket_edges_partition_the_rows_and_never_pad_more():
    from smdpjax.abstraction.imdp_compact import bucket_edges

    rng = np.random.default_rng(3)
    for widths in (rng.integers(1, 300, 1000), np.full(50, 7), rng.integers(100, 120, 10), np.array([5])):
        edges = bucket_edges(widths, max_buckets=6, gain=0.0)
        w = np.sort(widths)
        assert edges[0] == 0 and edges[-1] == w.size and np.all(np.diff(edges) > 0)
        padded = sum(int(w[b - 1]) * (b - a) for a, b in zip(edges[:-1], edges[1:]))
        assert padded <= w.max() * w.size and len(edges) - 1 <= 6
    wide = np.r_[np.full(5000, 10), np.full(5000, 1000)]
    assert list(bucket_edges(wide, max_buckets=6, gain=0.0)) == [0, 5000, 10000]  # the obvious cut


def test_abstract_imdp_is_compact_and_synthesizes_as_padded():
    system = sj.System(lambda x, u, w: x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w),
                       actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Gaussian([0, 0], [0.5, 0.5]))
    grid = sj.StateGrid([0, 0], [1, 1], 12, reach=[([0.75, 0.75], [1, 1])], avoid=[([0.4, 0.2], [0.6, 0.6])])
    noise = sj.NoiseGrid.ball([0, 0], 2.0, 6)
    compact = sj.abstract(system, grid, noise, "imdp")
    assert isinstance(compact, sj.CompactIMDP)
    padded = compact.padded()
    assert compact.nbytes < padded.nbytes
    for horizon in (None, 7):
        a, b = sj.synthesize(compact, horizon=horizon), sj.synthesize(padded, horizon=horizon)
        np.testing.assert_allclose(np.asarray(a.lower), np.asarray(b.lower), rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(a.upper), np.asarray(b.upper), rtol=0, atol=1e-12)
        np.testing.assert_array_equal(np.asarray(a.policy), np.asarray(b.policy))
