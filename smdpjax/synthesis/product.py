"""Synthesis for DFA specifications on the product of the DFA and an abstraction, never built.

The product's value is ``v[q, s]`` over DFA states q and grid states s (a flat vector of length
``P = |Q| (N+1)``, ``specification.tables``). The backup of (q, s) under action a is the
abstraction's own inner problem applied to

    u_q(s') = v[delta(q, L(s')), s']

(``ProductAbstraction.successor_values``; the worst of a cell's possible letters for the
minimizing adversary, the best for the maximizing one; 0 on the sink). So every class keeps its
exact inner problem: the SMDP takes range minima of u_q over its index boxes (one sparse table
per live DFA state), the IMDP, 2I-MDP and MI-MDP their greedy or certified LP bounds, vmapped
over the live DFA states. ``ProductAbstraction`` is itself an abstraction (``q_values``,
``restrict``, ``rows``, ``labels``), so ``synthesize``, ``verify``, the rounding allowance, the
certified warm start and the sound early stopping all apply to it unchanged.

Theorem 3 carries over: with the letters fixed, each class's inner problem on u_q is the same
function of u_q as on any value vector, and the ambiguity sets are nested, so the product values
are ordered as the classes' reach-avoid values are.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass, static_field
from ..abstraction.base import AbstractionMixin, check_adversary
from ..abstraction.imdp import IMDP
from ..partition import AVOID
from ..specification.specification import GridSpecification, as_grid_specification
from ..specification.tables import ProductTables
from .solution import Solution

__all__ = ["ProductAbstraction", "ProductSolution", "product", "synthesize_product", "verify_product"]

BATCHING = ("vmap", "map")


def default_batching() -> str:
    """``"map"`` on a CPU, ``"vmap"`` elsewhere. On a CPU the live DFA states' backups one after
    the other were faster on the larger grid: the vmapped gathers of a batch of value tables cost
    more than a loop (3-D unicycle 30^3, SMDP, 2 live DFA states: synthesis 2.9x the reach-avoid
    time mapped, 5.1x vmapped; 2-D 60x60: 2.1x mapped, 1.25x vmapped; ``benchmarks/dfa.py``,
    docs/performance.md). ``"map"`` also holds the memory of one base backup only."""
    return "map" if jax.default_backend() == "cpu" else "vmap"


def _summands(base):
    """The base's ``summands_per_backup``, traceable (the IMDP's depends on ``upper_rest``, which
    may be traced in gradients and sweeps). The one place that reads an IMDP's fields here."""
    if isinstance(base, IMDP):
        return 2 * base.successors.shape[2] + base.num_states * jnp.asarray(base.upper_rest, jnp.float64)
    return jnp.asarray(base.summands_per_backup, jnp.float64)


@pytree_dataclass
class ProductAbstraction(AbstractionMixin):
    """The product of an abstraction and a DFA specification, as an abstraction over the product
    states (flat index ``q (N+1) + s``).

    Attributes:
        base: the grid abstraction (any class). ``batched``: a stack of abstractions, one per live
            DFA state (``restrict`` and ``freeze`` make those: each DFA state has its own strategy
            or frozen multipliers).
        tables: ``ProductTables``.
        summands: scalar, the base's summands per backup (for the rounding allowance).
        batched: static, see ``base``.
        actions: static, |A| (1 after ``restrict``).
        batching: static, ``"vmap"`` (the live DFA states side by side) or ``"map"`` (one after
            the other: the memory of one backup of the base; faster on a CPU, ``default_batching``).
    """

    base: object
    tables: ProductTables
    summands: jax.Array
    batched: bool = static_field(default=False)
    actions: int = static_field(default=1)
    batching: str = static_field(default="vmap")
    kind: str = static_field(default="product")

    @classmethod
    def of(cls, base, tables: ProductTables, batching: str | None = None) -> "ProductAbstraction":
        """The product of ``base`` with the tables made for its rows (traceable in ``base``);
        ``batching=None``: ``default_batching()``."""
        batching = default_batching() if batching is None else batching
        if batching not in BATCHING:
            raise ValueError(f"batching must be one of {BATCHING}, got {batching!r}")
        return cls(base=base, tables=tables, summands=_summands(base), batched=False,
                   actions=int(base.num_actions), batching=batching, kind=f"product-{base.kind}")

    # -- the abstraction interface -------------------------------------------------------------
    @property
    def rows(self):
        return self.tables.rows

    @property
    def labels(self):
        return self.tables.labels

    @property
    def num_actions(self) -> int:
        return self.actions

    @property
    def summands_per_backup(self):
        return self.summands

    @property
    def freezable(self) -> bool:
        return bool(getattr(self.base, "freezable", False))

    @property
    def relaxation(self):
        """The product of the base's relaxation (the MI-MDP's IMDP), for warm starts; ``None``
        for a batched product or a base without one."""
        inner = getattr(self.base, "relaxation", None)
        if inner is None or self.batched:
            return None
        return ProductAbstraction.of(inner, self.tables, self.batching)

    def initial_values(self, objective: str = "reach_avoid"):
        """``(P,)`` p^0 = 1 on accepted pairs (``"reach_avoid"``, the default) or the trivial upper
        bound 1 on every pair that is not a trap (``"safety"``, what ``top_values`` asks for)."""
        if objective == "safety":
            return (self.tables.labels != AVOID).astype(jnp.float64)
        if objective != "reach_avoid":
            raise ValueError(f"a product abstraction's objective is its specification; got {objective!r}")
        return self.tables.v0

    def successor_values(self, v, minimize: bool = True):
        """``(Q_live, N+1)``: u_q(s') = v[delta(q, L(s')), s'] for every live DFA state, the
        worst (``minimize``) or best possible letter of a mixed cell."""
        picked = v[self.tables.succ]  # (Q_live, N+1, L)
        return picked.min(axis=-1) if minimize else picked.max(axis=-1)

    def _per_state(self, fn, u, *extra):
        """``fn(base_q, u_q, *extra_q)`` for every live DFA state, stacked ``(Q_live, ...)``."""
        if self.batched:
            call, args = fn, (self.base, u, *extra)
        else:
            call, args = (lambda *a: fn(self.base, *a)), (u, *extra)
        if self.batching == "map":
            return jax.lax.map(lambda a: call(*a), args)
        return jax.vmap(call)(*args)

    def _scatter(self, actions):
        """Row actions ``(R,)`` as ``(Q_live, R_base)`` (0 where a DFA state has no row)."""
        shape = (len(self.tables.live), self.tables.num_base_rows)
        return jnp.zeros(shape, jnp.int32).at[self.tables.row_q, self.tables.row_r].set(actions.astype(jnp.int32))

    def q_values(self, v, adversary: str = "min", actions=None):
        """``(R, A)`` (or ``(R,)`` with ``actions: (R,)``) the base's inner problem on u_q."""
        minimize = check_adversary(adversary)
        u = self.successor_values(v, minimize)
        if actions is None:
            q = self._per_state(lambda b, w: b.q_values(w, adversary), u)
        else:
            q = self._per_state(lambda b, w, a: b.q_values(w, adversary, a), u, self._scatter(actions))
        return q[self.tables.row_q, self.tables.row_r]

    def greedy_q_values(self, v):
        u = self.successor_values(v, True)
        q = self._per_state(lambda b, w: b.greedy_q_values(w), u)
        return q[self.tables.row_q, self.tables.row_r]

    def greedy_backup(self, v, floor=None, current=None):
        """``greedy_q_values(v)`` and the base's multipliers per product row (``(R, A, J, 2)``, or
        ``None`` for a base that keeps none; see ``MIMDP.greedy_backup``). ``floor`` and
        ``current`` are not used: every action is computed (``AbstractionMixin.greedy_backup``)."""
        u = self.successor_values(v, True)
        q, lam = self._per_state(lambda b, w: b.greedy_backup(w), u)
        pick = lambda a: a[self.tables.row_q, self.tables.row_r]
        return pick(q), (None if lam is None else pick(lam))

    def from_multipliers(self, lam) -> "ProductAbstraction":
        """The base frozen per live DFA state at the multipliers ``lam (R, A, J, 2)`` of the product
        rows (zeros on a base row a DFA state does not have)."""
        shape = (len(self.tables.live), self.tables.num_base_rows) + lam.shape[1:]
        full = jnp.zeros(shape, lam.dtype).at[self.tables.row_q, self.tables.row_r].set(lam)
        if self.batched:
            base = jax.vmap(lambda b, m: b.from_multipliers(m))(self.base, full)
        else:
            base = jax.vmap(lambda m: self.base.from_multipliers(m))(full)
        return dataclasses.replace(self, base=base, batched=True)

    def restrict(self, actions) -> "ProductAbstraction":
        """The single-action product of a stationary strategy over the product rows ``(R,)``: one
        restricted base per live DFA state (batched)."""
        act = self._scatter(actions)
        if self.batched:
            base = jax.vmap(lambda b, a: b.restrict(a))(self.base, act)
        else:
            base = jax.vmap(lambda a: self.base.restrict(a))(act)
        return dataclasses.replace(self, base=base, batched=True, actions=1)

    def freeze(self, v, adversary: str = "min") -> "ProductAbstraction":
        """A freezable base frozen per live DFA state at u_q (see ``MIMDP.freeze``)."""
        u = self.successor_values(v, check_adversary(adversary))
        if self.batched:
            base = jax.vmap(lambda b, w: b.freeze(w, adversary))(self.base, u)
        else:
            base = jax.vmap(lambda w: self.base.freeze(w, adversary))(u)
        return dataclasses.replace(self, base=base, batched=True)

    def frozen_at_zero(self) -> "ProductAbstraction":
        if self.batched:
            return dataclasses.replace(self, base=jax.vmap(lambda b: b.frozen_at_zero())(self.base))
        return dataclasses.replace(self, base=self.base.frozen_at_zero())

    def __repr__(self):
        t = self.tables
        return (f"ProductAbstraction({self.kind}, |Q|={t.num_dfa_states}, live={len(t.live)}, "
                f"|S|={t.num_grid_states}, rows={int(t.rows.shape[0])}, |A|={self.actions})")


def product(abstraction, specification, *, batching: str | None = None) -> ProductAbstraction:
    """The product of an abstraction and a specification on its grid (``spec.on(grid)``).

    The abstraction must have transitions for every cell the specification's runs can occupy:
    build it on a grid without reach/avoid boxes (the regions belong to the specification). An
    abstraction of a reach-avoid grid is fine for the reach-avoid DFA (``reach_avoid_of``).
    """
    if not isinstance(abstraction, AbstractionMixin) or isinstance(abstraction, ProductAbstraction):
        raise TypeError(f"expected an abstraction from smdpjax.abstract, got {type(abstraction).__name__}")
    spec = as_grid_specification(specification)
    if abstraction.num_states != spec.grid.num_states:
        raise ValueError(f"the abstraction has {abstraction.num_states} states, the specification's grid "
                         f"{spec.grid.num_states}: they must be of the same grid")
    return ProductAbstraction.of(abstraction, spec.tables(np.asarray(abstraction.rows)), batching)


@pytree_dataclass
class ProductSolution:
    """Bounds and strategy of a DFA specification, per DFA state and grid state.

    Attributes:
        lower, upper, lower_optimal: ``(Q, N+1)`` bounds of the product states (p_low of the
            strategy, p_up under it, the optimal robust lower value). ``lower[q, s]`` bounds the
            probability of satisfying the specification from any point of cell s when the DFA
            (having read that point's letter) is in state q: 1 on accepted pairs (acceptance
            ``"reach"``), 0 on traps, on the sink and on pairs no run can occupy.
        policy: ``(Q, N+1)`` action per product state, or ``(T, Q, N+1)`` for a finite horizon.
        initial_lower, initial_upper: ``(N+1,)`` the bounds from a start in each grid state:
            ``lower[delta(q0, L(s)), s]`` (the worst possible letter of a mixed cell for the
            lower bound, the best for the upper one). These are what ``simulate_product``
            checks.
        flat: the ``Solution`` over the flat product states (iterations, gap, allowance, ...).
        states: the DFA's state names (static).
    """

    lower: jax.Array
    upper: jax.Array
    lower_optimal: jax.Array
    policy: jax.Array
    initial_lower: jax.Array
    initial_upper: jax.Array
    flat: Solution
    states: tuple = static_field()

    @classmethod
    def from_flat(cls, flat: Solution, tables: ProductTables, states: tuple) -> "ProductSolution":
        q, size = tables.num_dfa_states, tables.num_grid_states
        grid = lambda a: jnp.reshape(a, (*a.shape[:-1], q, size))
        start = tables.start
        return cls(lower=grid(flat.lower), upper=grid(flat.upper), lower_optimal=grid(flat.lower_optimal),
                   policy=grid(flat.policy), initial_lower=flat.lower[start].min(axis=-1),
                   initial_upper=flat.upper[start].max(axis=-1), flat=flat, states=tuple(states))

    @property
    def gap(self) -> float:
        return self.flat.gap

    @property
    def converged(self) -> bool:
        return self.flat.converged

    @property
    def horizon(self):
        return self.flat.horizon

    @property
    def rounding_allowance(self) -> float:
        return self.flat.rounding_allowance

    def __repr__(self):
        lo, up = np.asarray(self.initial_lower)[:-1], np.asarray(self.initial_upper)[:-1]
        h = "inf" if self.flat.horizon is None else self.flat.horizon
        return (f"ProductSolution(|Q|={len(self.states)}, horizon={h}, iterations={self.flat.iterations}"
                f"+{self.flat.evaluation_iterations}, converged={self.flat.converged}, "
                f"mean initial lower={lo.mean():.4f}, mean initial upper={up.mean():.4f})")


def _check_horizon(spec: GridSpecification, horizon):
    if spec.acceptance == "final" and horizon is None:
        raise ValueError("acceptance 'final' judges the trace of exactly `horizon` steps: pass horizon=T")


def synthesize_product(abstraction, specification, horizon: int | None = None, tol: float = 1e-6, *,
                       max_iterations: int = 100_000, policy_sweeps: int | None = None, upper: bool = True,
                       batching: str | None = None) -> ProductSolution:
    """Robust synthesis for a DFA specification: p_low with an optimal strategy over (q, s),
    then p_up under it.

    Args:
        abstraction: any class from ``smdpjax.abstract``, on the specification's grid (built
            without reach/avoid boxes, see ``product``).
        specification: a ``GridSpecification`` (``spec.on(grid)``).
        horizon: ``None`` (unbounded, acceptance ``"reach"`` only) or T steps (a time-dependent
            strategy ``(T, Q, N+1)``).
        tol, max_iterations, policy_sweeps, upper: as in ``synthesize``; the same sound early
            stopping and rounding allowance apply (the product is an abstraction).
        batching: ``"vmap"`` or ``"map"``: the live DFA states' backups side by side, or one
            after the other (less memory); ``None``: ``default_batching()`` (``"map"`` on a CPU).

    Returns:
        ``ProductSolution``.
    """
    from . import synthesize

    spec = as_grid_specification(specification)
    _check_horizon(spec, horizon)
    prod = product(abstraction, spec, batching=batching)
    flat = synthesize(prod, horizon=horizon, tol=tol, max_iterations=max_iterations, policy_sweeps=policy_sweeps,
                      upper=upper)
    return ProductSolution.from_flat(flat, prod.tables, spec.dfa.states)


def verify_product(abstraction, specification, policy, horizon: int | None = None, tol: float = 1e-6, *,
                   max_iterations: int = 100_000, batching: str | None = None) -> ProductSolution:
    """Bounds of a given controller over (q, s): ``policy (Q, N+1)``, or ``(T, Q, N+1)`` with
    ``horizon=T`` (e.g. ``ProductSolution.policy``). Other arguments as in
    ``synthesize_product``."""
    from . import verify

    spec = as_grid_specification(specification)
    _check_horizon(spec, horizon)
    prod = product(abstraction, spec, batching=batching)
    policy = np.asarray(policy)
    q, size = spec.num_dfa_states, spec.grid.num_states
    if policy.shape[-2:] != (q, size) or policy.ndim not in (2, 3):
        raise ValueError(f"policy must have shape (Q, N+1) = ({q}, {size}) or (T, Q, N+1), got {policy.shape}")
    flat = verify(prod, policy.reshape(*policy.shape[:-2], q * size), horizon=horizon, tol=tol,
                  max_iterations=max_iterations)
    return ProductSolution.from_flat(flat, prod.tables, spec.dfa.states)

