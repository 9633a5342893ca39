"""Robust dynamic programming (the paper's RDP, Proposition 1) for any abstraction class.

The abstraction supplies the inner problem (``q_values``); this module supplies the outer
structure, all of it inside ``lax.while_loop`` / ``lax.scan`` under ``jit``:

* ``optimize_lower``: p_low^{k+1}(s) = max_a min_{gamma in Gamma_{s,a}} sum gamma(s') p_low^k(s'),
  iterated from p^0 = 1_{S_reach}, each such greedy backup followed by a few cheap backups of the
  greedy strategy alone (modified policy iteration). Iterates increase monotonically to p_low, so
  every iterate is a valid lower bound. The stationary strategy keeps its previous action unless
  another action is strictly better: an action is then only chosen when it raised the value,
  which rules out strategies that idle forever in a loop of equal values.
* ``evaluate``: the lower (adversary minimizes) or upper (adversary maximizes) value of a fixed
  strategy. The lower one, iterated from p^0, certifies the synthesized strategy (it is what the
  controller achieves at worst). The upper one is iterated from above, from ``top_values``
  (1 on every state that is not avoided): the Bellman operator is monotone, so iterates from
  any upper bound stay upper bounds of the least fixed point, and stopping early is sound.
  (From above, iterates approach the greatest fixed point; with unbounded noise the remainder
  cell reaches a value-1 state from everywhere, which makes the fixed point unique.)
* ``finite_horizon``: exactly T backups, a time-dependent strategy, lower and upper together.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .compiler import backup_jit


def _set_rows(v, rows, values):
    return _replicated(v.at[rows].set(values), rows)


def _replicated(v, rows):
    """Pin ``v`` to a full copy on every device when the rows are sharded (``smdpjax.sharding``).

    Each device then computes its rows' backups against the whole value vector, and the
    sorts and prefix sums over ``v`` are never split (which would change their rounding). A
    no-op for an abstraction on one device.
    """
    typeof = getattr(jax, "typeof", None)  # jax >= 0.5; older jax: leave it to the partitioner
    mesh = getattr(getattr(typeof(rows), "sharding", None), "mesh", None) if typeof is not None else None
    if mesh is None or mesh.empty or mesh.size <= 1:
        return v
    return jax.lax.with_sharding_constraint(v, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))


# A freezable class (the MI-MDP) sweeps with frozen multipliers, refrozen every SWEEPS_PER_FREEZE
# sweeps (one LP per row each time), FROZEN_SWEEPS sweeps per greedy backup by default. On the 2-D
# unicycle at 30x30 (8 actions, HiGHS; one cold synthesis each) 32 sweeps refrozen every 8 took
# 41 s; 64 sweeps, or refreezing every 4 or 16, 48-50 s. ``benchmarks/mimdp_freeze.py``: 32.6 s
# against 86.2 s for 8 sweeps with an LP per row each (medians of 2 warm runs).
FROZEN_SWEEPS = 32
SWEEPS_PER_FREEZE = 8
# The first round of sweeps starts from the greedy backup's own multipliers for the strategy's
# actions rather than refreezing at once: on Table 1 row 3 (benchmarks/mimdp_switch.py, medians
# of 3 alternating) 78 against 97 LP calls, 32 999 against 38 507 HiGHS solves, T_syn 37.9 against 40.5 s.
REUSE_GREEDY_MULTIPLIERS = True


# The strategy sweeps after a greedy backup stop once a sweep changes no value by more than
# SWEEP_STOP times that backup's change. Table 1's rows, one cold synthesis each against every
# sweep run: the 3-D unicycle's 2I-MDP rows 1.48-1.57x faster (row 18 112.1 -> 75.7 s), the 2-D
# rows 0.87-1.09x (row 14 43.9 -> 50.3 s: more greedy backups); docs/performance.md.
SWEEP_STOP = 0.25


def default_policy_sweeps(abstraction) -> int:
    """Policy sweeps per greedy backup when ``policy_sweeps=None``: ``|A|`` (none with one action),
    ``FROZEN_SWEEPS`` for a ``freezable`` class, whose sweeps need no solver call."""
    if abstraction.num_actions == 1:
        return 0
    return FROZEN_SWEEPS if abstraction.freezable else abstraction.num_actions


@backup_jit(static_argnames=("max_iterations", "policy_sweeps"))
def optimize_lower(abstraction, v0, tol, max_iterations: int, policy0=None, policy_sweeps: int | None = None,
                   sweep_stop=SWEEP_STOP):
    """Returns ``(p_low (N+1,), policy over rows (R,), backups, last change)``.

    ``v0`` must lie below p_low with ``v0 <= T(v0)`` (p^0 does; so does the value of a relaxation,
    an abstraction whose ambiguity sets contain this one's). ``policy0``: initial strategy.

    Each iteration is one greedy backup ``T`` (every action; its change is what is compared with
    ``tol``, at most ``max_iterations`` of them) followed, unless it converged, by
    ``policy_sweeps`` backups ``T_pi`` of the greedy strategy pi alone (modified policy
    iteration; default: the number of actions, which costs about one greedy backup, and none
    with one action). They are sound and only speed things up: with ``v <= v*`` and
    ``v <= T(v) = T_pi(v)``, the sweeps rise monotonically (``T_pi`` is monotone), stay below
    ``v*`` (``T_pi <= T``), keep ``v <= T(v)``, and stay above plain value iteration's iterates;
    what they skip is the slow propagation of values along the strategy, which costs ``|A|`` times
    less without the maximization. ``backups`` counts both kinds (the rounding allowance grows
    with each). The sweeps of an iteration stop early once one changes no value by more than
    ``sweep_stop`` times the greedy backup's change (0: always all of them): the values have
    then settled along the strategy, and what is left to gain needs a better strategy. A
    ``freezable`` abstraction always runs its ``policy_sweeps``, with its frozen operator
    ``T_lambda`` (refrozen every ``SWEEPS_PER_FREEZE`` sweeps): monotone and below ``T_pi``, so
    the sweeps stay below ``v*`` just the same, and they cost no solver call. The first round
    freezes the multipliers the greedy backup solved for (``greedy_backup``; exact at the values
    it backed up) instead of solving the strategy's LPs again.
    """
    rows = abstraction.rows
    sweeps = default_policy_sweeps(abstraction) if policy_sweeps is None else int(policy_sweeps)

    def follow(policy, v, delta, lam=None):
        fixed = abstraction.restrict(policy)  # once per iteration, not per sweep
        sweep = lambda op: (lambda _, w: _set_rows(w, rows, op.q_values(w, "min")[:, 0]))
        if not abstraction.freezable:
            def go_on(state):
                i, _, change = state
                return (i < sweeps) & (change >= sweep_stop * delta)

            def once(state):
                i, w, _ = state
                w_new = sweep(fixed)(i, w)
                return i + 1, w_new, jnp.max(jnp.abs(w_new - w))

            swept, w, _ = jax.lax.while_loop(go_on, once, (jnp.int32(0), v, jnp.asarray(jnp.inf, v.dtype)))
            return w, swept

        def chunk(_, carry):  # refreeze at the current values (keeping the better multipliers)
            frozen, w = carry
            frozen = frozen.freeze(w, "min")
            return frozen, jax.lax.fori_loop(0, SWEEPS_PER_FREEZE, sweep(frozen), w)

        rounds, extra = divmod(sweeps, SWEEPS_PER_FREEZE)
        if lam is not None and rounds:
            # the first round sweeps with the greedy backup's multipliers of the strategy's
            # actions, exact at the values it backed up (no LP call)
            frozen = fixed.from_multipliers(jnp.take_along_axis(lam, policy[:, None, None, None], axis=1))
            w = jax.lax.fori_loop(0, SWEEPS_PER_FREEZE, sweep(frozen), v)
            frozen, w = jax.lax.fori_loop(1, rounds, chunk, (frozen, w))
        else:
            frozen, w = jax.lax.fori_loop(0, rounds, chunk, (fixed.frozen_at_zero(), v))
        if extra:
            frozen = frozen.freeze(w, "min")
            w = jax.lax.fori_loop(0, extra, sweep(frozen), w)
        return w, jnp.int32(sweeps)

    def body(state):
        k, backups, v, policy, _ = state
        if abstraction.freezable and REUSE_GREEDY_MULTIPLIERS:
            q, lam = abstraction.greedy_backup(v)  # (R, A), (R, A, J, 2) or None
        else:
            q, lam = abstraction.greedy_q_values(v), None
        best = q.max(axis=1)
        kept = jnp.take_along_axis(q, policy[:, None], axis=1)[:, 0]
        policy = jnp.where(kept >= best, policy, jnp.argmax(q, axis=1).astype(jnp.int32))
        v_new = _set_rows(v, rows, best)
        delta = jnp.max(jnp.abs(v_new - v))
        if sweeps:
            go_on = delta > tol
            v_new, swept = jax.lax.cond(go_on, follow, lambda _, w, __, ___: (w, jnp.int32(0)), policy, v_new, delta,
                                        lam)
            backups = backups + swept
        return k + 1, backups + 1, v_new, policy, delta

    def cond(state):
        k, _, _, _, delta = state
        return (delta > tol) & (k < max_iterations)

    policy0 = jnp.zeros(rows.shape, jnp.int32) if policy0 is None else policy0
    init = (jnp.int32(0), jnp.int32(0), v0, policy0, jnp.asarray(jnp.inf, v0.dtype))
    _, backups, v, policy, delta = jax.lax.while_loop(cond, body, init)
    return v, policy, backups, delta


def top_values(abstraction):
    """``(N+1,)`` the trivial upper bound of every reach-avoid value: 1 except on avoided states
    (avoid cells and the sink, which are absorbing with value 0)."""
    return abstraction.initial_values("safety")


@backup_jit(static_argnames=("adversary", "max_iterations"))
def evaluate(abstraction, v0, adversary: str, tol, max_iterations: int):
    """Value of a single-action abstraction (a strategy already applied, see ``restrict``) against
    a minimizing or maximizing adversary, iterated from ``v0``: ``(values, iterations, change)``.

    From a ``v0`` below the least fixed point with ``v0 <= T(v0)`` (p^0) iterates rise to it and
    are lower bounds; from a ``v0`` above it (``top_values``) every iterate is an upper bound.

    Every backup here is exact (a ``freezable`` class solves its LPs each time): iterating a
    frozen operator stalls, because the Lagrangian bound with the multipliers of the values ``v``
    is kinked at ``v`` (its minimizer is not unique there), so it gains almost nothing beyond
    the backup it was frozen at. Measured: verifying a strategy with refreezing rounds took 2530
    LPs against 2645 with an LP per backup (4-action unicycle, 12x12).
    """
    rows = abstraction.rows

    def body(state):
        k, v, _ = state
        v_new = _set_rows(v, rows, abstraction.q_values(v, adversary)[:, 0])
        return k + 1, v_new, jnp.max(jnp.abs(v_new - v))

    def cond(state):
        k, _, delta = state
        return (delta > tol) & (k < max_iterations)

    k, v, delta = jax.lax.while_loop(cond, body, (jnp.int32(0), v0, jnp.asarray(jnp.inf, v0.dtype)))
    return v, k, delta


# Backups ``certified_start`` runs at most from one start: a row deep inside the safe set gains
# only through the margin of the states its paths reach, which one backup does not show.
CERTIFY_STEPS = 64


@backup_jit(static_argnames=("max_steps",))
def certified_start(abstraction, candidate, v0, slack, margin, max_steps: int = CERTIFY_STEPS):
    """A start for ``evaluate(..., "min")`` from a guess of the pessimistic value, if it is
    provably below it: ``(start (N+1,), certified bool, backups run)``, for a single-action
    abstraction.

    ``start`` is ``candidate - margin`` clipped to [0, 1] on the rows and ``v0`` elsewhere. It is
    certified when every row with ``start > 0`` gains strictly within some number ``j <=
    max_steps`` of backups (its own ``j``): the j-th computed iterate from ``start``, less ``j``
    times ``slack`` (the rounding bound of one backup), is still ``>= start`` there, so the exact
    operator T has ``T^j(start) > start`` at that row. Then ``start`` lies below the least fixed
    point v* (the strategy's true value): let sigma be the adversary's minimizing choice at v*,
    so that ``T(x) <= sigma x`` for every x and ``sigma v* = v*``, and let d = start - v*, which is
    <= 0 on terminal states. If M = max d > 0, take a row s with d(s) = M; start(s) > 0, so
    start(s) < T^j(start)(s) <= (sigma^j start)(s), i.e. d(s) < (sigma^j d)(s) <= M: a
    contradiction. (Strictness is what rules out a strategy that idles in a loop: there no state
    can gain. Several backups are what certify rows whose one-step mass to terminal states is
    too small for the margin to show within the rounding bound.) The iterations stop as soon as
    every row is certified, or at a backup that certifies no further row.
    """
    rows = abstraction.rows
    start = v0.at[rows].set(jnp.clip(candidate[rows] - margin, 0.0, 1.0))
    pending = start[rows] > 0.0

    def cond(state):
        j, _, pending, progress = state
        return (j < max_steps) & progress & jnp.any(pending)

    def body(state):
        j, y, pending, _ = state
        y = _set_rows(y, rows, abstraction.q_values(y, "min")[:, 0])
        j = j + 1
        still = pending & (y[rows] - j.astype(y.dtype) * slack < start[rows])
        return j, y, still, jnp.sum(still) < jnp.sum(pending)

    init = (jnp.int32(0), start, pending, jnp.asarray(True))
    steps, _, pending, _ = jax.lax.while_loop(cond, body, init)
    return start, ~jnp.any(pending), steps


# Margins tried below the guess, in units of the backup's rounding bound, while they stay under
# ``tol`` (the first is always tried), then ``tol`` itself, then ``tol`` times BEYOND_TOL: rows
# whose value has stopped changing gain under a backup only through the margin, scaled by their
# probability of reaching a terminal state, so the largest margin is often the only one that
# passes, and on slowly leaking rows even ``tol`` can fall short of the optimization's last
# rounding (row 3 of Table 1 in an earlier run: 26 of 767 rows by ~1e-11). A margin beyond
# ``tol`` costs at most that much of the start's height, where the cold start it avoids stops
# when a backup changes less than ``tol``, as far as ``tol / leak`` below the fixed point on
# exactly those rows (and took 1746 LP backups on row 7 in that run).
WARM_MARGINS = tuple(10.0 ** k for k in range(2, 13))
BEYOND_TOL = (10.0, 100.0)


def warm_margins(slack, tol):
    """The margins ``warm_start`` tries, in order: ``slack * WARM_MARGINS`` up to ``tol``, then
    ``tol`` (all of them capped at ``tol`` except the first), then ``tol * BEYOND_TOL``; an entry
    that does not exceed every earlier one is skipped."""
    dtype = jnp.result_type(slack, tol)
    ladder = slack * jnp.asarray(WARM_MARGINS + (jnp.inf,), dtype)
    capped = jnp.concatenate([ladder[:1], jnp.minimum(ladder[1:], tol)])
    return jnp.concatenate([capped, tol * jnp.asarray(BEYOND_TOL, dtype)])


@backup_jit
def warm_start(abstraction, guess, v0, slack, tol):
    """``certified_start`` with the first margin of ``warm_margins(slack, tol)`` that passes.

    Returns ``(start, certified, backups spent)``; ``start`` is ``v0`` when none passes.
    """
    margins = warm_margins(slack, tol).astype(v0.dtype)
    last = margins.shape[0] - 1

    def cond(state):
        i, _, done, _, _ = state
        return ~done & (i <= last)

    def body(state):
        i, _, _, spent, highest = state
        margin = margins[i]
        fresh = (i == 0) | (margin > highest)
        start, ok, steps = jax.lax.cond(fresh, lambda: certified_start(abstraction, guess, v0, slack, margin),
                                        lambda: (v0, jnp.asarray(False), jnp.int32(0)))
        return i + 1, jnp.where(ok, start, v0), ok, spent + steps, jnp.maximum(highest, margin)

    init = (jnp.int32(0), v0, jnp.asarray(False), jnp.int32(0), margins[0])
    _, start, certified, spent, _ = jax.lax.while_loop(cond, body, init)
    return start, certified, spent


# Rounding of one optimistic backup of a stationary strategy over a finite horizon beyond the
# abstraction's own (``rounding_per_backup``): ``1 - v`` and ``1 - min`` round once each, by at most
# 2^-53 for values in [0, 1].
COMPLEMENT_ROUNDING = 2.0 ** -52


@backup_jit(static_argnames=("horizon", "with_upper"))
def finite_horizon(abstraction, v0, horizon: int, policy=None, with_upper: bool = True):
    """T = ``horizon`` backups. ``policy``: ``None`` (optimized, time-dependent), ``(R,)``
    (stationary) or ``(T, R)`` (``policy[t]`` is the action at time t).

    Returns ``(lower, upper, policy (T, R))`` where ``policy[t]`` is the action at time t
    (``t = 0`` is the first step, i.e. the last backup). ``with_upper=False`` (optimized
    strategy only) skips the maximizing adversary's backups and returns ``top_values`` as
    ``upper``, the trivial bound. With a stationary ``policy``, a bound that one backup leaves
    unchanged bit for bit is not backed up again (the result is the same), and the optimistic
    backup is ``1 - min <gamma, 1 - v>``, whose rounding exceeds ``rounding_per_backup`` by
    ``COMPLEMENT_ROUNDING`` per backup (the caller widens ``upper`` by that too).
    """
    rows = abstraction.rows
    if policy is None:
        steps = None
    elif policy.ndim == 1:
        steps = jnp.broadcast_to(policy, (horizon, *policy.shape))
    else:
        steps = policy[::-1]  # backups run from the last time step to the first

    if horizon == 0:
        return v0, v0, jnp.zeros((0, *rows.shape), jnp.int32)
    if steps is not None and policy.ndim == 1:
        # A stationary strategy: once a backup leaves a bound v unchanged bit for bit, it is not
        # run again. v is then a bound at every later step too (v = T~(v) <= T(v) + e for the
        # lower bound, T monotone and non-expansive; the rounding allowance still counts every
        # step), and a deterministic backup would return v again anyway. The optimistic bounds of
        # the temperature rows settle after one of 15 steps. The strategy's actions are picked
        # once, not in every backup; with one action there is nothing to pick.
        fixed = abstraction if abstraction.num_actions == 1 else abstraction.restrict(policy)

        def backup(v, adversary):
            if adversary == "min":
                return _set_rows(v, rows, fixed.q_values(v, "min")[:, 0])
            # max_gamma <gamma, v> = 1 - min_gamma <gamma, 1 - v> (every gamma sums to 1): exactly 1
            # where a row can keep all its mass on states of value 1, where the sum of the masses
            # times 1 rounds to 1 +- 1 ulp and would never settle (COMPLEMENT_ROUNDING)
            return _set_rows(v, rows, 1.0 - fixed.q_values(1.0 - v, "min")[:, 0])

        def settling(v, adversary, settled):
            new = jax.lax.cond(settled, lambda: v, lambda: backup(v, adversary))
            return new, settled | jnp.all(new == v)

        def step(carry, _):
            lo, up, lo_settled, up_settled = carry
            lo, lo_settled = settling(lo, "min", lo_settled)
            up, up_settled = settling(up, "max", up_settled)
            return (lo, up, lo_settled, up_settled), None

        unsettled = jnp.asarray(False)
        (lo, up, _, _), _ = jax.lax.scan(step, (v0, v0, unsettled, unsettled), None, length=horizon)
        return lo, up, steps
    if steps is not None:
        def step(carry, act):
            lo, up = carry
            lo_rows = abstraction.q_values(lo, "min", act)
            up_rows = abstraction.q_values(up, "max", act)
            return (_set_rows(lo, rows, lo_rows), _set_rows(up, rows, up_rows)), act

        (lo, up), actions = jax.lax.scan(step, (v0, v0), steps, length=horizon)
        return lo, up, actions[::-1]

    def greedy(lo):  # one robust backup of the lower bound and the action it picks per row
        q = abstraction.greedy_q_values(lo)
        return _set_rows(lo, rows, q.max(axis=1)), jnp.argmax(q, axis=1).astype(jnp.int32)

    if not with_upper:
        lo, actions = jax.lax.scan(lambda lo, _: greedy(lo), v0, None, length=horizon)
        return lo, top_values(abstraction), actions[::-1]

    # Optimized strategy: the upper backup of time step t needs the action chosen by the lower
    # backup of step t, so it runs one iteration later, beside the next lower backup; the two
    # are then independent and XLA can run them concurrently (on 2 cores, 100 steps of the
    # models of benchmarks/storm_peer.py: 7-30% less wall time, none on the smallest one).
    def step(carry, first):
        lo, up, previous = carry
        lo_next, act = greedy(lo)
        up_next = _set_rows(up, rows, abstraction.q_values(up, "max", previous))
        up = jnp.where(first, up, up_next)  # no action yet at the first step
        return (lo_next, up, act), act

    first = jnp.arange(horizon) == 0
    start = (v0, v0, jnp.zeros(rows.shape, jnp.int32))
    (lo, up, last), actions = jax.lax.scan(step, start, first, length=horizon)
    up = _set_rows(up, rows, abstraction.q_values(up, "max", last))
    return lo, up, actions[::-1]
