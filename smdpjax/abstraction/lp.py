"""Host-side linear programs of the MI-MDP inner problem (Clarabel, or HiGHS if installed).

For every row (s, a) the MI-MDP inner problem ``min_{gamma in Gamma^MI} <gamma, w>`` is an LP.
This module solves a *surrogate* of it on the CPU only to obtain Lagrange multipliers of the
cluster constraints; ``mimdp.py`` turns any nonnegative multipliers into a certified bound (weak
duality), so nothing here affects soundness, only how tight the bound is.

The surrogate LP of one row, in the shifted variables ``y = gamma - lower`` (listed successors):

    min  sum_k w(succ_k) y_k + sum_b c_b u_b + c_rest u_rest
    s.t. sum_k y_k + sum_b u_b + u_rest = 1 - sum_k lower_k
         0 <= y_k <= upper_k - lower_k,  0 <= u_b <= rest,  0 <= u_rest <= (n_unlisted - B) rest
         lo_q - sum_{k in q} lower_k  <=  sum_{k in q} y_k  <=  up_q - sum_{k in q} lower_k

(multipliers lambda+ for the left side, lambda- for the right side of each cluster q). The
unlisted states (interval ``[0, rest]`` each) enter as ``B`` bucket variables priced at the B
cheapest unlisted states and a remainder variable priced at the (B+1)-th cheapest: a relaxation,
exact whenever ``B rest >= 1`` or ``B = n_unlisted``. When the unlisted states' total capacity is
negligible they are priced by the remainder variable alone. Cluster sides that the interval
bounds already imply are left out (multiplier 0).

The constraint data are built once per LP (at construction); each call changes only the
objective. Backends:

* ``"clarabel"`` (default, a declared dependency): interior point. The problem of each LP is
  set up once and re-solved after ``DefaultSolver.update(q=...)``; several LPs can be stacked
  block-diagonally into one problem (``block_size``; no gain measured, see
  ``benchmarks/mimdp_lp.py``). Variable bounds become rows of the nonnegative cone.
* ``"highs"`` (needs ``highspy``): simplex with native variable bounds and ranged rows. Each LP
  keeps its last optimal basis (one per adversary direction; its model is passed again as arrays
  at every call, see ``_highs_model``), and every call warm starts from that basis, which is
  nearly optimal again when the values change little between iterations. One ``Highs`` instance per thread solves the LPs one after the other (a ``Highs``
  object per LP would hold ~0.5 MB each). Before calling HiGHS, each LP's last optimal basis is
  re-priced at the new costs (``lp_reprice``, all LPs of a call at once in NumPy): where the
  re-priced duals are certified optimal (duality gap at most ``reprice_gap``), no solver is called.
  HiGHS runs without presolve (``PRESOLVE``): on LPs this small it cost more than it saved.

Both release the GIL while solving; ``threads > 1`` solves LPs concurrently.
"""

from __future__ import annotations

import collections
import threading
import time

import numpy as np

from .lp_reprice import BasisRecord, ranges, reprice

# A cluster constraint side counts as implied by the interval bounds within this slack.
_REDUNDANT_SLACK = 1e-12
# Unlisted states whose total capacity is below this are priced by one aggregated variable.
_NEGLIGIBLE_MASS = 1e-6
# LPs whose cluster data are prepared together: at most this many, and at most
# _BLOCK_ENTRIES (LP, cluster, member) entries, which bounds the float64 temporaries (~130 MB each;
# 4096 LPs at once peaked at 12 GB on the 4-room temperature row, 256 clusters x 81 members).
_LPS_PER_BLOCK = 4096
_BLOCK_ENTRIES = 1 << 24
# Locks shared by the LPs (LP p uses lock p % stripes): few, so that they cost nothing to keep
_LP_LOCK_STRIPES = 64
# ``Highs.passModel`` codes: row-wise matrix (``MatrixFormat.kRowwise``), ``ObjSense.kMinimize``
_HIGHS_ROWWISE, _HIGHS_MINIMIZE = 2, 1
BACKENDS = ("clarabel", "highs")
# Re-priced duals are used where their certified duality gap is at most this (``lp_reprice``).
REPRICE_GAP = 1e-10
# A large basis (a sparse re-pricing system) is re-priced at the next call after any optimal
# solve, also one that pivoted: the basis is optimal at the costs just solved for, and the next
# call often asks at the same ones (policy iteration's first adversary step after a greedy
# backup). Off: only after a solve that took no simplex iteration (22% of row 3's HiGHS solves
# then took none, re-solving a basis that re-pricing would have served).
REPRICE_AFTER_PIVOTS = True
# HiGHS presolves an LP before solving it from no basis (and not when given a basis). These LPs
# are small (~190 columns, ~135 rows on the 2-D unicycle): replaying row 3's 10 730 HiGHS solves
# in order, one thread, took 10.1 s without presolve against 13.2 s with it (medians of 3), the
# optimal values within 4.8e-10. ``settings={"presolve": "on"}`` restores it.
PRESOLVE = False
# LPs re-priced per task: about this many chunks per thread, each within these bounds (the sparse
# systems of ~50 LPs at a time cost 1.3x per LP what ~200 do: 8 chunks per thread before).
_REPRICE_CHUNKS_PER_THREAD = 2
_REPRICE_CHUNK = (32, 4096)
# Solver statuses of an optimal (or, for Clarabel, an optimal up to its reduced tolerances) solve
_OPTIMAL = frozenset({"Solved", "AlmostSolved", "Optimal"})


def new_highs(settings: dict):
    """A silent single-threaded ``Highs`` instance with presolve as ``PRESOLVE`` says, then ``settings``."""
    h = _import("highs").Highs()
    h.setOptionValue("output_flag", False)
    h.setOptionValue("threads", 1)
    h.setOptionValue("presolve", "on" if PRESOLVE else "off")
    for name, value in settings.items():
        h.setOptionValue(name, value)
    return h


class ClusterLPs:
    """LP data of every (row, action) of an MI-MDP and the solvers that use it.

    Compared and hashed by identity (it sits in a static PyTree field).

    Args:
        succ, lower, upper: ``(P, K)`` listed successors (padding ``>= num_states``) and their
            bounds (``upper`` includes ``rest``), one LP per leading index.
        rest: upper bound of every unlisted state.
        slots: ``(P, J, L)`` cluster members as slots into ``succ`` (padding ``>= K``).
        cluster_lower, cluster_upper: ``(P, J)`` cluster bounds.
        num_states: N + 1.
        backend: ``"highs"`` (default) or ``"clarabel"``.
        block_size: LPs stacked per Clarabel problem (``"clarabel"`` only).
        max_buckets: cap on the bucket variables of the unlisted states.
        settings: solver options (Clarabel settings attributes, or HiGHS option names).
        threads: LPs solved concurrently.
        max_cached_solvers: Clarabel solvers kept between calls (~0.5 MB each for LPs of ~170
            variables); the other LPs are set up again at every call (about +25% time).
        names: optional ``(P, 2)`` (cell, action) of each LP, for the warning about LPs that the
            solver did not solve (see `failures`).
        reprice: (HiGHS) re-price each LP's last optimal basis before calling the solver
            (``lp_reprice``); ``stats["repriced"]`` counts the LPs served so.
        reprice_gap: largest certified duality gap of re-priced duals that are used.

    A HiGHS solve warm-started from an LP's last basis that ends without an optimum is run
    again from no basis (``stats["cold_retries"]`` counts them). An LP that still ends without an
    optimum (infeasible, numerical failure, iteration limit) keeps
    the multipliers the solver returned, clipped at 0: the bound they certify is still sound
    (weak duality holds for any nonnegative multipliers) but may be loose. Each call that meets
    such LPs warns once, naming the first of them (cell, action, solver status) and how many
    there were; ``failures`` keeps the last 100 as ``(lp, status)`` and ``stats["failed"]``
    counts them all.
    """

    def __init__(self, succ, lower, upper, rest, slots, cluster_lower, cluster_upper, num_states, *,
                 backend: str = "highs", block_size: int = 1, max_buckets: int = 16,
                 settings: dict | None = None, threads: int = 1, cache_size: int = 4,
                 max_cached_solvers: int = 2048, names=None, reprice: bool = True, reprice_gap: float = REPRICE_GAP):
        if backend not in BACKENDS:
            raise ValueError(f"unknown LP backend {backend!r}; expected one of {BACKENDS}")
        _import(backend)  # fail early if it is missing
        self.backend = backend
        self.num_states = int(num_states)
        self.rest = float(rest)
        self.succ = np.ascontiguousarray(succ, dtype=np.int64)
        self.num_lps, self.width = self.succ.shape
        self.num_clusters = int(slots.shape[1])
        self.block_size = int(block_size)
        self.threads = int(threads)
        # Clarabel: iterative refinement of the KKT solves costs ~40% of the time and changes the
        # multipliers by ~1e-9 here (measured), which the certificate does not need
        # HiGHS: at its default feasibility tolerances (1e-7) it stops at vertices that violate
        # cluster constraints by ~5e-8, whose duals certify ~5e-8 less than the optimum
        defaults = ({"iterative_refinement_enable": False} if backend == "clarabel" else
                    {"primal_feasibility_tolerance": 1e-9, "dual_feasibility_tolerance": 1e-9})
        self.settings = {**defaults, **(settings or {})}
        self._cache_size = int(cache_size)
        self._plans: collections.OrderedDict = collections.OrderedDict()
        self._solvers: dict = {}  # Clarabel solvers and HiGHS bases, by key
        self._cached_solvers = 0
        self.max_cached_solvers = int(max_cached_solvers)
        self._local = threading.local()
        self._lock = threading.Lock()
        # the last optimal solve of each LP, per direction, for re-pricing (HiGHS only)
        self.reprice = bool(reprice) and backend == "highs"
        self.reprice_gap = float(reprice_gap)
        self._records = {}
        self._record_locks = (threading.Lock(), threading.Lock())
        # XLA may run host callbacks concurrently (a step's lower and upper backups, a mesh's
        # shards), so two calls can reach the same LP at once: its HiGHS basis (read, then
        # replaced) and its Clarabel solver are used under a lock
        self._lp_locks = tuple(threading.Lock() for _ in range(_LP_LOCK_STRIPES))
        self._executor = None
        self._constants = None
        self.stats = collections.Counter()
        self.names = None if names is None else np.asarray(names)
        self.failures = collections.deque(maxlen=100)
        self._build(np.asarray(lower, np.float64), np.asarray(upper, np.float64), np.asarray(slots),
                    np.asarray(cluster_lower, np.float64), np.asarray(cluster_upper, np.float64), int(max_buckets))

    # -- construction -------------------------------------------------------------------------
    def _build(self, lower, upper, slots, clo, cup, max_buckets):
        """Per-LP data: variable capacities and cost sources, cluster rows with their bounds."""
        n_states, width, rest = self.num_states, self.width, self.rest
        listed = self.succ < n_states
        n_unlisted = n_states - listed.sum(1)
        cap = np.where(listed, upper - lower, 0.0)
        lower = np.where(listed, lower, 0.0)
        if rest > 0:
            buckets = np.minimum(n_unlisted, min(max_buckets, int(np.ceil(1.0 / rest - 1e-9))))
            buckets = np.where(n_unlisted * rest <= _NEGLIGIBLE_MASS, 0, buckets)
            has_rest = n_unlisted > buckets
        else:
            buckets = np.zeros(self.num_lps, np.int64)
            has_rest = np.zeros(self.num_lps, bool)
        self.buckets = buckets.astype(np.int64)
        self.has_rest = has_rest
        self.cost_width = width + int(buckets.max(initial=0)) + 1  # listed slots, then cheapest unlisted

        free_mass = 1.0 - lower.sum(-1)
        is_var = listed & (cap > 0)
        var_of_slot = np.where(is_var, np.cumsum(is_var, axis=1) - 1, -1)
        # Cluster sides, vectorized over (LP, cluster, member) a block of LPs at a time (all at once
        # is several (LPs x clusters x members) float64 temporaries: ~9 GB each at 224k LPs).
        per_block = max(1, min(_LPS_PER_BLOCK, _BLOCK_ENTRIES // max(1, slots.shape[1] * slots.shape[2])))
        blocks = [self._build_block(block, slots[block], clo[block], cup[block], lower[block], cap[block],
                                    free_mass[block], is_var[block], var_of_slot[block], buckets[block],
                                    has_rest[block], n_unlisted[block])
                  for block in (slice(first, min(first + per_block, self.num_lps))
                                for first in range(0, self.num_lps, per_block))]
        self._lps = LPTable.concatenate(blocks)
        self.num_vars = np.diff(self._lps.var_start)
        sides = np.isfinite(self._lps.lo).astype(np.int64) + np.isfinite(self._lps.hi)
        lp_of_row = np.repeat(np.arange(self.num_lps), np.diff(self._lps.row_start))
        self.num_cluster_rows = np.bincount(lp_of_row, weights=sides, minlength=self.num_lps).astype(np.int64)
        # constraint rows in the Clarabel form (equality, two bounds per variable, cluster sides)
        self.num_rows = 1 + 2 * self.num_vars + self.num_cluster_rows
        self.nnz = int(3 * self.num_vars.sum() + 2 * self._lps.var.size)

    def _build_block(self, block, slots, clo, cup, lower, cap, free_mass, is_var, var_of_slot, buckets, has_rest,
                     n_unlisted) -> "LPTable":
        """The LP data of the LPs in ``block`` (arrays already sliced to it), all LPs at once."""
        width, rest = self.width, self.rest
        valid = slots < width
        # one flat index for the three gathers (take_along_axis builds its index for each)
        at = np.minimum(slots, width - 1).astype(np.int64) + (width * np.arange(slots.shape[0]))[:, None, None]
        take = lambda a, fill: np.where(valid, np.take(a, at), fill)
        low_fixed = take(lower, 0.0).sum(-1)
        room = take(cap, 0.0).sum(-1)
        need = np.minimum(clo - low_fixed, room)
        allow = np.maximum(cup - low_fixed, 0.0)
        member_var = take(var_of_slot, -1)
        has_var = np.any(member_var >= 0, axis=-1)
        use_lo = (clo - low_fixed > _REDUNDANT_SLACK) & has_var
        use_hi = (allow < np.minimum(room, free_mass[:, None]) - _REDUNDANT_SLACK) & has_var
        # variables of each LP: its listed slots with room, then its buckets, then the remainder
        lp_of_var, var_slot = np.nonzero(is_var)
        lp_of_bucket = np.repeat(np.arange(buckets.size), buckets)
        bucket = np.arange(lp_of_bucket.size) - np.repeat(np.cumsum(buckets) - buckets, buckets)
        lp_of_rest = np.flatnonzero(has_rest)
        owner = np.concatenate([lp_of_var, lp_of_bucket, lp_of_rest])
        order = np.argsort(owner, kind="stable")  # LP-major, each LP's parts in the order above
        caps = np.concatenate([cap[lp_of_var, var_slot], np.full(bucket.size, rest),
                               (n_unlisted[lp_of_rest] - buckets[lp_of_rest]) * rest])[order]
        cost_src = np.concatenate([var_slot, width + bucket, width + buckets[lp_of_rest]])[order]
        var_start = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=buckets.size))])
        # cluster rows of each LP and their members (variable ids)
        lp_of_row, cluster = np.nonzero(use_lo | use_hi)
        members = member_var[lp_of_row, cluster]  # (rows, L)
        keep = members >= 0
        row_start = np.concatenate([[0], np.cumsum(np.bincount(lp_of_row, minlength=buckets.size))])
        member_start = np.concatenate([[0], np.cumsum(keep.sum(1))])
        return LPTable(caps=caps.astype(np.float64), cost_src=cost_src.astype(np.int32), var_start=var_start,
                       free_mass=np.asarray(free_mass, np.float64), cluster=cluster.astype(np.int32),
                       lo=np.where(use_lo, need, -np.inf)[lp_of_row, cluster],
                       hi=np.where(use_hi, allow, np.inf)[lp_of_row, cluster], row_start=row_start,
                       var=members[keep], member_start=member_start)

    def _conic(self, p):
        """LP ``p`` in Clarabel's form ``A y + s = b``, ``s`` in {0} x R_+^(m-1):
        (rows, cols, vals, b, multiplier rows, multiplier targets)."""
        lp = self._lps[p]
        n = lp["caps"].size
        sides = np.stack([np.isfinite(lp["lo"]), np.isfinite(lp["hi"])], axis=1)  # (k, 2)
        side_row = 1 + 2 * n + np.cumsum(sides.ravel()).reshape(sides.shape) - 1
        cluster_of = np.repeat(np.arange(sides.shape[0]), np.diff(lp["ptr"]))  # cluster of each member entry
        member_side = sides[cluster_of]  # (entries, 2)
        entry, side = np.nonzero(member_side)
        kept_i, kept_s = np.nonzero(sides)
        rows = np.concatenate([np.zeros(n, np.int64), 1 + np.arange(n), 1 + n + np.arange(n),
                               side_row[cluster_of[entry], side]])
        cols = np.concatenate([np.arange(n)] * 3 + [lp["var"][entry]])
        vals = np.concatenate([np.ones(n), -np.ones(n), np.ones(n), np.where(side == 0, -1.0, 1.0)])
        bound = np.where(kept_s == 0, -lp["lo"][kept_i], lp["hi"][kept_i])
        rhs = np.concatenate([[lp["free_mass"]], np.zeros(n), lp["caps"], bound])
        return (rows, cols, vals, rhs, side_row[kept_i, kept_s].astype(np.int64),
                (2 * lp["cluster"][kept_i] + kept_s).astype(np.int64))

    def _clarabel_settings(self):
        clarabel = _import("clarabel")
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.presolve_enable = False  # keep every row so that update(q=...) stays allowed
        settings.max_threads = 1  # parallelism comes from solving several LPs at once
        for name, value in self.settings.items():
            setattr(settings, name, value)
        return settings

    def _clarabel_block(self, part):
        """One Clarabel problem for the LPs ``part`` stacked block-diagonally (equalities first)."""
        import scipy.sparse as sp

        clarabel = _import("clarabel")
        pieces = [self._conic(p) for p in part]
        n_eq = len(pieces)
        sizes = [self._lps[p]["caps"].size for p in part]
        var_off = np.concatenate([[0], np.cumsum(sizes)])
        ineq_off = n_eq + np.concatenate([[0], np.cumsum([pc[3].size - 1 for pc in pieces])])
        place = lambda i, r: np.where(r == 0, i, ineq_off[i] + r - 1)
        rows = np.concatenate([place(i, pc[0]) for i, pc in enumerate(pieces)])
        cols = np.concatenate([var_off[i] + pc[1] for i, pc in enumerate(pieces)])
        vals = np.concatenate([pc[2] for pc in pieces])
        m, n = int(ineq_off[-1]), int(var_off[-1])
        b = np.empty(m)
        for i, pc in enumerate(pieces):
            b[place(i, np.arange(pc[3].size))] = pc[3]
        A = sp.csc_matrix((vals, (rows, cols)), shape=(m, n))
        cones = [clarabel.ZeroConeT(n_eq), clarabel.NonnegativeConeT(m - n_eq)]
        solver = clarabel.DefaultSolver(sp.csc_matrix((n, n)), np.zeros(n), A, b, cones, self._clarabel_settings())
        # where each variable's cost comes from (block position, column), and the multiplier rows
        cost_pos = np.concatenate([np.full(sz, i) for i, sz in enumerate(sizes)]).astype(np.int64)
        cost_col = np.concatenate([self._lps[p]["cost_src"] for p in part])
        z_rows = np.concatenate([place(i, pc[4]) for i, pc in enumerate(pieces)]).astype(np.int64)
        z_pos = np.concatenate([np.full(pc[5].size, i) for i, pc in enumerate(pieces)]).astype(np.int64)
        z_target = np.concatenate([pc[5] for pc in pieces])
        var_pos = np.concatenate([np.arange(self._lps.var_start[p], self._lps.var_start[p + 1]) for p in part])
        return dict(solver=solver, lock=threading.Lock(), count=len(part), cost_pos=cost_pos, cost_col=cost_col,
                    z_rows=z_rows, z_pos=z_pos, z_target=z_target, ids=np.asarray(part, np.int64), var_pos=var_pos)

    def _highs_model(self, p, cost):
        """LP ``p`` with costs ``cost`` as the arrays of ``Highs.passModel``: bounds on the
        variables, ranged rows (equality first), a row-wise 0/1 matrix. Assembled at every call
        from the flat table, the constant parts sliced from shared arrays: a cached ``HighsLp``
        per LP held ~200 KB each on the 4-room temperature row (20 736 LPs of up to 256 clusters
        x 81 members: 4 GB), and setting its fields converted the arrays element by element
        (1.7 ms per LP). This runs under the GIL beside the other thread's solves, so it is kept
        to a few slices (26-29 us per LP of the 2-D unicycle, against 40-45 us through ``table[p]``)."""
        t, p = self._lps, int(p)
        v0, v1 = t.var_start[p], t.var_start[p + 1]
        r0, r1 = t.row_start[p], t.row_start[p + 1]
        m0, m1 = t.member_start[r0], t.member_start[r1]
        n, k, nnz = int(v1 - v0), int(r1 - r0), int(v1 - v0 + m1 - m0)
        const = self._model_constants(max(n, nnz))
        index = np.empty(nnz, np.int32)
        index[:n] = const["arange"][:n]
        index[n:] = t.var[m0:m1]
        start = np.empty(k + 2, np.int32)
        start[0] = 0
        np.subtract(t.member_start[r0:r1 + 1], m0 - n, out=start[1:], casting="unsafe")
        lo, hi = np.empty(k + 1), np.empty(k + 1)
        lo[0] = hi[0] = t.free_mass[p]
        lo[1:], hi[1:] = t.lo[r0:r1], t.hi[r0:r1]
        return (n, 1 + k, nnz, _HIGHS_ROWWISE, _HIGHS_MINIMIZE, 0.0, np.ascontiguousarray(cost, np.float64),
                const["zeros"][:n], t.caps[v0:v1], lo, hi, start, index, const["ones"][:nnz],
                const["integrality"][:n])  # integrality: all continuous (an empty array is read past its end)

    def _model_constants(self, size: int) -> dict:
        """Read-only ``arange``, ``zeros``, ``ones`` and integrality codes of at least ``size`` entries."""
        const = self._constants
        if const is None or const["ones"].size < size:
            size = max(size, 2 * (0 if const is None else const["ones"].size))
            const = dict(arange=np.arange(size, dtype=np.int32), zeros=np.zeros(size), ones=np.ones(size),
                         integrality=np.zeros(size, np.int32))
            for array in const.values():
                array.flags.writeable = False
            self._constants = const  # replaced whole, so a reader always sees one consistent dict
        return const

    def _highs_solver(self):
        """The calling thread's ``Highs`` instance (one model at a time; bases are kept per LP)."""
        h = getattr(self._local, "highs", None)
        if h is None:
            h = self._local.highs = new_highs(self.settings)
        return h

    def _solve_highs(self, p, direction, cost, out):
        model = self._highs_model(p, cost)
        h = self._highs_solver()
        key = ("basis", direction, int(p))
        with self._lp_locks[int(p) % _LP_LOCK_STRIPES]:  # the basis of an LP is read and replaced
            status = h.passModel(*model)  # None from highspy versions that raise instead
            if status is not None and status == _import("highs").HighsStatus.kError:
                raise RuntimeError(f"HiGHS refused the LP of row {int(p)} ({status})")
            basis = self._solvers.get(key)
            if basis is not None:
                h.setBasis(basis)
            h.run()
            status = h.modelStatusToString(h.getModelStatus())
            if status not in _OPTIMAL and basis is not None:
                # a warm start can end without an optimum where a cold solve finds one (HiGHS
                # 1.16: status "Unknown" from a last basis on the 2-D unicycle at 45x45)
                h.passModel(*model)
                h.run()
                status = h.modelStatusToString(h.getModelStatus())
                with self._lock:
                    self.stats["cold_retries"] += 1
            self._solvers[key] = h.getBasis()
            solution = h.getSolution()
            row_dual = np.asarray(solution.row_dual)
            # the optimal vertex (``vertices``) and, when re-pricing, the basis
            record, lock = self._record(direction), self._record_locks[direction]
            if status in _OPTIMAL:
                # re-price it next time (``REPRICE_AFTER_PIVOTS``; otherwise only a basis from
                # which the solve took no iteration, or a first solve's)
                stable = REPRICE_AFTER_PIVOTS or basis is None or h.getInfo().simplex_iteration_count == 0
                record.record(self._lps, p, solution, row_dual, lambda: _basic_variables(h), lock,
                              stable=stable, basis=self.reprice)
            else:
                with lock:
                    record.forget(p)
        dual = row_dual[1:]
        table = self._lps
        cluster = table.cluster[table.row_start[int(p)]:table.row_start[int(p) + 1]]
        out[2 * cluster] = dual  # both signs; ``multipliers`` clips each call's out at 0 once
        out[2 * cluster + 1] = -dual
        return status

    def _record(self, direction) -> BasisRecord:
        record = self._records.get(direction)
        if record is None:
            with self._lock:
                record = self._records.setdefault(
                    direction, BasisRecord(self._lps.caps.size, self._lps.cluster.size, self.num_lps))
        return record

    def _repriced(self, ids, costs, direction, flat):
        """Serve the LPs of ``ids`` whose last optimal basis, re-priced at ``costs``, is certified
        optimal (``lp_reprice``): their multipliers go to ``flat``. Returns which were served."""
        record = self._records.get(direction)
        accepted = np.zeros(ids.size, bool)
        have = np.flatnonzero(record.known[ids] & record.stable[ids]) if record is not None else np.zeros(0, np.int64)
        if have.size == 0:  # e.g. every basis too large to record
            return accepted
        table = self._lps
        gv, vq = ranges(table.var_start[ids[have]], table.var_start[ids[have] + 1])
        var_cost = costs[have[vq], table.cost_src[gv]]
        served_lps, rows, owner, duals = reprice(table, ids[have], var_cost, record, gap=self.reprice_gap,
                                                 lock=self._record_locks[direction])
        served = served_lps[owner]
        at, cluster, dual = have[owner[served]], table.cluster[rows[served]].astype(np.int64), duals[served]
        flat[at, 2 * cluster] = np.maximum(dual, 0.0)
        flat[at, 2 * cluster + 1] = np.maximum(-dual, 0.0)
        accepted[have] = served_lps
        return accepted

    def _cached(self, key, make):
        value = self._solvers.get(key)
        if value is None:
            start = time.perf_counter()
            value = make()
            with self._lock:
                value = self._solvers.setdefault(key, value)
                self.stats["setup_seconds"] += time.perf_counter() - start
        return value

    def _clarabel_single(self, p):
        """A Clarabel solver of LP ``p``: kept for the first ``max_cached_solvers`` LPs, otherwise
        rebuilt from the cached matrices at every call (a solver holds ~0.5 MB at 30x30)."""
        key = ("clarabel", int(p))
        block = self._solvers.get(key)
        if block is not None:
            return block
        if self._cached_solvers < self.max_cached_solvers:
            with self._lock:
                self._cached_solvers += 1
            return self._cached(key, lambda: self._clarabel_block([p]))
        start = time.perf_counter()
        block = self._clarabel_block([p])
        with self._lock:
            self.stats["setup_seconds"] += time.perf_counter() - start
        return block

    def _plan(self, ids):
        """Stacked Clarabel problems for the LPs ``ids`` (cached, least recently used dropped)."""
        key = ids.tobytes()
        with self._lock:
            if key in self._plans:
                self._plans.move_to_end(key)
                return self._plans[key]
        start = time.perf_counter()
        starts = range(0, ids.size, self.block_size)
        blocks = [(lo, self._clarabel_block(ids[lo:lo + self.block_size])) for lo in starts]
        with self._lock:
            self.stats["setup_seconds"] += time.perf_counter() - start
            self._plans[key] = blocks
            while len(self._plans) > self._cache_size:
                self._plans.popitem(last=False)
        return blocks

    # -- per call -----------------------------------------------------------------------------
    def cost_table(self, w: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """``(Q, cost_width)``: costs of the listed slots, then of the cheapest unlisted states."""
        n_states, width = self.num_states, self.width
        succ = self.succ[ids]
        listed = succ < n_states
        table = np.zeros((ids.size, self.cost_width))
        table[:, :width] = np.where(listed, w[np.minimum(succ, n_states - 1)], 0.0)
        if self.rest > 0 and np.any(self.buckets[ids] + self.has_rest[ids] > 0):
            cheapest = self.cheapest_unlisted(w, ids)
            table[:, width:width + cheapest.shape[1]] = w[cheapest]
        return table

    def cheapest_unlisted(self, w: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """``(Q, max buckets + 1)`` the cheapest states at costs ``w`` that LP ``ids[q]`` does not
        list, in increasing order of cost (ties by state id): where its bucket variables and then
        its remainder variable are priced (``cost_table``)."""
        n_states, width = self.num_states, self.width
        succ = self.succ[ids]
        listed = succ < n_states
        need = int(self.buckets[ids].max(initial=0)) + 1
        order = np.argsort(w, kind="stable")
        rank = np.empty(n_states, np.int64)
        rank[order] = np.arange(n_states)
        pad = 4 * n_states + np.arange(width)  # keeps lr[i] - i nondecreasing over the padding
        lr = np.sort(np.where(listed, rank[np.minimum(succ, n_states - 1)], pad), axis=1)
        # the j-th cheapest unlisted state sits at global position j + #{i : lr[i] - i <= j};
        # one searchsorted over all rows, each row offset by `big`
        big = 8 * n_states
        keys = (lr - np.arange(width) + big * np.arange(ids.size)[:, None]).ravel()
        queries = np.arange(need) + big * np.arange(ids.size)[:, None]
        counts = np.searchsorted(keys, queries.ravel(), side="right").reshape(ids.size, need)
        counts -= width * np.arange(ids.size)[:, None]
        pos = np.minimum(np.arange(need) + counts, n_states - 1)
        return order[pos]

    def vertices(self, w, ids, direction: int = 0):
        """Optimal points of the surrogate LPs ``ids (Q,)`` at costs ``w (N+1,)``, as the mass each
        puts on states above the listed successors' lower bounds.

        Solves (or re-prices) the LPs as ``multipliers`` does, then reads each one's optimal point:
        a listed successor's variable is its mass above its lower bound; a bucket's mass goes to
        the cheapest unlisted state of its rank at ``w``, the remainder's to the next one, where
        the LP prices them (``cheapest_unlisted``), so ``sum mass * w`` is the LP's optimal value
        less ``<lower, w>``. Returns ``(lp (E,), state (E,), mass (E,), solved (Q,) bool)``: the
        COO entries (``lp``: position in ``ids``; positive masses only) and which LPs ended with
        an optimum (an LP without one has no entries).
        """
        w = np.asarray(w, np.float64)
        ids = np.ascontiguousarray(np.asarray(ids, np.int64).ravel())
        self.multipliers(w, ids, direction)
        table, width = self._lps, self.width
        gv, vq = ranges(table.var_start[ids], table.var_start[ids + 1])
        record = self._record(direction)
        with self._record_locks[direction]:
            solved = record.vertex[ids].copy()
            mass = record.x[gv]
        keep = solved[vq] & (mass > 0.0)
        gv, vq, mass = gv[keep], vq[keep], mass[keep]
        src = table.cost_src[gv].astype(np.int64)
        listed = src < width
        state = np.empty(src.size, np.int64)
        state[listed] = self.succ[ids[vq[listed]], src[listed]]
        if not listed.all():
            cheapest = self.cheapest_unlisted(w, ids)
            state[~listed] = cheapest[vq[~listed], src[~listed] - width]
        return vq, state, mass, solved

    def multipliers(self, w, ids, direction: int = 0):
        """Nonnegative multipliers ``(*ids.shape, J, 2)`` (lambda+, lambda-) of the surrogate LPs
        ``ids`` for costs ``w (N+1,)``; 0 for constraint sides not in the LP and for negative ids
        (LPs not asked for, counted in ``stats["skipped"]``). ``direction`` (0:
        minimizing adversary, 1: maximizing) only selects which HiGHS warm start to use."""
        w = np.asarray(w, np.float64)
        shape = np.shape(ids)
        ids = np.ascontiguousarray(np.asarray(ids, np.int64).ravel())
        lam = np.zeros((ids.size, self.num_clusters, 2))
        if self.num_clusters == 0 or ids.size == 0:
            return lam.reshape(*shape, self.num_clusters, 2)
        skipped = ids < 0
        if skipped.any():  # no LP: zero multipliers, which certify the IMDP value
            with self._lock:
                self.stats["skipped"] += int(skipped.sum())
            lam[~skipped] = self.multipliers(w, ids[~skipped], direction)
            return lam.reshape(*shape, self.num_clusters, 2)
        costs = self.cost_table(w, ids)
        flat = lam.reshape(ids.size, -1)
        start = time.perf_counter()

        # each task returns [(position in ids of the (first) LP it solved, solver status), ...]
        if self.backend == "highs":
            cost_src, var_start = self._lps.cost_src, self._lps.var_start

            def solve(i):
                p = ids[i]
                return self._solve_highs(p, direction, costs[i, cost_src[var_start[p]:var_start[p + 1]]], flat[i])

            if self.reprice:  # a chunk of LPs per task: re-priced, the rest solved (chunks run concurrently)
                def run(part):
                    served = self._repriced(ids[part], costs[part], direction, flat[part])
                    with self._lock:
                        self.stats["repriced"] += int(served.sum())
                    return [(i, solve(i)) for i in range(part.start, part.stop) if not served[i - part.start]]
                chunk = int(np.clip(-(-ids.size // (_REPRICE_CHUNKS_PER_THREAD * self.threads)), *_REPRICE_CHUNK))
                tasks = [slice(lo, min(lo + chunk, ids.size)) for lo in range(0, ids.size, chunk)]
            else:
                run = lambda i: [(i, solve(i))]
                tasks = range(ids.size)
        elif self.block_size == 1:
            def run(i):
                return [(i, self._solve_clarabel(self._clarabel_single(ids[i]), costs[i:i + 1], flat[i:i + 1],
                                                 direction))]
            tasks = range(ids.size)
        else:
            plan = self._plan(ids)

            def run(task):
                lo, block = task
                return [(lo, self._solve_clarabel(block, costs[lo:lo + block["count"]], flat[lo:lo + block["count"]],
                                                  direction))]
            tasks = plan

        tasks = list(tasks)
        # Always on the pool's threads, never on the caller's: XLA runs host callbacks on its own
        # threads, whose Python thread state (and the thread-local HiGHS instance with it) may
        # not outlive one call; solving there crashed the 2-D unicycle's synthesis (row 3) with
        # threads=1.
        share = 1 if np.unique(ids).size != ids.size else max(1, min(self.threads, len(tasks)))
        parts = self._pool().map(lambda t: [r for task in tasks[t::share] for r in run(task)], range(share))
        solved = sorted(r for part in parts for r in part)
        np.maximum(lam, 0.0, out=lam)  # lambda+ = max(dual, 0), lambda- = max(-dual, 0)
        statuses = [status for _, status in solved]
        self.stats.update(statuses)
        self._report([ids[i] for i, _ in solved], statuses)
        self.stats["solve_seconds"] += time.perf_counter() - start
        self.stats["calls"] += 1
        return lam.reshape(*shape, self.num_clusters, 2)

    def _report(self, first_lps, statuses):
        """Warn about solves that ended without an optimum (``first_lps``: the first LP of each)."""
        failed = [(int(p), st) for p, st in zip(first_lps, statuses) if st not in _OPTIMAL]
        if not failed:
            return
        with self._lock:
            self.stats["failed"] += len(failed)
            self.failures.extend(failed)
        p, status = failed[0]
        where = f"LP {p}" if self.names is None else f"the LP of cell {int(self.names[p][0])}, action {int(self.names[p][1])}"
        import warnings

        warnings.warn(f"MI-MDP: {where} ended with solver status {status!r} ({len(failed)} of {len(statuses)} "
                      f"solves in this backup did not reach an optimum; ClusterLPs.failures lists them). Their "
                      f"multipliers still certify a sound bound, which may be loose.", RuntimeWarning, stacklevel=3)

    def _solve_clarabel(self, block, costs, out, direction):
        solver = block["solver"]
        with block["lock"]:  # a cached solver may be reached by two calls at once
            solver.update(q=costs[block["cost_pos"], block["cost_col"]])
            sol = solver.solve()
            z = np.asarray(sol.z)
            x = np.asarray(sol.x)
        out[block["z_pos"], block["z_target"]] = np.maximum(z[block["z_rows"]], 0.0)
        status = str(sol.status)
        record = self._record(direction)
        with self._record_locks[direction]:  # the optimal point, for ``vertices`` (a block's LPs share a status)
            record.x[block["var_pos"]] = x
            record.vertex[block["ids"]] = status in _OPTIMAL
        return status

    def reset(self):
        """Drop every solver, model and warm start (the next call sets them up again)."""
        with self._lock:
            self._plans.clear()
            self._solvers.clear()
            self._cached_solvers = 0
            self._local = threading.local()
            self._records.clear()

    def _pool(self):
        with self._lock:
            if self._executor is None:
                from concurrent.futures import ThreadPoolExecutor

                self._executor = ThreadPoolExecutor(self.threads, thread_name_prefix="mimdp-lp")
            return self._executor

    @property
    def data_nbytes(self) -> int:
        """Bytes of the LP data kept on the host (successor ids and per-LP capacities, cost
        sources, cluster sides and members). Not in ``MIMDP.nbytes`` (the abstraction's storage,
        the paper's metric): a re-encoding of the same abstraction for the solver, like its
        models and warm-start bases, which come on top and are not counted here either."""
        return int(sum(a.nbytes for a in (self.succ, self.buckets, self.has_rest)) + self._lps.nbytes)

    def __repr__(self):
        return (f"ClusterLPs({self.num_lps} LPs, backend={self.backend}, vars <= {int(self.num_vars.max(initial=0))}, "
                f"cluster sides <= {int(self.num_cluster_rows.max(initial=0))}, threads={self.threads})")


class LPTable:
    """The data of many LPs in flat arrays, LP ``p``'s pieces at ``[start[p], start[p + 1])``.

    ``table[p]`` is LP ``p`` as a dict of views: ``caps`` and ``cost_src`` of its variables,
    ``free_mass``, ``cluster`` (the cluster of each cluster row), ``lo`` and ``hi`` (the row's
    sides, infinite where a side is left out), ``ptr`` (where each row's members start in
    ``var``, from 0) and ``var`` (the members' variable ids, int16 where every LP's variables
    fit). One table instead of a dict of arrays per LP: building 224k small dicts took 21 s of
    the 3-D unicycle's MI-MDP (row 19), and each held ~1 KB of Python overhead.
    """

    def __init__(self, caps, cost_src, var_start, free_mass, cluster, lo, hi, row_start, var, member_start):
        self.caps, self.cost_src, self.var_start, self.free_mass = caps, cost_src, var_start, free_mass
        self.cluster, self.lo, self.hi, self.row_start = cluster, lo, hi, row_start
        self.member_start = member_start
        most = int(np.diff(var_start).max(initial=0))
        self.var = var.astype(np.int16 if most <= np.iinfo(np.int16).max else np.int32)

    @classmethod
    def concatenate(cls, tables) -> "LPTable":
        """One table of the LPs of ``tables``, in order."""
        cat = lambda name: np.concatenate([getattr(t, name) for t in tables])
        starts = lambda name: np.concatenate(
            [[0]] + [getattr(t, name)[1:] + off for t, off in
                     zip(tables, np.cumsum([0] + [getattr(t, name)[-1] for t in tables[:-1]]))])
        return cls(cat("caps"), cat("cost_src"), starts("var_start"), cat("free_mass"), cat("cluster"), cat("lo"),
                   cat("hi"), starts("row_start"), cat("var"), starts("member_start"))

    def __len__(self) -> int:
        return int(self.free_mass.size)

    def __getitem__(self, p) -> dict:
        p = int(p)
        v0, v1 = self.var_start[p], self.var_start[p + 1]
        r0, r1 = self.row_start[p], self.row_start[p + 1]
        ptr = self.member_start[r0:r1 + 1]
        return dict(caps=self.caps[v0:v1], cost_src=self.cost_src[v0:v1], free_mass=float(self.free_mass[p]),
                    cluster=self.cluster[r0:r1], ptr=(ptr - ptr[0]).astype(np.int32),
                    var=self.var[ptr[0]:ptr[-1]], lo=self.lo[r0:r1], hi=self.hi[r0:r1])

    def __iter__(self):
        return (self[p] for p in range(len(self)))

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.caps, self.cost_src, self.var_start, self.free_mass, self.cluster,
                                          self.lo, self.hi, self.row_start, self.var, self.member_start)))


def _basic_variables(h):
    """HiGHS's basic variables as an array (column ``j`` as ``j``, row ``i`` as ``-1 - i``):
    highspy returns ``(status, array)``, some versions the array alone."""
    listed = h.getBasicVariables()
    return listed[1] if isinstance(listed, tuple) else listed


def _import(backend: str):
    try:
        if backend == "highs":
            import highspy as module
        else:
            import clarabel as module
    except ImportError as err:  # pragma: no cover - depends on the environment
        package = "highspy" if backend == "highs" else "clarabel"
        raise ImportError(f"the MI-MDP LP backend {backend!r} needs the {package!r} package: "
                          f"pip install {package}") from err
    return module
