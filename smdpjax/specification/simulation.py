"""The product controller (it tracks the DFA state) and Monte Carlo judged by the DFA itself.

``ProductController(spec, policy)`` applies ``policy[q, cell of x]``: q is the DFA state after
reading the letters of the *true* states so far (``spec.point_letters``), not of cells. The
closed loop of the continuous system under it satisfies the specification with a probability in
``[initial_lower[s], initial_upper[s]]`` from every point of cell s (``ProductSolution``).
``simulate_product`` runs it and judges each trajectory by running the DFA on the letters of its
states (``Specification``'s semantics).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp


from ..simulation import SimulationResult, start_states
from ..system import System
from .specification import GridSpecification


@dataclasses.dataclass(frozen=True, eq=False)
class ProductController:
    """``kappa(x, q, t) = policy[q, locate(x)]`` (``policy[t, q, locate(x)]`` when time-dependent).

    Args:
        specification: the ``GridSpecification`` the policy was synthesized for.
        policy: ``(Q, N+1)`` or ``(T, Q, N+1)`` action indices (``ProductSolution.policy``).
    """

    specification: GridSpecification
    policy: jax.Array

    def __post_init__(self):
        if not isinstance(self.specification, GridSpecification):
            raise TypeError("specification must be a GridSpecification (spec.on(grid))")
        policy = jnp.asarray(self.policy, jnp.int32)
        shape = (self.specification.num_dfa_states, self.specification.grid.num_states)
        if policy.shape[-2:] != shape or policy.ndim not in (2, 3):
            raise ValueError(f"policy must have shape {shape} or (T, *{shape}), got {policy.shape}")
        object.__setattr__(self, "policy", policy)

    @property
    def time_varying(self) -> bool:
        return self.policy.ndim == 3

    @property
    def grid(self):
        return self.specification.grid

    def start(self, x):
        """DFA states ``(...)`` of trajectories starting at ``x: (..., n)``: delta(q0, L(x))."""
        dfa = self.specification.dfa
        return jnp.asarray(dfa.table)[dfa.initial_index, self.specification.point_letters(x)]

    def advance(self, q, x):
        """DFA states after moving to ``x``: delta(q, L(x))."""
        return jnp.asarray(self.specification.dfa.table)[q, self.specification.point_letters(x)]

    def __call__(self, x, q, t=0):
        """Action indices ``(...)`` at points ``x: (..., n)`` in DFA states ``q: (...)``."""
        cell = self.grid.locate(x)  # -1 outside: the sink's entry
        if self.time_varying:
            return self.policy[jnp.minimum(t, self.policy.shape[0] - 1), q, cell]
        return self.policy[q, cell]


@dataclasses.dataclass(frozen=True)
class ProductSimulationResult(SimulationResult):
    """Outcome per trajectory ``(B,)``.

    Attributes:
        satisfied: the DFA accepted (acceptance ``"reach"``: at some step, before leaving the
            grid box; ``"final"``: at the last step, never having left it).
        failed: left the grid box, or entered a DFA state from which no accepting state can be
            reached.
        steps: the step at which the trajectory was decided (``max_steps`` if never).
        dfa_state: the DFA state at the end.
        trajectories: ``(max_steps + 1, B, n)`` states if requested (frozen once decided).
    """

    dfa_state: jax.Array = None

    def __repr__(self):
        return super().__repr__().replace("SimulationResult(", "ProductSimulationResult(", 1)


def simulate_product(system: System, controller: ProductController, x0, key, *, max_steps: int = 1000,
                     return_trajectories: bool = False) -> ProductSimulationResult:
    """Monte Carlo of the closed loop under a product controller from ``x0: (B, n)``.

    Each trajectory is judged by the DFA on the letters of its true states. Acceptance
    ``"reach"``: it succeeds when the DFA accepts, fails when it leaves the grid box or the DFA
    enters a trap, and is cut at ``max_steps`` (pass the horizon T of a finite-horizon
    solution). Acceptance ``"final"``: it runs exactly ``max_steps`` steps (the horizon T) and
    succeeds when the DFA accepts at the end and it never left the grid box.
    """
    if not isinstance(controller, ProductController):
        raise TypeError(f"controller must be a ProductController, got {type(controller).__name__}")
    x0 = start_states(controller.grid, x0, max_steps)
    run = _rollout_fn(system, controller.specification, int(max_steps), bool(return_trajectories))
    satisfied, failed, steps, q, traj = run(controller.policy, x0, key)
    return ProductSimulationResult(satisfied=satisfied, failed=failed, steps=steps, dfa_state=q, trajectories=traj)


@functools.lru_cache(maxsize=32)
def _rollout_fn(system: System, spec: GridSpecification, max_steps: int, keep: bool):
    dfa, grid = spec.dfa, spec.grid
    final = spec.acceptance == "final"
    accepting = jnp.asarray(dfa.accepting_mask)
    trap = jnp.asarray(~dfa.coreachable(spec.labelling.occurring))

    def judge(x, q, t, satisfied, failed, steps):
        running = ~(satisfied | failed)
        fail = running & ((grid.locate(x) < 0) | trap[q])
        win = running & ~fail & accepting[q] & (not final)
        steps = jnp.where(fail | win, t, steps)
        return satisfied | win, failed | fail, steps

    @jax.jit
    def run(policy, x0, key):
        controller = ProductController(spec, policy)
        b = x0.shape[0]
        q0 = controller.start(x0)
        satisfied, failed, steps = judge(x0, q0, 0, jnp.zeros(b, bool), jnp.zeros(b, bool), jnp.full(b, max_steps))

        def advance(x, q, t, satisfied, failed, steps, key):
            running = ~(satisfied | failed)
            w = system.noise.sample(key, (b,))
            x_next = system.step(x, controller(x, q, t), w)
            x = jnp.where(running[:, None], x_next, x)
            q = jnp.where(running, controller.advance(q, x), q)
            return (x, q, *judge(x, q, t + 1, satisfied, failed, steps))

        keys = jax.random.split(key, max_steps)
        if keep:
            def body(carry, inp):
                t, k = inp
                carry = advance(*carry[:2], t, *carry[2:], k)
                return carry, carry[0]

            (x, q, satisfied, failed, steps), path = jax.lax.scan(
                body, (x0, q0, satisfied, failed, steps), (jnp.arange(max_steps), keys))
            traj = jnp.concatenate([x0[None], path])
        else:
            def cond(carry):
                t, _, _, sat, fail, _ = carry
                return (t < max_steps) & ~jnp.all(sat | fail)

            def body(carry):
                t, x, q, sat, fail, st = carry
                return (t + 1, *advance(x, q, t, sat, fail, st, keys[t]))

            _, x, q, satisfied, failed, steps = jax.lax.while_loop(cond, body, (0, x0, q0, satisfied, failed, steps))
            traj = None
        if final:
            satisfied = ~failed & accepting[q]
        return satisfied, failed, steps, q, traj

    return run


__all__ = ["ProductController", "ProductSimulationResult", "simulate_product"]


