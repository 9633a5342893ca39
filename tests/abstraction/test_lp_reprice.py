"""Re-pricing the MI-MDP LPs' last optimal bases (``lp_reprice``) against HiGHS solves."""

import numpy as np
import pytest

from smdpjax.abstraction.lp import ClusterLPs
from smdpjax.abstraction.lp_reprice import BasisRecord, ranges, reprice

pytest.importorskip("highspy")
# some of the random LPs are infeasible: they are reported, not recorded, and never re-priced
pytestmark = pytest.mark.filterwarnings("ignore:MI-MDP.*did not reach an optimum:RuntimeWarning")


def surrogate_dual(lps, p, cost, lam):
    """The surrogate LP's dual function of LP ``p`` at multipliers ``lam (J, 2)``, its equality
    multiplier chosen optimally (a 1-D concave maximization, by checking every breakpoint)."""
    lp = lps._lps[p]
    mu = np.zeros(lp["cluster"].size)
    offset = 0.0
    for i, (c, lo, hi) in enumerate(zip(lp["cluster"], lp["lo"], lp["hi"])):
        plus, minus = lam[c]
        mu[i] = plus - minus
        offset += (plus * lo if plus > 0 else 0.0) - (minus * hi if minus > 0 else 0.0)
    shifted = cost.copy()
    for i in range(mu.size):
        shifted[lp["var"][lp["ptr"][i]:lp["ptr"][i + 1]]] -= mu[i]
    dual = lambda nu: nu * lp["free_mass"] + np.sum(lp["caps"] * np.minimum(shifted - nu, 0.0))
    return offset + max(dual(nu) for nu in shifted)


@pytest.fixture
def lps_and_costs(random_lps):
    """``make(seed, rest)``: HiGHS ``ClusterLPs`` of ``random_lps``, costs ``(N+1,)`` and a generator."""
    def make(seed, rest=0.0):
        succ, lower, upper, rest, slots, clo, cup, n = random_lps(seed, rest)
        k = succ.shape[1]  # HiGHS refuses a row that names a variable twice: distinct members
        slots = np.sort(np.where(np.diff(slots, prepend=-1, axis=-1) == 0, k, slots), axis=-1)
        lps = ClusterLPs(succ, lower, upper, rest, slots, clo, cup, n, backend="highs")
        rng = np.random.default_rng(seed + 100)
        return lps, rng.uniform(0, 1, lps.num_states), rng
    return make


def test_ranges_and_owners():
    index, owner = ranges(np.array([3, 0, 7]), np.array([5, 0, 10]))
    np.testing.assert_array_equal(index, [3, 4, 7, 8, 9])
    np.testing.assert_array_equal(owner, [0, 0, 2, 2, 2])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_at_the_same_costs_every_basis_reprices_to_the_solvers_duals(seed, lps_and_costs):
    """The last solve's basis is optimal at its own costs: every LP is accepted, with HiGHS's duals."""
    lps, w, _ = lps_and_costs(seed, rest=0.01)
    ids = np.arange(lps.num_lps)
    solved = lps.multipliers(w, ids).reshape(ids.size, -1)  # no records yet: every LP solved
    optimal = lps._record(0).known  # only optimal solves are recorded
    assert optimal.sum() == ids.size - lps.stats["failed"] >= 15 and lps.stats["repriced"] == 0
    repriced = np.zeros_like(solved)
    served = lps._repriced(ids, lps.cost_table(w, ids), 0, repriced)
    np.testing.assert_array_equal(served, optimal & (lps.num_vars > 0))
    np.testing.assert_allclose(repriced[served], solved[served], rtol=0, atol=1e-12)
    again = lps.multipliers(w, ids).reshape(ids.size, -1)  # the same through multipliers
    assert lps.stats["repriced"] == served.sum()
    np.testing.assert_allclose(again[served], solved[served], rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 3])
@pytest.mark.parametrize("step", [1e-4, 1e-2, 1.0])
def test_accepted_duals_certify_the_fresh_solves_value(seed, step, lps_and_costs):
    """After the costs move (a little, or to unrelated ones), an accepted LP's multipliers certify
    what a fresh HiGHS solve's certify, within the gap; small steps keep many bases optimal,
    unrelated costs few."""
    lps, w, rng = lps_and_costs(seed, rest=0.01)
    ids = np.arange(lps.num_lps)
    lps.multipliers(w, ids)  # records every basis
    accepted_total = 0
    for _ in range(3):
        w = np.clip(w + step * rng.uniform(-1, 1, w.size), 0, 1)
        costs = lps.cost_table(w, ids)
        out = np.zeros((ids.size, 2 * lps.num_clusters))
        served = lps._repriced(ids, costs, 0, out)
        lps.reprice = False
        fresh = lps.multipliers(w, ids).reshape(ids.size, -1)
        lps.reprice = True
        for p in np.flatnonzero(served):
            cost = costs[p, lps._lps[p]["cost_src"]]
            ours = surrogate_dual(lps, p, cost, out[p].reshape(-1, 2))
            theirs = surrogate_dual(lps, p, cost, fresh[p].reshape(-1, 2))
            assert ours >= theirs - 1e-9
        accepted_total += served.sum()
        lps.multipliers(w, ids)  # solve the rest, recording their bases
    if step <= 1e-4:
        assert accepted_total > ids.size  # most bases stay optimal under small steps


@pytest.mark.parametrize("seed", [0, 3])
def test_the_sparse_systems_reprice_as_the_dense_ones(seed, lps_and_costs, monkeypatch):
    """Every system solved as one sparse block-diagonal system (``SIZES = (2,)``: all but the
    smallest) gives the duals and the accepted LPs that the dense systems give, at the costs of
    the last solve (all accepted, HiGHS's duals) and after the costs moved."""
    from smdpjax.abstraction import lp_reprice

    lps, w, rng = lps_and_costs(seed, rest=0.01)
    ids = np.arange(lps.num_lps)
    solved = lps.multipliers(w, ids).reshape(ids.size, -1)
    table, record = lps._lps, lps._record(0)
    gv, vq = ranges(table.var_start[ids], table.var_start[ids + 1])
    size = np.bincount(vq[record.basic[gv]], minlength=ids.size)
    assert (size > 2).sum() >= 10 and size.max() <= lp_reprice.SIZES[-1]
    for w_now in (w, np.clip(w + 1e-4 * rng.uniform(-1, 1, w.size), 0, 1)):
        var_cost = lps.cost_table(w_now, ids)[vq, table.cost_src[gv]]
        dense = reprice(table, ids, var_cost, record, gap=1e-10)
        with monkeypatch.context() as m:
            m.setattr(lp_reprice, "SIZES", (2,))
            sparse = reprice(table, ids, var_cost, record, gap=1e-10)
        np.testing.assert_array_equal(sparse[0], dense[0])
        np.testing.assert_allclose(sparse[3], dense[3], rtol=0, atol=1e-12)
        assert dense[0].sum() >= ids.size // 2
    out = np.zeros_like(solved)
    monkeypatch.setattr(lp_reprice, "SIZES", (2,))
    served = lps._repriced(ids, lps.cost_table(w, ids), 0, out)
    assert served[size > 2].all()
    np.testing.assert_allclose(out[served], solved[served], rtol=0, atol=1e-12)


def test_a_refused_basis_waits_for_a_solve_that_keeps_it(lps_and_costs, monkeypatch):
    """An LP whose re-priced sparse system was refused is not re-priced again until HiGHS has
    solved it again (its basis then stable again); the dense systems (here only those of at
    most 2 unknowns) are always tried."""
    from smdpjax.abstraction import lp_reprice

    monkeypatch.setattr(lp_reprice, "SIZES", (2,))
    lps, w, _ = lps_and_costs(5)
    ids = np.arange(lps.num_lps)
    lps.multipliers(w, ids)
    record = lps._record(0)
    assert record.stable[record.known].all()  # a first solve from no basis: counted as stable
    costs = lps.cost_table(1.0 - w, ids)
    served = lps._repriced(ids, costs, 0, np.zeros((ids.size, 2 * lps.num_clusters)))
    table = lps._lps
    gv, vq = ranges(table.var_start[ids], table.var_start[ids + 1])
    large = np.bincount(vq[record.basic[gv]], minlength=ids.size) > 2
    refused = record.known & ~served & large
    assert refused.any() and not record.stable[refused].any()
    assert record.stable[record.known & ~large].all()
    again = lps._repriced(ids, costs, 0, np.zeros((ids.size, 2 * lps.num_clusters)))
    assert not again[refused].any()
    lps.multipliers(1.0 - w, ids)  # HiGHS moves the refused bases
    lps.multipliers(1.0 - w, ids)  # at the same costs: served, or solved with no iteration
    assert record.stable[record.known].all()


def test_a_stale_basis_is_rejected_not_trusted(lps_and_costs):
    """Costs reversed: the recorded bases are not optimal any more. Each is rejected by its
    certificate, or accepted only where its duals are still optimal."""
    lps, w, _ = lps_and_costs(5)
    ids = np.arange(lps.num_lps)
    lps.multipliers(w, ids)
    w2 = 1.0 - w
    costs = lps.cost_table(w2, ids)
    out = np.zeros((ids.size, 2 * lps.num_clusters))
    served = lps._repriced(ids, costs, 0, out)
    lps.reprice = False
    fresh = lps.multipliers(w2, ids).reshape(ids.size, -1)
    rejected = 0
    for p in ids:
        cost = costs[p, lps._lps[p]["cost_src"]]
        best = surrogate_dual(lps, p, cost, fresh[p].reshape(-1, 2))
        if served[p]:
            assert surrogate_dual(lps, p, cost, out[p].reshape(-1, 2)) >= best - 1e-9
        else:
            rejected += 1
    assert rejected > 0


@pytest.mark.parametrize("sizes", [None, (1,)])
def test_reprice_handles_singular_and_oversized_systems(lps_and_costs, monkeypatch, sizes):
    """A record whose system is singular, or larger than ``max_size``, is not accepted (the LP
    goes to the solver), and the other LPs of the call are unaffected; through the dense systems
    and (``SIZES = (1,)``) the sparse one, where the singular record is also marked not stable."""
    from smdpjax.abstraction import lp_reprice

    if sizes is not None:
        monkeypatch.setattr(lp_reprice, "SIZES", sizes)
    lps, w, _ = lps_and_costs(2)
    ids = np.arange(lps.num_lps)
    lps.multipliers(w, ids)
    table, record = lps._lps, lps._record(0)
    gv, vq = ranges(table.var_start[ids], table.var_start[ids + 1])
    var_cost = lps.cost_table(w, ids)[vq, table.cost_src[gv]]
    accepted, *_ = reprice(table, ids, var_cost, record, gap=1e-10)
    size = np.bincount(vq[record.basic[gv]], minlength=ids.size)
    assert accepted[size > 0].all()
    small, *_ = reprice(table, ids, var_cost, record, gap=1e-10, max_size=1)
    np.testing.assert_array_equal(small, accepted & (size <= 1))

    # singular: the equality and one row active, two basic variables outside that row (the
    # same column (1, 0) twice)
    broken = BasisRecord(table.caps.size, table.cluster.size, lps.num_lps)
    for name in ("x", "basic", "active", "eq_active", "known", "stable"):
        setattr(broken, name, getattr(record, name).copy())
    for p in np.flatnonzero(np.diff(table.row_start) > 0):
        v0, v1, r0, r1 = table.var_start[p], table.var_start[p + 1], table.row_start[p], table.row_start[p + 1]
        outside = np.flatnonzero(~np.isin(np.arange(v1 - v0), table.var[table.member_start[r0]:table.member_start[r0 + 1]]))
        if outside.size >= 2:
            break
    else:
        pytest.fail("no LP with two variables outside its first row")
    broken.active[r0:r1] = False
    broken.active[r0] = True
    broken.eq_active[p] = True
    broken.basic[v0:v1] = False
    broken.basic[v0 + outside[:2]] = True
    again, *_ = reprice(table, ids, var_cost, broken, gap=1e-10)
    assert not again[p]
    np.testing.assert_array_equal(np.delete(again, p), np.delete(accepted, p))
    assert broken.stable[p] == (sizes is None)


def test_a_zero_dual_rounded_toward_a_missing_side_is_accepted_as_zero():
    """min c0 x0 + c1 x1, x0 + x1 = 1, x0 <= 1/2 (the lower side left out), x in [0, 1]^2, at the
    vertex (1/2, 1/2) with both variables basic: nu = c1 and y = c0 - c1. With c0 = 0.1 + 0.2
    and c1 = 0.3, y rounds to +5.6e-17, pointing at the missing lower side (D would be -inf);
    it is taken as 0 (the exact dual), and the certificate accepts: the optimum is 0.3, and
    D(0.3, 0) = 0.3."""
    from smdpjax.abstraction.lp import LPTable

    table = LPTable(caps=np.ones(2), cost_src=np.arange(2), var_start=np.array([0, 2]), free_mass=np.ones(1),
                    cluster=np.zeros(1, np.int64), lo=np.array([-np.inf]), hi=np.array([0.5]),
                    row_start=np.array([0, 1]), var=np.array([0]), member_start=np.array([0, 1]))
    record = BasisRecord(2, 1, 1)
    record.x[:] = 0.5
    record.basic[:] = record.active[0] = record.eq_active[0] = record.known[0] = record.stable[0] = True
    cost = np.array([0.1 + 0.2, 0.3])
    assert cost[0] - cost[1] > 0  # the rounding this is about
    accepted, rows, owner, duals = reprice(table, np.array([0]), cost, record, gap=1e-15)
    assert accepted[0]
    np.testing.assert_array_equal(duals, [0.0])
    # a dual of the wrong sign that is not rounding (the basis is no longer optimal) stays refused
    refused, *_ = reprice(table, np.array([0]), np.array([1.0, 0.3]), record, gap=1e-10)
    assert not refused[0]


def test_degenerate_solves_record_the_solvers_basis(lps_and_costs, monkeypatch):
    """Tied costs make the optimum degenerate: some nonbasic variables have reduced cost 0, so the
    duals do not tell the basis and the record reads HiGHS's statuses. Those bases re-price to
    HiGHS's duals all the same."""
    from smdpjax.abstraction import lp_reprice

    lps, w, _ = lps_and_costs(4, rest=0.01)
    w = np.round(w * 3) / 3  # four distinct values: many ties
    ids = np.arange(lps.num_lps)
    read = []
    record = lp_reprice.BasisRecord.record

    def counted(self, table, p, solution, row_dual, basic_variables, lock=None, **kwargs):
        return record(self, table, p, solution, row_dual, lambda: read.append(p) or basic_variables(), lock, **kwargs)

    monkeypatch.setattr(lp_reprice.BasisRecord, "record", counted)
    solved = lps.multipliers(w, ids).reshape(ids.size, -1)
    assert read  # some solves were degenerate
    out = np.zeros_like(solved)
    served = lps._repriced(ids, lps.cost_table(w, ids), 0, out)
    assert served[read].all()
    np.testing.assert_allclose(out[served], solved[served], rtol=0, atol=1e-12)


def test_bases_too_large_to_reprice_are_not_recorded(lps_and_costs, monkeypatch):
    """A basis of more unknowns than the largest system size (``MAX_SIZE``) is not recorded (its
    LP is solved every time); the others are, as without the limit."""
    from smdpjax.abstraction import lp_reprice

    def recorded():
        lps, w, _ = lps_and_costs(1, rest=0.01)
        ids = np.arange(lps.num_lps)
        lps.multipliers(w, ids)
        table, record = lps._lps, lps._record(0)
        unknowns = np.array([record.active[table.row_start[p]:table.row_start[p + 1]].sum() + record.eq_active[p]
                             for p in ids])
        return record.known.copy(), unknowns

    known, unknowns = recorded()
    monkeypatch.setattr(lp_reprice, "MAX_SIZE", 2)
    limited, _ = recorded()
    np.testing.assert_array_equal(limited, known & (unknowns <= 2))
    assert limited.any() and (known & ~limited).any()


@pytest.mark.parametrize("after_pivots", [False, True])
def test_a_basis_solved_with_pivots_is_repriced_at_the_next_call(lps_and_costs, monkeypatch, after_pivots):
    """With ``REPRICE_AFTER_PIVOTS`` a large basis that HiGHS reached by pivoting is re-priced at
    the next call, and at the same costs it is accepted with duals that certify the optimum;
    without it, HiGHS solves it again."""
    from smdpjax.abstraction import lp, lp_reprice

    monkeypatch.setattr(lp_reprice, "SIZES", (2,))
    monkeypatch.setattr(lp, "REPRICE_AFTER_PIVOTS", after_pivots)
    lps, w, _ = lps_and_costs(5)
    ids = np.arange(lps.num_lps)
    lps.multipliers(w, ids)
    lps.multipliers(1.0 - w, ids)  # large bases refused, HiGHS pivots from them
    record = lps._record(0)
    pivoted = record.known & ~record.stable
    assert pivoted.any() != after_pivots
    solves, served = lps.stats["Optimal"], lps.stats["repriced"]
    lam = lps.multipliers(1.0 - w, ids).reshape(ids.size, -1, 2)
    if not after_pivots:
        assert lps.stats["Optimal"] - solves >= pivoted.sum()
        return
    assert lps.stats["Optimal"] == solves and lps.stats["repriced"] - served == record.known.sum()
    costs = lps.cost_table(1.0 - w, ids)
    table = lps._lps
    for p in np.flatnonzero(record.known):
        cost = costs[p, table[p]["cost_src"]]
        optimum = cost @ record.x[table.var_start[p]:table.var_start[p + 1]]  # the vertex just solved for
        assert surrogate_dual(lps, p, cost, lam[p]) >= optimum - 1e-9


@pytest.mark.parametrize("presolve, setting, presolved", [(False, None, False), (True, None, True), (False, "on", True)])
def test_highs_presolves_only_when_asked_and_reaches_the_same_optimum(lps_and_costs, monkeypatch, presolve, setting,
                                                                     presolved):
    """``lp.PRESOLVE`` (off by default) decides whether HiGHS presolves the LPs it solves from no
    basis, a ``presolve`` setting overrides it; either way the multipliers certify each LP's optimum."""
    import highspy

    from smdpjax.abstraction import lp

    assert lp.PRESOLVE is False
    monkeypatch.setattr(lp, "PRESOLVE", presolve)
    lps, w, _ = lps_and_costs(4)
    if setting is not None:
        lps.settings["presolve"] = setting  # read when the solver thread sets up its instance
    statuses = []
    solve = ClusterLPs._solve_highs

    def solve_and_note(self, *args):
        status = solve(self, *args)
        statuses.append(self._highs_solver().getModelPresolveStatus())
        return status

    monkeypatch.setattr(ClusterLPs, "_solve_highs", solve_and_note)
    ids = np.arange(lps.num_lps)
    lam = lps.multipliers(w, ids).reshape(ids.size, -1, 2)
    presolved_solves = sum(status != highspy.HighsPresolveStatus.kNotPresolved for status in statuses)
    # (with presolve, HiGHS still skips it on some LPs, e.g. ones its bounds show infeasible)
    assert len(statuses) == ids.size and (presolved_solves > ids.size // 2 if presolved else presolved_solves == 0)
    record = lps._record(0)
    costs = lps.cost_table(w, ids)
    table = lps._lps
    assert record.vertex.sum() >= ids.size // 2
    for p in np.flatnonzero(record.vertex):
        cost = costs[p, table[p]["cost_src"]]
        optimum = cost @ record.x[table.var_start[p]:table.var_start[p + 1]]
        assert surrogate_dual(lps, p, cost, lam[p]) >= optimum - 1e-9
