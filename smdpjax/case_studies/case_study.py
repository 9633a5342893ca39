"""A benchmark problem: system, partitions, specification, and how to validate it."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..partition import NoiseGrid, StateGrid
from ..system import System


@dataclasses.dataclass(frozen=True, eq=False)
class CaseStudy:
    """Everything a Table 1 row needs besides the abstraction class.

    Attributes:
        name: short identifier (``"unicycle_2d"``, ...).
        system, state_grid, noise_grid: the inputs of ``smdpjax.abstract``.
        objective: ``"reach_avoid"`` (synthesis, unbounded horizon) or ``"safety"``.
        horizon: ``None`` for unbounded reach-avoid, else the number of steps.
        controller: ``(N,)`` fixed action index per cell for verification (abstract only that
            action, ``|A| = 1``), or ``None`` when a controller is synthesized.
        max_steps: cap on Monte Carlo trajectory length.
        reach_method: the reachable-set enclosure to use (``abstract(..., method=)``). Every
            method is sound; ``"natural"`` is chosen where it gives the same index boxes as
            ``"both"`` on the system (measured, and checked by the tests), at a fraction of the
            cost, since the centred form only helps where a variable occurs several times.
    """

    name: str
    system: System
    state_grid: StateGrid
    noise_grid: NoiseGrid
    objective: str
    horizon: int | None = None
    controller: np.ndarray | None = None
    max_steps: int = 1000
    reach_method: str = "both"

    @property
    def num_actions(self) -> int:
        """|A| of the abstraction: 1 when a fixed controller is verified."""
        return 1 if self.controller is not None else self.system.num_actions

    def abstract(self, kind: str = "smdp", **options):
        """``smdpjax.abstract`` of this problem (the controller's actions only, if there is one)."""
        from ..abstraction import abstract

        return abstract(self.system, self.state_grid, self.noise_grid, kind, method=self.reach_method,
                        policy=self.controller, **options)

    def solve(self, abstraction, tol: float = 1e-6):
        """``synthesize`` (reach-avoid) or ``verify`` the fixed controller (safety)."""
        from ..synthesis import synthesize, verify

        if self.controller is not None:
            return verify(abstraction, horizon=self.horizon, tol=tol, objective=self.objective)
        return synthesize(abstraction, horizon=self.horizon, tol=tol, objective=self.objective)

    def closed_loop_policy(self, solution) -> np.ndarray:
        """The controller to simulate: the fixed table (with the sink's entry appended) or the
        synthesized ``solution.policy``."""
        if self.controller is not None:
            return np.append(self.controller, 0).astype(np.int32)
        return np.asarray(solution.policy)

    def __repr__(self):
        spec = self.objective if self.horizon is None else f"{self.objective}, {self.horizon} steps"
        return (f"CaseStudy({self.name}: n={self.state_grid.n}, |S|={self.state_grid.num_states}, "
                f"|A|={self.num_actions}, |C|={self.noise_grid.num_cells}, {spec})")
