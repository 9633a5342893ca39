"""The refined controller kappa(x) = sigma*(cell of x), and Monte Carlo of the closed loop."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .partition import StateGrid
from .system import System


@dataclasses.dataclass(frozen=True, eq=False)
class Controller:
    """``kappa(x, t) = policy[locate(x)]`` (``policy[t, locate(x)]`` for a time-dependent one).

    Args:
        grid: the state partition the policy is defined on.
        policy: ``(N+1,)`` or ``(T, N+1)`` action indices (e.g. ``Solution.policy``).
    """

    grid: StateGrid
    policy: jax.Array

    def __post_init__(self):
        policy = jnp.asarray(self.policy, jnp.int32)
        if policy.shape[-1] != self.grid.num_states or policy.ndim not in (1, 2):
            raise ValueError(f"policy must have shape ({self.grid.num_states},) or (T, {self.grid.num_states}), "
                             f"got {policy.shape}")
        object.__setattr__(self, "policy", policy)

    @property
    def time_varying(self) -> bool:
        return self.policy.ndim == 2

    def __call__(self, x, t=0):
        """Action indices ``(...)`` for points ``x: (..., n)`` at time ``t``; outside the grid the
        sink's entry (the trajectory has already failed there)."""
        cell = self.grid.locate(x)  # -1 outside: the sink's entry, the last one
        if self.time_varying:
            t = jnp.minimum(t, self.policy.shape[0] - 1)
            return self.policy[t, cell]
        return self.policy[cell]


@dataclasses.dataclass(frozen=True)
class SimulationResult:
    """Outcome per trajectory ``(B,)`` and the empirical probability.

    Attributes:
        satisfied: reached X_reach before X_avoid (reach-avoid), or never left the safe set
            within the horizon (safety).
        failed: entered X_avoid (or left the grid box).
        steps: time step at which the trajectory stopped (``max_steps`` if it never did).
        trajectories: ``(max_steps + 1, B, n)`` states if requested (frozen after stopping), else None.
    """

    satisfied: jax.Array
    failed: jax.Array
    steps: jax.Array
    trajectories: jax.Array | None

    @property
    def probability(self) -> float:
        return float(jnp.mean(self.satisfied))

    @property
    def undecided(self) -> int:
        """Reach-avoid trajectories that hit ``max_steps`` before reaching or failing."""
        return int(jnp.sum(~self.satisfied & ~self.failed))

    def __repr__(self):
        return (f"SimulationResult(trajectories={self.satisfied.shape[0]}, probability={self.probability:.4f}, "
                f"failed={int(jnp.sum(self.failed))}, undecided={self.undecided})")


def start_states(grid: StateGrid, x0, max_steps: int):
    """``x0`` as a ``(B, n)`` float64 array; ValueError for another shape or ``max_steps <= 0``."""
    x0 = jnp.asarray(x0, jnp.float64)
    if x0.ndim != 2 or x0.shape[1] != grid.n:
        raise ValueError(f"x0 must have shape (B, {grid.n}), got {x0.shape}")
    if int(max_steps) <= 0:
        raise ValueError(f"max_steps must be positive, got {max_steps}")
    return x0


def simulate(system: System, controller: Controller, x0, key, *, max_steps: int = 1000,
             objective: str = "reach_avoid", return_trajectories: bool = False) -> SimulationResult:
    """Monte Carlo of the closed loop ``x[t+1] = f(x[t], kappa(x[t], t), w[t])`` from ``x0: (B, n)``.

    The specification is judged on the true sets of ``controller.grid`` (X_reach, X_avoid), not on
    cells. Reach-avoid: a trajectory succeeds when it enters X_reach before X_avoid; it is cut at
    ``max_steps``. Safety: it succeeds if it stays out of X_avoid for ``max_steps`` steps.
    """
    if objective not in ("reach_avoid", "safety"):
        raise ValueError(f"unknown objective {objective!r}; expected 'reach_avoid' or 'safety'")
    x0 = start_states(controller.grid, x0, max_steps)
    run = _rollout_fn(system, controller.grid, int(max_steps), objective, bool(return_trajectories))
    satisfied, failed, steps, traj = run(controller.policy, x0, key)
    return SimulationResult(satisfied=satisfied, failed=failed, steps=steps, trajectories=traj)


@functools.lru_cache(maxsize=32)
def _rollout_fn(system: System, grid: StateGrid, max_steps: int, objective: str, keep: bool):
    safety = objective == "safety"

    def judge(x, t, satisfied, failed, steps):
        running = ~(satisfied | failed)
        hit_avoid = grid.in_avoid(x) & running
        hit_reach = (grid.in_reach(x) & running & ~hit_avoid) if not safety else jnp.zeros_like(running)
        steps = jnp.where(hit_avoid | hit_reach, t, steps)
        return satisfied | hit_reach, failed | hit_avoid, steps

    @jax.jit
    def run(policy, x0, key):
        controller = Controller(grid, policy)
        b = x0.shape[0]
        satisfied, failed, steps = judge(x0, 0, jnp.zeros(b, bool), jnp.zeros(b, bool), jnp.full(b, max_steps))

        def advance(x, t, satisfied, failed, steps, key):
            running = ~(satisfied | failed)
            w = system.noise.sample(key, (b,))
            x_next = system.step(x, controller(x, t), w)
            x = jnp.where(running[:, None], x_next, x)
            return (x, *judge(x, t + 1, satisfied, failed, steps))

        keys = jax.random.split(key, max_steps)
        if keep:
            def body(carry, inp):
                x, sat, fail, st = carry
                t, k = inp
                x, sat, fail, st = advance(x, t, sat, fail, st, k)
                return (x, sat, fail, st), x

            (x, satisfied, failed, steps), path = jax.lax.scan(
                body, (x0, satisfied, failed, steps), (jnp.arange(max_steps), keys))
            traj = jnp.concatenate([x0[None], path])
        else:
            def cond(carry):
                t, _, sat, fail, _ = carry
                return (t < max_steps) & ~jnp.all(sat | fail)

            def body(carry):
                t, x, sat, fail, st = carry
                x, sat, fail, st = advance(x, t, sat, fail, st, keys[t])
                return t + 1, x, sat, fail, st

            _, x, satisfied, failed, steps = jax.lax.while_loop(cond, body, (0, x0, satisfied, failed, steps))
            traj = None
        if safety:
            satisfied = ~failed
        return satisfied, failed, steps, traj

    return run


def uniform_in_cells(grid: StateGrid, cells, per_cell: int, key):
    """``(len(cells) * per_cell, n)`` points uniform in the given flat cells (cell-major order)."""
    cells = np.asarray(cells)
    lo, hi = grid.cell_bounds(jnp.repeat(jnp.asarray(cells), per_cell))
    u = jax.random.uniform(key, lo.shape, dtype=jnp.float64)
    return lo + (hi - lo) * u
