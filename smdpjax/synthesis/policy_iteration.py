"""Robust policy iteration: strategies improved by greedy backups, each evaluated by linear solves.

Value iteration (``value_iteration.optimize_lower``) moves the lower bound up by backups, and on a
class whose backups call a solver each backup is dear: the MI-MDP of Table 1 row 3 needs 18
greedy backups and 576 strategy sweeps to settle within 1e-6, because probability mass
propagates slowly along long paths. Policy iteration evaluates each strategy exactly instead:

* **improvement**: one greedy backup at the current strategy's value ``v``, which solves the LPs
  of the current actions and of the actions whose screen value exceeds ``v`` only
  (``greedy_backup(v, floor, current)``); a row switches to its best action only where that
  gains more than ``IMPROVEMENT * tol`` over the current action's certified value (the solver's
  values carry its tolerances, and the chain's values can lie below the certified ones, see
  ``MIMDP.worst_case_transitions``; a switch on a tie could start an idle loop);
* **evaluation** against the adversary (minimizing, for the lower bound) by its own policy
  iteration: fix the adversary's optimal distributions at ``v`` (``worst_case_transitions``: the
  MI-MDP's LP vertices), solve the Markov chain they define for its reach probabilities
  (``reach_values``, one sparse linear system), and repeat at the new values until they change
  by at most ``IMPROVEMENT * tol``. The adversary's values fall monotonically to the strategy's
  robust value (each new distribution is optimal at the previous values).

It stops when a greedy backup gains at most ``tol`` over every current action's certified value.
The values it carries are **not lower bounds**: a fixed adversary's value lies above the robust
one until the adversary's iteration has converged, and a solver's vertex satisfies the
constraints only to its tolerances (and its surrogate LP's, see ``worst_case_transitions``).
``synthesize`` therefore uses them as a guess: the strategy's lower bound is
certified from below (``value_iteration.warm_start``, then ``evaluate``), exactly as it does for
value iteration's last iterate, and ``Solution.lower_optimal`` reports only certified bounds.
"""

from __future__ import annotations

import numpy as np

from .compiler import backup_jit

# A row switches action only when the greedy backup gains more than this times ``tol`` over its
# current action's value, and an evaluation stops once the adversary's iteration changes no value
# by more than this times ``tol``.
IMPROVEMENT = 1e-3
# ``synthesize`` starts policy iteration from the relaxation's value iteration stopped at this
# tolerance (or ``tol`` if looser): the start only has to be good, not tight (Table 1 row 7: the
# IMDP's 5.5 s at 1e-6 against 3.0 s at 1e-3, with the same 9 greedy backups after it).
START_TOL = 1e-3
# Adversary steps (linear solves) per evaluation, at most; and an evaluation also stops after this
# many steps in a row that did not bring the largest change below its smallest so far (a solver
# whose points are optimal only to its tolerances, such as an interior point method, leaves noise
# of that size, which no step removes).
MAX_ADVERSARY_STEPS = 64
STALLED_STEPS = 3
# A chain's linear system is solved by BiCGSTAB from the previous values where there are some
# (Table 1 row 7: ~30 iterations, 12 ms against SuperLU's 76 ms, same values to 1e-14), and by
# SuperLU when that does not bring the largest residual down to RESIDUAL_TOL within KRYLOV_STEPS.
KRYLOV_STEPS = 500
RESIDUAL_TOL = 1e-12
# Greedy backups after the first solve only the LPs of the strategy's actions and of the actions
# that may beat its value by more than IMPROVEMENT * tol (by the class's screen)
# (benchmarks/mimdp_switch.py).
SCREEN_BY_STRATEGY_VALUE = True


def supports(abstraction) -> bool:
    """Whether ``abstraction`` offers the adversary's optimal distributions (``worst_case_transitions``)."""
    return callable(getattr(abstraction, "worst_case_transitions", None))


def preferred(abstraction) -> bool:
    """Whether ``synthesize`` uses policy iteration by default: supported, and the class's
    distributions are exact vertices (``exact_transitions``; the MI-MDP's with HiGHS)."""
    return supports(abstraction) and bool(getattr(abstraction, "exact_transitions", True))


def reach_values(transitions, rows, terminal, guess=None):
    """Values of the Markov chain whose state ``rows[r]`` moves by ``transitions[r]``.

    Args:
        transitions: ``(R, N+1)`` SciPy sparse matrix, row ``r`` the distribution from state
            ``rows[r]`` (rows repeated in ``rows`` must repeat their distribution).
        rows: ``(R,)`` the non-terminal states.
        terminal: ``(N+1,)`` values of the absorbing states (1 on reach cells, 0 on avoid cells
            and the sink); its entries at ``rows`` are ignored.
        guess: ``(N+1,)`` optional values close to the solution (the previous chain's): the
            system is then solved iteratively from them (BiCGSTAB), directly (SuperLU) if that
            leaves a residual above ``RESIDUAL_TOL``.
    Returns:
        ``(N+1,)`` float64: ``terminal`` on absorbing states and, on ``rows``, the expected terminal
        value reached, ``x = P_rows x + P_terminal terminal``: 0 where no state of positive value
        can be reached (found on the graph, which keeps the linear system nonsingular), else the
        solution of the sparse system, clipped to ``[0, 1]``.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order

    rows = np.asarray(rows, np.int64)
    terminal = np.asarray(terminal, np.float64)
    n = terminal.size
    rows, first = np.unique(rows, return_index=True)  # sharding repeats the last row
    p = sp.csr_matrix(transitions)[first]
    is_row = np.zeros(n, bool)
    is_row[rows] = True
    # states that reach a positive terminal state: search from a virtual node n along reversed edges
    coo = p.tocoo()
    positive = coo.data > 0
    sources = np.flatnonzero(~is_row & (terminal > 0))
    graph = sp.csr_matrix((np.ones(int(positive.sum()) + sources.size),
                           (np.concatenate([coo.col[positive], np.full(sources.size, n)]),
                            np.concatenate([rows[coo.row[positive]], sources]))), shape=(n + 1, n + 1))
    reaching = np.zeros(n + 1, bool)
    reaching[breadth_first_order(graph, n, directed=True, return_predecessors=False)] = True
    keep = reaching[rows]
    values = terminal.copy()
    values[rows] = 0.0
    if keep.any():
        live = rows[keep]
        pk = p[keep]
        fixed = pk @ np.where(is_row, 0.0, terminal)
        system = sp.identity(live.size, format="csr") - pk[:, live]
        values[live] = np.clip(_solve(system, fixed, None if guess is None else np.asarray(guess, np.float64)[live]),
                               0.0, 1.0)
    return values


def _solve(system, rhs, x0):
    """``system^-1 rhs``: BiCGSTAB from ``x0`` where given and good enough, else SuperLU."""
    from scipy.sparse.linalg import bicgstab, spsolve

    if x0 is not None:
        x, info = bicgstab(system, rhs, x0=x0, rtol=0.0, atol=0.1 * RESIDUAL_TOL, maxiter=KRYLOV_STEPS)
        if info == 0 and np.all(np.isfinite(x)) and np.max(np.abs(rhs - system @ x), initial=0.0) <= RESIDUAL_TOL:
            return x
    return spsolve(system.tocsc(), rhs)


@backup_jit
def _greedy(abstraction, v, floor, current):
    return abstraction.greedy_backup(v, floor, current)[0]


def optimize(abstraction, start, terminal, tol: float, max_iterations: int, policy0=None):
    """Policy iteration from ``start`` (any values; the relaxation's lower bound is a good one).

    Args:
        abstraction: a class with ``worst_case_transitions`` (see ``supports``).
        start: ``(N+1,)`` initial values; ``terminal``: ``(N+1,)`` values of the absorbing states
            (``initial_values``).
        tol: stop once a greedy backup gains at most ``tol`` on every row.
        max_iterations: greedy backups at most.
        policy0: ``(R,)`` initial strategy (default action 0).
    Returns:
        ``(guess (N+1,), policy (R,), greedy backups, adversary steps, converged)``, or ``None``
        where some LP ended without an optimum (no distribution to evaluate with; the caller
        falls back to value iteration). ``guess`` is the last strategy's value against its
        adversary: not a certified bound (see the module docstring).
    """
    rows = np.asarray(abstraction.rows, np.int64)
    order = np.arange(rows.size)
    v = np.asarray(start, np.float64)
    policy = np.zeros(rows.size, np.int64) if policy0 is None else np.asarray(policy0, np.int64)
    eps = IMPROVEMENT * float(tol)
    steps = 0
    for k in range(1, int(max_iterations) + 1):
        if k == 1 or not SCREEN_BY_STRATEGY_VALUE:  # every action, as no strategy's value is known yet
            floor = np.full(rows.size, -1.0)
        else:  # v is the strategy's value: other actions are solved only where they could beat it
            floor = v[rows] + eps
        q = np.asarray(_greedy(abstraction, v, floor, policy))
        best = q.max(axis=1)
        # gains over the current action's certified value, not over v: the chain's values come
        # from the solver's surrogate LP (unlisted states priced in buckets) and can lie below it
        kept = q[order, policy]
        gain = float(np.max(best - kept))
        switch = (best > kept + eps) & (np.argmax(q, axis=1) != policy)
        if gain <= tol or (k > 1 and not switch.any()):  # from k = 2 on, v is the strategy's value
            # converged; or a stable strategy whose greedy backup still gains more than tol
            return v, policy.astype(np.int32), k, steps, gain <= tol
        policy = np.where(switch, np.argmax(q, axis=1), policy)
        found = _evaluate(abstraction, v, policy, rows, terminal, eps)
        if found is None:
            return None
        v, taken = found
        steps += taken
    return v, policy.astype(np.int32), int(max_iterations), steps, False


def _evaluate(abstraction, v, policy, rows, terminal, stop):
    """The adversary's iteration for ``policy`` from its optimum at ``v``, until the values change
    by at most ``stop`` (or stall, or ``MAX_ADVERSARY_STEPS``): ``(values, steps)``, or ``None``
    where an LP ended without an optimum."""
    smallest, stalled = np.inf, 0
    for step in range(1, MAX_ADVERSARY_STEPS + 1):
        transitions, solved = abstraction.worst_case_transitions(v, policy)
        if not solved.all():
            return None
        new = reach_values(transitions, rows, terminal, guess=v)
        change = float(np.max(np.abs(new - v)))
        v = new
        stalled = 0 if change < smallest else stalled + 1
        smallest = min(smallest, change)
        if change <= stop or stalled >= STALLED_STEPS:
            break
    return v, step
