"""Half-open cells: which cells a reachable box meets, checked against exact rational computations."""

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.abstraction import GridClusters, build, compute_grid_clusters, index_boxes
from smdpjax.partition import NONTERMINAL


def snap(grid, lo, hi, hi_open=None):
    lo, hi = jnp.atleast_2d(jnp.asarray(lo, jnp.float64)), jnp.atleast_2d(jnp.asarray(hi, jnp.float64))
    flags = None if hi_open is None else jnp.atleast_2d(jnp.asarray(hi_open, bool))
    b = index_boxes(grid, lo, hi, flags)
    return [np.asarray(v)[0] for v in (b.start, b.length, b.sink)]


def test_faces_of_a_flat_dimension():
    g = sj.StateGrid([0.0], [1.0], 10)
    assert g.edges[0][3] == 0.3  # the nearest float to 3/10, as a user types it
    def cells(lo, hi, hi_open=False):
        start, length, sink = snap(g, [lo], [hi], [hi_open])
        return int(start[0]), int(length[0]), bool(sink)
    assert cells(0.3, 0.35) == (3, 1, False)  # a lower end on a face does not reach the cell below
    assert cells(0.25, 0.3, hi_open=False) == (2, 2, False)  # a closed upper end on a face does
    assert cells(0.25, 0.3, hi_open=True) == (2, 1, False)  # an open one does not
    assert cells(0.3, 0.3, hi_open=True) == (3, 1, False)  # a null box keeps its cell (safe side)
    assert cells(0.0, 0.05) == (0, 1, False)  # the grid box is closed: low is inside
    assert cells(-1e-17, 0.05) == (0, 1, True)
    assert cells(0.95, 1.0) == (9, 1, False)  # ... and so is high (the last cell is closed)
    assert cells(0.95, float(np.nextafter(1.0, 2.0))) == (9, 1, True)
    assert cells(1.0, 1.5) == (9, 1, True)
    assert cells(1.5, 2.0)[1:] == (0, True)  # misses the grid: the sink alone


def reference_cells(edges, periodic, lo, hi, hi_open):
    """The cells (0..N-1) whose half-open interval [e_k, e_{k+1}) + m P (last cell closed on a flat
    axis) meets {y : lo <= y <= hi} (y < hi when hi_open), and whether the box leaves the grid
    box; exact rationals."""
    e = [Fraction(float(v)) for v in edges]
    n, lo, hi = len(e) - 1, Fraction(lo), Fraction(hi)
    period = e[-1] - e[0]
    shifts = range(-2, 3) if periodic else [0]
    met = set()
    for m in shifts:
        for k in range(n):
            a, b = e[k] + m * period, e[k + 1] + m * period
            closed_top = not periodic and k == n - 1
            upper_ok = (a < hi) or (a == hi and not hi_open)
            lower_ok = (lo < b) or (closed_top and lo <= b)
            if upper_ok and lower_ok:
                met.add(k)
    leaves = (not periodic) and (lo < e[0] or hi > e[-1])
    return met, leaves


def cells_of(start, length, n, periodic):
    ks = set()
    for i in range(length):
        k = start + i
        ks.add(k % n if periodic else k)
    return ks


@pytest.mark.parametrize("periodic", [False, True])
def test_index_boxes_equal_exact_half_open_snapping(periodic):
    """Ends on faces, one float off a face, and inside cells, near and across the seam; both
    flags. The index boxes equal the exact rational answer, except that a periodic box farther
    than one period out may only add cells."""
    high = 2 * np.pi if periodic else 1.0
    g = sj.StateGrid([0.0], [high], 8, periodic=[periodic])
    e = g.edges[0]
    rng = np.random.default_rng(0)
    candidates = []
    for v in np.concatenate([e, e - high, e + high]):
        candidates += [v, np.nextafter(v, -np.inf), np.nextafter(v, np.inf), v + 0.1]
    candidates = np.array(candidates)
    lo = rng.choice(candidates, 3000)
    hi = lo + rng.choice(candidates - candidates.min(), 3000) * rng.uniform(0, 0.6, 3000)
    hi = np.where(rng.uniform(size=3000) < 0.5, rng.choice(candidates, 3000), hi)
    hi = np.maximum(hi, lo)
    flags = rng.uniform(size=3000) < 0.5
    b = index_boxes(g, jnp.asarray(lo)[:, None], jnp.asarray(hi)[:, None], jnp.asarray(flags)[:, None])
    start, length, sink = (np.asarray(v) for v in (b.start[:, 0], b.length[:, 0], b.sink))
    exact_count = 0
    for i in range(3000):
        want, leaves = reference_cells(e, periodic, lo[i], hi[i], flags[i])
        got = cells_of(int(start[i]), int(length[i]), 8, periodic) if length[i] > 0 else set()
        assert want <= got, (lo[i], hi[i], flags[i], want, got)  # sound: never a cell too few
        if not periodic:
            assert bool(sink[i]) == leaves or (not want and sink[i])
        subnormal = 0 < abs(lo[i]) < 2.3e-308 or 0 < abs(hi[i]) < 2.3e-308  # taken outward to 0 / tiny
        if not subnormal and (not periodic or (lo[i] >= -high and hi[i] <= 2 * high)):
            assert got == want or (lo[i] == hi[i] and flags[i]), (lo[i], hi[i], flags[i], want, got)
            exact_count += 1
    assert exact_count > 1500


def test_locate_is_half_open_and_agrees_with_index_boxes():
    g = sj.StateGrid([0.0, 0.0], [1.0, 2 * np.pi], [10, 8], periodic=[False, True])
    e0, e1 = g.edges
    pts = np.array([[e0[3], e1[2]], [np.nextafter(e0[3], 0), e1[2]], [1.0, e1[7]], [0.0, 2 * np.pi]])
    idx = np.asarray(g.locate(pts))
    np.testing.assert_array_equal(idx // 8, [3, 2, 9, 0])
    np.testing.assert_array_equal(idx % 8, [2, 2, 7, 0])  # 2 pi is heading 0 again
    b = index_boxes(g, jnp.asarray(pts), jnp.asarray(pts))
    np.testing.assert_array_equal(np.asarray(b.start)[:, 0], idx // 8)
    np.testing.assert_array_equal(np.asarray(b.length), 1)


def test_labels_avoid_boxes_are_open_and_reach_boxes_closed():
    g = sj.StateGrid([0.0, 0.0], [1.0, 1.0], 10, reach=[([0.8, 0.8], [1.0, 1.0])], avoid=[([0.4, 0.4], [0.6, 0.6])])
    labels = g.labels.reshape(10, 10)
    assert (labels[4:6, 4:6] == 2).all() and (labels[3, :] != 2).all() and (labels[6, :] != 2).all()
    assert (labels[8:, 8:] == 1).all() and (labels[7, :] != 1).all()
    # the simulation judges the same sets: an avoid box's face is safe, a reach box's face reached
    pts = jnp.array([[0.4, 0.5], [0.5, 0.5], [0.8, 0.9], [0.79, 0.9]])
    np.testing.assert_array_equal(np.asarray(g.in_avoid(pts)), [False, True, False, False])
    np.testing.assert_array_equal(np.asarray(g.in_reach(pts)), [False, False, True, False])


# ------------------------------------------------------------------ whole abstractions

def shift(x, u, w):
    """Moves exactly u cells of 1/8 (dyadic: every operation is exact); the noise is multiplied by 0."""
    return x + 0.125 * u + 0.0 * w


@pytest.mark.parametrize("kind", ["imdp", "2imdp", "mimdp", "smdp"])
def test_exact_shifts_give_exact_guarantees_in_every_class(kind):
    """x' = x + 1/8 on a grid of 1/8 cells: every box is exactly the next cell, so from every cell
    the target [3/4, 1] is reached surely (hand computation: p_low = p_up = 1). Counting the
    touched faces would let the adversary step back or stall, giving p_low < 1."""
    system = sj.System(shift, actions=np.array([[1.0]]), noise=sj.Uniform([-1.0], [1.0]))
    grid = sj.StateGrid([0.0], [1.0], 8, reach=[([0.75], [1.0])])
    noise = sj.NoiseGrid.box([-1.0], [1.0], 2)
    options = {"lp_backend": "highs"} if kind == "mimdp" else {}
    sol = sj.synthesize(sj.abstract(system, grid, noise, kind, **options), tol=1e-9)
    nt = grid.nonterminal
    np.testing.assert_allclose(np.asarray(sol.lower)[nt], 1.0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(sol.upper)[nt], 1.0, atol=1e-9)


def test_lemma1_lower_bounds_count_boxes_that_end_on_a_face():
    system = sj.System(shift, actions=np.array([[1.0], [-1.0]]), noise=sj.Uniform([-1.0], [1.0]))
    grid = sj.StateGrid([0.0], [1.0], 8, reach=[([0.75], [1.0])])
    imdp = sj.abstract(system, grid, sj.NoiseGrid.box([-1.0], [1.0], 2), "imdp")
    succ, lower = np.asarray(imdp.successors), np.asarray(imdp.lower)
    for r, cell in enumerate(np.asarray(imdp.rows)):
        right = lower[r, 0][succ[r, 0] == cell + 1]
        assert right.size == 1 and right[0] == 1.0  # all mass in the next cell, exactly
        left = lower[r, 1][succ[r, 1] == (cell - 1 if cell > 0 else grid.sink)]
        assert left.size == 1 and left[0] == 1.0


def saturate(x, u, w):
    """Pushed right by the noise, but held at the wall 0.5: an atom exactly on the face e_5."""
    return jnp.minimum(x + u * w, 0.5)


def test_an_atom_on_an_interior_face_is_counted():
    """From cell 4 = [0.4, 0.5) the next state is min(x + w, 0.5) with w ~ U(0, 0.1): it equals 0.5
    (cell 5, the target) with probability (x - 0.4) / 0.1 (hand computation), up to 1 as x -> 0.5,
    so the one-step p_up of cell 4 is 1 and its cluster must contain cell 5."""
    system = sj.System(saturate, actions=np.array([[1.0]]), noise=sj.Uniform([0.0], [0.1]))
    grid = sj.StateGrid([0.0], [1.0], 10, reach=[([0.5], [1.0])])
    noise = sj.NoiseGrid.box([0.0], [0.1], 4)
    clusters = compute_grid_clusters(system, grid, noise)
    row = int(np.flatnonzero(clusters.rows == 4)[0])
    start, length = np.asarray(clusters.boxes.start)[row, 0], np.asarray(clusters.boxes.length)[row, 0]
    # noise cell c = [c/40, (c+1)/40): x + w in [0.4 + c/40, 0.5 + (c+1)/40) meets 0.5 for every c
    np.testing.assert_array_equal(start[:, 0] + length[:, 0] - 1, [5, 5, 5, 5])
    sol = sj.synthesize(build("smdp", grid, clusters), horizon=1)
    assert float(sol.upper[4]) == 1.0 and float(sol.lower[4]) == 0.0
    # Monte Carlo from just below the wall: the atom is hit with probability ~ (x - 0.4) / 0.1
    x0 = jnp.full((4000, 1), 0.49)
    mc = sj.simulate(system, sj.Controller(grid, np.asarray(sol.policy)), x0, jax.random.PRNGKey(0), max_steps=1)
    assert 0.85 < float(mc.probability) <= float(sol.upper[4])
    # Without the wall the upper end 0.5 of x itself is open: x' = x never reaches cell 5.
    still = sj.System(lambda x, u, w: x + 0.0 * w, actions=np.array([[0.0]]), noise=sj.Uniform([0.0], [0.1]))
    c2 = compute_grid_clusters(still, grid, noise)
    row = int(np.flatnonzero(c2.rows == 4)[0])
    np.testing.assert_array_equal(np.asarray(c2.boxes.length)[row, 0, :, 0], 1)


def drift2(x, u, w):
    return x + 0.125 * (u + w)


def exact_boxes(grid, rows, actions, w_lo, w_hi):
    """Index boxes of x + 1/8 (u + w) over half-open cells and noise boxes, in exact rationals:
    first = the cell of the exact lower end, last = the cell below the exact upper end (an open
    end: the state's upper face is not in its cell and the noise has a density)."""
    e = [[Fraction(float(v)) for v in edges] for edges in grid.edges]
    x_lo, x_hi = (np.asarray(b) for b in grid.cell_bounds(rows))
    R, A, C, n = len(rows), len(actions), len(w_lo), grid.n
    start = np.zeros((R, A, C, n), np.int32)
    length = np.zeros((R, A, C, n), np.int32)
    sink = np.zeros((R, A, C), bool)
    touches = 0
    for r in range(R):
        for a in range(A):
            for c in range(C):
                empty = False
                for d in range(n):
                    lo = Fraction(float(x_lo[r, d])) + Fraction(0.125) * (Fraction(float(actions[a, d])) + Fraction(float(w_lo[c, d])))
                    hi = Fraction(float(x_hi[r, d])) + Fraction(0.125) * (Fraction(float(actions[a, d])) + Fraction(float(w_hi[c, d])))
                    ed = e[d]
                    touches += (lo in ed) + (hi in ed)
                    first = max([k for k in range(len(ed) - 1) if ed[k] <= lo] or [0])
                    last = max([k for k in range(len(ed) - 1) if ed[k] < hi] or [-1])
                    sink[r, a, c] |= lo < ed[0] or hi > ed[-1]
                    if hi <= ed[0] or lo > ed[-1] or last < first:
                        empty = True
                    start[r, a, c, d], length[r, a, c, d] = first, max(last - first + 1, 0)
                if empty:
                    start[r, a, c], length[r, a, c], sink[r, a, c] = 0, 0, True
    return start, length, sink, touches


def test_affine_smdp_equals_exact_floor_ceil_snapping():
    """An affine system with exactly representable data (axis actions, noise cells with a face at
    0, a 1/8 step on a grid whose faces are not all multiples of it): the SMDP's p_low equals that
    of the SMDP built from exact rational index boxes to 1e-9, and is never above it."""
    actions = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    system = sj.System(drift2, actions=actions, noise=sj.Gaussian([0.0, 0.0], [0.25, 0.25]))
    grid = sj.StateGrid([0.0, 0.0], [1.0, 1.0], 12, reach=[([0.75, 0.75], [1.0, 1.0])],
                        avoid=[([0.25, 0.5], [0.5, 0.75])])
    noise = sj.NoiseGrid.ball([0.0, 0.0], 1.0, 4)  # faces at -1, -0.5, 0, 0.5, 1; 4 sigma
    clusters = compute_grid_clusters(system, grid, noise, method="natural")
    w_lo, w_hi = (np.asarray(b) for b in noise.boxes())
    start, length, sink, touches = exact_boxes(grid, clusters.rows, actions, w_lo, w_hi)
    assert touches > 1000  # boxes ending exactly on faces: what closed cells would count as crossings
    np.testing.assert_array_equal(np.asarray(clusters.boxes.length), length)
    np.testing.assert_array_equal(np.asarray(clusters.boxes.start)[length > 0], start[length > 0])
    np.testing.assert_array_equal(np.asarray(clusters.boxes.sink), sink)
    exact = GridClusters(rows=clusters.rows, boxes=type(clusters.boxes)(start=jnp.asarray(start), length=jnp.asarray(length),
                                                                       sink=jnp.asarray(sink)),
                         prob=clusters.prob, prob_rest=clusters.prob_rest)
    ours = sj.synthesize(build("smdp", grid, clusters), tol=1e-10, upper=False)
    ref = sj.synthesize(build("smdp", grid, exact), tol=1e-10, upper=False)
    nt = grid.labels == NONTERMINAL
    lo, lo_ref = np.asarray(ours.lower)[:-1][nt], np.asarray(ref.lower)[:-1][nt]
    assert np.all(lo <= lo_ref + 1e-12)
    np.testing.assert_allclose(lo, lo_ref, atol=1e-9)
    assert lo.mean() > 0.05 and lo.max() > 0.3  # a guarantee worth comparing


def test_snapping_end_gives_the_cells_of_an_open_upper_end():
    """The compact hand-over of the enclosure (one upper end instead of an end and a flag) snaps
    to exactly the cells the end and its flag give, on faces, next to them, at 0, at the grid
    box's top (where the float above ``high`` must still reach the sink) and beyond."""
    from smdpjax.abstraction.clusters import snapping_end

    g = sj.StateGrid([-1.0, 0.0], [1.0, 3.0], [8, 30])
    rng = np.random.default_rng(1)
    ends = []
    for d in range(2):
        e = np.concatenate([g.edges[d], [0.0, -0.0, 2.3e-308, -2.3e-308, 1e-300, np.inf, -np.inf, 5.0, -5.0]])
        near = np.concatenate([e, np.nextafter(e, np.inf), np.nextafter(e, -np.inf), e + 1e-3])
        ends.append(near[~np.isnan(near)])
    size = 4000
    lo = np.stack([rng.choice(ends[d], size) for d in range(2)], axis=-1)
    hi = np.stack([rng.choice(ends[d], size) for d in range(2)], axis=-1)
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    flags = rng.uniform(size=(size, 2)) < 0.5
    want = index_boxes(g, jnp.asarray(lo), jnp.asarray(hi), jnp.asarray(flags))
    got = index_boxes(g, jnp.asarray(lo), snapping_end(jnp.asarray(hi), jnp.asarray(flags), g.high))
    for field in ("start", "length", "sink"):
        np.testing.assert_array_equal(np.asarray(getattr(got, field)), np.asarray(getattr(want, field)), err_msg=field)
    assert np.any(hi == np.nextafter(g.high, np.inf)) and np.any(flags & (hi == g.edges[0][3]))


def test_dimension_codes_take_either_layout():
    from smdpjax.abstraction.clusters import decode_boxes, dimension_codes

    g = sj.StateGrid([0.0, 0.0], [1.0, 2 * np.pi], [10, 12], periodic=[False, True])
    rng = np.random.default_rng(2)
    lo = rng.uniform(-0.5, 7.0, (50, 2))
    hi = lo + rng.uniform(0, 2.0, (50, 2))
    flags = rng.uniform(size=(50, 2)) < 0.5
    last = dimension_codes(g, jnp.asarray(lo), jnp.asarray(hi), jnp.asarray(flags))
    first = dimension_codes(g, list(jnp.asarray(lo.T)), list(jnp.asarray(hi.T)), list(jnp.asarray(flags.T)),
                            normal_ends=True)
    np.testing.assert_array_equal(np.asarray(last), np.asarray(first))
    boxes = decode_boxes(first)
    assert boxes.start.shape == (50, 2) and boxes.sink.shape == (50,)


def test_heading_face_below_pi_moves_the_vehicle_up():
    """sin is positive on a heading cell that starts at fl(pi) (1.2e-16 below pi), so a moving
    vehicle at the top of its y cell crosses the face above: the exact answer, which float
    arithmetic rounded to nearest misses (the reason row 20 stays at 0.389, docs/concepts/semantics.md)."""
    mpmath = pytest.importorskip("mpmath")
    from smdpjax.case_studies.unicycle_3d import dynamics
    from smdpjax.reach import reachable_boxes

    g = sj.StateGrid([0, 0, 0], [1, 1, 2 * np.pi], 30, periodic=[False, False, True])
    cell = int(np.ravel_multi_index((15, 0, 15), (30, 30, 30)))
    x_lo, x_hi = g.cell_bounds(np.array([cell]))
    assert x_lo[0, 2] == np.pi  # fl(pi), below pi
    w_lo, w_hi = np.array([[0.45, 0.0]]), np.array([[0.5, 0.5]])  # speed in [0, 0.05]
    lo, hi, hi_open = reachable_boxes(dynamics, x_lo, x_hi, np.array([[0.5, 0.0]]), w_lo, w_hi, method="natural",
                                      x_high_open=~np.asarray(g.upper_attained(np.array([cell]))), noise_open=True)
    boxes = index_boxes(g, lo.reshape(1, 3), hi.reshape(1, 3), hi_open.reshape(1, 3))
    assert int(boxes.length[0, 1]) == 2  # rows 0 and 1 in y
    mpmath.mp.prec = 200
    face = mpmath.mpf(float(g.edges[1][1]))
    sup = mpmath.mpf(float(x_hi[0, 1])) + mpmath.mpf(0.1) * (mpmath.mpf(0.5) - mpmath.mpf(0.45)) * mpmath.sin(mpmath.mpf(float(x_lo[0, 2])))
    assert sup > face  # values just below the supremum lie above the face: the row is reached
    assert float(x_hi[0, 1]) + 0.1 * (0.5 - 0.45) * np.sin(x_lo[0, 2]) == g.edges[1][1]  # rounded to nearest: on the face
