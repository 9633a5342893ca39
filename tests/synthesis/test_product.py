"""Synthesis for DFA specifications on the implicit product (``smdpjax.synthesis.product``).

* reach-avoid written as the 3-state DFA gives the built-in reach-avoid's p_low, p_up and
  strategy to 1e-12, for all four classes, unbounded and finite horizon (on the reach-avoid grid's
  abstraction, and on an abstraction of the same grid without regions, whose every cell is a row);
  safety as a DFA gives the built-in safety bounds;
* an exact small case computed by hand (a 3-cell SMDP and IMDP, "visit a then b");
* Theorem 3's order holds on the product (sequence specification, same reachable sets);
* Monte Carlo, judged by the DFA on the true states, falls inside [p_low, p_up];
* verify_product, batching="map", mixed cells, bad input.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax import specification as sp
from smdpjax.abstraction import build, compute_grid_clusters
from smdpjax.partition import AVOID, NONTERMINAL
from smdpjax.synthesis.product import ProductAbstraction

TOL12 = 1e-12


def damped_unicycle(x, u, w):  # heading u[0], contracting towards the unit circle (tests/test_storm.py)
    return 0.6 * x + 0.5 * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + 0.02 * w


SYSTEM = sj.System(damped_unicycle, actions=(np.arange(8) * np.pi / 4)[:, None], noise=sj.Gaussian([0, 0], [1.0, 1.0]))
NOISE = sj.NoiseGrid.ball([0, 0], 3.5, 6)
CELLS = 8
LOW, HIGH = [-1, -1], [1, 1]
REACH = [([0.5, 0.5], [1.0, 1.0])]
AVOID_BOXES = [([-0.25, 0.0], [0.25, 0.5])]
RA_GRID = sj.StateGrid(LOW, HIGH, CELLS, reach=REACH, avoid=AVOID_BOXES)
FREE_GRID = sj.StateGrid(LOW, HIGH, CELLS)
A_BOX = [([-1.0, 0.5], [-0.5, 1.0])]
B_BOX = [([0.5, -1.0], [1.0, -0.5])]


@pytest.fixture(scope="module")
def clusters():
    return {"ra": compute_grid_clusters(SYSTEM, RA_GRID, NOISE, method="natural"),
            "free": compute_grid_clusters(SYSTEM, FREE_GRID, NOISE, method="natural")}


@pytest.fixture(scope="module")
def abstractions(clusters):
    out = {}
    for kind in sj.KINDS:
        options = {"block": 2} if kind == "2imdp" else {}
        out[kind] = (build(kind, RA_GRID, clusters["ra"], **options), build(kind, FREE_GRID, clusters["free"], **options))
    return out


def assert_close(a, b, tol=TOL12):
    assert np.max(np.abs(np.asarray(a, float) - np.asarray(b, float))) <= tol


@pytest.mark.parametrize("kind", sj.KINDS)
def test_reach_avoid_dfa_equals_the_built_in(abstractions, kind):
    ra, free = abstractions[kind]
    spec = sp.reach_avoid_of(RA_GRID)
    rows = np.asarray(ra.rows)
    for horizon in (None, 7):
        ref = sj.synthesize(ra, horizon=horizon, method="value_iteration")  # as the product is optimized
        for abstraction, grid in ((ra, RA_GRID), (free, FREE_GRID)):
            sol = sj.synthesize_product(abstraction, spec.on(grid), horizon=horizon)
            assert_close(sol.initial_lower, ref.lower)
            assert_close(sol.initial_upper, ref.upper)
            assert_close(sol.lower[0], np.where(np.asarray(ref.policy if horizon is None else ref.policy[0]) >= 0,
                                                sol.lower[0], 0))  # shapes line up
            run = sol.lower[0]  # DFA state "run": the built-in values on the non-terminal cells
            assert_close(run[rows], ref.lower[rows])
            policy, ref_policy = np.asarray(sol.policy), np.asarray(ref.policy)
            np.testing.assert_array_equal(policy[..., 0, rows], ref_policy[..., rows])
            assert np.all(np.asarray(sol.lower[1, :-1]) == 1.0) and np.all(np.asarray(sol.lower[2]) == 0.0)
        assert 0.05 < float(np.mean(np.asarray(ref.lower)[rows])) < 0.99  # not a trivial comparison


def test_safety_dfa_equals_the_built_in(abstractions):
    smdp_free = abstractions["smdp"][1]
    grid = sj.StateGrid(LOW, HIGH, CELLS, avoid=AVOID_BOXES)
    smdp = build("smdp", grid, compute_grid_clusters(SYSTEM, grid, NOISE, method="natural"))
    spec = sp.safety(AVOID_BOXES)
    with pytest.raises(ValueError, match="horizon"):
        sj.synthesize_product(smdp, spec.on(grid))
    for horizon in (1, 6):
        ref = sj.synthesize(smdp, horizon=horizon, objective="safety")
        for abstraction, g in ((smdp, grid), (smdp_free, FREE_GRID)):
            sol = sj.synthesize_product(abstraction, spec.on(g), horizon=horizon)
            assert_close(sol.initial_lower, ref.lower)
            assert_close(sol.initial_upper, ref.upper)
        assert 0.05 < float(np.mean(np.asarray(ref.lower)[:-1])) < 0.99


# ------------------------------------------------------------------ an exact case by hand

def line_specification():
    """Three cells on [0, 3]: a = cell 0, b = cell 2; visit a, then b."""
    grid = sj.StateGrid([0.0], [3.0], 3)
    spec = sp.sequence({"a": [([0.0], [1.0])], "b": [([2.0], [3.0])]})
    return grid, spec.on(grid)


def test_hand_computed_product_values():
    """One action; from every cell the SMDP moves with probability 1/2 to a cluster and 1/2 to
    another. Cell 0: {1} and {0, 1}; cell 1: {0} and {2}; cell 2: {1, 2} and {sink}.

    DFA states: visit_a (0), visit_b (1), done (2), fail (3). u = v[delta(q, L(s')), s'].
    Stage b (q = 1), unbounded, SMDP (adversary takes each cluster's minimum); entering cell 2
    reads b -> done (value 1), so (visit_b, cell 2) is never occupied (value 0, no row):
        v1(0) = 1/2 v1(1) + 1/2 min(v1(0), v1(1)),  v1(1) = 1/2 v1(0) + 1/2 * 1.
    With v1(0) <= v1(1): v1(0) = v1(1)/2 + v1(0)/2 -> v1(0) = v1(1), and v1(1) = v1(1)/2 + 1/2 -> 1.
    So v1 = (1, 1). Stage a (q = 0): entering cell 0 reads a -> stage b, so
        u0 = (v1(0), v0(1), v0(2)) = (1, v0(1), v0(2)); v0(1) = 1/2 * 1 + 1/2 v0(2) (cell 2 is b,
        but b before a changes nothing: stage a) and v0(2) = 1/2 min(v0(1), v0(2)) + 0.
    Least fixed point: v0(2) = v0(2)/2 -> 0 and v0(1) = 1/2. Start values: cell 0 reads a -> v1(0) = 1;
    cell 1 -> v0(1) = 1/2; cell 2 -> v0(2) = 0.
    """
    grid, spec = line_specification()
    members = jnp.array([[[[1, 4], [0, 1]]], [[[0, 4], [2, 4]]], [[[1, 2], [3, 4]]]], jnp.int32)  # padding 4
    smdp = sj.SMDP.from_members(members, jnp.array([0.5, 0.5]), 0.0, jnp.arange(3), jnp.array(grid.state_labels))
    sol = sj.synthesize_product(smdp, spec, tol=1e-13)
    np.testing.assert_allclose(np.asarray(sol.lower[1]), [1.0, 1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_array_equal(np.asarray(sol.lower[2]), [1.0, 1.0, 1.0, 0.0])  # done; the sink fails
    np.testing.assert_allclose(np.asarray(sol.lower[0, 1:3]), [0.5, 0.0], atol=1e-9)
    np.testing.assert_allclose(np.asarray(sol.initial_lower), [1.0, 0.5, 0.0, 0.0], atol=1e-9)
    # the maximizing adversary: v1 = (1, 1) again; stage a: v0(2) = 1/2 max(v0(1), v0(2)),
    # v0(1) = 1/2 + 1/2 v0(2): from above, v0(2) = 1/2 v0(1) -> v0(1) = 2/3, v0(2) = 1/3
    np.testing.assert_allclose(np.asarray(sol.initial_upper), [1.0, 2 / 3, 1 / 3, 0.0], atol=1e-5)
    assert np.all(np.asarray(sol.initial_lower) <= np.asarray(sol.initial_upper))
    # the IMDP of the same clusters (Lemma 1) is looser and below
    imdp = sj.IMDP.from_members(members, jnp.array([0.5, 0.5]), 0.0, jnp.arange(3), jnp.array(grid.state_labels))
    sol_i = sj.synthesize_product(imdp, spec, tol=1e-13)
    assert np.all(np.asarray(sol_i.initial_lower) <= np.asarray(sol.initial_lower) + 1e-12)
    # two steps, by hand: v^0 = 1 on done. Stage b after one step: v1^1 = (0, 1/2, 0); after two:
    # v1^2(0) = 1/2 v1^1(1) + 1/2 min(v1^1(0), v1^1(1)) = 1/4. Start in cell 0 reads a: 1/4.
    fin = sj.synthesize_product(smdp, spec, horizon=2)
    assert abs(float(fin.initial_lower[0]) - 0.25) < 1e-12


def test_product_tables_of_the_line():
    grid, spec = line_specification()
    tables = spec.tables(np.arange(3))
    size = 4
    assert tables.live == (0, 1)
    # stage a: cell 0 -> stage b, cell 1 -> stage a, cell 2 (b) -> stage a, sink -> (0, sink)
    np.testing.assert_array_equal(np.asarray(tables.succ)[0, :, 0], [1 * size + 0, 1, 2, 3])
    np.testing.assert_array_equal(np.asarray(tables.succ)[1, :, 0], [size + 0, size + 1, 2 * size + 2, size + 3])
    labels = np.asarray(tables.labels).reshape(4, size)
    # stage a is occupied in cells 1 and 2 only (cell 0 reads a); stage b everywhere but cell 2 (b -> done)
    np.testing.assert_array_equal(labels[0], [AVOID, NONTERMINAL, NONTERMINAL, AVOID])
    np.testing.assert_array_equal(labels[1], [NONTERMINAL, NONTERMINAL, AVOID, AVOID])
    np.testing.assert_array_equal(np.asarray(tables.start)[:, 0], [size + 0, 1, 2, 3])


# ------------------------------------------------------------------ Theorem 3, Monte Carlo

SEQ = sp.sequence({"a": A_BOX, "b": B_BOX}, avoid=AVOID_BOXES)


@pytest.fixture(scope="module")
def sequence_solutions(abstractions):
    spec = SEQ.on(FREE_GRID)
    return {kind: sj.synthesize_product(abstractions[kind][1], spec) for kind in sj.KINDS}


def test_theorem3_order_on_the_product(sequence_solutions):
    lo = {k: np.asarray(s.lower_optimal) for k, s in sequence_solutions.items()}
    eps = 1e-9
    assert np.all(lo["smdp"] >= lo["mimdp"] - eps)
    assert np.all(lo["mimdp"] >= lo["imdp"] - eps)
    assert np.all(lo["2imdp"] >= lo["imdp"] - eps)
    assert np.mean(lo["smdp"]) > np.mean(lo["imdp"]) + 0.01  # the order is not all ties
    for s in sequence_solutions.values():
        assert np.all(np.asarray(s.lower) <= np.asarray(s.upper))
        assert np.all(np.asarray(s.initial_lower) <= np.asarray(s.initial_upper))


def monte_carlo_inside(spec, sol, cells, per_cell, key, max_steps):
    controller = sp.ProductController(spec, sol.policy)
    x0 = sj.uniform_in_cells(spec.grid, cells, per_cell, key)
    res = sp.simulate_product(SYSTEM, controller, x0, jax.random.fold_in(key, 1), max_steps=max_steps)
    freq = np.asarray(res.satisfied).reshape(len(cells), per_cell).mean(axis=1)
    lo, up = np.asarray(sol.initial_lower)[cells], np.asarray(sol.initial_upper)[cells]
    band = 4 * np.sqrt(np.maximum(freq * (1 - freq), 1e-4) / per_cell)
    assert np.all(freq >= lo - band) and np.all(freq <= up + band), (freq, lo, up)
    return freq, res


def test_monte_carlo_inside_the_bounds(sequence_solutions, key):
    spec = SEQ.on(FREE_GRID)
    sol = sequence_solutions["smdp"]
    cells = np.array([0, 9, 18, 27, 36, 45, 63, 7])
    freq, res = monte_carlo_inside(spec, sol, cells, 200, key, 400)
    assert res.undecided == 0 and 0.2 < freq.mean() < 1.0
    # the strategy differs per DFA state: going to a first, then to b
    policy = np.asarray(sol.policy)
    assert np.any(policy[0, :-1] != policy[1, :-1])


def test_finite_horizon_monte_carlo_and_final_acceptance(abstractions, key):
    smdp = abstractions["smdp"][1]
    spec = SEQ.on(FREE_GRID)
    sol = sj.synthesize_product(smdp, spec, horizon=25)
    assert np.asarray(sol.policy).shape == (25, 4, FREE_GRID.num_states)
    monte_carlo_inside(spec, sol, np.array([0, 27, 54]), 300, key, 25)
    # "final": stay out of the obstacle for 12 steps, and end inside b
    dfa = sp.DFA(["ok", "end", "bad"], ["o", "b"],
                 {"ok": {"o": "bad", "!o & b": "end", "!o & !b": "ok"},
                  "end": {"o": "bad", "!o & b": "end", "!o & !b": "ok"}, "bad": {"true": "bad"}}, "ok", ["end"])
    final = sp.Specification(dfa, {"o": sp.Region(AVOID_BOXES, closed=False), "b": B_BOX}, acceptance="final",
                             faces="interior").on(FREE_GRID)
    fin = sj.synthesize_product(smdp, final, horizon=12)
    freq, _ = monte_carlo_inside(final, fin, np.array([6, 15, 39, 55]), 300, key, 12)
    assert freq.max() > 0.3


def test_verify_product_and_batching(abstractions):
    imdp = abstractions["imdp"][1]
    spec = SEQ.on(FREE_GRID)
    sol = sj.synthesize_product(imdp, spec, horizon=9)
    again = sj.verify_product(imdp, spec, sol.policy, horizon=9)
    assert_close(again.initial_lower, sol.initial_lower)
    assert_close(again.initial_upper, sol.initial_upper)
    mapped = sj.synthesize_product(imdp, spec, horizon=9, batching="map")
    assert_close(mapped.initial_lower, sol.initial_lower)
    assert_close(mapped.initial_upper, sol.initial_upper)
    stationary = sj.verify_product(abstractions["smdp"][1], spec, np.asarray(sol.policy[0]))
    assert np.all(np.asarray(stationary.initial_lower) <= np.asarray(stationary.initial_upper))


def test_mixed_cells_are_conservative(abstractions, key):
    """A region off the grid's faces: its boundary cells get both letters; Monte Carlo on the
    true regions stays inside the bounds, which bracket those of refined letters."""
    smdp = abstractions["smdp"][1]
    spec = sp.sequence({"a": [([-1.0, 0.4], [-0.45, 1.0])], "b": [([0.45, -1.0], [1.0, -0.4])]}, avoid=AVOID_BOXES)
    with pytest.warns(UserWarning, match="cells lie partly inside"):
        on = spec.on(FREE_GRID)
    assert on.mixed_cells.size > 0
    sol = sj.synthesize_product(smdp, on)
    cells = np.array([int(c) for c in on.mixed_cells[:4]] + [27, 36])
    monte_carlo_inside(on, sol, cells, 200, key, 400)
    # a smaller a region (inside the mixed one, grid-aligned) can only lower p_low
    inner = sp.sequence({"a": [([-1.0, 0.5], [-0.5, 1.0])], "b": [([0.5, -1.0], [1.0, -0.5])]}, avoid=AVOID_BOXES)
    sol_in = sj.synthesize_product(smdp, inner.on(FREE_GRID))
    start = np.asarray(sol.initial_lower)
    assert np.all(start >= np.asarray(sol_in.initial_lower) - 1e-9)


def test_exact_faces_match_interior_faces_for_p_low(abstractions):
    smdp = abstractions["smdp"][1]
    exact = sp.sequence({"a": A_BOX, "b": B_BOX}, avoid=AVOID_BOXES, faces="exact").on(FREE_GRID)
    interior = SEQ.on(FREE_GRID)
    assert np.any(exact.labelling.count > 1) and not np.any(interior.labelling.count > 1)
    lo_e = sj.synthesize_product(smdp, exact)
    lo_i = sj.synthesize_product(smdp, interior)
    # closed regions to visit and open obstacles: the faces cost p_low nothing, p_up may grow
    assert_close(lo_e.initial_lower, lo_i.initial_lower, 1e-7)
    assert np.all(np.asarray(lo_e.initial_upper) >= np.asarray(lo_i.initial_upper) - 1e-7)


# ------------------------------------------------------------------ bad input

def test_errors(abstractions):
    ra = abstractions["smdp"][0]
    with pytest.raises(ValueError, match="no transitions for"):
        sj.synthesize_product(ra, SEQ.on(RA_GRID))  # reach/avoid cells of the grid are absorbing
    with pytest.raises(ValueError, match="states"):
        sj.synthesize_product(ra, SEQ.on(sj.StateGrid(LOW, HIGH, 5), warn=False))
    with pytest.raises(ValueError, match="spec.on"):
        sj.synthesize_product(ra, SEQ)
    with pytest.raises(TypeError):
        sj.synthesize_product(np.zeros(3), SEQ.on(FREE_GRID))
    with pytest.raises(ValueError, match="policy must have shape"):
        sj.verify_product(abstractions["smdp"][1], SEQ.on(FREE_GRID), np.zeros((2, 3), np.int32))


def test_product_is_an_abstraction(abstractions):
    prod = sj.synthesis.product(abstractions["smdp"][1], SEQ.on(FREE_GRID))
    assert isinstance(prod, ProductAbstraction) and prod.num_states == 4 * FREE_GRID.num_states
    flat = sj.synthesize(prod, horizon=3)  # the plain synthesize works on it
    again = sj.synthesize_product(abstractions["smdp"][1], SEQ.on(FREE_GRID), horizon=3)
    assert_close(flat.lower, np.asarray(again.lower).reshape(-1))
