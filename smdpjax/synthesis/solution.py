"""The result of synthesis or verification."""

from __future__ import annotations

import jax
import numpy as np

from .._pytree import pytree_dataclass, static_field


@pytree_dataclass
class Solution:
    """Satisfaction bounds and the strategy that achieves them.

    Arrays are indexed by state: flat grid cells ``0 .. N-1`` and the sink ``N`` last, so
    ``lower[grid.locate(x)]`` is right for every point (``locate`` gives -1 outside the grid).

    Attributes:
        lower: ``(N+1,)`` p_low under ``policy``: for every x in cell s, the closed loop satisfies
            the specification with probability >= lower[s] (sound at every stopping point).
        upper: ``(N+1,)`` p_up under ``policy`` (the adversary maximizes); iterated from above, so
            it is an upper bound at every stopping point.
        policy: ``(N+1,)`` action index per state, or ``(T, N+1)`` for a finite horizon
            (``policy[t]`` at time t). Terminal states hold 0.
        lower_optimal: ``(N+1,)`` the optimal robust value max_sigma min_xi (equal to ``lower``
            when the synthesized strategy is optimal; never below it).
        iterations: Bellman backups of the optimization (greedy ones and the cheaper sweeps of
            the greedy strategy between them, see ``synthesize(policy_sweeps=)``), or T.
        evaluation_iterations: iterations spent evaluating the strategy (0 for finite horizon).
        converged: whether both loops stopped on the tolerance rather than on max_iterations.
        upper_change: sup-norm change of the last upper-bound iteration.
        gap: ``max(upper - lower)`` over the non-terminal states: how wide the certified interval
            still is (abstraction error plus whatever the tolerance left).
        rounding_allowance: bound on accumulated float64 rounding, already added to ``upper``
            on non-terminal states (and subtracted from ``lower``, less the
            ``value_iteration.COMPLEMENT_ROUNDING`` per step that only the upper bound of a
            stationary strategy over a finite horizon carries).
    """

    lower: jax.Array
    upper: jax.Array
    policy: jax.Array
    lower_optimal: jax.Array
    iterations: int = static_field()
    evaluation_iterations: int = static_field()
    converged: bool = static_field()
    upper_change: float = static_field()
    gap: float = static_field()
    rounding_allowance: float = static_field()
    horizon: int | None = static_field()
    objective: str = static_field()

    def __repr__(self):
        lo, up = np.asarray(self.lower), np.asarray(self.upper)
        h = "inf" if self.horizon is None else self.horizon
        return (f"Solution({self.objective}, horizon={h}, iterations={self.iterations}"
                f"+{self.evaluation_iterations}, converged={self.converged}, "
                f"mean lower={lo[:-1].mean():.4f}, mean upper={up[:-1].mean():.4f})")
