"""Differentiable guarantees: gradients of p_low through the converged fixed point.

What is differentiated
----------------------
An abstraction has two parts that depend on continuous parameters theta (noise mean and std,
the noise partition's radius r_W, center w0 and per-axis edges, parameters of the dynamics):

* the **cluster structure**: which states every cluster q_{s,a,c} contains. It comes from the
  reachable boxes snapped to the grid, so it is *piecewise constant* in theta (a box edge
  crossing a grid line changes it). ``ClusterStructure`` holds it; it is computed from concrete
  parameter values, outside any differentiated path.
* the **probabilities** P_W(c) and P_W(rest): smooth functions of theta
  (``partition.cell_probabilities``). The SMDP is linear in them; the IMDP's Lemma-1 bounds are
  sums of them (``ClusterStructure.abstraction`` rebuilds either class from them, traceably).

The robust lower value p_low = T(p_low; theta) is the least fixed point of

    T(p)(s) = max_a min_{gamma in Gamma_{s,a}(theta)} sum_s' gamma(s') p(s')   (s non-terminal).

``robust_lower`` solves it by value iteration (``lax.while_loop``, which reverse-mode AD cannot
go through) and differentiates it by the implicit function theorem (``jax.custom_vjp``): at the
solution the controller's action sigma*(s) and the adversary's minimizing choice (SMDP: the
argmin member of each cluster and the argmin state for the remainder; IMDP: the greedy's optimal
gamma, i.e. the order of the values) are frozen. Then p = P_sel(theta) p + b(theta) is linear,
and the vector-Jacobian product solves the adjoint system

    (I - P_sel^T) lambda = g,   theta_bar = (d T / d theta)^T lambda,

by fixed-point iteration of the transposed map (JAX's own VJP of the frozen Bellman operator, so
the same code serves every class). States with p_low = 0 are pinned to 0 first: such a value is 0
under every strategy, hence locally constant, and leaving those states free would make the
system singular (closed classes of zero-valued states). Cost: one forward solve plus one
adjoint solve of similar length, instead of back-propagating through thousands of iterations.

What the gradient is, precisely
-------------------------------
``jax.grad`` returns the derivative of p_low **with the cluster structure frozen** at the
current parameters, and with sigma* and the minimizing selection frozen at the solution:

* Where the structure is locally constant and the optimal action and the adversary's minimizer
  are unique (generic parameters), this is the true gradient of p_low(theta).
* At a tie (two actions, or two minimizing members, of equal value) p_low is still continuous
  but has a kink: the result is the derivative of one active linear piece, i.e. a one-sided
  (directional) derivative / an element of the generalized gradient, not a two-sided gradient.
  For the SMDP, ties among members are averaged by JAX's ``min`` rule, a randomized but still
  minimizing selection.
* Where the structure changes (a reachable box crosses a grid line as r_W, w0, an edge or a
  dynamics parameter moves) p_low jumps; the jump is invisible to the gradient.
* Parameters that enter *only* through the reachable boxes (e.g. a time step or gain in the
  dynamics) move nothing but the frozen structure: their gradient is 0 between structure
  changes, and the value is piecewise constant in them. Noise-grid edges enter both ways: the
  gradient is the probability part only (exact wherever the structure is locally constant).
* The reported value is the optimal robust lower value (``Solution.lower_optimal`` before the
  ~1e-10 rounding allowance), converged to ``tol``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib

import jax
import jax.numpy as jnp
import numpy as np

from ._pytree import pytree_dataclass, static_field
from .abstraction.clusters import cluster_members, max_lengths
from .abstraction.grid_clusters import GridClusters, compute_grid_clusters
from .abstraction.imdp import IMDP, successor_width
from .abstraction.smdp import SMDP
from .partition import NoiseGrid, StateGrid, cell_probabilities
from .synthesis import value_iteration
from .system import System

__all__ = ["ClusterStructure", "cluster_structure", "robust_lower", "mean_lower", "guarantee", "noise_grid_of"]

KINDS = ("smdp", "imdp")


@pytree_dataclass
class ClusterStructure:
    """The piecewise-constant part of an abstraction: the clusters of every (row, action, noise cell).

    Attributes:
        members: ``(R, A, C_b, K)`` padded cluster member lists (as ``SMDP.members``; padding ``N+1``).
        rows: ``(R,)`` int32 state index of each row (the non-terminal cells).
        labels: ``(N+1,)`` int8 state labels.
        width: successors per row of the IMDP built from it (static, so ``abstraction`` traces).

    Pass it to jitted functions as an argument rather than closing over it: as a constant, XLA
    would constant-fold the IMDP's sort of the member lists, which makes compiling slow.
    """

    members: jax.Array
    rows: jax.Array
    labels: jax.Array
    width: int = static_field()

    @classmethod
    def from_clusters(cls, grid: StateGrid, clusters: GridClusters) -> "ClusterStructure":
        members = cluster_members(grid, clusters.boxes, max_lengths(clusters.boxes))
        return cls(members=members, rows=jnp.asarray(clusters.rows, jnp.int32),
                   labels=jnp.asarray(grid.state_labels), width=successor_width(members, grid.num_states))

    @classmethod
    def compute(cls, system: System, state_grid: StateGrid, noise_grid: NoiseGrid, *, method: str = "both",
                policy=None) -> "ClusterStructure":
        """The structure at concrete parameters (reachable sets; not differentiable, not jittable)."""
        clusters = compute_grid_clusters(system, state_grid, noise_grid, method=method, policy=policy)
        return cls.from_clusters(state_grid, clusters)

    def abstraction(self, prob, prob_rest, kind: str = "smdp"):
        """The SMDP or IMDP of this structure under noise-cell probabilities ``prob (C_b,)``,
        ``prob_rest``; differentiable (and vmappable) in the probabilities."""
        if kind == "smdp":
            return SMDP.from_members(self.members, prob, prob_rest, self.rows, self.labels)
        if kind == "imdp":
            return IMDP.from_members(self.members, prob, prob_rest, self.rows, self.labels, width=self.width)
        raise ValueError(f"kind must be one of {KINDS} for differentiable abstractions, got {kind!r}")

    def padded(self, k: int, width: int | None = None) -> "ClusterStructure":
        """The same structure with member lists padded to ``k`` slots (and IMDP ``width``).

        Padding changes no value; it keeps shapes fixed while the structure changes (an
        optimizer's steps), so jitted functions of the structure compile once.
        """
        r, a, c, k0 = self.members.shape
        if k < k0 or (width is not None and width < self.width):
            raise ValueError(f"cannot pad K={k0}, width={self.width} down to K={k}, width={width}")
        fill = jnp.full((r, a, c, k - k0), self.labels.shape[0], self.members.dtype)
        return dataclasses.replace(self, members=jnp.concatenate([self.members, fill], axis=-1),
                                   width=self.width if width is None else int(width))

    @property
    def num_bounded(self) -> int:
        """C_b: the bounded noise cells the structure was built for."""
        return int(self.members.shape[2])

    def fingerprint(self) -> str:
        """A hash of the structure: equal for equal structures (used to group sweep values)."""
        h = hashlib.sha1()
        for a in (self.members, self.rows, self.labels):
            a = np.asarray(a)
            h.update(str((a.shape, a.dtype.str)).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    def same_as(self, other: "ClusterStructure") -> bool:
        """Whether two structures are identical (same member lists, rows and labels)."""
        return all(np.asarray(a).shape == np.asarray(b).shape and np.array_equal(np.asarray(a), np.asarray(b))
                   for a, b in ((self.members, other.members), (self.rows, other.rows),
                                (self.labels, other.labels)))

    def __repr__(self):
        r, a, c, k = self.members.shape
        return f"ClusterStructure(|S|={self.labels.shape[0]}, rows={r}, |A|={a}, C_b={c}, K={k}, width={self.width})"


def cluster_structure(system: System, state_grid: StateGrid, noise_grid: NoiseGrid, **options) -> ClusterStructure:
    """``ClusterStructure.compute``: the frozen structure at concrete parameter values."""
    return ClusterStructure.compute(system, state_grid, noise_grid, **options)


def noise_grid_of(edges, remainder: bool = True) -> NoiseGrid:
    """A concrete ``NoiseGrid`` from (possibly jax) per-axis edges, to compute the structure with
    exactly the edges whose probabilities are differentiated."""
    return NoiseGrid.from_edges([np.asarray(jax.device_get(e), np.float64) for e in edges], remainder)


# -- the fixed point and its adjoint ------------------------------------------------------------


def frozen_bellman(abstraction, v, policy):
    """G(v) = p^0 off the rows, T_sigma(v) on them: the Bellman operator with the strategy fixed.

    Terminal states are constants (not ``v``), so dG/dv has zero rows there. The adversary's
    minimization stays inside; its derivative at ``v`` is the frozen minimizing selection.
    """
    q = abstraction.q_values(v, "min", policy)
    return abstraction.initial_values().at[abstraction.rows].set(q)


@functools.partial(jax.custom_vjp, nondiff_argnums=(1, 2, 3))
def _fixed_point(abstraction, tol, max_iterations, adjoint_tol):
    return _solve(abstraction, tol, max_iterations)[0]


def _solve(abstraction, tol, max_iterations):
    v, policy, _, _ = value_iteration.optimize_lower(abstraction, abstraction.initial_values(), tol, max_iterations)
    return v, policy


def _fixed_point_fwd(abstraction, tol, max_iterations, adjoint_tol):
    v, policy = _solve(abstraction, tol, max_iterations)
    return v, (abstraction, v, policy)


def _fixed_point_bwd(tol, max_iterations, adjoint_tol, residuals, g):
    abstraction, v, policy = residuals
    keep = (v > 0).astype(v.dtype)  # p_low = 0 is 0 under every strategy: pinned, not solved for
    _, pull_v = jax.vjp(lambda x: frozen_bellman(abstraction, x, policy), v)
    adjoint_tol = tol if adjoint_tol is None else adjoint_tol

    def body(state):
        k, u, _ = state
        u_new = g + pull_v(u * keep)[0]
        scale = jnp.maximum(jnp.max(jnp.abs(u_new)), jnp.finfo(v.dtype).tiny)
        return k + 1, u_new, jnp.max(jnp.abs(u_new - u)) / scale

    def cond(state):
        k, _, delta = state
        return (delta > adjoint_tol) & (k < max_iterations)

    _, u, _ = jax.lax.while_loop(cond, body, (jnp.int32(0), g, jnp.asarray(jnp.inf, v.dtype)))
    _, pull_a = jax.vjp(lambda a: frozen_bellman(a, v, policy), abstraction)
    return pull_a(u * keep)


_fixed_point.defvjp(_fixed_point_fwd, _fixed_point_bwd)


def robust_lower(abstraction, *, tol: float = 1e-12, max_iterations: int = 100_000,
                 adjoint_tol: float | None = None):
    """The optimal robust lower value p_low ``(N+1,)`` of an SMDP or IMDP, differentiable in its
    probabilities (``prob``/``prob_rest``, or ``lower``/``upper``/``upper_rest``).

    Forward: value iteration from p^0 to ``tol`` (sup-norm change). Backward: the adjoint system
    of the fixed point with the strategy and the adversary's selection frozen, iterated to a
    relative change ``adjoint_tol`` (default ``tol``); see the module docstring for what the
    gradient means at ties and structure changes. Works under ``jit``, ``grad`` and ``vmap``.
    """
    if not tol > 0:
        raise ValueError(f"tol must be > 0, got {tol}")
    return _fixed_point(abstraction, float(tol), int(max_iterations),
                        None if adjoint_tol is None else float(adjoint_tol))


def mean_lower(abstraction, cells, **solver_options):
    """Mean of p_low over the states ``cells`` (flat indices): a differentiable scalar guarantee."""
    return robust_lower(abstraction, **solver_options)[jnp.asarray(cells)].mean()


def guarantee(structure: ClusterStructure, noise, edges, cells, *, remainder: bool = True, kind: str = "smdp",
              **solver_options):
    """Mean p_low over ``cells`` as a function of the noise distribution and the noise-grid edges.

    Args:
        structure: the frozen clusters, computed at the same parameters
            (``cluster_structure(system, grid, noise_grid_of(edges, remainder))``).
        noise: a ``Distribution`` PyTree (``Gaussian(mean, std)``; its leaves may be traced).
        edges: per-axis noise-grid edges ``(k_i + 1,)`` (traced or concrete; e.g. from
            ``partition.noise_grid.ball_edges(center, radius, cells)``).
        cells: initial states S_0 (flat indices).
        kind: ``"smdp"`` or ``"imdp"``.

    Returns:
        Scalar mean p_low; ``jax.grad`` gives its derivative in ``noise`` and ``edges`` with the
        structure frozen (the true derivative wherever the structure is locally constant).
    """
    prob, rest = cell_probabilities(noise, edges, remainder)
    if prob.shape[0] != structure.num_bounded:
        raise ValueError(f"the edges give {prob.shape[0]} bounded noise cells but the structure has "
                         f"{structure.num_bounded}")
    return mean_lower(structure.abstraction(prob, rest, kind), cells, **solver_options)

