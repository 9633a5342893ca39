"""Re-pricing the MI-MDP LPs' last optimal bases: their duals without a solver call.

Between two backups only the costs of an LP (``lp.ClusterLPs``) change; its constraints do not, so
the last optimal vertex ``x`` stays feasible and its basis often stays optimal (76% of the HiGHS
solves of the 4-room temperature row took no simplex iteration). Re-pricing that basis for the new
costs ``c`` is one small linear system per LP, solved here for many LPs at once in NumPy:

* the equations are the basic variables of the last solve (reduced cost 0): for each,
  ``nu + sum_{active rows i containing j} y_i = c_j``;
* the unknowns are the equality's multiplier ``nu`` and the duals ``y_i`` of the active
  (nonbasic) cluster rows. A basis has as many of each; an LP with more than ``max_size``, or
  whose system is singular, is left to the solver.

The duals are accepted only with a certificate: the surrogate LP's dual function at them,

    D(nu, y) = nu * free_mass + sum_i (y_i lo_i if y_i > 0 else y_i hi_i)
               + sum_j cap_j min(0, c_j - nu - sum_{i containing j} y_i),

is a lower bound of the optimum for *any* ``(nu, y)`` (weak duality, variables in ``[0, cap_j]``),
and ``c . x`` an upper bound (``x`` is feasible). A re-priced dual of a row with one side (the
other implied, hence left out) whose sign points at the missing side is set to 0 first: the
re-priced value of a zero dual rounds to either sign (on the 3-D temperature row, 1 650 of the 11 200
solver calls of a warm synthesis took no simplex iteration and were only refused for this). Where ``c . x - D(nu, y) <= gap`` the duals are
optimal to within ``gap``: what a solver returns, to its tolerance. Nothing here bears on
soundness (``mimdp`` certifies any nonnegative multipliers); a rejected LP is solved as before.
"""

from __future__ import annotations

import contextlib

import numpy as np

# Dense systems solved at once: at most this many matrix entries (float64: 32 MB).
_SYSTEM_ENTRIES = 1 << 22
# Systems are padded to the next of these sizes; an LP of more unknowns goes to the solver: a
# dense system of 64-128 unknowns costs about what HiGHS's warm solve of the 2-D unicycle's LPs
# does (~0.2 ms; measured with sizes up to 128: row 3 of Table 1 took 0.74x the time).
SIZES = (8, 16, 32)
# ``HighsBasisStatus.kBasic``
_BASIC = 1


class BasisRecord:
    """The last optimal solve of every LP (one record per adversary direction).

    Attributes (flat over the LP table's variables / cluster rows / LPs):
        x: ``(V,)`` float64 the last optimal vertex.
        basic: ``(V,)`` bool the basic variables.
        active: ``(W,)`` bool the nonbasic cluster rows (at one of their sides).
        eq_active: ``(P,)`` bool the equality row is nonbasic.
        known: ``(P,)`` bool the LP has a record.
    """

    def __init__(self, num_vars: int, num_rows: int, num_lps: int):
        self.x = np.zeros(num_vars)
        self.basic = np.zeros(num_vars, bool)
        self.active = np.zeros(num_rows, bool)
        self.eq_active = np.zeros(num_lps, bool)
        self.known = np.zeros(num_lps, bool)

    def record(self, table, p: int, solution, row_dual, basis, lock=None) -> None:
        """Keep LP ``p``'s optimal vertex (``solution.col_value``) and its basis: the basic
        variables and the nonbasic rows. ``solution``'s columns are read only for a basis small
        enough to re-price (highspy copies them out at every read).

        Read from the duals where they tell (the solver sets the reduced cost of a basic variable
        and the dual of a basic row to exactly 0); where a zero dual leaves it open (a degenerate
        solve: as many basic variables as nonbasic rows is not met), from ``basis()``, the
        solver's statuses (slower to read: ~0.3 ms per 1 300 variables). ``lock`` is held while
        the record is written."""
        v0, v1 = table.var_start[p], table.var_start[p + 1]
        r0, r1 = table.row_start[p], table.row_start[p + 1]
        nonbasic_rows = np.asarray(row_dual) != 0.0
        # the basis has as many basic variables as nonbasic rows, at least the rows of nonzero
        # dual: too many of those, and nothing else is read (most solves of the 2-D unicycle)
        if nonbasic_rows.sum() > SIZES[-1]:
            with lock or contextlib.nullcontext():
                self.known[p] = False
            return
        x = np.asarray(solution.col_value, np.float64)
        basic = np.asarray(solution.col_dual, np.float64) == 0.0
        if basic.sum() != nonbasic_rows.sum():
            status = basis()
            basic = np.fromiter(map(int, status.col_status), np.int8, v1 - v0) == _BASIC
            nonbasic_rows = np.fromiter(map(int, status.row_status), np.int8, r1 - r0 + 1) != _BASIC
        if nonbasic_rows.sum() > SIZES[-1]:  # too large to re-price: not worth recording
            with lock or contextlib.nullcontext():
                self.known[p] = False
            return
        with lock or contextlib.nullcontext():
            self.x[v0:v1] = x
            self.basic[v0:v1] = basic
            self.active[r0:r1] = nonbasic_rows[1:]
            self.eq_active[p] = nonbasic_rows[0]
            self.known[p] = True

    def forget(self, p: int) -> None:
        self.known[p] = False

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.x, self.basic, self.active, self.eq_active, self.known)))


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


def reprice(table, ids, var_cost, record: BasisRecord, *, gap: float, max_size: int = SIZES[-1], lock=None):
    """Re-priced duals of the LPs ``ids`` at new costs, where certified optimal within ``gap``.

    Args:
        table: the ``lp.LPTable`` of the LPs.
        ids: ``(Q,)`` LP ids.
        var_cost: ``(V_q,)`` the new cost of every variable of ``ids[0]``, ``ids[1]``, ...
            (concatenated in that order).
        record: their last optimal solves (``BasisRecord``; LPs without one are not accepted).
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
        x, known = record.x[gv], record.known[ids]
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
