"""Multi-interval MDP abstraction (Definition 5) with informed clusters, and its inner problem.

Ambiguity set of a row (s, a) (Definition 5, eq. Gamma_poly, as set up in Section 6.2):

    Gamma^MI(s, a) = { gamma in Gamma^IMDP(s, a) : P_low(s,a,q) <= sum_{s' in q} gamma(s') <= P_up(s,a,q)
                                                     for every cluster q of (s, a) },

where Gamma^IMDP is the interval polytope of Lemma 1 (``relaxation``) and the clusters are the
*informed* clusters q~_c (the states met by Reach(s, a, c), one per bounded noise cell c; the
paper's Example 2), optionally extended by user-given clusters. Lemma 1 bounds a cluster by

    P_low(s,a,q) = sum_c' 1(members(c') inside q) P_W(c'),
    P_up(s,a,q)  = sum_c' 1(members(c') meets q)  P_W(c') + P_W(rest),

with members(c') the states met by the (box enclosure of the) reachable set Reach(s, a, c'):
they cover Reach(s, a, c'), so "inside" implies the reachable set lies inside the union of q,
and a reachable set that meets q has a member in q. Both bounds are therefore sound. The
remainder noise cell (unbounded W) reaches every state: it meets every cluster and lies inside
none (short of q = S, which is never useful). Identical clusters of a row are kept once, and
single-state clusters are dropped (they are the IMDP's own constraints).

Gamma^MI is contained in Gamma^IMDP (so the IMDP's robust values bound the MI-MDP's from the
safe side, which warm starts use) and contains Gamma^SMDP (Theorem 2).

Inner problem (``q_values``) and why it is sound whatever the LP solver does
------------------------------------------------------------------------------
``min_{gamma in Gamma^MI} <gamma, w>`` is an LP. Write the cluster constraints as
``lo <= M gamma <= up``. For *any* multipliers ``lambda+, lambda- >= 0`` and every feasible
gamma, ``<lambda+, M gamma - lo> + <lambda-, up - M gamma> >= 0``, hence (weak duality)

    <gamma, w> >= g(lambda) := <lambda+, lo> - <lambda-, up>
                               + min_{gamma in Gamma^IMDP} <gamma, w - M^T (lambda+ - lambda-)>.

The multipliers come from an LP solver on the CPU (Clarabel or HiGHS, ``lp.ClusterLPs``, through
``jax.pure_callback``); negatives are clipped to 0, and values above ``multiplier_cap`` to the
cap (which keeps float rounding bounded; any value in ``[0, cap]`` is valid). The result is also
never below the IMDP value (lambda = 0 is valid too, so the larger of the two is returned).
The last term is an interval problem whose listed successors carry a per-row modified cost
(clusters only contain listed successors) while unlisted states keep ``w``; it is solved in JAX
by ``interval_min_rows`` through its own dual (a threshold cost), which is a lower bound for any
threshold and exact at the one it finds except in near-ties it documents. So ``q_values(v,
"min")`` never exceeds the true minimum over Gamma^MI (up to float rounding, see
``summands_per_backup``), and equals it when the multipliers are optimal. ``"max"`` applies
the same to ``-v`` and negates: a valid *upper* bound of the maximum. Both directions are the
conservative ones for the robust values.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass, static_field
from .base import AbstractionMixin, check_adversary
from .box_bounds import _fixed_point, _to_float
from .clusters import IndexBoxes, cluster_members, max_lengths
from .grid_clusters import GridClusters
from .imdp import IMDP, interval_min, row_chunks
from .imdp_compact import CompactIMDP
from .lp import ClusterLPs
from .smdp import SMDP

_BOUND_ROWS_PER_CHUNK = 64
# (row, cluster, member) terms of the weak-duality bound materialized at once (``certified_min``):
# ~270 MB of float64 and half that per int32 temporary
_MEMBER_TERMS_PER_CHUNK = 1 << 25
_MEMBER_ROWS_PER_CHUNK = 1024
# (row, action) pairs per row that a greedy backup certifies, when it solved no more LPs than that
# in all (the others keep their IMDP value, which lambda = 0 certifies; otherwise every pair is
# certified). Row 3 of Table 1 solves ~1.5 LPs per row in a greedy backup, of 8 actions.
GREEDY_CERTIFIED_PAIRS_PER_ROW = 2
# (row, successor) entries of a frozen view's interval problem at once (``shifted_min``): ~32 MB
# per float64 temporary.
_SHIFTED_ENTRIES_PER_CHUNK = 1 << 22
# Entries of the position table of ``_slots_of`` (int32: 64 MB).
_SLOT_TABLE_ENTRIES = 1 << 24
# Member positions encoded as runs at once (``ClusterRuns.from_slots``).
_RUN_POSITIONS_PER_CHUNK = 1 << 22
# Real-number bisection steps that narrow the threshold bracket of ``interval_min_rows``.
_REAL_BISECTIONS = 20
# Then steps from item to item (exact unless more listed costs than this share the bracket).
_WALK_STEPS = 4


@pytree_dataclass
class MIMDP(AbstractionMixin):
    """Attributes (J = clusters per row after deduplication, L = largest cluster, K = listed successors):
        relaxation: the IMDP of the same reachable sets (Gamma^MI is inside its ambiguity sets),
            stored compactly (``CompactIMDP``); its padded ``(R, A, K)`` views, which the inner
            problem reads, are built inside each backup. Its successor lists also hold every
            member of a user-given cluster.
        cluster_members: the members of each row's ``J`` clusters as runs of consecutive
            positions in ``relaxation.successors[r, a]`` (``ClusterRuns``); ``cluster_slots``
            expands them to ``(R, A, J, L')`` positions padded with ``K``.
        cluster_lower, cluster_upper: ``(R, A, J)`` P_low, P_up of each cluster (0 and 1 on padding).
        lp_index: ``(R, A)`` int32 index of each row's LP in the host-side solver cache ``lps``.
        rows: ``(R,)`` int32 state index of each row (the non-terminal cells).
        labels: ``(N + 1,)`` int8 state labels.
        lps: host-side ``ClusterLPs`` (static; compared by identity).
        multiplier_cap: multipliers are clipped to ``[0, multiplier_cap]`` (static).
        screen: the SMDP of the same clusters (``None``: no screening), whose ambiguity sets
            lie inside Gamma^MI (Theorem 2): its robust q-values bound this class's from the
            other side than the IMDP's. Every backup skips the LPs of rows where the two meet
            (``q_values``), and a greedy backup also those of actions that cannot be the best
            one (``greedy_q_values``).
        frozen: ``(R, A, J, 2)`` multipliers used instead of the LPs (``None``: solve the LPs at
            every call). See ``freeze``.
        frozen_shift, frozen_offset: ``(R, A, K)`` and ``(R, A)``, the terms of ``frozen`` that do
            not depend on the values (``cluster_terms``), computed once when it is frozen
            (``None`` with ``frozen``).
    """

    relaxation: CompactIMDP
    cluster_members: "ClusterRuns"
    cluster_lower: jax.Array
    cluster_upper: jax.Array
    lp_index: jax.Array
    rows: jax.Array
    labels: jax.Array
    lps: ClusterLPs = static_field()
    multiplier_cap: float = static_field(default=4.0)
    kind: str = static_field(default="mimdp")
    screen: SMDP | None = None
    frozen: jax.Array | None = None
    frozen_shift: jax.Array | None = None
    frozen_offset: jax.Array | None = None
    freeze_multipliers: bool = static_field(default=True)

    @property
    def freezable(self) -> bool:
        """Whether loops may iterate frozen views (``freeze``) instead of solving LPs at every
        backup (``from_clusters(freeze_multipliers=...)``)."""
        return self.freeze_multipliers

    @classmethod
    def from_clusters(cls, grid, clusters: GridClusters, extra_clusters=None, *, lp_backend: str = "highs",
                      block_size: int = 1, max_buckets: int = 16, multiplier_cap: float = 4.0,
                      threads: int | None = None, solver_settings: dict | None = None,
                      screen_actions: bool = True, freeze_multipliers: bool = True,
                      reprice_bases: bool = True) -> "MIMDP":
        """MI-MDP with the informed clusters of ``clusters`` (plus ``extra_clusters``).

        Args:
            grid: the state grid.
            clusters: reachable sets of every (row, action, noise cell) (``compute_grid_clusters``).
            extra_clusters: optional user-given clusters, ``(R, A, E, L_e)`` integer state ids
                (cells ``0..N-1``, sink ``N``) per row and action, padded with ``N + 1`` (or any
                id > N); a cluster that is all padding is ignored. Their bounds follow the same
                formula as the informed clusters'.
            lp_backend: ``"highs"`` (the default: dual simplex warm-started from the previous
                call's basis, bases re-priced without a solve where they stay optimal) or
                ``"clarabel"`` (interior point, every LP solved from scratch: 6x slower on Table
                1's row 35). See ``lp``. Soundness does not depend on the choice.
            block_size: LPs stacked block-diagonally into one Clarabel problem. 1 (no stacking)
                was fastest on the 2-D unicycle at 12x12 and 30x30 (``benchmarks/mimdp_lp.py``):
                a stacked problem needs as many interior-point iterations as its hardest block.
                Stacking only paid off for tiny LPs (a few cluster constraints), where the
                per-call overhead dominates.
            max_buckets: bucket variables for the unlisted states in each LP (see ``lp``).
            multiplier_cap: clip multipliers to ``[0, multiplier_cap]`` (bounds rounding).
            threads: threads that solve LPs concurrently (Clarabel releases the GIL while it
                solves); default ``min(8, os.cpu_count())``.
            solver_settings: solver options to override (Clarabel settings attributes, e.g.
                ``{"tol_gap_rel": 1e-7}``, or HiGHS option names).
            screen_actions: keep the SMDP of ``clusters`` (``screen``) so that backups skip the
                LPs of rows whose IMDP and SMDP values meet, and greedy backups those of actions
                that cannot be the best. Costs the SMDP's memory (a few % of the MI-MDP's) and
                one SMDP backup per backup; on the 3-room temperature verification (row 35) it
                halved the LPs (24 192 instead of 51 840: every optimistic one is pinned).
            freeze_multipliers: let the optimization's strategy sweeps iterate with frozen
                multipliers, refreshed by one LP per row now and then (``freeze``;
                ``synthesis.value_iteration.optimize_lower``), instead of solving every row's
                LP at every sweep. Sound either way; ``False`` reproduces the LP-per-sweep
                iteration (the strategy's evaluation solves its LPs at every backup in both).
            reprice_bases: (HiGHS) re-price each LP's last optimal basis at the new values and
                call the solver only where the re-priced duals are not certified optimal
                (``lp_reprice``); ``False`` calls HiGHS for every LP.
        """
        n_cells = grid.num_cells
        sentinel = n_cells + 1
        boxes = clusters.boxes
        num_rows, num_actions, _ = boxes.sink.shape
        if extra_clusters is not None:
            extra = np.asarray(extra_clusters)
            if extra.ndim != 4 or extra.shape[:2] != (num_rows, num_actions):
                raise ValueError(f"extra_clusters must have shape (R, A, E, L) = ({num_rows}, {num_actions}, E, L), "
                                 f"got {extra.shape}")
            if not np.issubdtype(extra.dtype, np.integer) or np.any(extra < 0):
                raise ValueError("extra_clusters must hold nonnegative integer state ids (padding N + 1)")
            extra = np.where(extra <= n_cells, extra, sentinel)
        imdp = IMDP.from_clusters(grid, clusters)
        prob = jnp.asarray(clusters.prob)
        rest = float(clusters.prob_rest)
        lengths = max_lengths(boxes)
        informed_lo, informed_up = informed_cluster_bounds(boxes, prob, rest, grid.cells)

        succ = np.asarray(imdp.successors)
        lower = np.asarray(imdp.lower)
        upper = np.asarray(imdp.upper)
        if extra_clusters is not None:
            succ, lower, upper = _extend_successors(succ, lower, upper, extra, rest, sentinel)
            imdp = dataclasses.replace(imdp, successors=jnp.asarray(succ, jnp.int32), lower=jnp.asarray(lower),
                                       upper=jnp.asarray(upper))
        # Member lists are expanded a chunk of rows at a time: all of them at once is R x A x C_b x K
        # ids (1.1e9 on the 3-D unicycle at |C| = 65, more than 24 GB with the temporaries).
        k = succ.shape[-1]
        # narrowed per chunk: as int64 the padded pieces and their concatenation peaked at 12 GB
        # on the 4-room temperature row (20 736 rows x 256 clusters x 81 members); the smallest
        # type that holds the padding K (uint8 on the 2-D unicycle rows, K <= 225: half of int16)
        slot_type = next(t for t in (np.uint8, np.int16, np.int32) if k <= np.iinfo(t).max)
        pieces = []
        for start in range(0, num_rows, _MEMBER_ROWS_PER_CHUNK):
            stop = min(start + _MEMBER_ROWS_PER_CHUNK, num_rows)
            part = jax.tree.map(lambda a: a[start:stop], boxes)
            members = np.asarray(cluster_members(grid, part, lengths))
            members = np.where(members <= n_cells, members, sentinel)
            ids, b_lo, b_up = members, np.asarray(informed_lo[start:stop]), np.asarray(informed_up[start:stop])
            if extra_clusters is not None:
                ex_lo, ex_up = member_cluster_bounds(members, extra[start:stop], np.asarray(prob), rest, sentinel)
                width = max(members.shape[-1], extra.shape[-1])
                pad = lambda a: np.pad(a, [(0, 0)] * 3 + [(0, width - a.shape[-1])], constant_values=sentinel)
                ids = np.concatenate([pad(members), pad(extra[start:stop])], axis=2)
                b_lo, b_up = np.concatenate([b_lo, ex_lo], axis=2), np.concatenate([b_up, ex_up], axis=2)
            slots = _slots_of(succ[start:stop], ids, sentinel)
            slots, b_lo, b_up = _distinct_clusters(slots, b_lo, b_up, k)
            pieces.append((slots.astype(slot_type), b_lo, b_up))
        slots, clo, cup = _concat_padded(pieces, k)
        flat = lambda a: a.reshape(num_rows * num_actions, *a.shape[2:])
        lps = ClusterLPs(flat(succ), flat(lower), flat(upper), rest, flat(slots), flat(clo), flat(cup),
                         grid.num_states, backend=lp_backend, block_size=block_size, max_buckets=max_buckets,
                         settings=solver_settings, threads=threads or min(8, os.cpu_count() or 1),
                         reprice=reprice_bases,
                         names=np.stack([np.repeat(np.asarray(imdp.rows), num_actions),
                                         np.tile(np.arange(num_actions), num_rows)], axis=1))
        lp_index = np.arange(num_rows * num_actions, dtype=np.int32).reshape(num_rows, num_actions)
        screen = SMDP.from_clusters(grid, clusters) if screen_actions else None
        # stored without padding to the widest list (lossless: the padded views, built in each
        # backup, are these arrays again, so the cluster slots stay valid)
        relaxation = CompactIMDP.from_lists(succ, lower, upper, imdp.upper_rest, imdp.rows, imdp.labels)
        return cls(relaxation=relaxation, cluster_members=ClusterRuns.from_slots(slots, k),
                   cluster_lower=jnp.asarray(clo),
                   cluster_upper=jnp.asarray(cup), lp_index=jnp.asarray(lp_index), rows=imdp.rows,
                   labels=imdp.labels, lps=lps, multiplier_cap=float(multiplier_cap), screen=screen,
                   freeze_multipliers=bool(freeze_multipliers))

    # -- interface ----------------------------------------------------------------------------
    @property
    def num_actions(self) -> int:
        return int(self.lp_index.shape[1])

    @property
    def num_clusters(self) -> int:
        return int(self.cluster_members.start.shape[2])

    @property
    def cluster_slots(self):
        """``(R, A, J, L')`` int32 cluster members as positions in ``relaxation.successors[r, a]``,
        padded with ``K`` (expanded from ``cluster_members``)."""
        return self.cluster_members.slots()

    @property
    def summands_per_backup(self) -> float:
        # the interval part as in the IMDP, plus the cluster terms: lambda.lo, lambda.up and the
        # modified costs (one multiplier per member), each term up to multiplier_cap in size
        j, size = self.num_clusters, self.cluster_members.size
        return self.relaxation.summands_per_backup + float(self.multiplier_cap * j * (size + 2) * 2)

    def restrict(self, actions) -> "MIMDP":
        """The single-action MI-MDP of a stationary strategy ``actions: (R,)``."""
        pick = lambda a: jnp.take_along_axis(a, actions.reshape((-1, 1) + (1,) * (a.ndim - 2)), axis=1)
        return dataclasses.replace(self, relaxation=self.relaxation.restrict(actions),
                                   cluster_members=self.cluster_members.map(pick), cluster_lower=pick(self.cluster_lower),
                                   cluster_upper=pick(self.cluster_upper), lp_index=pick(self.lp_index),
                                   screen=None if self.screen is None else self.screen.restrict(actions),
                                   **{name: None if getattr(self, name) is None else pick(getattr(self, name))
                                      for name in ("frozen", "frozen_shift", "frozen_offset")})

    def freeze(self, v, adversary: str = "min") -> "MIMDP":
        """This MI-MDP with its multipliers fixed at the LPs' for ``v``: a view whose backups need
        no LP, for loops that apply the operator many times (the strategy sweeps of
        ``value_iteration.optimize_lower``).

        By weak duality (module docstring) *any* multipliers give a bound on the conservative
        side, so the frozen operator ``T_lambda`` lies below the exact one for ``"min"`` (above it
        for ``"max"``) at every value vector, and equals it at ``v`` when the LPs are solved
        exactly: iterating it from below (above) gives valid lower (upper) bounds throughout. Where
        this view is already frozen, each (row, action) keeps whichever of its old and new
        multipliers certifies more at ``v``, so ``T_lambda(v)`` never falls by refreezing.

        The multipliers' terms that do not depend on the values (``cluster_terms``: each listed
        successor's cost shift and the constant) are computed here once, so that a backup of the
        view is an interval problem with shifted costs and no scatter of member terms (a
        strategy's sweep of Table 1's row 3: ~3x faster): the same operations on the same multipliers.
        """
        minimize = check_adversary(adversary)
        w = v if minimize else -v
        fresh = self._frozen_at(self.multipliers(w, self.lp_index, 0 if minimize else 1))
        if self.frozen is None:
            return fresh
        old = self.q_values(v, adversary)
        new = fresh.q_values(v, adversary)
        better = (new >= old) if minimize else (new <= old)
        keep = lambda name: jnp.where(better.reshape(better.shape + (1,) * (getattr(fresh, name).ndim - better.ndim)),
                                      getattr(fresh, name), getattr(self, name))
        return dataclasses.replace(self, **{name: keep(name) for name in ("frozen", "frozen_shift", "frozen_offset")})

    def frozen_at_zero(self) -> "MIMDP":
        """This MI-MDP frozen at zero multipliers (its IMDP relaxation's operator): the start of a
        loop that refreezes, whose carried PyTree must keep one structure."""
        shape = (*self.lp_index.shape, self.num_clusters, 2)
        return dataclasses.replace(self, frozen=jnp.zeros(shape, jnp.float64),
                                   frozen_shift=jnp.zeros((*self.lp_index.shape, self.relaxation.width), jnp.float64),
                                   frozen_offset=jnp.zeros(self.lp_index.shape, jnp.float64))

    def _frozen_at(self, lam) -> "MIMDP":
        """This MI-MDP frozen at the multipliers ``lam (R, A, J, 2)``."""
        shift, offset = _cluster_terms(self.relaxation.width, self.cluster_members, self.cluster_lower,
                                       self.cluster_upper, lam, self.multiplier_cap)
        return dataclasses.replace(self, frozen=lam, frozen_shift=shift, frozen_offset=offset)

    def q_values(self, v, adversary: str = "min", actions=None):
        """Certified inner values (see the module docstring): for ``"min"`` a lower bound of
        ``min_{Gamma^MI} <gamma, v>`` (exact when the LP multipliers are optimal), for ``"max"``
        an upper bound of the maximum. ``(R, A)``, or ``(R,)`` with ``actions: (R,)``."""
        minimize = check_adversary(adversary)
        imdp = self.relaxation
        pick = lambda a: jnp.take_along_axis(a, actions.reshape((-1, 1) + (1,) * (a.ndim - 2)), axis=1)[:, 0]
        chosen = (lambda a: a) if actions is None else (lambda a: a.map(pick) if isinstance(a, ClusterRuns) else pick(a))
        w = v if minimize else -v
        if self.frozen is not None:  # the multipliers' terms were computed when they were frozen
            value = _shifted_min(w, *(chosen(a) for a in (imdp.successors, imdp.lower, imdp.upper)), imdp.upper_rest,
                                 chosen(self.frozen_shift), chosen(self.frozen_offset))
            return value if minimize else -value
        lp = chosen(self.lp_index)
        imdp_value = None
        if self.screen is not None:
            # the relaxation's own backup (a block of rows at a time), 6x faster than the
            # padded views' on the 4-room temperature row
            imdp_value = imdp.q_values(v, adversary, actions)
            imdp_value = imdp_value if minimize else -imdp_value
            lp = jnp.where(self._pinned(imdp_value, v, adversary, actions), -1, lp)
        lam = self.multipliers(w, lp, 0 if minimize else 1)

        def certify():
            arrays = (imdp.successors, imdp.lower, imdp.upper, self.cluster_members, self.cluster_lower,
                      self.cluster_upper)
            succ, lower, upper, slots, clo, cup = (chosen(a) for a in arrays)
            return _certified_min(w, succ, lower, upper, imdp.upper_rest, slots, clo, cup, lam, self.multiplier_cap,
                                  imdp_value=imdp_value)

        value = certify() if imdp_value is None else _unless_all_zero(lam, certify, imdp_value)
        return value if minimize else -value

    def _screen_margin(self) -> float:
        # the rounding of the IMDP's and the SMDP's sums (K and C_b + 1 terms of total <= 1); a
        # wider margin only solves more LPs
        terms = self.relaxation.width + self.screen.clusters.shape[2] + 8
        return 4.0 * float(np.finfo(np.float64).eps) * terms

    def _pinned(self, imdp_value, v, adversary, actions=None):
        """Where the IMDP's value of ``min <gamma, w>`` (``imdp_value``, w = v or -v) already is the
        MI-MDP's within the screen margin: the ``screen`` SMDP's value, from the other side
        (Gamma^SMDP inside Gamma^MI inside Gamma^IMDP), meets it. No LP is needed there; the
        certified bound with lambda = 0 is the IMDP value, sound whatever the screen says."""
        high = self.screen.q_values(v, adversary, actions)
        high = high if adversary == "min" else -high
        return high <= imdp_value + self._screen_margin()

    def greedy_q_values(self, v):
        """``(R, A)`` lower bounds of the minimizing q-values, as ``q_values(v, "min")`` on every
        action that can still be a row's best one and the IMDP's value on the others, so that
        the row maximum (and its argmax) equals ``q_values``'s while only those actions' LPs
        are solved.

        With the IMDP below (Gamma^MI inside Gamma^IMDP) and the ``screen`` SMDP above
        (Gamma^SMDP inside Gamma^MI), an action whose SMDP q-value is below another action's IMDP
        q-value is below that action's MI-MDP q-value too, so it is not the argmax; and where the
        two bounds meet, the IMDP value is the MI-MDP's without an LP. Every entry is a valid
        lower bound whatever the screen says (a skipped LP is lambda = 0, which certifies the
        IMDP value); a wrong screen could only cost tightness.

        Only the (row, action) pairs whose LPs were solved are certified (a pair without one has
        lambda = 0, which certifies the IMDP value it already has), as one batch of
        ``GREEDY_CERTIFIED_PAIRS_PER_ROW`` times the rows when no more were solved, else every pair.
        """
        return self.greedy_backup(v)[0]

    def greedy_backup(self, v, floor=None, current=None):
        """``(q (R, A), lam (R, A, J, 2))``: ``greedy_q_values(v)`` and the multipliers that
        certify it (zeros on the pairs whose LPs it did not solve; ``None`` for a frozen view),
        which a loop may freeze for the greedy strategy's sweeps (``from_multipliers``): they
        are exact at ``v`` on every pair they certify.

        ``floor (R,)`` and ``current (R,)`` (optional, for policy iteration, which knows its
        strategy's values): an action whose screen value is below ``floor`` is not solved either
        (it cannot exceed ``floor``), except ``current``, the row's present action, which is
        solved wherever the screen does not pin it (the others are compared with its certified
        value). Every entry stays a certified lower bound; the row maximum is then
        ``q_values``'s where it exceeds ``floor`` or is the current action's."""
        if self.frozen is not None:
            return self.q_values(v, "min"), None
        if self.screen is None:  # nothing to skip
            lam = self.multipliers(v, self.lp_index)
            value = _certified_min(v, self.relaxation.successors, self.relaxation.lower, self.relaxation.upper,
                                   self.relaxation.upper_rest, self.cluster_members, self.cluster_lower,
                                   self.cluster_upper, lam, self.multiplier_cap)
            return value, lam
        imdp = self.relaxation
        low = imdp.q_values(v, "min")
        high = self.screen.q_values(v, "min")
        margin = self._screen_margin()  # a wider margin only keeps more contenders
        best = low.max(axis=1, keepdims=True)
        best = best if floor is None else jnp.maximum(best, jnp.asarray(floor, best.dtype)[:, None])
        contender = high >= best - margin
        pinned = high <= low + margin  # the IMDP value is already the MI-MDP's, within the margin
        if current is not None:
            contender |= jnp.arange(low.shape[1]) == jnp.asarray(current)[:, None]
        solve = contender & ~pinned
        lam = self.multipliers(v, jnp.where(solve, self.lp_index, -1))
        arrays = (imdp.successors, imdp.lower, imdp.upper, self.cluster_members, self.cluster_lower,
                  self.cluster_upper, lam, low)
        rows, actions = low.shape
        budget = min(GREEDY_CERTIFIED_PAIRS_PER_ROW * rows, rows * actions)

        def certify(pairs):  # the certified values of the (row, action) pairs ``pairs (P,)``, flat
            take = lambda a: a.reshape(rows * actions, *a.shape[2:])[jnp.minimum(pairs, rows * actions - 1)]
            succ, lower, upper, slots, clo, cup, lam_p, low_p = (
                a.map(take) if isinstance(a, ClusterRuns) else take(a) for a in arrays)
            return _certified_min(v, succ, lower, upper, imdp.upper_rest, slots, clo, cup, lam_p, self.multiplier_cap,
                                  imdp_value=low_p)

        def every():
            succ, lower, upper, slots, clo, cup, _, _ = arrays
            return _certified_min(v, succ, lower, upper, imdp.upper_rest, slots, clo, cup, lam, self.multiplier_cap,
                                  imdp_value=low)

        if budget == rows * actions:
            return _unless_all_zero(lam, every, low), lam

        def few():  # at most ``budget`` LPs solved: certify those pairs only (padding dropped)
            pairs = jnp.nonzero(solve.reshape(-1), size=budget, fill_value=rows * actions)[0]
            return low.reshape(-1).at[pairs].set(certify(pairs), mode="drop").reshape(rows, actions)

        q = jax.lax.cond(jnp.any(lam > 0), lambda: jax.lax.cond(jnp.sum(solve) <= budget, few, every), lambda: low)
        return q, lam

    @property
    def exact_transitions(self) -> bool:
        """Whether ``worst_case_transitions`` returns the LPs' optimal vertices (HiGHS's simplex),
        rather than interior points optimal to the solver's tolerance (Clarabel), whose noise
        slows policy iteration down (``synthesize`` then defaults to value iteration)."""
        return self.lps.backend == "highs"

    def worst_case_transitions(self, v, actions, adversary: str = "min"):
        """The adversary's optimal distributions for a stationary strategy at values ``v``: for each
        row, an optimal point of the LP of ``min`` (or ``max``) ``<gamma, v>`` for the row's action
        ``actions[r]`` (``lp.ClusterLPs.vertices``), the LPs solved or re-priced at ``v``.

        Host-side (NumPy in, SciPy out), for loops that evaluate a strategy against a fixed
        adversary by a linear solve (``synthesis.policy_iteration``); not a bound by itself. The
        point is the solver's surrogate LP's, which prices the unlisted states beyond its buckets
        at one state (``lp.ClusterLPs``): where that remainder carries mass, the distribution
        puts it on that state, above its own upper bound, and its value lies below the certified
        q-value (``q_values``), which bounds every unlisted state exactly.
        Returns ``(matrix, solved)``: a ``scipy.sparse.csr_matrix`` ``(R, N+1)`` whose row ``r`` is
        that distribution (the unlisted states' mass where the LP's buckets price it), and
        ``solved (R,)`` bool, False where the LP ended without an optimum (its row then holds the
        lower bounds only).
        """
        import scipy.sparse as sp

        minimize = check_adversary(adversary)
        v = np.asarray(v, np.float64)
        actions = np.asarray(actions, np.int64)
        rows = np.arange(actions.size)
        ids = np.asarray(self.lp_index)[rows, actions]
        lp, state, mass, solved = self.lps.vertices(v if minimize else -v, ids, 0 if minimize else 1)
        lower_succ = np.asarray(self.relaxation.lower_succ)[rows, actions]  # (R, L)
        lower_value = np.asarray(self.relaxation.lower_value)[rows, actions]
        has = (lower_value > 0) & (lower_succ < self.num_states)
        r = np.concatenate([lp, np.nonzero(has)[0]])
        c = np.concatenate([state, lower_succ[has]])
        m = np.concatenate([mass, lower_value[has]])
        matrix = sp.csr_matrix((m, (r, c)), shape=(actions.size, self.num_states))
        matrix.sum_duplicates()
        return matrix, solved

    def from_multipliers(self, lam) -> "MIMDP":
        """This MI-MDP frozen at the multipliers ``lam (R, A, J, 2)`` (any nonnegative ones give a
        view on the conservative side; see ``freeze``)."""
        return self._frozen_at(lam)

    def multipliers(self, w, lp_index, direction: int = 0):
        """``(*lp_index.shape, J, 2)`` multipliers (lambda+, lambda-) of the LPs for costs ``w``,
        from the host solver (callable under ``jit``; ``direction`` 1 for the maximizing
        adversary's LPs, which keep their own warm starts). A negative index gets zeros (no LP)."""
        shape = jax.ShapeDtypeStruct((*lp_index.shape, self.num_clusters, 2), jnp.float64)
        if self.num_clusters == 0:
            return jnp.zeros(shape.shape, shape.dtype)
        host = functools.partial(self.lps.multipliers, direction=int(direction))
        return jax.pure_callback(host, shape, w, lp_index, vmap_method="sequential")

    def __repr__(self):
        r, a, j = self.cluster_members.start.shape[:3]
        size, k = self.cluster_members.size, self.relaxation.width
        return (f"MIMDP(|S|={self.num_states}, rows={r}, |A|={a}, max successors={k}, clusters per row={j}, "
                f"max cluster size={size}, memory={self.nbytes / 1e6:.2f} MB)")


@pytree_dataclass
class ClusterRuns:
    """Clusters as runs of consecutive positions in their row's sorted successor list.

    A box of cells is, per line along the last grid dimension, one run of consecutive cell ids,
    hence of consecutive positions in the sorted list (every cell between two members is a
    member): a 4 x 4 cluster is 4 runs of 4 positions, stored as 4 starts and 4 lengths instead
    of 16 positions. Any set of positions has a run encoding, so the encoding is lossless for
    every cluster (user-given ones included, at worst one run per member).

    Attributes:
        start: ``(..., J, M)`` first position of each run (the type of the positions), ``pad``
            on padding runs.
        length: ``(..., J, M)`` uint8 positions per run (0 on padding runs).
        longest: the longest run (static).
        pad: the padding position ``K`` (static).
        size: the most members any cluster has (static).
    """

    start: jax.Array
    length: jax.Array
    longest: int = static_field(default=1)
    pad: int = static_field(default=0)
    size: int = static_field(default=1)

    @classmethod
    def from_slots(cls, slots, pad: int, rows_per_chunk: int | None = None) -> "ClusterRuns":
        """Runs of the sorted positions ``slots (R, A, J, L)`` (padding ``pad`` at the end of
        each cluster), a chunk of rows at a time (default: ~4M positions, a few int64
        temporaries of 32 MB)."""
        slots = np.asarray(slots)
        rows_per_chunk = rows_per_chunk or max(1, _RUN_POSITIONS_PER_CHUNK // max(1, math.prod(slots.shape[1:])))
        parts = [_runs(slots[i:i + rows_per_chunk], pad) for i in range(0, slots.shape[0], rows_per_chunk)]
        most = max(max(p[0].shape[-1] for p in parts), 1)
        widen = lambda a, fill: np.pad(a, [(0, 0)] * (a.ndim - 1) + [(0, most - a.shape[-1])], constant_values=fill)
        start = np.concatenate([widen(p[0], pad) for p in parts]).astype(slots.dtype)
        length = np.concatenate([widen(p[1], 0) for p in parts])
        longest = int(length.max(initial=1))
        if longest > np.iinfo(np.uint8).max:
            raise ValueError(f"a run of {longest} positions does not fit the uint8 run lengths")
        size = int((slots < pad).sum(-1).max(initial=1))
        return cls(start=jnp.asarray(start), length=jnp.asarray(length.astype(np.uint8)), longest=longest,
                   pad=int(pad), size=size)

    @property
    def slots_shape(self) -> tuple:
        """Shape of ``slots()``: ``(..., J, M * longest)``."""
        return tuple(self.start.shape[:-1]) + (self.start.shape[-1] * self.longest,)

    def map(self, fn) -> "ClusterRuns":
        """``fn`` applied to ``start`` and ``length`` (a take, a slice, a reshape of the leading axes)."""
        return dataclasses.replace(self, start=fn(self.start), length=fn(self.length))

    def slots(self):
        """``(..., J, M * longest)`` int32 positions of the members, padded with ``pad``."""
        step = jnp.arange(self.longest, dtype=jnp.int32)
        positions = self.start.astype(jnp.int32)[..., None] + step
        positions = jnp.where(step < self.length.astype(jnp.int32)[..., None], positions, self.pad)
        return positions.reshape(self.slots_shape)


def _runs(slots, pad):
    """``(start (..., J, M), length (..., J, M))`` of the runs of consecutive positions in each
    sorted cluster ``slots (..., J, L)`` (padding ``pad`` last); ``M`` the most runs of any."""
    s = slots.astype(np.int32)
    real = s < pad
    s_real = np.where(real, s, -2)  # padding continues no run (pad may follow K - 1)
    edge = np.full(s.shape[:-1] + (1,), -2, np.int32)
    before = np.concatenate([edge, s_real[..., :-1]], axis=-1)
    after = np.concatenate([s_real[..., 1:], edge], axis=-1)
    first = real & (s != before + 1)
    last = real & (after != s + 1)
    run = np.cumsum(first, axis=-1, dtype=np.int32) - 1  # run index of each member
    most = int(first.sum(-1).max(initial=0))
    lead = s.shape[:-1]
    start = np.full(lead + (most,), pad, np.int32)
    length = np.zeros(lead + (most,), np.int32)
    where_first, where_last = np.nonzero(first), np.nonzero(last)  # the same runs, in the same order
    start[where_first[:-1] + (run[where_first],)] = s[where_first]
    length[where_first[:-1] + (run[where_first],)] = where_last[-1] - where_first[-1] + 1
    return start, length


# -- the certified inner value ------------------------------------------------------------------
def certified_min(w, succ, lower, upper, upper_rest, slots, cluster_lower, cluster_upper, lam, cap=np.inf, *,
                  imdp_value=None, rows_per_chunk: int | None = None):
    """The weak-duality bound ``g(lambda)`` of the module docstring, for every row.

    Args:
        w: ``(N+1,)`` costs.
        succ, lower, upper: ``(..., K)`` the interval polytope (as in ``interval_min``).
        upper_rest: upper bound of every unlisted state.
        slots: ``(..., J, L)`` cluster members as positions in ``succ`` (padding ``>= K``), or
            ``ClusterRuns`` with leading shape ``(..., J)`` (expanded a chunk of rows at a time).
        cluster_lower, cluster_upper: ``(..., J)`` cluster bounds.
        lam: ``(..., J, 2)`` multipliers (lambda+, lambda-); clipped to ``[0, cap]``.
        imdp_value: ``(...)`` the interval problem's value ``g(0)`` if the caller has it already
            (computed here otherwise).
        rows_per_chunk: rows whose ``(J, L)`` member terms are materialized at once (``None``:
            as many as keep them under ``_MEMBER_TERMS_PER_CHUNK``). One chunk at a time
            bounds the temporaries: all 20 736 rows of the 4-room temperature row at once
            (256 clusters x 81 members) are three arrays of 430M terms, ~7 GB per backup
            direction.
    Returns:
        ``(...)`` lower bounds of ``min <gamma, w>`` over the MI-MDP polytope: the larger of
        ``g(lambda)`` and ``g(0)`` (the IMDP value), both valid.
    """
    batch, k = succ.shape[:-1], succ.shape[-1]
    rows = int(np.prod(batch)) if batch else 1
    flat = lambda a, tail: a.reshape(rows, *a.shape[a.ndim - tail:])
    runs = slots.map(lambda a: flat(a, 2)) if isinstance(slots, ClusterRuns) else None
    members = (runs.start, runs.length) if runs is not None else (flat(slots, 2),)
    arrays = (flat(succ, 1), flat(lower, 1), flat(upper, 1), *members, flat(cluster_lower, 1),
              flat(cluster_upper, 1), flat(lam, 2))
    if imdp_value is not None:
        arrays += (jnp.reshape(imdp_value, (rows,)),)

    def kernel(*part):
        head, tail = part[:3], part[3 + len(members):]
        part_slots = (dataclasses.replace(runs, start=part[3], length=part[4]).slots() if runs is not None
                      else part[3])
        return _certified_min_rows(w, upper_rest, *head, part_slots, *tail, cap=cap)

    terms = max(1, int(np.prod(runs.slots_shape[-2:] if runs is not None else slots.shape[-2:])))
    chunk = rows_per_chunk or max(1, _MEMBER_TERMS_PER_CHUNK // terms)
    return _by_row_chunks(kernel, arrays, rows, chunk, jnp.zeros(rows, w.dtype)).reshape(batch)


def cluster_terms(width: int, slots, cluster_lower, cluster_upper, lam, cap=np.inf, *,
                  rows_per_chunk: int | None = None):
    """The multipliers' part of ``g(lambda)`` (module docstring), which does not depend on the
    costs: ``(shift (..., width), offset (...))``, the shift ``M^T (lambda+ - lambda-)`` of each
    listed successor's cost and ``<lambda+, lo> - <lambda-, up>``.

    ``shifted_min(w, ..., shift, offset)`` is then ``certified_min`` with the same multipliers
    (the same operations, hence the same rounding allowance): a frozen view (``MIMDP.freeze``)
    computes these once instead of at every backup.
    Arguments as in ``certified_min`` (``width``: the ``K`` of the successor lists).
    """
    batch = cluster_lower.shape[:-1]
    rows = int(np.prod(batch)) if batch else 1
    flat = lambda a, tail: a.reshape(rows, *a.shape[a.ndim - tail:])
    runs = slots.map(lambda a: flat(a, 2)) if isinstance(slots, ClusterRuns) else None
    members = (runs.start, runs.length) if runs is not None else (flat(slots, 2),)
    arrays = (*members, flat(cluster_lower, 1), flat(cluster_upper, 1), flat(lam, 2))

    def kernel(*part):
        part_slots = (dataclasses.replace(runs, start=part[0], length=part[1]).slots() if runs is not None
                      else part[0])
        return _cluster_terms_rows(width, part_slots, *part[len(members):], cap=cap)

    terms = max(1, int(np.prod(runs.slots_shape[-2:] if runs is not None else slots.shape[-2:])))
    chunk = rows_per_chunk or max(1, _MEMBER_TERMS_PER_CHUNK // terms)
    out = (jnp.zeros((rows, width), lam.dtype), jnp.zeros(rows, lam.dtype))
    shift, offset = _by_row_chunks(kernel, arrays, rows, chunk, out)
    return shift.reshape(*batch, width), offset.reshape(batch)


def shifted_min(w, succ, lower, upper, upper_rest, shift, offset, imdp_value=None):
    """``g(lambda)`` from the multipliers' terms of ``cluster_terms``: ``(...)`` lower bounds of
    ``min <gamma, w>`` over the MI-MDP polytope, never below ``imdp_value`` (``g(0)``, computed
    here if not given). Arguments as in ``certified_min``; ``shift (..., K)``, ``offset (...)``."""
    batch, k = succ.shape[:-1], succ.shape[-1]
    rows = int(np.prod(batch)) if batch else 1
    arrays = tuple(a.reshape(rows, k) for a in (succ, lower, upper, shift)) + (offset.reshape(rows),)
    if imdp_value is not None:
        arrays += (jnp.reshape(imdp_value, (rows,)),)
    kernel = lambda *part: _shifted_min_rows(w, upper_rest, *part)
    chunk = max(1, _SHIFTED_ENTRIES_PER_CHUNK // max(k, 1))
    return _by_row_chunks(kernel, arrays, rows, chunk, jnp.zeros(rows, w.dtype)).reshape(batch)


def _by_row_chunks(kernel, arrays, rows: int, chunk: int, out):
    """``kernel(*arrays)`` (``(rows, ...)`` each, outputs shaped like ``out``) in equal chunks of
    ``chunk`` rows; the last one starts at ``rows - chunk``, overlapping its predecessor (those
    rows are computed twice, to the same values)."""
    if chunk >= rows:
        return kernel(*arrays)

    def body(i, acc):
        start = jnp.minimum(i * chunk, rows - chunk)
        part = [jax.lax.dynamic_slice_in_dim(a, start, chunk) for a in arrays]
        return jax.tree.map(lambda o, r: jax.lax.dynamic_update_slice_in_dim(o, r, start, 0), acc, kernel(*part))

    return jax.lax.fori_loop(0, -(-rows // chunk), body, out)


def _cluster_terms_rows(width, slots, cluster_lower, cluster_upper, lam, *, cap):
    """``cluster_terms`` of ``(rows, ...)`` arrays, all rows at once."""
    lam = jnp.clip(lam, 0.0, cap)
    lam_plus, lam_minus = lam[..., 0], lam[..., 1]
    mu = lam_plus - lam_minus
    rows = slots.shape[0]
    flat_slots = slots.reshape(rows, -1).astype(jnp.int32)
    flat_index = jnp.where(flat_slots < width, jnp.arange(rows)[:, None] * width + flat_slots, rows * width)
    per_member = jnp.broadcast_to(mu[..., None], slots.shape).reshape(rows, -1)
    shift = jnp.zeros(rows * width, lam.dtype).at[flat_index].add(per_member, mode="drop").reshape(rows, width)
    offset = jnp.sum(lam_plus * cluster_lower - lam_minus * cluster_upper, axis=-1)
    return shift, offset


def _shifted_min_rows(w, upper_rest, succ, lower, upper, shift, offset, imdp_value=None):
    """``shifted_min`` of ``(rows, K)`` arrays, all rows at once."""
    listed = succ < w.shape[0]
    w_listed = jnp.where(listed, w.at[succ].get(mode="fill", fill_value=0.0) - shift, 0.0)
    bound = offset + interval_min_rows(w, w_listed, succ, lower, upper, upper_rest)
    # lambda = 0 is valid too and gives the IMDP value: never return less (inexact multipliers)
    if imdp_value is None:
        imdp_value = interval_min(w, succ, lower, upper, upper_rest)
    return jnp.maximum(bound, imdp_value)


def _certified_min_rows(w, upper_rest, succ, lower, upper, slots, cluster_lower, cluster_upper, lam,
                        imdp_value=None, *, cap):
    """``certified_min`` of ``(rows, ...)`` arrays, all rows at once."""
    shift, offset = _cluster_terms_rows(succ.shape[-1], slots, cluster_lower, cluster_upper, lam, cap=cap)
    return _shifted_min_rows(w, upper_rest, succ, lower, upper, shift, offset, imdp_value)


_certified_min = jax.jit(certified_min, static_argnums=9, static_argnames="rows_per_chunk")  # one compilation per shape
_cluster_terms = jax.jit(cluster_terms, static_argnums=(0, 5), static_argnames="rows_per_chunk")
_shifted_min = jax.jit(shifted_min)


def _unless_all_zero(lam, certify, imdp_value):
    """``certify()``, or ``imdp_value`` without it where every multiplier is 0 (every LP skipped):
    ``g(0)`` is the interval problem's value, so the certified bound is the IMDP value there
    (the larger of the two, and both are sound). Half the backups of the 4-room temperature row
    solve no LP; each certification costs ~4 s there."""
    return jax.lax.cond(jnp.any(lam > 0), certify, lambda: imdp_value)


def interval_min_rows(w, w_listed, succ, lower, upper, upper_rest):
    """``min <gamma, cost>`` over the interval polytope, where listed successors cost ``w_listed``
    (per row) and every unlisted state s costs ``w(s)``.

    Args:
        w: ``(N+1,)`` costs of the unlisted states (a listed state's entry is ignored).
        w_listed: ``(..., K)`` costs of the listed successors.
        succ, lower, upper: ``(..., K)`` listed successors (padding ``>= N+1``), bounds.
        upper_rest: upper bound of every unlisted state (lower bound 0).

    The value is the interval LP's dual function at a threshold cost tau,

        L(tau) = tau + sum_i lower_i (c_i - tau) + sum_i (upper_i - lower_i) min(c_i - tau, 0),

    over all items i (the K listed successors and the unlisted states, ``lower = 0``,
    ``upper = upper_rest``). Weak duality makes ``L(tau)`` a lower bound of the minimum for
    *every* tau, and it equals the minimum at the greedy's threshold tau* (the smallest item cost
    whose items, with every cheaper one, hold mass ``>= 1``). tau* is searched without sorting the
    row (a per-row sort of the shifted costs was 3/4 of the time): a bisection over the sorted
    ``w`` brackets it between two consecutive values of ``w``, a bisection over real numbers
    narrows that bracket, and a walk from its lower end over the next ``_WALK_STEPS`` item costs
    stops at the first with enough mass: tau is exact unless more listed costs than that share the
    narrowed bracket. Otherwise tau is the bracket's upper end: still a valid bound, within
    (bracket width) x (total mass) of the minimum, the bracket being 2^-_REAL_BISECTIONS of a
    gap of ``w`` (or of the costs' range below the smallest ``w``).
    """
    n = w.shape[0]
    w_sorted = jnp.sort(w)
    prefix = jnp.concatenate([jnp.zeros(1, w.dtype), jnp.cumsum(w_sorted)])
    listed = succ < n
    own = jnp.where(listed, w.at[succ].get(mode="fill", fill_value=0.0), 0.0)  # listed states' w
    cost = jnp.where(listed, w_listed, 0.0)
    lo = jnp.where(listed, lower, 0.0)
    cap = jnp.where(listed, upper - lower, 0.0)
    base = lo.sum(-1)

    def unlisted_below(t, strict):  # unlisted states with cost < t (<= t)
        count = jnp.searchsorted(w_sorted, t, side="left" if strict else "right")
        own_below = listed & ((own < t[..., None]) if strict else (own <= t[..., None]))
        return count, own_below, count - jnp.sum(own_below, axis=-1)

    def listed_room(t, strict=False):  # room above the lower bounds of the listed items of cost < t (<= t)
        below = (cost < t[..., None]) if strict else (cost <= t[..., None])
        return jnp.sum(jnp.where(below, cap, 0.0), axis=-1)

    def mass(t, strict=False):  # mass held by the items of cost < t (<= t), each at its upper bound
        return base + listed_room(t, strict) + upper_rest * unlisted_below(t, strict)[2]

    def smallest_enough(_, bounds):  # over the index into w_sorted
        lo_i, hi_i = bounds
        mid = (lo_i + hi_i) // 2
        enough = mass(w_sorted[jnp.minimum(mid, n - 1)]) >= 1.0
        return jnp.where(enough, lo_i, mid + 1), jnp.where(enough, mid, hi_i)

    zeros = jnp.zeros(base.shape, jnp.int32)
    j_star = jax.lax.fori_loop(0, int(n).bit_length(), smallest_enough, (zeros, zeros + n))[1]
    # tau* lies in (w_sorted[j*-1], w_sorted[j*]]: the bracket's ends, made finite at the edges
    big = jnp.maximum(w_sorted[-1], jnp.max(jnp.where(listed, cost, -jnp.inf), axis=-1))
    small = jnp.minimum(w_sorted[0], jnp.min(jnp.where(listed, cost, jnp.inf), axis=-1)) - 1.0
    upper_end = jnp.where(j_star < n, w_sorted[jnp.minimum(j_star, n - 1)], big)
    lower_end = jnp.where(j_star > 0, w_sorted[jnp.maximum(j_star - 1, 0)], small)

    # strictly inside the bracket no value of w lies, so the unlisted states below t are the same
    # for every t there: those with w below the upper end (all of them when j* = N)
    own_inside = listed & ((own < upper_end[..., None]) | (j_star == n)[..., None])
    unlisted_inside = j_star - jnp.sum(own_inside, axis=-1)
    fixed_inside = base + upper_rest * unlisted_inside

    def narrow(_, bounds):  # keeps mass(<= a) < 1 <= mass(<= b) (when the polytope is feasible)
        a, b = bounds
        mid = a + 0.5 * (b - a)
        enough = fixed_inside + listed_room(mid) >= 1.0
        return jnp.where(enough, a, mid), jnp.where(enough, mid, b)

    a, b = jax.lax.fori_loop(0, _REAL_BISECTIONS, narrow, (lower_end, upper_end))

    def walk(_, state):  # from a, step to the cheapest item above it until it has enough mass
        a, tau, found = state
        # a listed cost, or the upper end (no w value lies strictly inside the bracket)
        step = jnp.minimum(jnp.min(jnp.where(listed & (cost > a[..., None]), cost, jnp.inf), axis=-1), upper_end)
        enough = ~found & (mass(step) >= 1.0)
        return jnp.where(found | enough, a, step), jnp.where(enough, step, tau), found | enough

    _, tau, _ = jax.lax.fori_loop(0, _WALK_STEPS, walk, (a, b, jnp.zeros(a.shape, bool)))

    below = cost < tau[..., None]
    count, own_below, _ = unlisted_below(tau, True)
    fill_listed = jnp.sum(jnp.where(below, cap * cost, 0.0), axis=-1)
    fill_unlisted = upper_rest * (prefix[count] - jnp.sum(jnp.where(own_below, own, 0.0), axis=-1))
    return (lo * cost).sum(-1) + fill_listed + fill_unlisted + (1.0 - mass(tau, True)) * tau


# -- construction helpers -----------------------------------------------------------------------
def informed_cluster_bounds(boxes: IndexBoxes, prob, rest, cells):
    """P_low, P_up ``(R, A, C)`` of every informed cluster q_c = members(c), from index boxes.

    ``members(c') inside q_c`` and ``members(c') meets q_c`` are decided per dimension on the
    index intervals (cyclic ones on periodic dimensions; the same test is exact on flat ones) and
    on the sink flags, in O(C^2 n) per row instead of comparing member lists. The sums of P_W
    (and ``rest``) are exact in fixed point and rounded outward, as Lemma 1's
    (``box_bounds._fixed_point``): P_low never above, P_up never below the exact sum.
    """
    cells = tuple(int(c) for c in np.asarray(cells))
    prob = jnp.asarray(prob)
    parts = [_box_bounds(part.start, part.length, part.sink, prob, rest, cells)
             for part in row_chunks(boxes, _BOUND_ROWS_PER_CHUNK)]
    return tuple(jnp.concatenate(p) for p in zip(*parts))


@functools.partial(jax.jit, static_argnums=(5,))
def _box_bounds(start, length, sink, prob, rest, cells):
    n_cells = jnp.asarray(cells, jnp.int32)
    # a: the reachable set c' (axis -2 after expansion), b: the cluster q_c (axis -3)
    a0, la, sa = start[..., None, :, :], length[..., None, :, :], sink[..., None, :]
    b0, lb, sb = start[..., :, None, :], length[..., :, None, :], sink[..., :, None]
    empty_a = jnp.any(la == 0, axis=-1)
    empty_b = jnp.any(lb == 0, axis=-1)
    # starts lie in [0, cells), so a0 - b0 lies in (-cells, cells): one conditional wrap instead
    # of an integer modulo (half the time of this O(C^2 n) test on the 4-room temperature row)
    diff = a0 - b0
    d_ab = jnp.where(diff < 0, diff + n_cells, diff)
    d_ba = jnp.where(diff > 0, n_cells - diff, -diff)
    inside_dim = (lb >= n_cells) | ((la <= lb) & (d_ab + la <= lb))
    meet_dim = (la >= n_cells) | (lb >= n_cells) | (d_ab < lb) | (d_ba < la)
    grid_inside = empty_a | (~empty_b & jnp.all(inside_dim, axis=-1))
    grid_meet = ~empty_a & ~empty_b & jnp.all(meet_dim, axis=-1)
    inside = grid_inside & (~sa | sb)
    meets = grid_meet | (sa & sb)
    return _exact_sums(inside, meets, prob, rest)


def _exact_sums(inside, meets, prob, rest):
    """``(sum of prob where inside, sum where meets + rest)`` over the last axis, summed exactly in
    fixed point and rounded outward (down and up)."""
    low = jnp.sum(jnp.where(inside, _fixed_point(prob, False), 0), axis=-1)
    up = jnp.sum(jnp.where(meets, _fixed_point(prob, True), 0), axis=-1) + _fixed_point(rest, True)
    return _to_float(low, False), _to_float(up, True)


def member_cluster_bounds(members, clusters, prob, rest, sentinel):
    """P_low, P_up ``(R, A, E)`` of arbitrary clusters ``(R, A, E, L)`` (state ids, padding
    ``sentinel``) from the member lists ``(R, A, C, K)`` of the reachable sets (sums rounded
    outward as ``informed_cluster_bounds``')."""
    lows, ups = [], []
    for start in range(0, members.shape[0], _BOUND_ROWS_PER_CHUNK):
        m = members[start:start + _BOUND_ROWS_PER_CHUNK]
        q = clusters[start:start + _BOUND_ROWS_PER_CHUNK]
        # hit[r, a, e, c, k]: member k of reachable set c lies in cluster e
        hit = np.any(m[:, :, None, :, :, None] == np.where(q < sentinel, q, -1)[:, :, :, None, None, :], axis=-1)
        real = (m < sentinel)[:, :, None]
        inside = np.all(hit | ~real, axis=-1) & np.any(q < sentinel, axis=-1)[..., None]
        meets = np.any(hit & real, axis=-1)
        low, up = _exact_sums(inside, meets, prob, rest)
        lows.append(np.asarray(low))
        ups.append(np.asarray(up))
    return np.concatenate(lows), np.concatenate(ups)


def _extend_successors(succ, lower, upper, extra, rest, sentinel):
    """Add every member of the extra clusters to the successor lists (bounds ``[0, rest]``)."""
    r, a, k = succ.shape
    both = np.concatenate([succ, extra.reshape(r, a, -1)], axis=-1)
    both = np.sort(both, axis=-1)
    first = np.concatenate([np.ones_like(both[..., :1], bool), both[..., 1:] != both[..., :-1]], axis=-1)
    first &= both < sentinel
    width = max(int(first.sum(-1).max(initial=0)), 1)
    order = np.argsort(~first, axis=-1, kind="stable")[..., :width]
    new = np.where(np.take_along_axis(first, order, -1), np.take_along_axis(both, order, -1), sentinel)
    slot = _slots_of(new, succ[..., None, :], sentinel)[..., 0, :]  # old slot -> new slot
    new_lower = np.zeros(new.shape)
    new_upper = np.where(new < sentinel, float(rest), 0.0)
    rr, aa = np.meshgrid(np.arange(r), np.arange(a), indexing="ij")
    keep = slot < width
    new_lower[rr[..., None].repeat(k, -1)[keep], aa[..., None].repeat(k, -1)[keep], slot[keep]] = lower[keep]
    new_upper[rr[..., None].repeat(k, -1)[keep], aa[..., None].repeat(k, -1)[keep], slot[keep]] = upper[keep]
    return new.astype(np.int32), new_lower, new_upper


def _slots_of(succ, ids, sentinel):
    """Positions of the state ids ``(R, A, C, L)`` in the sorted successor lists ``(R, A, K)``
    (``K`` for padding).

    Through a table of every state's position, a block of lists at a time: each list writes its
    positions, each id reads one (a binary search over all lists took 14 of the 113 s of the 3-D
    unicycle's MI-MDP, row 19). The table is never cleared: an id a list does not hold reads a
    stale or unset entry, and the check that the list holds the id at that position rejects it."""
    r, a, k = succ.shape
    flat_succ = succ.reshape(r * a, k)
    q = ids.reshape(r * a, -1)
    width = sentinel + 1  # ids 0..sentinel - 1, and a column for the padding of the lists
    per = max(1, min(r * a, _SLOT_TABLE_ENTRIES // width))
    table = np.empty((per, width), np.int32)
    pos = np.empty(q.shape, np.int64)
    for first in range(0, r * a, per):
        last = min(first + per, r * a)
        lists = np.minimum(flat_succ[first:last], sentinel).astype(np.int64)
        rows = np.arange(last - first)[:, None]
        table[rows, lists] = np.arange(k, dtype=np.int32)
        pos[first:last] = table[rows, np.minimum(q[first:last], sentinel).astype(np.int64)]
    pos = np.clip(pos, 0, k - 1)
    found = (q < sentinel) & (np.take_along_axis(flat_succ, pos, axis=1) == q)
    if np.any((q < sentinel) & ~found):
        raise AssertionError("a cluster member is missing from the successor list")
    return np.where(found, pos, k).reshape(ids.shape)


def _concat_padded(pieces, k):
    """Concatenate per-chunk ``(slots, lo, up)`` of ``_distinct_clusters`` along rows, padding the
    cluster count and size to the widest chunk's (padding: empty clusters, bounds [0, 1])."""
    j = max(p[0].shape[2] for p in pieces)
    size = max(p[0].shape[3] for p in pieces)
    out = ([], [], [])
    for slots, lo, up in pieces:
        dj, ds = j - slots.shape[2], size - slots.shape[3]
        out[0].append(np.pad(slots, [(0, 0), (0, 0), (0, dj), (0, ds)], constant_values=k))
        out[1].append(np.pad(lo, [(0, 0), (0, 0), (0, dj)], constant_values=0.0))
        out[2].append(np.pad(up, [(0, 0), (0, 0), (0, dj)], constant_values=1.0))
    return tuple(np.concatenate(parts) for parts in out)


def _distinct_clusters(slots, lo, up, k):
    """Drop clusters of at most one state and repeated clusters of a row; compact to ``J``."""
    r, a, c, size = slots.shape
    slots = np.sort(slots, axis=-1)
    count = (slots < k).sum(-1)
    flat = slots.reshape(r * a * c, size)
    group = np.repeat(np.arange(r * a), c)
    order, repeat = _grouped_order(flat, group)
    duplicate = np.zeros(flat.shape[0], bool)
    duplicate[order[1:]] = repeat
    keep = (count.ravel() >= 2) & ~duplicate
    keep = keep.reshape(r, a, c)
    j = int(keep.sum(-1).max(initial=0))
    size_kept = int(np.where(keep, count, 0).max(initial=0))
    pick = np.argsort(~keep, axis=-1, kind="stable")[..., :j]
    kept = np.take_along_axis(keep, pick, -1)
    slots = np.where(kept[..., None], np.take_along_axis(slots, pick[..., None], 2), k)[..., :max(size_kept, 1)]
    lo = np.where(kept, np.take_along_axis(lo, pick, -1), 0.0)
    up = np.where(kept, np.take_along_axis(up, pick, -1), 1.0)
    return slots, lo, up


def _grouped_order(rows, group, weights=None):
    """``(order (M,), repeat (M - 1,))``: a stable order of ``rows (M, S)`` (integers) by ``group
    (M,)`` in which equal rows of a group are adjacent, and whether each row in that order after
    the first equals the one before it in the same group.

    Sorted by a 64-bit hash of each row (a product with random odd weights, modulo 2^64) instead
    of by all ``S`` columns: a lexicographic sort over the 76 member positions of the 3-D
    unicycle's clusters took 12 of the 113 s of its MI-MDP (row 19). Equal rows have equal
    hashes, so they are adjacent unless rows with another content share their hash; that is
    checked, and then the rows are sorted by all columns. ``weights``: ``(S,)`` uint64 (tests)."""
    if weights is None:
        weights = np.random.default_rng(0).integers(1, 2 ** 63, size=rows.shape[1], dtype=np.uint64) | np.uint64(1)
    key = np.zeros(rows.shape[0], np.uint64)
    for i in range(rows.shape[1]):  # one column at a time: no (M, S) uint64 temporary
        key += rows[:, i].astype(np.uint64) * weights[i]

    def adjacent(order):  # (same group, same row) of each row in ``order`` and the one before it
        g, r = group[order], rows[order]
        same_group = g[1:] == g[:-1]
        return same_group, same_group & np.all(r[1:] == r[:-1], axis=1)

    order = np.lexsort((key, group))
    same_group, repeat = adjacent(order)
    if np.any(same_group & (key[order][1:] == key[order][:-1]) & ~repeat):  # a collision
        order = np.lexsort(tuple(rows[:, i] for i in range(rows.shape[1] - 1, -1, -1)) + (group,))
        repeat = adjacent(order)[1]
    return order, repeat
