"""Batched parameter sweeps: many noise parameters, one jitted synthesis call.

The cluster structure (which states each cluster contains) depends on the dynamics, the state
grid and the noise-grid edges only; the noise distribution and, for parameter values that
happen to share a structure, the edges themselves enter through P_W(c) alone. So a batch of
parameter values that share one structure is solved by mapping (``jax.vmap`` or ``lax.map``,
see below) the function

    parameters -> (P_W(c), P_W(rest)) -> SMDP/IMDP -> p_low, strategy, p_up under it

over the values inside one ``jax.jit``. ``sweep`` recomputes the structure per value where it
can change, groups values with identical structure, and runs one batched call per group.

Semantics match ``smdpjax.synthesize`` (unbounded reach-avoid): the optimal lower value and its
strategy, the strategy's certified lower value and its upper value, each widened by the same
rounding allowance. Under ``vmap`` the loop runs until the slowest value has converged (values
that converged earlier are held fixed), so each result is the one ``synthesize`` gives.

Strategy: a vmapped loop does ``B x max(iterations)`` backups where a Python loop does
``sum(iterations)``, and under ``vmap`` every ``lax.cond`` of the solver (the policy sweeps
after a converged greedy backup, the warm start's untried margins) runs both of its branches.
The Bellman backups are gathers, which XLA:CPU does not speed up by batching. So the batched
call picks its chunk size (``choose_batch_size``) by platform when ``batch_size`` is not given:

* on a CPU, one value at a time (``batch_size=1``): the values run one after the other inside
  the one jitted program (``lax.map`` over the values, no ``vmap``), which does exactly the
  Python loop's ``sum(iterations)`` backups without its per-call dispatch;
* on an accelerator, where one abstraction rarely fills the device, as many values side by side
  as fit a memory budget (``auto_batch_size``), in sequential chunks beyond that.

Every strategy gives the same results (each value's solve is the same function; a vmapped loop
holds the values that have converged while the others go on).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._pytree import pytree_dataclass
from .abstraction.imdp import IMDP
from .gradients import ClusterStructure
from .partition import NONTERMINAL
from .synthesis import value_iteration
from .synthesis.compiler import backup_jit

__all__ = ["BatchSolution", "SweepResult", "solve", "batched_synthesis", "sweep", "auto_batch_size",
           "choose_batch_size"]


@pytree_dataclass
class BatchSolution:
    """What ``synthesize`` returns, for a batch of parameter values (leading axis ``B``).

    Attributes:
        lower: ``(B, N+1)`` certified p_low of the synthesized strategy (allowance subtracted).
        upper: ``(B, N+1)`` p_up under that strategy (allowance added).
        lower_optimal: ``(B, N+1)`` optimal robust lower value.
        policy: ``(B, N+1)`` int32 action per state (0 on terminal states).
        iterations: ``(B,)`` optimization iterations; ``evaluation_iterations``: ``(B,)`` both
            evaluations together.
        converged: ``(B,)`` every loop stopped on the tolerance.
        upper_change: ``(B,)`` last change of the upper-bound iteration.
        rounding_allowance: ``(B,)`` the float64 rounding bound applied.
    """

    lower: jax.Array
    upper: jax.Array
    lower_optimal: jax.Array
    policy: jax.Array
    iterations: jax.Array
    evaluation_iterations: jax.Array
    converged: jax.Array
    upper_change: jax.Array
    rounding_allowance: jax.Array

    def __getitem__(self, index):
        return jax.tree.map(lambda a: a[index], self)

    def __len__(self):
        return int(self.iterations.shape[0])


def _rounding_per_backup(abstraction):
    """``abstraction.rounding_per_backup()``, traceable (the IMDP's depends on ``upper_rest``)."""
    if isinstance(abstraction, IMDP):
        summands = 2 * abstraction.successors.shape[2] + abstraction.num_states * abstraction.upper_rest
    else:
        summands = abstraction.summands_per_backup
    u = float(np.finfo(np.float64).eps) / 2
    return 2.02 * (summands + 4.0) * u * 2


def solve(abstraction, tol: float = 1e-6, max_iterations: int = 100_000) -> BatchSolution:
    """``synthesize(abstraction, tol=tol)`` as one pure, jittable and vmappable function.

    Returns a ``BatchSolution`` without the batch axis. Reach-avoid, unbounded horizon, no
    relaxation warm start (SMDP and IMDP have none); the strategy's evaluation starts from the
    same certified start as in ``synthesize``.
    """
    v0 = abstraction.initial_values()
    lower_opt, policy_rows, k_opt, d_opt = value_iteration.optimize_lower(abstraction, v0, tol, max_iterations)
    fixed = abstraction.restrict(policy_rows)
    # The certified warm start of ``synthesize`` (v0 itself when no margin passes).
    start, _, k_check = value_iteration.warm_start(fixed, lower_opt, v0, 2.0 * _rounding_per_backup(abstraction), tol)
    lower, k_lo, d_lo = value_iteration.evaluate(fixed, start, "min", tol, max_iterations)
    k_lo = k_lo + k_check
    upper, k_up, d_up = value_iteration.evaluate(fixed, value_iteration.top_values(abstraction), "max", tol,
                                                 max_iterations)
    allowance = _rounding_per_backup(abstraction) * (k_opt + k_lo + k_up)
    nonterminal = abstraction.labels == NONTERMINAL
    widen = lambda v, sign: jnp.where(nonterminal, jnp.clip(v + sign * allowance, 0.0, 1.0), v)
    policy = jnp.zeros(abstraction.num_states, jnp.int32).at[abstraction.rows].set(policy_rows)
    lower_opt = jnp.maximum(lower_opt, lower)
    return BatchSolution(lower=widen(lower, -1), upper=widen(upper, +1), lower_optimal=widen(lower_opt, -1),
                         policy=policy, iterations=k_opt, evaluation_iterations=k_lo + k_up,
                         converged=(d_opt <= tol) & (d_lo <= tol) & (d_up <= tol), upper_change=d_up,
                         rounding_allowance=jnp.asarray(allowance, lower.dtype))


def auto_batch_size(structure: ClusterStructure, budget_bytes: int = 1 << 29) -> int:
    """Values per vmapped chunk so that one backup's float64 temporaries (the gathered member
    values ``(R, A, C_b, K)`` and a few ``(R, A, C_b)``) stay near ``budget_bytes``."""
    r, a, c, k = structure.members.shape
    return max(1, int(budget_bytes // (8 * r * a * c * (k + 3))))


def _platform(structure: ClusterStructure) -> str:
    """The platform (``"cpu"``, ``"gpu"``, ``"tpu"``) holding the structure's arrays."""
    try:
        return next(iter(structure.members.devices())).platform
    except Exception:  # not a concrete jax.Array (a tracer, a NumPy array): the default backend
        return jax.default_backend()


def choose_batch_size(structure: ClusterStructure, batch: int, platform: str | None = None) -> int:
    """The chunk size ``batched_synthesis`` uses when ``batch_size`` is not given.

    ``1`` on a CPU: the values are solved one after the other inside the jitted call
    (``lax.map``, no ``vmap``), the Python loop's work without its per-call overhead. Batching
    does not make the gathers of a backup cheaper per value on a CPU, a vmapped loop runs every
    value of a chunk until the slowest has converged, and under ``vmap`` the solver's
    ``lax.cond`` branches both run (``benchmarks/sweep.py`` measures all of them against the
    loop). On an accelerator: ``auto_batch_size(structure)`` values side by side, at most
    ``batch``.

    Args:
        structure: the shared cluster structure.
        batch: the number of values.
        platform: ``"cpu"``, ``"gpu"``, ``"tpu"``; default: where the structure's arrays live.
    """
    platform = _platform(structure) if platform is None else platform
    if platform == "cpu":
        return 1
    return max(1, min(int(batch), auto_batch_size(structure)))


@backup_jit(static_argnames=("probabilities", "kind", "max_iterations", "batch_size"))
def _batched(structure, params, tol, probabilities, kind, max_iterations, batch_size):
    def one(prob, rest):
        return solve(structure.abstraction(prob, rest, kind), tol, max_iterations)

    prob, rest = jax.vmap(probabilities)(params)
    batch = prob.shape[0]
    if batch_size == 1:  # one value after the other, no vmap: each solve keeps its own loops and conds
        return jax.lax.map(lambda pr: one(*pr), (prob, rest))
    if batch_size >= batch:
        return jax.vmap(one)(prob, rest)
    # Chunks of ``batch_size`` values run one after the other (lax.map), each vmapped; the last
    # chunk is padded with copies of the last value, dropped afterwards.
    chunks = -(-batch // batch_size)
    pad = chunks * batch_size - batch
    prob = jnp.concatenate([prob, jnp.repeat(prob[-1:], pad, axis=0)]).reshape(chunks, batch_size, -1)
    rest = jnp.concatenate([rest, jnp.repeat(rest[-1:], pad)]).reshape(chunks, batch_size)
    out = jax.lax.map(lambda pr: jax.vmap(one)(*pr), (prob, rest))
    return jax.tree.map(lambda a: a.reshape(chunks * batch_size, *a.shape[2:])[:batch], out)


def batched_synthesis(structure: ClusterStructure, probabilities: Callable, params, *, kind: str = "smdp",
                      tol: float = 1e-6, max_iterations: int = 100_000,
                      batch_size: int | None = None) -> BatchSolution:
    """Probabilities and synthesis for a batch of parameter values sharing ``structure``: one
    jitted call over all the values (vmapped chunks, or one value after the other).

    Args:
        structure: the frozen clusters (``gradients.cluster_structure``), shared by every value.
        probabilities: ``params_i -> (prob (C_b,), prob_rest)``, a pure JAX function of one
            value, e.g. ``lambda s: cell_probabilities(Gaussian(mean, s), edges, True)``. It is a
            static argument: pass the same function object each time to reuse the compiled call.
        params: a PyTree whose leaves have a leading batch axis ``B`` (e.g. ``(64,)`` stds).
        kind: ``"smdp"`` or ``"imdp"``.
        batch_size: values solved side by side (vmapped); more run in sequential chunks of this
            size inside the same call (bounds memory: one SMDP backup holds ``R*A*C_b`` floats
            per value). ``1`` solves the values one after the other without ``vmap``. Default
            ``choose_batch_size(structure, B)``: ``1`` on a CPU, where batching is slower than a
            loop, else ``auto_batch_size(structure)`` (~0.5 GB of temporaries).

    Returns:
        ``BatchSolution`` with leading axis ``B``, equal to ``synthesize(abstraction, tol)`` per
        value (a vmapped loop holds the values that have converged while the others go on).
    """
    if not tol > 0:
        raise ValueError(f"tol must be > 0, got {tol}")
    if kind not in ("smdp", "imdp"):
        raise ValueError(f"kind must be 'smdp' or 'imdp', got {kind!r}")
    if batch_size is None:
        batch_size = choose_batch_size(structure, int(np.shape(jax.tree.leaves(params)[0])[0]))
    batch_size = int(batch_size)
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    return _batched(structure, params, jnp.asarray(tol, jnp.float64), probabilities, kind, int(max_iterations),
                    batch_size)


def given_probabilities(p):
    """``probabilities`` for params that already are ``(prob (C_b,), prob_rest)``."""
    return p


@dataclasses.dataclass(frozen=True)
class SweepResult:
    """Results of ``sweep`` in the order of ``values``.

    Attributes:
        values: the swept values.
        solution: ``BatchSolution`` with leading axis ``len(values)``.
        group: ``(V,)`` index into ``structures`` of each value's cluster structure.
        structures: the distinct structures met, in order of first appearance.
    """

    values: list
    solution: BatchSolution
    group: np.ndarray
    structures: list

    @property
    def lower(self):
        return self.solution.lower

    @property
    def upper(self):
        return self.solution.upper

    def mean_lower(self, cells):
        """``(V,)`` mean p_low over ``cells`` per value."""
        return np.asarray(self.solution.lower)[:, np.asarray(cells)].mean(axis=1)


def _geometry_key(system, grid, noise_grid, method):
    """What the structure depends on; equal keys give equal structures (so it is reused)."""
    grid_key = (grid.low.tobytes(), grid.high.tobytes(), grid.cells.tobytes(), grid.periodic.tobytes(),
                grid.labels.tobytes())
    edges = tuple(np.asarray(e).tobytes() for e in noise_grid.edges)
    return (system.dynamics, system.actions.tobytes(), grid_key, edges, noise_grid.remainder, method)


def sweep(problem: Callable, values: Sequence, *, kind: str = "smdp", probabilities: Callable | None = None,
          tol: float = 1e-6, method: str = "both", max_iterations: int = 100_000,
          batch_size: int | None = None, specification=None) -> SweepResult:
    """Synthesis for every value in ``values``, batched by cluster structure.

    Args:
        problem: ``value -> (system, state_grid, noise_grid)`` with concrete parameters. The
            structure is computed once per distinct (dynamics, actions, grid, noise edges), and
            values whose structures coincide share one batched call.
        values: the parameter values (numbers or PyTrees of arrays of equal shapes).
        probabilities: optional ``value -> (prob, prob_rest)`` in JAX, run inside the batched
            call; by default each value's ``noise_grid.probabilities(system.noise)`` is
            computed beforehand.
        kind, tol, method, max_iterations: as in ``abstract`` and ``synthesize``.
        batch_size: as in ``batched_synthesis``.
        specification: optional ``GridSpecification`` (``spec.on(grid)``, on the problems' grid,
            built without reach/avoid boxes): synthesize for it on the product instead of
            reach-avoid. The solutions are then over the product states, ``(V, Q * (N+1))``
            (``reshape(V, Q, N+1)``; ``spec.start_states(cells)`` indexes the starts).

    Returns:
        ``SweepResult``; ``result.group`` tells which values shared a structure.
    """
    values = list(values)
    if not values:
        raise ValueError("sweep needs at least one value")
    cache, structures, fingerprints, group, inputs = {}, [], {}, [], []
    for value in values:
        system, grid, noise_grid = problem(value)
        key = _geometry_key(system, grid, noise_grid, method)
        if key not in cache:
            cache[key] = ClusterStructure.compute(system, grid, noise_grid, method=method)
            if specification is not None:
                from .specification.structure import ProductStructure
                cache[key] = ProductStructure.of(cache[key], specification)
        structure = cache[key]
        fp = structure.fingerprint()
        if fp not in fingerprints:
            fingerprints[fp] = len(structures)
            structures.append(structure)
        group.append(fingerprints[fp])
        inputs.append(value if probabilities is not None else noise_grid.probabilities(system.noise))
    sizes = {int(s.labels.shape[0]) for s in structures}
    if len(sizes) > 1:
        raise ValueError(f"swept values give state grids of different sizes {sorted(sizes)}; sweep one grid at a time")
    group = np.asarray(group)
    fn = probabilities if probabilities is not None else given_probabilities
    batches, order = [], []
    for g, structure in enumerate(structures):
        idx = np.flatnonzero(group == g)
        params = jax.tree.map(lambda *leaves: jnp.stack([jnp.asarray(x) for x in leaves]), *[inputs[i] for i in idx])
        batches.append(batched_synthesis(structure, fn, params, kind=kind, tol=tol, max_iterations=max_iterations,
                                         batch_size=batch_size))
        order.append(idx)
    back = np.argsort(np.concatenate(order))  # from group order back to the order of ``values``
    solution = jax.tree.map(lambda *leaves: jnp.concatenate(leaves)[back], *batches)
    return SweepResult(values=values, solution=solution, group=group, structures=structures)
