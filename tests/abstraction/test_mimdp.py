"""MI-MDP abstraction (Definition 5 with informed clusters): bounds, inner problem, Theorem 2."""

import warnings
from fractions import Fraction

import cvxpy as cp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linprog

import smdpjax as sj
from smdpjax.abstraction import IMDP, SMDP, CompactIMDP, cluster_members, compute_grid_clusters
from smdpjax.abstraction.clusters import max_lengths
from smdpjax.abstraction.mimdp import MIMDP, ClusterRuns, certified_min, interval_min_rows


def q_values(abstraction, v, adversary="min"):
    """``abstraction.q_values`` under jit (eager calls would retrace the loops every time)."""
    return np.asarray(_q_values(abstraction, jnp.asarray(v), adversary))


_q_values = jax.jit(lambda m, v, adversary: m.q_values(v, adversary), static_argnums=2)


def unicycle(x, u, w):
    return x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)


def drift(x, u, w):  # bounded noise, and a periodic second coordinate
    return x + jnp.array([0.05 * u[0], 0.37]) + jnp.array([0.1, 0.2]) * w


def build(system, grid, noise, **options):
    clusters = compute_grid_clusters(system, grid, noise)
    return grid, clusters, MIMDP.from_clusters(grid, clusters, **options)


@pytest.fixture(scope="module")
def small_clusters():
    """6x6 unicycle with a noise ball of radius 3 sigma: the remainder's mass (~5e-3 per state)
    matters, so the unlisted states are exercised; plus random user-given clusters."""
    system = sj.System(unicycle, actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 6, reach=[([2 / 3, 2 / 3], [1.0, 1.0])], avoid=[([1 / 3, 1 / 3], [0.5, 0.5])])
    noise = sj.NoiseGrid.ball([0.0, 0.0], 0.9, 3)
    clusters = compute_grid_clusters(system, grid, noise)
    rng = np.random.default_rng(3)
    r, a = clusters.rows.size, system.num_actions
    extra = np.full((r, a, 2, 5), grid.num_states)  # padding N + 1
    for i in range(r):
        for j in range(a):
            for e in range(2):
                size = rng.integers(2, 6)
                extra[i, j, e, :size] = rng.choice(grid.num_states, size, replace=False)
    extra[0, 0, 1] = grid.num_states  # an all-padding cluster is ignored
    return grid, clusters, extra


@pytest.fixture(scope="module")
def small(small_clusters):
    """Clarabel's LPs (HiGHS is the default: ``small_highs``)."""
    grid, clusters, extra = small_clusters
    return grid, clusters, MIMDP.from_clusters(grid, clusters, extra_clusters=extra, lp_backend="clarabel"), extra


@pytest.fixture(scope="module")
def small_highs(small_clusters):
    pytest.importorskip("highspy")
    grid, clusters, extra = small_clusters
    return grid, clusters, MIMDP.from_clusters(grid, clusters, extra_clusters=extra, lp_backend="highs"), extra


@pytest.fixture(scope="module")
def unicycle_12():
    system = sj.System(unicycle, actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 12, reach=[([0.75, 0.75], [1.0, 1.0])], avoid=[([0.4, 0.25], [0.6, 0.6])])
    return build(system, grid, sj.NoiseGrid.ball([0.0, 0.0], 2.1, 6))


@pytest.fixture(scope="module")
def bounded():
    system = sj.System(drift, actions=[[-1.0], [1.0]], noise=sj.Uniform([-1.0, -1.0], [1.0, 1.0]))
    grid = sj.StateGrid([0, 0], [1, 1], [8, 5], reach=[([0.75, 0.0], [1.0, 0.2])], periodic=[False, True])
    return build(system, grid, sj.NoiseGrid.box([-1.0, -1.0], [1.0, 1.0], 3))


# -- helpers ---------------------------------------------------------------------------------
def row_data(mimdp, r, a):
    """Per-state bounds ``(N+1,)`` and the clusters ``[(state ids, lo, up)]`` of row (r, a)."""
    imdp, n = mimdp.relaxation, mimdp.num_states
    rest = float(imdp.upper_rest)
    succ = np.asarray(imdp.successors[r, a])
    keep = succ < n
    lo, hi = np.zeros(n), np.full(n, rest)
    lo[succ[keep]] = np.asarray(imdp.lower[r, a])[keep]
    hi[succ[keep]] = np.asarray(imdp.upper[r, a])[keep]
    clusters = []
    for slots, clo, cup in zip(np.asarray(mimdp.cluster_slots[r, a]), np.asarray(mimdp.cluster_lower[r, a]),
                               np.asarray(mimdp.cluster_upper[r, a])):
        slots = slots[slots < succ.size]
        if slots.size:
            clusters.append((succ[slots], float(clo), float(cup)))
    return lo, hi, clusters


def in_gamma_mi(mimdp, r, a, gamma, tol=1e-12):
    """Membership of ``gamma (N+1,)`` in Gamma^MI of row (r, a), from the stored arrays."""
    lo, hi, clusters = row_data(mimdp, r, a)
    ok = abs(gamma.sum() - 1) <= tol and np.all(gamma >= lo - tol) and np.all(gamma <= hi + tol)
    return bool(ok and all(clo - tol <= gamma[ids].sum() <= cup + tol for ids, clo, cup in clusters))


def reference_lps(mimdp):
    """CVXPY problems over all N+1 states with every constraint written out, one per (r, a)."""
    cost = cp.Parameter(mimdp.num_states)
    problems = {}
    for r in range(mimdp.num_rows):
        for a in range(mimdp.num_actions):
            lo, hi, clusters = row_data(mimdp, r, a)
            member = np.zeros((len(clusters), mimdp.num_states))
            for j, (ids, _, _) in enumerate(clusters):
                member[j, ids] = 1.0
            clo = np.array([c[1] for c in clusters])
            cup = np.array([c[2] for c in clusters])
            g = cp.Variable(mimdp.num_states)
            cons = [cp.sum(g) == 1, g >= lo, g <= hi, member @ g >= clo, member @ g <= cup]
            problems[r, a] = cp.Problem(cp.Minimize(cost @ g), cons)
    return cost, problems


def vertex_reference(mimdp, r, a, w):
    """The same LP by HiGHS dual simplex with tight tolerances: a vertex, feasible to ~1e-10 (so not
    below the true minimum by more than that times the values' range) and usually to rounding."""
    lo, hi, clusters = row_data(mimdp, r, a)
    member = np.zeros((len(clusters), mimdp.num_states))
    for j, (ids, _, _) in enumerate(clusters):
        member[j, ids] = 1.0
    res = linprog(w, A_ub=np.vstack([member, -member]), b_ub=np.r_[[c[2] for c in clusters], [-c[1] for c in clusters]],
                  A_eq=np.ones((1, mimdp.num_states)), b_eq=[1.0], bounds=list(zip(lo, hi)), method="highs-ds",
                  options=dict(primal_feasibility_tolerance=1e-10, dual_feasibility_tolerance=1e-10))
    assert res.status == 0
    return res.fun


def solve_reference(cost, problems, w):
    cost.value = np.asarray(w)
    out = {}
    for key, prob in problems.items():
        prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11)
        assert prob.status == cp.OPTIMAL
        out[key] = prob.value
    return out


# -- the inner problem -----------------------------------------------------------------------
@pytest.mark.parametrize("rest", [0.0, 1e-3, 0.02])
def test_interval_min_rows_matches_lp(rest):
    rng = np.random.default_rng(11 + int(rest * 1e4))
    n, k, rows = 40, 9, 120
    succ = np.stack([rng.choice(n, k, replace=False) for _ in range(rows)])
    lower = rng.uniform(0, 1, (rows, k)) * rng.integers(0, 2, (rows, k))
    lower *= rng.uniform(0.2, 0.9, (rows, 1)) / np.maximum(lower.sum(1, keepdims=True), 1e-12)
    upper = lower + rng.uniform(0, 0.4, (rows, k)) + rest
    upper *= np.maximum(1.0, (1 - (n - k) * rest) / upper.sum(1, keepdims=True) + 0.05)
    w = rng.choice([0.0, 0.5, 1.0], n) if rest == 0.02 else rng.uniform(0, 1, n)  # ties too
    w_listed = w[succ] + rng.choice([0.0, 0.3, -0.7], (rows, k))  # per-row costs, some equal to w
    pad = np.full((rows, 2), n + 1)
    got = np.asarray(interval_min_rows(jnp.asarray(w), jnp.asarray(np.c_[w_listed, 0 * pad]),
                                       jnp.asarray(np.c_[succ, pad]),
                                       jnp.asarray(np.c_[lower, 0 * pad]), jnp.asarray(np.c_[upper, 0 * pad]), rest))
    for i in range(rows):
        c, lo, hi = w.copy(), np.zeros(n), np.full(n, rest)
        c[succ[i]], lo[succ[i]], hi[succ[i]] = w_listed[i], lower[i], upper[i]
        res = linprog(c, A_eq=np.ones((1, n)), b_eq=[1.0], bounds=list(zip(lo, hi)), method="highs")
        assert res.status == 0
        assert got[i] == pytest.approx(res.fun, abs=1e-9)


@pytest.mark.parametrize("bisections, walk", [(2, 0), (0, 1), (20, 4)])
def test_interval_min_rows_threshold_search_is_sound_when_cut_short(monkeypatch, bisections, walk):
    """Listed costs packed into a tiny range (near-ties of the shifted costs): a threshold search
    cut short must still return a lower bound of the LP (weak duality at any tau), and the
    default search must be within its documented slack."""
    from smdpjax.abstraction import mimdp as module

    monkeypatch.setattr(module, "_REAL_BISECTIONS", bisections)
    monkeypatch.setattr(module, "_WALK_STEPS", walk)
    rng = np.random.default_rng(5)
    n, k, rows, rest = 30, 8, 80, 0.01
    succ = np.stack([rng.choice(n, k, replace=False) for _ in range(rows)])
    lower = rng.uniform(0, 0.05, (rows, k))
    upper = lower + rng.uniform(0.05, 0.2, (rows, k))
    w = rng.uniform(0, 1, n)
    w_listed = 0.4 + rng.integers(0, 6, (rows, k)) * 1e-6 + rng.uniform(0, 1e-9, (rows, k))  # 6 near-tied groups
    got = np.asarray(interval_min_rows(jnp.asarray(w), jnp.asarray(w_listed), jnp.asarray(succ),
                                       jnp.asarray(lower), jnp.asarray(upper), rest))
    below = 0
    for i in range(rows):
        c, lo, hi = w.copy(), np.zeros(n), np.full(n, rest)
        c[succ[i]], lo[succ[i]], hi[succ[i]] = w_listed[i], lower[i], upper[i]
        res = linprog(c, A_eq=np.ones((1, n)), b_eq=[1.0], bounds=list(zip(lo, hi)), method="highs")
        assert got[i] <= res.fun + 1e-12
        below += got[i] < res.fun - 1e-13
        if walk == 4:  # exact, or off by at most (bracket width 2^-20 of a gap of w) x (mass)
            assert got[i] == pytest.approx(res.fun, abs=1e-8)
    if walk < 4:
        assert below > 0  # the cut-short search really took the fallback


@pytest.mark.parametrize("case", ["small", "small_highs"])
def test_q_values_equal_reference_lp(case, request):
    grid, clusters, mimdp, _ = request.getfixturevalue(case)
    cost, problems = reference_lps(mimdp)
    rng = np.random.default_rng(0)
    for trial in range(2):
        v = rng.uniform(0, 1, grid.num_states) if trial else rng.choice([0.0, 0.4, 1.0], grid.num_states)
        q_min = q_values(mimdp, v, "min")
        q_max = q_values(mimdp, v, "max")
        ref_min = solve_reference(cost, problems, v)
        ref_max = {key: -val for key, val in solve_reference(cost, problems, -v).items()}
        for (r, a), val in ref_min.items():
            assert q_min[r, a] == pytest.approx(val, abs=1e-6)
            assert q_max[r, a] == pytest.approx(ref_max[r, a], abs=1e-6)
            # certified: never above the minimum / below the maximum. The interior-point
            # reference is itself only accurate to ~1e-11, so this is checked against vertex
            # solutions of the same LPs.
            assert q_min[r, a] <= vertex_reference(mimdp, r, a, v) + 1e-12
            assert q_max[r, a] >= -vertex_reference(mimdp, r, a, -v) - 1e-12
    # the clusters do cut: some rows are strictly tighter than the IMDP
    q_imdp = q_values(mimdp.relaxation, v, "min")
    assert np.max(q_min - q_imdp) > 1e-3


def test_certificate_is_sound_for_any_multipliers(small):
    """Weak duality: garbage multipliers still give a lower bound (never above the LP value)."""
    grid, _, mimdp, _ = small
    from smdpjax.abstraction.mimdp import certified_min
    imdp = mimdp.relaxation
    v = jnp.asarray(np.random.default_rng(5).uniform(0, 1, grid.num_states))
    exact = q_values(mimdp, v, "min")
    bound = jax.jit(certified_min, static_argnums=9)
    for seed in range(3):
        lam = jnp.asarray(np.random.default_rng(seed).exponential(0.5, mimdp.cluster_slots.shape[:3] + (2,)))
        g = np.asarray(bound(v, imdp.successors, imdp.lower, imdp.upper, imdp.upper_rest,
                                     mimdp.cluster_slots, mimdp.cluster_lower, mimdp.cluster_upper, lam, 10.0))
        assert np.all(g <= exact + 1e-9)


@pytest.mark.parametrize("chunk", [1, 7, 1000])
def test_certified_min_in_row_chunks_equals_all_rows_at_once(small, chunk):
    """Row chunks (bounding the (row, cluster, member) temporaries) change nothing: 7 does not
    divide the 124 (row, action) pairs, so the last chunk overlaps its predecessor."""
    grid, _, mimdp, _ = small
    from smdpjax.abstraction.mimdp import certified_min
    imdp = mimdp.relaxation
    assert mimdp.lp_index.size % 7 != 0
    rng = np.random.default_rng(6)
    v = jnp.asarray(rng.uniform(0, 1, grid.num_states))
    lam = mimdp.multipliers(v, mimdp.lp_index)  # the LPs' own, which lift some rows above the IMDP
    args = (v, imdp.successors, imdp.lower, imdp.upper, imdp.upper_rest, mimdp.cluster_slots, mimdp.cluster_lower,
            mimdp.cluster_upper, lam, 10.0)
    bound = jax.jit(certified_min, static_argnums=9, static_argnames="rows_per_chunk")
    whole = np.asarray(bound(*args))
    assert whole.shape == mimdp.lp_index.shape
    np.testing.assert_array_equal(np.asarray(bound(*args, rows_per_chunk=chunk)), whole)
    given = jnp.asarray(q_values(imdp, v, "min"))
    np.testing.assert_array_equal(np.asarray(bound(*args, imdp_value=given, rows_per_chunk=chunk)),
                                  np.asarray(bound(*args, imdp_value=given)))
    assert np.any(whole > np.asarray(given) + 1e-6)  # the multipliers do lift some rows


# -- bounds of the clusters ------------------------------------------------------------------
@pytest.mark.parametrize("case", ["small", "bounded"])
def test_cluster_bounds_brute_force(case, request):
    data = request.getfixturevalue(case)
    grid, clusters, mimdp = data[:3]
    extra = data[3] if len(data) > 3 else None
    members = np.asarray(cluster_members(grid, clusters.boxes, max_lengths(clusters.boxes)))
    prob, rest = np.asarray(clusters.prob), float(clusters.prob_rest)
    n = grid.num_states
    for r in range(mimdp.num_rows):
        for a in range(mimdp.num_actions):
            reach = [frozenset(int(s) for s in m if s < n) for m in members[r, a]]
            wanted = set(reach)
            if extra is not None:
                wanted |= {frozenset(int(s) for s in e if s < n) for e in extra[r, a]}
            wanted = {q for q in wanted if len(q) >= 2}
            _, _, stored = row_data(mimdp, r, a)
            got = {frozenset(ids.tolist()): (lo, up) for ids, lo, up in stored}
            assert len(got) == len(stored), "a cluster is stored twice"
            assert set(got) == wanted
            for q, (lo, up) in got.items():
                # the exact sums of the float64 P_W, as rationals: lo at most, up at least those,
                # within the fixed-point grid (C terms of 2^-61) and one ulp of rounding outward
                low = sum(Fraction(float(p)) for m, p in zip(reach, prob) if m <= q)
                high = sum(Fraction(float(p)) for m, p in zip(reach, prob) if m & q) + Fraction(rest)
                slack = Fraction(len(prob) + 1, 2 ** 61)
                assert low - slack - Fraction(np.spacing(float(low))) <= Fraction(lo) <= low
                assert high <= Fraction(up) <= high + slack + Fraction(np.spacing(float(high)))


def test_extra_clusters_are_validated(small_clusters):
    grid, clusters, extra = small_clusters
    with pytest.raises(ValueError, match="shape"):
        MIMDP.from_clusters(grid, clusters, extra_clusters=extra[:, :, 0])
    with pytest.raises(ValueError, match="nonnegative"):
        MIMDP.from_clusters(grid, clusters, extra_clusters=extra - grid.num_states)


# -- Theorem 2: Gamma^SMDP inside Gamma^MI inside Gamma^IMDP ---------------------------------
@pytest.mark.parametrize("case", ["unicycle_12", "bounded"])
def test_theorem2_ordering(case, request):
    grid, clusters, mimdp = request.getfixturevalue(case)
    smdp, imdp = SMDP.from_clusters(grid, clusters), IMDP.from_clusters(grid, clusters)
    rng = np.random.default_rng(1)
    tighter = 0.0
    for _ in range(1 if case == "unicycle_12" else 2):
        v = jnp.asarray(rng.uniform(0, 1, grid.num_states))
        s, m, i = (q_values(x, v, "min") for x in (smdp, mimdp, imdp))
        assert np.all(s >= m - 1e-9) and np.all(m - 1e-9 >= i - 2e-9)
        tighter = max(tighter, float(np.max(m - i)))
        s, m, i = (q_values(x, v, "max") for x in (smdp, mimdp, imdp))
        assert np.all(s <= m + 1e-9) and np.all(m + 1e-9 <= i + 2e-9)
    assert tighter > 1e-3


# -- the paper's Example 3 -------------------------------------------------------------------
def test_example3_spurious_distribution():
    """Example 3 (s3 of Examples 1-2 split in two). A uniform grid cannot split one region only,
    so the example is reconstructed in 1-D with the same clusters: seven unit cells, and
    Reach(s1, a, c_i) (w ~ U[-1, 1], five cells) meets the cells {1,2}, {2,3',3''}, {3',3'',4},
    {4,5}, {5,6} (paper numbering s1, s2, s3', s3'', s4, s5, s6 = cells 0..6)."""
    system = sj.System(lambda x, u, w: 0.2 * x + 3.5 + 3.0 * w, actions=[[0.0]], noise=sj.Uniform([-1.0], [1.0]))
    grid = sj.StateGrid([0.0], [7.0], [7])
    noise = sj.NoiseGrid.box([-1.0], [1.0], 5)
    grid, clusters, mimdp = build(system, grid, noise)
    smdp, imdp = SMDP.from_clusters(grid, clusters), IMDP.from_clusters(grid, clusters)
    assert int(mimdp.rows[0]) == 0  # row 0 is s1
    _, _, stored = row_data(mimdp, 0, 0)
    got = {tuple(sorted(ids.tolist())): (lo, up) for ids, lo, up in stored}
    expect = {(0, 1): (0.2, 0.4), (1, 2, 3): (0.2, 0.6), (2, 3, 4): (0.2, 0.6), (4, 5): (0.2, 0.6), (5, 6): (0.2, 0.4)}
    assert set(got) == set(expect)
    for key, bounds in expect.items():
        np.testing.assert_allclose(got[key], bounds, atol=1e-12)

    gamma = np.zeros(grid.num_states)
    gamma[[0, 2, 5]] = 0.2  # s1, s3', s5
    gamma[3] = 0.4  # s3''
    assert in_gamma_mi(mimdp, 0, 0, gamma)
    # Every SMDP distribution puts at most P(c2) + P(c3) = 2/5 on {s3', s3''}: only those two
    # reachable sets meet them. gamma puts 3/5 there, so it is not in Gamma^SMDP.
    v = jnp.ones(grid.num_states).at[jnp.array([2, 3])].set(0.0)
    q_smdp, q_mimdp, q_imdp = (float(q_values(x, v, "min")[0, 0]) for x in (smdp, mimdp, imdp))
    assert q_smdp == pytest.approx(0.6)
    assert float(v @ gamma) == pytest.approx(0.4) and float(v @ gamma) < q_smdp - 0.1
    assert q_mimdp == pytest.approx(0.4, abs=1e-7)  # gamma is the MI-MDP's minimizer
    assert q_imdp == pytest.approx(0.2)  # the IMDP may even put 4/5 there


# -- JAX integration -------------------------------------------------------------------------
def test_jit_while_loop_and_restrict(small):
    grid, _, mimdp, _ = small
    rows = mimdp.rows
    v0 = mimdp.initial_values()

    def body(state):
        k, v = state
        return k + 1, v.at[rows].set(mimdp.q_values(v, "min").max(axis=1))

    _, v_loop = jax.jit(lambda v: jax.lax.while_loop(lambda s: s[0] < 3, body, (0, v)))(v0)
    v_ref = v0
    for _ in range(3):
        v_ref = v_ref.at[rows].set(q_values(mimdp, v_ref, "min").max(axis=1))
    np.testing.assert_allclose(np.asarray(v_loop), np.asarray(v_ref), atol=1e-12)

    v = v_loop.at[rows].set(jnp.asarray(np.random.default_rng(4).uniform(0, 1, rows.size)))
    actions = jnp.asarray(np.random.default_rng(2).integers(0, mimdp.num_actions, mimdp.num_rows), jnp.int32)
    fixed = mimdp.restrict(actions)
    assert fixed.num_actions == 1
    picked = np.asarray(jax.jit(lambda m, x, act: m.q_values(x, "max", act))(mimdp, v, actions))  # traced actions
    np.testing.assert_allclose(q_values(fixed, v, "max")[:, 0], picked, atol=1e-12)
    full = q_values(mimdp, v, "max")
    np.testing.assert_allclose(picked, full[np.arange(mimdp.num_rows), np.asarray(actions)], atol=1e-7)



def test_relaxation_is_stored_compactly_and_losslessly(small_clusters):
    # the padded views the inner problem reads are the padded IMDP's arrays exactly (the informed
    # clusters alone: no extension of the lists)
    grid, clusters, _ = small_clusters
    mimdp = MIMDP.from_clusters(grid, clusters)
    padded = IMDP.from_clusters(grid, clusters)
    assert isinstance(mimdp.relaxation, CompactIMDP) and mimdp.relaxation.width == padded.successors.shape[-1]
    for name in ("successors", "lower", "upper"):
        np.testing.assert_array_equal(np.asarray(getattr(mimdp.relaxation, name)), np.asarray(getattr(padded, name)))
    assert mimdp.relaxation.nbytes < padded.nbytes
    v = jnp.asarray(np.random.default_rng(7).uniform(size=grid.num_states))
    np.testing.assert_allclose(q_values(mimdp.relaxation, v), q_values(padded, v), rtol=0, atol=1e-14)


def test_highs_with_repriced_bases_is_the_default(small_clusters):
    grid, clusters, _ = small_clusters
    for mimdp in (MIMDP.from_clusters(grid, clusters), sj.abstraction.build("mimdp", grid, clusters)):
        assert mimdp.lps.backend == "highs" and mimdp.lps.reprice


def test_cluster_runs_hold_exactly_the_members():
    pad = 12
    slots = np.array([[[[0, 1, 2, 5, 6, 9, pad, pad],  # three runs
                        [10, 11, pad, pad, pad, pad, pad, pad],  # a run ending at K - 1, then the padding K
                        [pad] * 8,  # a padding cluster
                        [3, 4, 5, 6, 7, 8, 9, 11]]]], np.uint8)
    runs = ClusterRuns.from_slots(slots, pad)
    assert runs.start.shape == (1, 1, 4, 3) and runs.longest == 7 and runs.size == 8 and runs.length.dtype == np.uint8
    np.testing.assert_array_equal(np.asarray(runs.start[0, 0, 0]), [0, 5, 9])
    np.testing.assert_array_equal(np.asarray(runs.length[0, 0, 0]), [3, 2, 1])
    expanded = np.asarray(runs.slots())
    for j in range(4):
        members = expanded[0, 0, j]
        np.testing.assert_array_equal(np.sort(members[members < pad]), slots[0, 0, j][slots[0, 0, j] < pad])
        assert np.all(members[members >= pad] == pad)


def test_cluster_runs_give_the_backup_of_the_member_positions(small):
    # the MI-MDP's runs against the positions they stand for, in the certified bound: the same
    # sums, up to the order XLA adds them in (the rounding allowance counts every summand)
    grid, _, mimdp, _ = small
    imdp = mimdp.relaxation
    runs = mimdp.cluster_members
    assert runs.start.shape[-1] < runs.size  # fewer runs than members: the encoding is smaller
    v = jnp.asarray(np.random.default_rng(11).uniform(size=grid.num_states))
    lam = jnp.asarray(np.random.default_rng(12).exponential(0.5, runs.start.shape[:3] + (2,)))
    args = (v, imdp.successors, imdp.lower, imdp.upper, imdp.upper_rest)
    tail = (mimdp.cluster_lower, mimdp.cluster_upper, lam, 4.0)
    dense = np.asarray(certified_min(*args, runs.slots(), *tail))
    np.testing.assert_allclose(np.asarray(certified_min(*args, runs, *tail)), dense, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(certified_min(*args, runs, *tail, rows_per_chunk=7)), dense, rtol=0,
                               atol=1e-15)

def test_pytree_leaves_and_repr(small):
    _, _, mimdp, _ = small
    leaves = jax.tree_util.tree_leaves(mimdp)
    assert any(leaf is mimdp.relaxation.chunk_succ for leaf in leaves)
    assert mimdp.nbytes > mimdp.relaxation.nbytes
    assert mimdp.summands_per_backup > mimdp.relaxation.summands_per_backup
    assert "MIMDP(" in repr(mimdp) and mimdp.kind == "mimdp"
    fixed = mimdp.restrict(jnp.zeros(mimdp.num_rows, jnp.int32))
    assert fixed.lps is mimdp.lps and fixed.lp_index.shape == (mimdp.num_rows, 1)
    # the host LP data: at least every LP's variable capacities (float64), cluster members (int16
    # here: few variables per LP) and successor ids; not part of the abstraction's nbytes
    lps = mimdp.lps
    members = sum(lp["var"].size for lp in lps._lps)
    assert all(lp["var"].dtype == np.int16 for lp in lps._lps)
    assert lps.data_nbytes >= 8 * int(lps.num_vars.sum()) + 2 * members + lps.succ.nbytes
    assert members > 0 and mimdp.nbytes == sum(np.asarray(x).nbytes for x in leaves)


@pytest.mark.parametrize("chunk", [1, 5])
@pytest.mark.parametrize("with_extra", [False, True])
def test_member_chunks_do_not_change_the_structure(small_clusters, monkeypatch, with_extra, chunk):
    """Cluster member lists are expanded a chunk of rows at a time (memory). Chunks of 1 row (whose
    widest cluster differs from row to row, so chunks are padded) and of 5 rows (an uneven last
    chunk) give the same arrays as one chunk."""
    from smdpjax.abstraction import mimdp as mimdp_module

    grid, clusters, extra = small_clusters
    extra = extra if with_extra else None
    whole = MIMDP.from_clusters(grid, clusters, extra_clusters=extra)
    monkeypatch.setattr(mimdp_module, "_MEMBER_ROWS_PER_CHUNK", chunk)
    chunked = MIMDP.from_clusters(grid, clusters, extra_clusters=extra)
    for name in ("cluster_slots", "cluster_lower", "cluster_upper"):
        a, b = np.asarray(getattr(whole, name)), np.asarray(getattr(chunked, name))
        assert a.shape == b.shape and a.dtype == b.dtype, name
        np.testing.assert_array_equal(a, b, err_msg=name)
    for name in ("successors", "lower", "upper"):
        np.testing.assert_array_equal(np.asarray(getattr(whole.relaxation, name)),
                                      np.asarray(getattr(chunked.relaxation, name)), err_msg=name)


def test_lp_blocks_do_not_change_the_lps(small_clusters, monkeypatch):
    """The per-LP data are prepared a block of LPs at a time (memory); blocks of 7 LPs give the
    same LPs as one block."""
    from smdpjax.abstraction import lp as lp_module

    grid, clusters, extra = small_clusters
    whole = MIMDP.from_clusters(grid, clusters, extra_clusters=extra).lps
    monkeypatch.setattr(lp_module, "_LPS_PER_BLOCK", 7)
    blocked = MIMDP.from_clusters(grid, clusters, extra_clusters=extra).lps
    assert whole.num_lps % 7 != 0 and len(whole._lps) == len(blocked._lps) == whole.num_lps
    for a, b in zip(whole._lps, blocked._lps):
        assert a.keys() == b.keys()
        for key in a:
            np.testing.assert_array_equal(np.asarray(a[key]), np.asarray(b[key]), err_msg=key)
    np.testing.assert_array_equal(whole.num_rows, blocked.num_rows)
    assert whole.nnz == blocked.nnz


def test_a_model_highs_refuses_raises_instead_of_solving_the_previous_one(small_highs, monkeypatch):
    """``Highs.passModel`` reports a refused model by its status and keeps the model before it;
    solving on would read that model's duals. An integrality code that does not exist is refused."""
    lps = small_highs[2].lps
    build = lps._highs_model
    illegal = lambda model: model[:-1] + (np.full(model[0], 99, np.int32),)
    monkeypatch.setattr(lps, "_highs_model", lambda p, cost: illegal(build(p, cost)))
    w = np.linspace(0.0, 1.0, lps.num_states)
    with pytest.raises(RuntimeError, match="HiGHS refused the LP"):
        lps.multipliers(w, np.array([0]))


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("case", ["small", "small_highs"])
def test_concurrent_multiplier_calls_are_safe(case, threads, request, monkeypatch):
    """XLA may run host callbacks concurrently (the lower and upper backups of one step, or the
    shards of a mesh), so several ``multipliers`` calls on the same LPs overlap. Each must give
    what it gives alone: no solver shared mid-solve ("Already borrowed" from Clarabel), no cost
    vector overwritten by another thread before HiGHS reads it."""
    from concurrent.futures import ThreadPoolExecutor

    from smdpjax.abstraction.mimdp import certified_min

    grid, _, mimdp, _ = request.getfixturevalue(case)
    imdp, lps, ids = mimdp.relaxation, mimdp.lps, np.asarray(mimdp.lp_index)
    monkeypatch.setattr(lps, "threads", threads)
    bound = jax.jit(certified_min)
    rng = np.random.default_rng(11)
    jobs = [(rng.uniform(0, 1, mimdp.num_states), direction) for direction in (0, 1) for _ in range(4)]

    def value(w, lam):
        return np.asarray(bound(jnp.asarray(w), imdp.successors, imdp.lower, imdp.upper, imdp.upper_rest,
                                mimdp.cluster_slots, mimdp.cluster_lower, mimdp.cluster_upper, jnp.asarray(lam)))

    alone = [value(w, lps.multipliers(w, ids, d)) for w, d in jobs]
    with ThreadPoolExecutor(len(jobs)) as pool:
        together = list(pool.map(lambda job: lps.multipliers(job[0], ids, job[1]), jobs * 3))
    for (w, _), expected, lam in zip(jobs * 3, alone * 3, together):
        np.testing.assert_allclose(value(w, lam), expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize("case", ["small", "unicycle_12"])
def test_greedy_q_values_screen_out_actions_without_changing_the_backup(case, request):
    """The SMDP screen skips LPs of actions that cannot be the best, and the greedy backup (row
    maximum, argmax) is the one of ``q_values``; every entry stays a lower bound of it."""
    data = request.getfixturevalue(case)
    grid, mimdp = data[0], data[2]
    assert mimdp.screen is not None and mimdp.screen.kind == "smdp"
    greedy = jax.jit(lambda m, x: m.greedy_q_values(x))
    rng = np.random.default_rng(8)
    for start, v in ((True, np.asarray(mimdp.initial_values())), (False, rng.uniform(0, 1, mimdp.num_states))):
        v = jnp.asarray(v).at[-1].set(0.0)
        full = q_values(mimdp, v, "min")
        before = mimdp.lps.stats["skipped"]
        screened = np.asarray(greedy(mimdp, v))
        skipped = mimdp.lps.stats["skipped"] - before
        assert 0 < skipped and (start or skipped < full.size)  # p^0: often no LP is needed at all
        np.testing.assert_allclose(screened.max(axis=1), full.max(axis=1), rtol=0, atol=1e-9)
        assert np.all(screened <= full + 1e-9)
        # the screen's own bounds hold: IMDP <= MI-MDP <= SMDP
        smdp = np.asarray(jax.jit(lambda m, x: m.q_values(x, "min"))(mimdp.screen, v))
        assert np.all(full <= smdp + 1e-9)
        top2 = np.sort(full, axis=1)[:, -2:]
        clear = top2[:, 1] - top2[:, 0] > 1e-7
        np.testing.assert_array_equal(screened.argmax(axis=1)[clear], full.argmax(axis=1)[clear])


def test_greedy_certifies_only_the_pairs_whose_lps_it_solved(unicycle_12, monkeypatch):
    """With at most ``GREEDY_CERTIFIED_PAIRS_PER_ROW`` times the rows solved LPs, a greedy backup
    certifies only those (row, action) pairs (the others keep their IMDP value); with more, every
    pair. Either way the values are those of certifying every pair, to rounding."""
    from smdpjax.abstraction import mimdp as mimdp_module

    grid, _, mimdp = unicycle_12
    v = jnp.asarray(np.random.default_rng(4).uniform(0, 1, mimdp.num_states)).at[-1].set(0.0)
    low = np.asarray(mimdp.relaxation.q_values(v, "min"))
    high = np.asarray(mimdp.screen.q_values(v, "min"))
    margin = mimdp._screen_margin()
    solved = int(((high >= low.max(axis=1, keepdims=True) - margin) & ~(high <= low + margin)).sum())
    fits = -(-solved // mimdp.num_rows)  # pairs per row that hold every solved LP
    assert 2 <= fits < mimdp.num_actions
    values = {}
    for per_row in (fits - 1, fits, mimdp.num_actions):  # every pair (fallback), the solved ones, all
        monkeypatch.setattr(mimdp_module, "GREEDY_CERTIFIED_PAIRS_PER_ROW", per_row)
        values[per_row] = np.asarray(jax.jit(lambda m, x: m.greedy_q_values(x))(mimdp, v))
    full = values[mimdp.num_actions]
    for per_row in (fits - 1, fits):
        np.testing.assert_allclose(values[per_row], full, rtol=0, atol=1e-14)
    assert np.any(full > low + 1e-6)  # the LPs lift some pairs above their IMDP value


def test_greedy_backup_skips_actions_below_a_floor_but_not_the_current_ones(unicycle_12):
    """With ``floor`` and ``current`` (policy iteration's hints) a greedy backup solves fewer LPs,
    every entry stays a lower bound of ``q_values``, wherever some action's value exceeds the
    floor the row maximum and its argmax are ``q_values``'s, and the current action is solved
    even below the floor."""
    grid, _, mimdp = unicycle_12
    v = jnp.asarray(np.random.default_rng(11).uniform(0, 1, mimdp.num_states)).at[-1].set(0.0)
    full = q_values(mimdp, v, "min")
    current = np.argmax(full, axis=1)
    # odd rows: a floor above every action's value (nothing can beat it); even rows: none
    high = np.arange(mimdp.num_rows) % 2 == 1
    floor = np.where(high, full.max(axis=1) + 0.05, -1.0)
    plain_before = mimdp.lps.stats["skipped"]
    jax.jit(lambda m, x: m.greedy_backup(x)[0])(mimdp, v)
    plain_skipped = mimdp.lps.stats["skipped"] - plain_before
    greedy = jax.jit(lambda m, x, f, c: m.greedy_backup(x, f, c)[0])
    before = mimdp.lps.stats["skipped"]
    hinted = np.asarray(greedy(mimdp, v, floor, np.full(mimdp.num_rows, -1)))
    assert mimdp.lps.stats["skipped"] - before > plain_skipped
    assert np.all(hinted <= full + 1e-9)
    above = full.max(axis=1) > floor + 1e-7
    np.testing.assert_array_equal(above, ~high)
    np.testing.assert_allclose(hinted.max(axis=1)[above], full.max(axis=1)[above], rtol=0, atol=1e-9)
    top2 = np.sort(full, axis=1)[:, -2:]
    clear = above & (top2[:, 1] - top2[:, 0] > 1e-7)
    np.testing.assert_array_equal(hinted.argmax(axis=1)[clear], current[clear])
    # above every value: the current action is still solved (its certified value is q_values's),
    # the others below the floor by the screen keep their IMDP value
    low = np.asarray(mimdp.relaxation.q_values(v, "min"))
    high = np.asarray(mimdp.screen.q_values(v, "min"))
    floor = full.max(axis=1) + 0.05
    forced = np.asarray(greedy(mimdp, v, floor, current))
    rows = np.arange(mimdp.num_rows)
    np.testing.assert_allclose(forced[rows, current], full[rows, current], rtol=0, atol=1e-9)
    assert np.any(full[rows, current] > low[rows, current] + 1e-6)  # the LPs lift them
    below = high < floor[:, None] - mimdp._screen_margin()
    below[rows, current] = False
    assert below.sum() > below.size // 2
    np.testing.assert_allclose(forced[below], low[below], rtol=0, atol=1e-12)


def test_screening_does_not_change_synthesis(unicycle_12):
    grid, clusters, screened = unicycle_12
    plain = MIMDP.from_clusters(grid, clusters, screen_actions=False)
    assert plain.screen is None and screened.screen is not None
    a, b = sj.synthesize(screened, tol=1e-8), sj.synthesize(plain, tol=1e-8)
    np.testing.assert_allclose(np.asarray(a.lower), np.asarray(b.lower), rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.asarray(a.lower_optimal), np.asarray(b.lower_optimal), rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.asarray(a.upper), np.asarray(b.upper), rtol=0, atol=1e-7)


@pytest.mark.parametrize("adversary", ["min", "max"])
def test_q_values_skip_the_lps_of_rows_the_screen_pins(small_clusters, adversary):
    """Where the IMDP's and the SMDP's values meet, the MI-MDP's lies between them: ``q_values``
    returns the IMDP value there without an LP, in every backup (with or without ``actions``, and
    after ``restrict``), and equals the LP-per-row values of an unscreened MI-MDP elsewhere."""
    grid, clusters, _ = small_clusters
    screened = MIMDP.from_clusters(grid, clusters)
    plain = MIMDP.from_clusters(grid, clusters, screen_actions=False)
    rng = np.random.default_rng(11)
    actions = jnp.asarray(rng.integers(0, screened.num_actions, screened.rows.size), jnp.int32)
    with_actions = jax.jit(lambda m, x: m.q_values(x, adversary, actions))
    pinned_somewhere = False
    for v in (np.asarray(screened.initial_values()), rng.uniform(0, 1, screened.num_states)):
        v = jnp.asarray(v).at[-1].set(0.0)
        imdp = q_values(screened.relaxation, v, adversary)
        before = screened.lps.stats["skipped"]
        fast = q_values(screened, v, adversary)
        skipped = screened.lps.stats["skipped"] - before
        np.testing.assert_allclose(fast, q_values(plain, v, adversary), rtol=0, atol=1e-9)
        smdp = q_values(screened.screen, v, adversary)
        pins = np.abs(smdp - imdp) <= 1e-12
        assert skipped >= pins.sum()  # at least every row whose bounds meet is solved without an LP
        np.testing.assert_array_equal(fast[pins], imdp[pins])
        pinned_somewhere |= bool(pins.any() and not pins.all())
        for one_action in (screened.restrict(actions), plain.restrict(actions)):
            np.testing.assert_allclose(q_values(one_action, v, adversary)[:, 0], fast[np.arange(actions.size), actions],
                                       rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.asarray(with_actions(screened, v)), fast[np.arange(actions.size), actions],
                                   rtol=0, atol=1e-9)
    assert pinned_somewhere  # the check bites: some rows need their LP, some do not


def test_single_action_verification_keeps_its_screen(small_clusters):
    """A single-action MI-MDP (a verified look-up table) has a screen too, and its finite-horizon
    bounds equal those of one that solves every row's LP."""
    grid, clusters, _ = small_clusters
    table = np.arange(grid.num_cells) % 4
    system = sj.System(unicycle, actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    one = compute_grid_clusters(system, grid, sj.NoiseGrid.ball([0.0, 0.0], 0.9, 3), policy=table)
    screened = MIMDP.from_clusters(grid, one)
    plain = MIMDP.from_clusters(grid, one, screen_actions=False)
    assert screened.num_actions == 1 and screened.screen is not None and plain.screen is None
    a, b = sj.verify(screened, horizon=6), sj.verify(plain, horizon=6)
    assert screened.lps.stats["skipped"] > 0 and plain.lps.stats["skipped"] == 0
    np.testing.assert_allclose(np.asarray(a.lower), np.asarray(b.lower), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(a.upper), np.asarray(b.upper), rtol=0, atol=1e-9)


# -- frozen multipliers ----------------------------------------------------------------------
@pytest.mark.parametrize("adversary", ["min", "max"])
def test_frozen_view_is_exact_where_frozen_and_conservative_elsewhere(small, adversary):
    """Weak duality with fixed multipliers: the frozen operator equals the LP one at the values it
    was frozen at, bounds the true LP value from the conservative side at any other values (checked
    against vertex solutions), calls no LP, and refreezing never loses what it had."""
    grid, _, mimdp, _ = small
    sign = 1.0 if adversary == "min" else -1.0  # sign * q: larger is tighter
    rng = np.random.default_rng(11)
    v = jnp.asarray(rng.uniform(0, 1, grid.num_states))
    other = jnp.asarray(rng.uniform(0, 1, grid.num_states))
    freeze = jax.jit(lambda m, x: m.freeze(x, adversary))
    frozen = freeze(mimdp, v)
    assert frozen.frozen.shape == (*mimdp.lp_index.shape, mimdp.num_clusters, 2)
    calls = mimdp.lps.stats["calls"]
    at_v, elsewhere = q_values(frozen, v, adversary), q_values(frozen, other, adversary)
    assert mimdp.lps.stats["calls"] == calls
    np.testing.assert_allclose(at_v, q_values(mimdp, v, adversary), rtol=0, atol=1e-9)
    exact = q_values(mimdp, other, adversary)
    assert np.all(sign * elsewhere <= sign * exact + 1e-9)
    assert np.max(sign * (exact - elsewhere)) > 1e-4  # stale multipliers do cost tightness here
    for r, a in [(0, 0), (3, 1), (7, 2), (mimdp.num_rows - 1, 3)]:
        truth = vertex_reference(mimdp, r, a, np.asarray(other)) if sign > 0 else \
            -vertex_reference(mimdp, r, a, -np.asarray(other))
        assert sign * elsewhere[r, a] <= sign * truth + 1e-12
    refrozen = freeze(frozen, other)
    again = q_values(refrozen, other, adversary)
    assert np.all(sign * again >= sign * elsewhere - 1e-12)
    np.testing.assert_allclose(again, exact, rtol=0, atol=1e-9)
    # a strategy's view keeps its own rows' multipliers
    actions = jnp.asarray(rng.integers(0, mimdp.num_actions, mimdp.num_rows), jnp.int32)
    picked = q_values(refrozen.restrict(actions), other, adversary)[:, 0]
    np.testing.assert_allclose(picked, again[np.arange(mimdp.num_rows), np.asarray(actions)], rtol=0, atol=1e-12)


def test_frozen_sweeps_reach_the_values_of_an_lp_at_every_sweep(unicycle_12):
    """Synthesis whose strategy sweeps use frozen multipliers (the default) ends within the
    tolerance's reach of the synthesis that solves every row's LP at every sweep: same certified
    values, optimal lower bounds and upper bounds."""
    grid, clusters, _ = unicycle_12
    sols = {}
    for freeze in (True, False):
        mimdp = MIMDP.from_clusters(grid, clusters, lp_backend="highs", freeze_multipliers=freeze)
        assert mimdp.freezable is freeze
        sols[freeze] = sj.synthesize(mimdp, tol=1e-9, method="value_iteration")
        assert sols[freeze].converged
    for name in ("lower", "lower_optimal", "upper"):
        np.testing.assert_allclose(np.asarray(getattr(sols[True], name)), np.asarray(getattr(sols[False], name)),
                                   rtol=0, atol=1e-6, err_msg=name)


@pytest.mark.parametrize("screen", [False, True])
def test_greedy_backup_multipliers_certify_its_values(small_clusters, screen):
    """``greedy_backup`` returns ``greedy_q_values`` and the multipliers it solved for: frozen at
    them (no LP call), the view gives those values back at the same vector on every pair whose LP
    was solved, and stays on the conservative side of the LP value at any other vector."""
    grid, clusters, extra = small_clusters
    mimdp = MIMDP.from_clusters(grid, clusters, extra_clusters=extra, screen_actions=screen)
    rng = np.random.default_rng(21)
    v = jnp.asarray(rng.uniform(0, 1, grid.num_states)).at[-1].set(0.0)
    other = jnp.asarray(rng.uniform(0, 1, grid.num_states)).at[-1].set(0.0)
    q, lam = jax.jit(lambda m, x: m.greedy_backup(x))(mimdp, v)
    np.testing.assert_array_equal(np.asarray(q), np.asarray(jax.jit(lambda m, x: m.greedy_q_values(x))(mimdp, v)))
    assert lam.shape == (*mimdp.lp_index.shape, mimdp.num_clusters, 2) and bool(jnp.all(lam >= 0))
    frozen = mimdp.from_multipliers(lam)
    calls = mimdp.lps.stats["calls"]
    at_v, elsewhere = q_values(frozen, v), q_values(frozen, other)
    assert mimdp.lps.stats["calls"] == calls
    solved = np.asarray(jnp.any(lam > 0, axis=(-2, -1)))
    assert solved.any() and (screen or solved.mean() > 0.5)
    np.testing.assert_allclose(at_v[solved], np.asarray(q)[solved], rtol=0, atol=1e-12)
    assert np.all(at_v <= np.asarray(q) + 1e-12)
    assert np.all(elsewhere <= q_values(mimdp, other) + 1e-9)
    assert np.all(elsewhere >= q_values(mimdp.relaxation, other) - 1e-12)  # never below lambda = 0
    # a frozen view has no LPs to keep multipliers of
    fq, flam = frozen.greedy_backup(v)
    assert flam is None
    np.testing.assert_array_equal(np.asarray(fq), at_v)


def test_sweeps_from_the_greedy_multipliers_save_lps_not_tightness(unicycle_12, monkeypatch):
    """The first round of strategy sweeps after a greedy backup reuses its multipliers instead of
    solving the strategy's LPs again: fewer LP calls, the same bounds to the tolerance."""
    from smdpjax.synthesis import value_iteration

    grid, clusters, _ = unicycle_12
    sols, calls = {}, {}
    for reuse in (True, False):
        monkeypatch.setattr(value_iteration, "REUSE_GREEDY_MULTIPLIERS", reuse)
        mimdp = MIMDP.from_clusters(grid, clusters, lp_backend="highs")  # a new model: a new trace
        sols[reuse] = sj.synthesize(mimdp, tol=1e-9, method="value_iteration")
        calls[reuse] = mimdp.lps.stats["calls"]
        assert sols[reuse].converged
    assert calls[True] < calls[False]
    for name in ("lower", "lower_optimal", "upper"):
        np.testing.assert_allclose(np.asarray(getattr(sols[True], name)), np.asarray(getattr(sols[False], name)),
                                   rtol=0, atol=1e-6, err_msg=name)


@pytest.mark.parametrize("backend", ["clarabel", "highs"])
def test_unsolved_lps_are_reported_with_their_cell_and_action(backend):
    if backend == "highs":
        pytest.importorskip("highspy")
    system = sj.System(unicycle, actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 6, reach=[([2 / 3, 2 / 3], [1.0, 1.0])])
    noise = sj.NoiseGrid.ball([0.0, 0.0], 0.9, 3)
    clusters = compute_grid_clusters(system, grid, noise)
    solved = MIMDP.from_clusters(grid, clusters, lp_backend=backend, screen_actions=False)
    limit = {"max_iter": 1} if backend == "clarabel" else {"simplex_iteration_limit": 0}
    starved = MIMDP.from_clusters(grid, clusters, lp_backend=backend, screen_actions=False, solver_settings=limit)
    v = jnp.asarray(np.random.default_rng(0).random(grid.num_states))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # solved LPs: no warning
        good = np.asarray(solved.q_values(v))
    assert solved.lps.stats["failed"] == 0
    with pytest.warns(RuntimeWarning, match=r"the LP of cell \d+, action \d+ ended with solver status"):
        loose = np.asarray(starved.q_values(v))
    assert starved.lps.stats["failed"] > 0
    p, status = starved.lps.failures[0]
    cell, action = starved.lps.names[p]
    assert cell == int(np.asarray(starved.rows)[p // system.num_actions]) and action == p % system.num_actions
    # still sound: never above the values of the solved LPs (each a valid lower bound on the true min)
    assert np.all(loose <= good + 1e-8)


def test_a_failed_warm_start_is_solved_again_cold(monkeypatch):
    """A HiGHS solve from an LP's last basis that ends without an optimum is run again from no
    basis: the values are those of a solver that never failed, and no failure is reported."""
    highspy = pytest.importorskip("highspy")
    system = sj.System(unicycle, actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 6, reach=[([2 / 3, 2 / 3], [1.0, 1.0])])
    clusters = compute_grid_clusters(system, grid, sj.NoiseGrid.ball([0.0, 0.0], 0.9, 3))
    plain = MIMDP.from_clusters(grid, clusters, lp_backend="highs", screen_actions=False, reprice_bases=False)
    flaky = MIMDP.from_clusters(grid, clusters, lp_backend="highs", screen_actions=False, reprice_bases=False)

    class WarmFails:  # a Highs whose runs from a given basis end with status "Unknown"
        def __init__(self, inner):
            self.inner, self.warm = inner, False

        def passModel(self, *args):
            self.warm = False
            return self.inner.passModel(*args)

        def setBasis(self, basis):
            self.warm = True
            return self.inner.setBasis(basis)

        def getModelStatus(self):
            return highspy.HighsModelStatus.kUnknown if self.warm else self.inner.getModelStatus()

        def __getattr__(self, name):
            return getattr(self.inner, name)

    solver = flaky.lps._highs_solver
    monkeypatch.setattr(flaky.lps, "_highs_solver", lambda: WarmFails(solver()))
    rng = np.random.default_rng(4)
    for v in (rng.random(grid.num_states), rng.random(grid.num_states)):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # nothing reported as failed
            np.testing.assert_allclose(q_values(flaky, v), q_values(plain, v), rtol=0, atol=1e-9)
    lps = plain.num_rows * plain.num_actions
    assert flaky.lps.stats["cold_retries"] == lps and flaky.lps.stats["failed"] == 0  # the second call's


def test_slots_of_reads_a_table_that_is_never_cleared(monkeypatch):
    """Positions of ids in sorted lists, through a position table reused block after block (3
    lists per block here): stale entries of earlier lists must not be read as positions."""
    from smdpjax.abstraction import mimdp as mimdp_module

    rng = np.random.default_rng(3)
    n, k = 30, 8
    sentinel = n + 1
    succ = np.sort(np.stack([rng.choice(n + 1, size=k, replace=False) for _ in range(20)]), axis=1)
    succ[::4, -2:] = sentinel  # padded lists
    succ = succ.reshape(5, 4, k)
    members = np.where(rng.random((5, 4, 3, 6)) < 0.8,
                       np.take_along_axis(succ[:, :, None, :], rng.integers(0, k, (5, 4, 3, 6)), axis=-1), sentinel)
    members = np.where(members > n, sentinel, members)
    want = np.full(members.shape, k)
    for idx in np.ndindex(members.shape):
        row = succ[idx[:2]]
        if members[idx] < sentinel:
            want[idx] = int(np.flatnonzero(row == members[idx])[0])
    monkeypatch.setattr(mimdp_module, "_SLOT_TABLE_ENTRIES", 3 * (sentinel + 1))
    np.testing.assert_array_equal(mimdp_module._slots_of(succ, members, sentinel), want)
    missing = members.copy()
    absent = next(s for s in range(n) if s not in succ[4, 3])
    missing[4, 3, 0, 0] = absent  # an id the list of the last block does not hold, listed by earlier ones
    with pytest.raises(AssertionError, match="missing"):
        mimdp_module._slots_of(succ, missing, sentinel)


@pytest.mark.parametrize("weights", [None, "colliding"])
def test_grouped_order_puts_equal_rows_of_a_group_next_to_each_other(weights):
    """Equal rows of a group adjacent and in their original order (the first one is kept), with
    the hash of the rows and with weights whose hashes collide ([1, 2] and [2, 1] with weights 1:
    the full sort is used)."""
    from smdpjax.abstraction.mimdp import _grouped_order

    rng = np.random.default_rng(0)
    rows = rng.integers(0, 3, (200, 2))
    group = rng.integers(0, 4, 200)
    w = None if weights is None else np.ones(2, np.uint64)
    order, _ = _grouped_order(rows, group, w)
    assert sorted(order.tolist()) == list(range(200))
    seen = {}
    for pos, i in enumerate(order):
        key = (int(group[i]), *rows[i].tolist())
        if key in seen:  # adjacent to its equal, after it in the original order
            assert seen[key][0] == pos - 1 and seen[key][1] < i
        seen[key] = (pos, int(i))


@pytest.mark.parametrize("threads", [1, 2])
def test_lps_are_solved_on_the_pool_threads_only(unicycle_12, threads, monkeypatch):
    """XLA runs host callbacks on its own threads, whose Python thread state (and a thread-local
    HiGHS instance with it) may not outlive one call: solving there crashed row 3 of Table 1
    with ``threads=1`` (segmentation fault). Every solve runs on the LP pool's threads, and a
    synthesis gives the same bounds with one thread as with two."""
    import threading

    pytest.importorskip("highspy")
    grid, clusters, _ = unicycle_12
    mimdp = MIMDP.from_clusters(grid, clusters, lp_backend="highs", threads=threads)
    solve, where = mimdp.lps._solve_highs, set()

    def recorded(*args):
        where.add(threading.current_thread().name)
        return solve(*args)

    monkeypatch.setattr(mimdp.lps, "_solve_highs", recorded)
    solution = sj.synthesize(mimdp, tol=1e-8)
    assert where and all(name.startswith("mimdp-lp") for name in where)
    assert len(where) <= threads
    reference = sj.synthesize(MIMDP.from_clusters(grid, clusters, lp_backend="highs", threads=2), tol=1e-8)
    np.testing.assert_allclose(np.asarray(solution.lower), np.asarray(reference.lower), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(solution.upper), np.asarray(reference.upper), rtol=0, atol=1e-9)


def test_repriced_bases_give_the_synthesis_of_an_lp_solve_each_time(unicycle_12):
    """Re-pricing the LPs' last optimal bases (``lp_reprice``) serves some LPs without HiGHS and
    gives the bounds and strategy of solving every LP, to the solvers' tolerance."""
    pytest.importorskip("highspy")
    grid, clusters, _ = unicycle_12
    repriced = MIMDP.from_clusters(grid, clusters, lp_backend="highs")
    solved = MIMDP.from_clusters(grid, clusters, lp_backend="highs", reprice_bases=False)
    a, b = sj.synthesize(repriced, tol=1e-8), sj.synthesize(solved, tol=1e-8)
    assert repriced.lps.stats["repriced"] > 0 and solved.lps.stats["repriced"] == 0
    assert repriced.lps.stats["Optimal"] < solved.lps.stats["Optimal"]
    for field in ("lower", "upper", "lower_optimal"):
        np.testing.assert_allclose(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)), rtol=0, atol=1e-8)
    np.testing.assert_array_equal(np.asarray(a.policy), np.asarray(b.policy))


@pytest.mark.parametrize("chunked", [False, True])
def test_frozen_terms_give_the_certificate_of_their_multipliers(small, monkeypatch, chunked):
    """``cluster_terms`` then ``shifted_min`` is ``certified_min`` with the same multipliers (all
    rows at once or in overlapping chunks of rows), and a frozen view's backup is that value."""
    from smdpjax.abstraction import mimdp as mimdp_module

    grid, _, mimdp, _ = small
    rng = np.random.default_rng(7)
    imdp = mimdp.relaxation
    shape = (*mimdp.lp_index.shape, mimdp.num_clusters, 2)
    w = jnp.asarray(rng.uniform(0, 1, grid.num_states))
    # the LPs' multipliers on half the rows, random ones (some beyond the cap) on the others
    random = rng.uniform(0, 5, shape) * (rng.random(shape) < 0.3)
    lam = jnp.where(jnp.asarray(rng.random(shape[:2]) < 0.5)[..., None, None], mimdp.multipliers(w, mimdp.lp_index),
                    jnp.asarray(random))
    polytope = (imdp.successors, imdp.lower, imdp.upper)
    cap = mimdp.multiplier_cap
    reference = np.asarray(certified_min(w, *polytope, imdp.upper_rest, mimdp.cluster_members, mimdp.cluster_lower,
                                         mimdp.cluster_upper, lam, cap))
    if chunked:
        monkeypatch.setattr(mimdp_module, "_SHIFTED_ENTRIES_PER_CHUNK", 7 * imdp.width)
    shift, offset = mimdp_module.cluster_terms(imdp.width, mimdp.cluster_members, mimdp.cluster_lower,
                                               mimdp.cluster_upper, lam, cap, rows_per_chunk=5 if chunked else None)
    assert shift.shape == (*mimdp.lp_index.shape, imdp.width) and offset.shape == mimdp.lp_index.shape
    got = np.asarray(mimdp_module.shifted_min(w, *polytope, imdp.upper_rest, shift, offset))
    np.testing.assert_allclose(got, reference, rtol=0, atol=1e-15)
    assert np.any(got > np.asarray(imdp.q_values(w, "min")) + 1e-6)  # the multipliers do lift some rows
    frozen = mimdp._frozen_at(lam)
    np.testing.assert_allclose(q_values(frozen, w), reference, rtol=0, atol=1e-15)
    np.testing.assert_allclose(q_values(frozen, -w + 1, "max"), -np.asarray(certified_min(
        w - 1, *polytope, imdp.upper_rest, mimdp.cluster_members, mimdp.cluster_lower, mimdp.cluster_upper, lam, cap)),
        rtol=0, atol=1e-15)
