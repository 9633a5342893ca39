"""What every abstraction class provides to synthesis, simulation and metrics.

States are the grid cells ``0 .. N-1`` and the sink ``N``; value vectors have length ``N + 1``.
Only the non-terminal cells (``rows``) have transitions: reach cells are absorbing with value 1,
avoid cells and the sink absorbing with value 0 (the reach-avoid reduction of the paper's RDP).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..partition import AVOID, REACH


class AbstractionMixin:
    """Shared behaviour; subclasses are PyTree dataclasses with ``rows`` and ``labels`` leaves.

    Subclasses implement ``q_values(v, adversary, actions=None)``: the inner problem of the
    robust Bellman operator for every row, ``min`` (``adversary="min"``) or ``max`` over the
    ambiguity set of sum_s' gamma(s') v(s'). Shapes: ``v (N+1,)`` -> ``(R, A)``, or ``(R,)`` when
    ``actions: (R,)`` fixes one action per row. ``restrict(actions)`` returns the single-action
    abstraction of a stationary strategy (``|A| = 1``), for loops that evaluate one strategy.
    """

    kind: str = "abstract"
    # True for a class whose inner problem calls an outside solver (the MI-MDP's LPs) and that
    # offers ``freeze``/``frozen_at_zero``: views whose backups bound its own from the
    # conservative side at every value vector without calling the solver, exact at the vector
    # they were frozen at. Loops that apply one operator many times refreeze now and then
    # instead of solving at every backup (the strategy sweeps of
    # ``value_iteration.optimize_lower``).
    freezable = False

    @property
    def num_states(self) -> int:
        """|S|: grid cells plus the sink."""
        return int(self.labels.shape[0])

    @property
    def num_rows(self) -> int:
        return int(self.rows.shape[0])

    def greedy_q_values(self, v):
        """``(R, A)`` what a greedy backup (max over actions) needs: lower bounds of
        ``q_values(v, "min")`` that equal it on every action that can be a row's best, so the row
        maximum and its argmax are ``q_values``'s. Here all of ``q_values``; a class that can
        tell cheaply which actions cannot win overrides it to skip their work (the MI-MDP)."""
        return self.q_values(v, "min")

    def greedy_backup(self, v, floor=None, current=None):
        """``(q (R, A), lam)``: ``greedy_q_values(v)`` and, for a ``freezable`` class, the
        multipliers that certify it, which a loop may freeze for the greedy strategy's sweeps;
        ``lam`` is ``None`` here (a class with no multipliers, or one that does not keep them).
        ``floor`` and ``current`` (``(R,)``, optional) say which values a caller can do without
        (those below ``floor``, except the row's ``current`` action's); a class whose q-values
        cost a solver call skips them (the MI-MDP), this one computes everything."""
        return self.greedy_q_values(v), None

    def initial_values(self, objective: str = "reach_avoid"):
        """``(N+1,)`` p^0: the indicator of S_reach (reach-avoid) or of the safe cells (safety)."""
        if objective not in ("reach_avoid", "safety"):
            raise ValueError(f"unknown objective {objective!r}; expected 'reach_avoid' or 'safety'")
        return _initial_values(self.labels, objective)

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays that store the abstraction (the paper's memory metric)."""
        return int(sum(np.asarray(leaf).nbytes for leaf in jax.tree_util.tree_leaves(self)))

    @property
    def summands_per_backup(self) -> float:
        """How many nonnegative terms one inner problem adds up (for the rounding allowance)."""
        raise NotImplementedError

    def rounding_per_backup(self) -> float:
        """A bound on the float64 rounding error of one Bellman backup (values in [0, 1]).

        A sum of T nonnegative terms of total <= 1 is off by at most ~T u (u = 2^-53); the
        probabilities P_W(c) carry a few ulps each from erf. The robust Bellman operator is
        non-expansive in the sup norm, so errors add up over iterations at most linearly.
        """
        u = float(np.finfo(np.float64).eps) / 2
        return 2.02 * (self.summands_per_backup + 4.0) * u * 2

    def _check_values(self, v):
        if v.shape != (self.num_states,):
            raise ValueError(f"value vector must have shape ({self.num_states},), got {v.shape}")


def check_adversary(adversary: str) -> bool:
    """True for a minimizing adversary."""
    if adversary not in ("min", "max"):
        raise ValueError(f"adversary must be 'min' or 'max', got {adversary!r}")
    return adversary == "min"


@functools.partial(jax.jit, static_argnums=1)
def _initial_values(labels, objective: str):  # one dispatch instead of three (small problems)
    if objective == "reach_avoid":
        return (labels == REACH).astype(jnp.float64)
    return (labels != AVOID).astype(jnp.float64)
