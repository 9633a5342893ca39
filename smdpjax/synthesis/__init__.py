"""Robust controller synthesis and verification on any abstraction class."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..abstraction.base import AbstractionMixin
from ..partition import NONTERMINAL
from . import policy_iteration, value_iteration
from .solution import Solution

__all__ = ["synthesize", "verify", "Solution", "synthesize_product", "verify_product", "ProductAbstraction",
           "ProductSolution", "product"]


def _check(abstraction, horizon, tol, objective):
    if not isinstance(abstraction, AbstractionMixin):
        raise TypeError(f"expected an abstraction from smdpjax.abstract, got {type(abstraction).__name__}")
    if horizon is not None and (int(horizon) != horizon or horizon < 0):
        raise ValueError(f"horizon must be None or a non-negative integer, got {horizon}")
    if not tol > 0:
        raise ValueError(f"tol must be > 0, got {tol}")
    if objective == "safety" and horizon is None:
        raise ValueError("safety is checked over a finite horizon: pass horizon=T")
    return abstraction.initial_values(objective)


def _finish(abstraction, lower, upper, policy_rows, lower_opt, iterations, eval_iterations,
            converged, change, horizon, objective, upper_extra: float = 0.0):
    """Widen by the rounding allowance (``upper`` by ``upper_extra`` more), expand the row policy
    to states, measure the gap."""
    allowance = abstraction.rounding_per_backup() * (int(iterations) + int(eval_iterations))
    lower, upper, lower_opt, policy, gap = _finish_arrays(abstraction.labels, abstraction.rows, lower,
                                                          upper, lower_opt, policy_rows, allowance,
                                                          allowance + upper_extra)
    return Solution(lower=lower, upper=upper, policy=policy, lower_optimal=lower_opt,
                    iterations=int(iterations), evaluation_iterations=int(eval_iterations),
                    converged=bool(converged), upper_change=float(change), gap=float(gap),
                    rounding_allowance=float(allowance + upper_extra), horizon=horizon, objective=objective)


@jax.jit
def _finish_arrays(labels, rows, lower, upper, lower_opt, policy_rows, allowance, upper_allowance):
    nonterminal = labels == NONTERMINAL
    widen = lambda v, sign: jnp.where(nonterminal, jnp.clip(v + sign * (allowance if sign < 0 else upper_allowance),
                                                            0.0, 1.0), v)
    n_states = labels.shape[0]
    if policy_rows.ndim == 1:
        policy = jnp.zeros(n_states, jnp.int32).at[rows].set(policy_rows)
    else:
        policy = jnp.zeros((policy_rows.shape[0], n_states), jnp.int32).at[:, rows].set(policy_rows)
    lower, upper = widen(lower, -1), widen(upper, +1)
    gap = jnp.max(jnp.where(nonterminal, upper - lower, 0.0))
    return lower, upper, widen(lower_opt, -1), policy, gap


METHODS = ("value_iteration", "policy_iteration")


def synthesize(abstraction, horizon: int | None = None, tol: float = 1e-6, *, objective: str = "reach_avoid",
               max_iterations: int = 100_000, policy_sweeps: int | None = None, upper: bool = True,
               method: str | None = None) -> Solution:
    """Robust dynamic programming: p_low with an optimal strategy, then p_up under it.

    Args:
        abstraction: any class from ``smdpjax.abstract`` (IMDP, 2I-MDP, MI-MDP, SMDP).
        horizon: ``None`` iterates to convergence (unbounded reach-avoid); an integer T runs
            exactly T backups and returns a time-dependent strategy ``(T, N+1)``.
        tol: stop each loop when an iteration changes no value by more than ``tol``. Stopping
            early only ever loosens the bounds, never makes them unsound: ``lower`` is iterated
            from below (every iterate is below the least fixed point) and ``upper`` from above
            (every iterate is above it). ``Solution.gap`` reports the widest remaining interval.
        objective: ``"reach_avoid"`` (p^0 = 1 on reach cells) or ``"safety"`` (stay in the safe
            cells for ``horizon`` steps; p^0 = 1 on every safe cell).
        max_iterations: cap on each loop for unbounded horizons.
        policy_sweeps: the most backups of the current greedy strategy alone after each greedy
            backup of the optimization (modified policy iteration, see
            ``value_iteration.optimize_lower``; they stop once one changes no value by more than
            ``value_iteration.SWEEP_STOP`` times the greedy backup's change, except the MI-MDP's,
            which always run); ``None``: the number of actions, or
            ``value_iteration.FROZEN_SWEEPS`` for the MI-MDP, whose sweeps iterate frozen LP
            multipliers instead of solving LPs (``MIMDP.freeze``); ``0``: plain
            value iteration. Sound for any value; only the speed and where the optimization
            stops within ``tol`` change.
        upper: ``False`` skips the optimistic bound (about half the work of a finite horizon)
            when only the guarantee and its strategy are needed; ``Solution.upper`` is then the
            trivial bound (1 on every state that is not avoided) and ``gap`` reports its width.
        method: how an unbounded horizon's strategy is optimized: ``"value_iteration"`` (modified
            policy iteration from below, ``value_iteration.optimize_lower``; every class) or
            ``"policy_iteration"`` (each strategy evaluated by linear solves against the
            adversary's optimal distributions, ``policy_iteration.optimize``; classes with
            ``worst_case_transitions``: the MI-MDP). ``None``: policy iteration where the class
            offers exact vertices (``exact_transitions``: the MI-MDP with HiGHS), else value
            iteration. Both end with the same certified evaluation of the
            strategy; policy iteration's values are only its guess. Falls back to value
            iteration where an LP ends without an optimum.

    Returns:
        ``Solution``. ``lower`` is the certified value of the returned strategy, evaluated
        separately from the optimization so that a tie-broken strategy can never claim more
        than it achieves; ``upper`` the strategy's optimistic value, iterated from above.

    An abstraction with a ``relaxation`` attribute (an abstraction of the same system whose
    ambiguity sets contain its own, e.g. the IMDP inside an MI-MDP) is solved warm: each loop
    starts from the relaxation's value, which lies below the abstraction's own (smaller
    ambiguity sets, higher robust values) and is cheap to compute. Iterates are still valid
    lower bounds, and far fewer expensive backups are needed.
    """
    v0 = _check(abstraction, horizon, tol, objective)
    if policy_sweeps is not None and (int(policy_sweeps) != policy_sweeps or policy_sweeps < 0):
        raise ValueError(f"policy_sweeps must be None or a non-negative integer, got {policy_sweeps}")
    if method is not None and method not in METHODS:
        raise ValueError(f"method must be None or one of {METHODS}, got {method!r}")
    if method == "policy_iteration" and not policy_iteration.supports(abstraction):
        raise ValueError(f"policy iteration needs the adversary's optimal distributions (worst_case_transitions), "
                         f"which {type(abstraction).__name__} does not offer: use method='value_iteration'")
    if horizon is not None:
        lo, up, policy = value_iteration.finite_horizon(abstraction, v0, int(horizon), with_upper=bool(upper))
        return _finish(abstraction, lo, up, policy, lo, horizon, 0, True, 0.0, int(horizon), objective)
    sweeps = None if policy_sweeps is None else int(policy_sweeps)
    iterate = method == "policy_iteration" or (method is None and policy_iteration.preferred(abstraction))
    guess, policy, k, converged, lo_opt = _optimize(abstraction, v0, tol, max_iterations, sweeps, iterate)
    if upper:
        lo, up, k_eval, (converged_eval, change) = _evaluate_both(abstraction, v0, policy, tol, max_iterations,
                                                                  guess=guess)
    else:
        lo, k_eval, converged_eval = _pessimistic(abstraction, v0, policy, tol, max_iterations, guess)
        up, change = value_iteration.top_values(abstraction), 0.0
    lo_opt = jnp.maximum(lo_opt, lo)  # both are lower bounds of the optimum (the strategy's value is one)
    return _finish(abstraction, lo, up, policy, lo_opt, k, k_eval, converged and converged_eval, change, None,
                   objective)


def verify(abstraction, policy=None, horizon: int | None = None, tol: float = 1e-6, *,
           objective: str = "reach_avoid", max_iterations: int = 100_000) -> Solution:
    """Lower and upper bounds of a given controller (no optimization).

    Args:
        policy: action index per grid cell, ``(N,)`` or ``(N+1,)`` (e.g. a look-up table), or
            ``(T, N)``/``(T, N+1)`` per time step when ``horizon=T``. May be omitted for a
            single-action abstraction (``abstract(..., policy=table)`` abstracts the table's
            action only).

    The other arguments are as in ``synthesize``.
    """
    v0 = _check(abstraction, horizon, tol, objective)
    n = abstraction.num_states
    if policy is None:
        if abstraction.num_actions != 1:
            raise ValueError(f"the abstraction has {abstraction.num_actions} actions: pass the policy to verify")
        policy = np.zeros(n, np.int32)
    policy = np.asarray(policy)
    if not np.issubdtype(policy.dtype, np.integer):
        raise TypeError(f"policy must hold integer action indices, got dtype {policy.dtype}")
    if policy.shape[-1] not in (n - 1, n) or policy.ndim not in (1, 2):
        raise ValueError(f"policy must have shape (N,) or (N+1,) with N={n - 1} cells (or (T, .)), got {policy.shape}")
    if policy.ndim == 2 and (horizon is None or policy.shape[0] != horizon):
        raise ValueError(f"a time-dependent policy of shape {policy.shape} needs horizon={policy.shape[0]}")
    if np.any(policy < 0) or np.any(policy >= abstraction.num_actions):
        raise ValueError(f"policy entries must lie in [0, {abstraction.num_actions})")
    rows_policy = policy[..., np.asarray(abstraction.rows)].astype(np.int32)  # jit moves it to the device
    if horizon is not None:
        lo, up, pol = value_iteration.finite_horizon(abstraction, v0, int(horizon), rows_policy)
        extra = value_iteration.COMPLEMENT_ROUNDING * int(horizon) if rows_policy.ndim == 1 else 0.0
        return _finish(abstraction, lo, up, pol, lo, horizon, 0, True, 0.0, int(horizon), objective, extra)
    lo, up, k, (converged, change) = _evaluate_both(abstraction, v0, rows_policy, tol, max_iterations)
    return _finish(abstraction, lo, up, rows_policy, lo, 0, k, converged, change, None, objective)


def _optimize(abstraction, v0, tol, max_iterations, policy_sweeps=None, iterate_policies=False):
    """The optimized strategy, warm-started from a relaxation where there is one:
    ``(guess, policy, backups, converged, lower)``. ``guess`` (N+1,) is the optimization's last
    value, where the strategy's evaluation starts; ``lower`` a certified lower bound of the
    optimum: ``guess`` itself after value iteration (its iterates rise from below), the
    relaxation's lower bound (or p^0) after policy iteration, whose values are not bounds."""
    relaxation = getattr(abstraction, "relaxation", None)
    start, policy0, k0 = v0, None, 0
    if relaxation is not None:
        # policy iteration needs a start, not a tight one (it is not a bound it reports)
        start_tol = max(tol, policy_iteration.START_TOL) if iterate_policies else tol
        start, policy0, k0, _, _ = _optimize(relaxation, v0, start_tol, max_iterations, policy_sweeps)
    if iterate_policies:
        found = policy_iteration.optimize(abstraction, start, v0, tol, max_iterations, policy0)
        if found is not None:
            guess, policy, k, _, converged = found
            return jnp.asarray(guess), jnp.asarray(policy), k + int(k0), converged, start
    lo, policy, k, delta = value_iteration.optimize_lower(abstraction, start, tol, max_iterations, policy0,
                                                          policy_sweeps=policy_sweeps)
    return lo, policy, int(k) + int(k0), bool(delta <= tol), lo


def _pessimistic(abstraction, v0, policy_rows, tol, max_iterations, guess=None):
    """The strategy's value against the minimizing adversary, iterated from below: from a
    certified ``guess`` (see ``_warm_start``), else from p^0 or from a relaxation's value."""
    restricted = abstraction.restrict(policy_rows)
    k_check = 0  # backups spent on checking the guess (counted in the rounding allowance)
    if guess is not None:
        start, k_check = _warm_start(abstraction, restricted, v0, guess, tol)
        if start is not None:
            lo, k, delta = value_iteration.evaluate(restricted, start, "min", tol, max_iterations)
            return lo, int(k) + k_check, bool(delta <= tol)
    relaxation = getattr(abstraction, "relaxation", None)
    start, k0 = v0, 0
    if relaxation is not None:
        start, k0, _ = _pessimistic(relaxation, v0, policy_rows, tol, max_iterations)
    lo, k, delta = value_iteration.evaluate(restricted, start, "min", tol, max_iterations)
    return lo, int(k) + k0 + k_check, bool(delta <= tol)


def _warm_start(abstraction, restricted, v0, guess, tol):
    """A certified lower start for the strategy's pessimistic value, or ``None``.

    The optimization's last iterate ``guess`` is close to what the strategy achieves against the
    minimizing adversary, but it is not a certificate by itself (rounding; and a strategy that
    idles in a loop of states keeps its value in the optimization's iterate without ever
    reaching the goal). ``value_iteration.certified_start`` makes it one: the start, a little
    below ``guess``, must gain strictly under one exact backup wherever it is positive, which
    puts it below the least fixed point. Evaluating from it then takes the few iterations left
    instead of the many that a start from p^0 needs. ``restricted``: ``abstraction`` under the
    strategy (``restrict``). Returns ``(start or None, backups spent)``.
    """
    slack = 2.0 * abstraction.rounding_per_backup()
    start, certified, tries = value_iteration.warm_start(restricted, guess, v0, slack, tol)
    return (start if bool(certified) else None), int(tries)


def _optimistic(abstraction, policy_rows, tol, max_iterations):
    """The strategy's value against the maximizing adversary, iterated from above.

    Starts from 1 on every state that is not avoided (above any probability), or from a
    relaxation's optimistic value: its ambiguity sets are larger, so its optimistic value is
    higher, and any iterate from above of it lies above this abstraction's least fixed point.
    Every iterate from such a start is a valid upper bound, so stopping at ``tol`` is sound.
    """
    relaxation = getattr(abstraction, "relaxation", None)
    if relaxation is not None:
        start, k0, _ = _optimistic(relaxation, policy_rows, tol, max_iterations)
    else:
        start, k0 = value_iteration.top_values(abstraction), 0
    up, k, delta = value_iteration.evaluate(abstraction.restrict(policy_rows), start, "max", tol, max_iterations)
    return up, int(k) + k0, float(delta)


def _evaluate_both(abstraction, v0, policy_rows, tol, max_iterations, guess=None):
    """Pessimistic value of the strategy from below, optimistic value from above."""
    lo, k_lo, converged_lo = _pessimistic(abstraction, v0, policy_rows, tol, max_iterations, guess)
    up, k_up, d_up = _optimistic(abstraction, policy_rows, tol, max_iterations)
    converged = converged_lo and d_up <= tol
    return lo, up, k_lo + k_up, (converged, d_up)


from .product import ProductAbstraction, ProductSolution, product, synthesize_product, verify_product  # noqa: E402
