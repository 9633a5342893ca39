"""Re-pricing the MI-MDP LPs' last optimal bases: their duals without a solver call.

Between two backups only the costs of an LP (``lp.ClusterLPs``) change; its constraints do not, so
the last optimal vertex ``x`` stays feasible and its basis often stays optimal (76% of the HiGHS
solves of the 4-room temperature row took no simplex iteration). Re-pricing that basis for the new
costs ``c`` is one small linear system per LP, solved for many LPs at once (dense NumPy systems up
to 32 unknowns, one sparse block-diagonal SuperLU factorization for larger ones):

* the equations are the basic variables of the last solve (reduced cost 0): for each,
  ``nu + sum_{active rows i containing j} y_i = c_j``;
* the unknowns are the equality's multiplier ``nu`` and the duals ``y_i`` of the active
  (nonbasic) cluster rows. A basis has as many of each; an LP with more than ``max_size``, or
  whose system is singular, is left to the solver. A large basis (sparse system) that the
  certificate refused is not re-priced again until the solver has solved its LP again
  (``BasisRecord.stable``; with ``lp.REPRICE_AFTER_PIVOTS`` off, until a solve that took no
  simplex iteration): most of the 2-D unicycle's refused ones keep moving, and their systems
  cost ~0.1 ms each.

The duals are accepted only with a certificate: the surrogate LP's dual function at them,

    D(nu, y) = nu * free_mass + sum_i (y_i lo_i if y_i > 0 else y_i hi_i)
               + sum_j cap_j min(0, c_j - nu - sum_{i containing j} y_i),

is a lower bound of the optimum for *any* ``(nu, y)`` (weak duality, variables in ``[0, cap_j]``),
and ``c . x`` an upper bound (``x`` is feasible). A re-priced dual of a row with one side (the
other implied, hence left out) whose sign points at the missing side is set to 0 first: the
re-priced value of a zero dual rounds to either sign (on the 3-D temperature row, 1 650 of the
11 200 solver calls of a warm synthesis took no simplex iteration and were only refused for
this). Where ``c . x - D(nu, y) <= gap`` the duals are optimal to within ``gap``: what a solver
returns, to its tolerance. Nothing here bears on soundness (``mimdp`` certifies any nonnegative
multipliers); a rejected LP is solved as before.
"""

from __future__ import annotations

import contextlib

import numpy as np

# Dense systems solved at once: at most this many matrix entries (float64: 32 MB).
_SYSTEM_ENTRIES = 1 << 22
# Systems of up to SIZES[-1] unknowns are padded to the next of these sizes and solved densely;
# larger ones (up to MAX_SIZE) as one sparse block-diagonal system per call. Dense systems of
# 64-128 unknowns cost about what HiGHS's warm solve of the 2-D unicycle's LPs does (row 3 of
# Table 1 took 65.8 s against 48.97 s with them); the sparse factorization of its 767 strategy
# LPs' systems (median 53 unknowns) takes ~0.1 ms per LP against HiGHS's ~0.5 ms.
SIZES = (8, 16, 32)
MAX_SIZE = 512


class BasisRecord:
    """The last optimal solve of every LP (one record per adversary direction).

    Attributes (flat over the LP table's variables / cluster rows / LPs):
        x: ``(V,)`` float64 the last optimal vertex (the solver's optimal point; kept for every LP
            that has one, ``vertex``, whether or not its basis is recorded).
        basic: ``(V,)`` bool the basic variables.
        active: ``(W,)`` bool the nonbasic cluster rows (at one of their sides).
        eq_active: ``(P,)`` bool the equality row is nonbasic.
        known: ``(P,)`` bool the LP has a record (its basis, for re-pricing).
        vertex: ``(P,)`` bool ``x`` holds the LP's last optimal point.
        stable: ``(P,)`` bool worth re-pricing: a basis small enough for the dense systems,
            or one the solver returned since its last refusal (see ``record``'s ``stable``).
            A larger basis that the certificate refused waits for the solver's next solve.
    """

    def __init__(self, num_vars: int, num_rows: int, num_lps: int):
        self.x = np.zeros(num_vars)
        self.basic = np.zeros(num_vars, bool)
        self.active = np.zeros(num_rows, bool)
        self.eq_active = np.zeros(num_lps, bool)
        self.known = np.zeros(num_lps, bool)
        self.stable = np.zeros(num_lps, bool)
        self.vertex = np.zeros(num_lps, bool)

    def record(self, table, p: int, solution, row_dual, basic_variables, lock=None, stable: bool = True,
               basis: bool = True) -> None:
        """Keep LP ``p``'s optimal vertex (``solution.col_value``) and, with ``basis``, its basis: the
        basic variables and the nonbasic rows (a basis too large to re-price is not kept).

        Read from the duals where they tell (the solver sets the reduced cost of a basic variable
        and the dual of a basic row to exactly 0); where a zero dual leaves it open (a degenerate
        solve: as many basic variables as nonbasic rows is not met), from
        ``basic_variables()``, the solver's basic variables (``Highs.getBasicVariables``: column
        ``j`` as ``j``, row ``i`` as ``-1 - i``). ``lock`` is held while the record is written.
        ``stable``: re-price this basis at the next call (``lp.REPRICE_AFTER_PIVOTS``: after
        every optimal solve; otherwise after one that took no simplex iteration from the LP's
        last basis)."""
        v0, v1 = table.var_start[p], table.var_start[p + 1]
        r0, r1 = table.row_start[p], table.row_start[p + 1]
        x = np.asarray(solution.col_value, np.float64)
        nonbasic_rows = np.asarray(row_dual) != 0.0
        # the basis has as many basic variables as nonbasic rows, at least the rows of nonzero
        # dual: too many of those, and nothing else is read
        if not basis or nonbasic_rows.sum() > MAX_SIZE:
            self.keep_point(table, p, x, lock)
            return
        basic = np.asarray(solution.col_dual, np.float64) == 0.0
        if basic.sum() != nonbasic_rows.sum():
            listed = np.asarray(basic_variables(), np.int64)
            basic = np.zeros(v1 - v0, bool)
            basic[listed[listed >= 0]] = True
            nonbasic_rows = np.ones(r1 - r0 + 1, bool)
            nonbasic_rows[-1 - listed[listed < 0]] = False
        if nonbasic_rows.sum() > MAX_SIZE:  # too large to re-price: not worth recording
            self.keep_point(table, p, x, lock)
            return
        with lock or contextlib.nullcontext():
            self.x[v0:v1] = x
            self.vertex[p] = True
            self.basic[v0:v1] = basic
            self.active[r0:r1] = nonbasic_rows[1:]
            self.eq_active[p] = nonbasic_rows[0]
            self.known[p] = True
            self.stable[p] = stable or nonbasic_rows.sum() <= SIZES[-1]

    def keep_point(self, table, p: int, x, lock=None) -> None:
        """Keep LP ``p``'s optimal point ``x`` without a basis (not re-priced)."""
        with lock or contextlib.nullcontext():
            self.x[table.var_start[p]:table.var_start[p + 1]] = x
            self.vertex[p] = True
            self.known[p] = False

    def forget(self, p: int) -> None:
        self.known[p] = False
        self.vertex[p] = False

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.x, self.basic, self.active, self.eq_active, self.known, self.stable,
                                          self.vertex)))


def ranges(start, stop):
    """``(index, owner)``: the ranges ``[start[q], stop[q])`` concatenated, and the ``q`` of each entry."""
    lengths = np.asarray(stop, np.int64) - start
    owner = np.repeat(np.arange(lengths.size), lengths)
    first = np.cumsum(lengths) - lengths
    return np.arange(int(lengths.sum()), dtype=np.int64) - first[owner] + np.asarray(start, np.int64)[owner], owner


def _rank(mask, owner, count):
    """Position of each ``True`` entry among its owner's ``True`` entries (entries grouped by owner)."""
    totals = np.bincount(owner[mask], minlength=count)
    return np.cumsum(mask) - 1 - (np.cumsum(totals) - totals)[owner]


def reprice(table, ids, var_cost, record: BasisRecord, *, gap: float, max_size: int = MAX_SIZE, lock=None):
    """Re-priced duals of the LPs ``ids`` at new costs, where certified optimal within ``gap``.

    Args:
        table: the ``lp.LPTable`` of the LPs.
        ids: ``(Q,)`` LP ids.
        var_cost: ``(V_q,)`` the new cost of every variable of ``ids[0]``, ``ids[1]``, ...
            (concatenated in that order).
        record: their last optimal solves (``BasisRecord``; LPs without one, or not ``stable``,
            are not accepted). A refused LP of more than ``SIZES[-1]`` unknowns (singular, or
            not certified) is marked not ``stable`` there.
        gap: accept where the certified duality gap is at most this.
        max_size: LPs with more basic variables go to the solver.
        lock: held while the record is read (solves of other calls may be writing it).
    Returns:
        ``(accepted (Q,) bool, rows (W_q,) int64, owner (W_q,), duals (W_q,))``: the cluster
        rows of the ``ids`` (table indices, concatenated like ``var_cost``), the position in
        ``ids`` of each, and their duals (0 where the LP is not accepted or the row is not active).
    """
    ids = np.asarray(ids, np.int64)
    q_count = ids.size
    gv, vq = ranges(table.var_start[ids], table.var_start[ids + 1])
    gr, rq = ranges(table.row_start[ids], table.row_start[ids + 1])
    var_offset = np.concatenate([[0], np.cumsum(np.bincount(vq, minlength=q_count))])[:-1]
    with lock or contextlib.nullcontext():
        basic, active, eq = record.basic[gv], record.active[gr], record.eq_active[ids]
        x, known = record.x[gv], record.known[ids] & record.stable[ids]
    size = np.bincount(vq[basic], minlength=q_count)
    unknowns = np.bincount(rq[active], minlength=q_count) + eq
    ok = known & (size == unknowns) & (size > 0) & (size <= max_size)

    # the equations (basic variables) and unknowns (nu first where the equality is active, then
    # the active rows) of each LP, numbered within it
    equation = np.where(basic, _rank(basic, vq, q_count), -1)
    column = np.where(active, eq[rq] + _rank(active, rq, q_count), -1)
    use = active & ok[rq]
    members, member_row = ranges(table.member_start[gr[use]], table.member_start[gr[use] + 1])
    row_q = rq[use][member_row]
    pos = var_offset[row_q] + table.var[members].astype(np.int64)  # gathered variable of each entry
    entry_col = column[use][member_row]

    nu = np.zeros(q_count)
    y_active = np.zeros(int(use.sum()))
    solved = np.zeros(q_count, bool)
    padded = np.array(SIZES + (np.iinfo(np.int32).max,))[np.searchsorted(SIZES, size)]
    for s in SIZES:
        group = np.flatnonzero(ok & (padded == s))
        for part in np.array_split(group, -(-group.size * s * s // _SYSTEM_ENTRIES)) if group.size else ():
            slot = np.full(q_count, -1)
            slot[part] = np.arange(part.size)
            y, good = _solve_systems(part, slot, s, size, eq, vq, basic, equation, var_cost, row_q, pos, entry_col)
            nu[part], solved[part] = np.where(eq[part], y[:, 0], 0.0), good
            take = slot[rq[use]] >= 0
            y_active[take] = y[slot[rq[use][take]], column[use][take]]
    tried = ok & (size > SIZES[-1])  # the sparse systems: refused ones are marked not stable below
    sparse = np.flatnonzero(tried)
    if sparse.size:
        slot = np.full(q_count, -1)
        slot[sparse] = np.arange(sparse.size)
        y, start, good = _solve_sparse(sparse, slot, size, eq, vq, basic, equation, var_cost, row_q, pos, entry_col)
        nu[sparse], solved[sparse] = np.where(eq[sparse], y[start[:-1]], 0.0), good
        take = slot[rq[use]] >= 0
        y_active[take] = y[start[slot[rq[use][take]]] + column[use][take]]
    ok &= solved

    # the certificate: c . x - D(nu, y)
    y_rows = np.zeros(gr.size)
    y_rows[use] = y_active
    y_rows[~ok[rq]] = 0.0
    lo, hi = table.lo[gr], table.hi[gr]
    # a dual whose sign points at a side left out (infinite) would make D = -inf: set to 0 (any
    # duals give a valid D; the certificate below decides whether these are still optimal)
    y_rows[((y_rows > 0) & np.isneginf(lo)) | ((y_rows < 0) & np.isposinf(hi))] = 0.0
    z = nu[vq] + np.bincount(pos, weights=y_rows[use][member_row], minlength=gv.size)
    reduced = var_cost - z
    caps = table.caps[gv]
    primal = np.bincount(vq, weights=var_cost * x, minlength=q_count)
    with np.errstate(invalid="ignore"):  # 0 * inf where a dual is 0 on a side left out: counted as 0
        side = np.where(y_rows > 0, y_rows * lo, np.where(y_rows < 0, y_rows * hi, 0.0))
    dual = (nu * table.free_mass[ids] + np.bincount(rq, weights=side, minlength=q_count)
            + np.bincount(vq, weights=caps * np.minimum(reduced, 0.0), minlength=q_count))
    accepted = ok & np.isfinite(dual) & (primal - dual <= gap)
    with lock or contextlib.nullcontext():
        record.stable[ids[tried & ~accepted]] = False  # the solver's next solve tells again
    y_rows[~accepted[rq]] = 0.0
    return accepted, gr, rq, y_rows


def _solve_systems(part, slot, s, size, eq, vq, basic, equation, var_cost, row_q, pos, entry_col):
    """``(y (len(part), s), solved)``: the systems of the LPs ``part`` (``slot``: their index in
    it, -1 elsewhere), each padded to ``s`` unknowns with the identity."""
    matrix = np.zeros((part.size, s, s))
    rhs = np.zeros((part.size, s))
    in_part = basic & (slot[vq] >= 0)
    g, e = slot[vq[in_part]], equation[in_part]
    rhs[g, e] = var_cost[in_part]
    with_nu = eq[vq[in_part]]
    matrix[g[with_nu], e[with_nu], 0] = 1.0
    entries = (slot[row_q] >= 0) & basic[pos]
    matrix[slot[row_q[entries]], equation[pos[entries]], entry_col[entries]] = 1.0
    diagonal = np.arange(s)
    matrix[:, diagonal, diagonal] += diagonal >= size[part][:, None]  # identity on the padding
    # A 0/1 matrix has an integer determinant: |det| >= 1 exactly when it is nonsingular. A
    # degenerate last solve can make the system singular; those LPs go to the solver.
    solved = np.abs(np.linalg.det(matrix)) > 0.5
    matrix[~solved] = np.eye(s)
    y = np.linalg.solve(matrix, rhs[..., None])[..., 0]
    return y, solved & np.isfinite(y).all(axis=1)


def _solve_sparse(part, slot, size, eq, vq, basic, equation, var_cost, row_q, pos, entry_col):
    """``(y, start, solved)``: the systems of the LPs ``part`` as one sparse block-diagonal system,
    LP ``part[i]``'s unknowns at ``y[start[i]:start[i + 1]]``. A singular system (SuperLU stops at
    an exactly zero pivot) is found by halving the set until it is alone; it is not solved."""
    from scipy.sparse import csc_matrix
    from scipy.sparse.linalg import splu

    start = np.concatenate([[0], np.cumsum(size[part])])
    var_base = start[slot[vq]]  # the first unknown of each variable's LP (where it is in part)
    in_part = basic & (slot[vq] >= 0)
    eq_rows = in_part & eq[vq]
    entries = (slot[row_q] >= 0) & basic[pos]
    entry_base = start[slot[row_q[entries]]]
    rows = np.concatenate([var_base[eq_rows] + equation[eq_rows], entry_base + equation[pos[entries]]])
    cols = np.concatenate([var_base[eq_rows], entry_base + entry_col[entries]])
    owner = np.repeat(np.arange(part.size), size[part])
    rhs = np.zeros(start[-1])
    rhs[var_base[in_part] + equation[in_part]] = var_cost[in_part]
    y = np.zeros(start[-1])
    solved = np.zeros(part.size, bool)
    entry_owner = owner[rows]

    def solve(lo, hi):  # the LPs part[lo:hi], unknowns start[lo]..start[hi]
        keep = (entry_owner >= lo) & (entry_owner < hi)
        n = int(start[hi] - start[lo])
        matrix = csc_matrix((np.ones(int(keep.sum())), (rows[keep] - start[lo], cols[keep] - start[lo])), shape=(n, n))
        try:
            # block-diagonal: the natural column order keeps the fill inside the blocks (the
            # default COLAMD took 1.25x as long on row 3's 767 strategy LPs)
            y[start[lo]:start[hi]] = splu(matrix, permc_spec="NATURAL").solve(rhs[start[lo]:start[hi]])
            solved[lo:hi] = True
        except RuntimeError:  # exactly singular
            if hi - lo > 1:
                mid = (lo + hi) // 2
                solve(lo, mid)
                solve(mid, hi)

    solve(0, part.size)
    finite = np.bincount(owner, weights=~np.isfinite(y), minlength=part.size) == 0
    return np.where(np.isfinite(y), y, 0.0), start, solved & finite
