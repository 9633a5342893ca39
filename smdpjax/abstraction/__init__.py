"""Uncertain-MDP abstractions of a gridded system: one module per class.

``abstract(system, state_grid, noise_grid, kind)`` computes the reachable sets once
(``grid_clusters``) and builds the requested class from them. ``abstract(..., kind="imdp",
bounds="direct")`` instead integrates the noise of an additive-noise system directly
(``direct``).
"""

from __future__ import annotations

import warnings

from ..partition import NoiseGrid, StateGrid
from ..system import System
from .base import AbstractionMixin
from .clusters import IndexBoxes, cluster_members, index_boxes
from .direct import direct_imdp
from .grid_clusters import GridClusters, compute_grid_clusters
from .imdp import IMDP, interval_min
from .imdp_compact import CompactIMDP
from .mimdp import MIMDP
from .smdp import SMDP
from .structured import pays_off
from .twolayer import TwoLayerIMDP

# kind="imdp" builds the compact storage (rows bucketed by width, sparse lower bounds); the padded
# ``IMDP`` stays the storage of the MI-MDP's relaxation, direct bounds, gradients and Storm imports.
_BUILDERS = {"imdp": CompactIMDP, "2imdp": TwoLayerIMDP, "mimdp": MIMDP, "smdp": SMDP}
KINDS = ("imdp", "2imdp", "mimdp", "smdp")


def build(kind: str, grid: StateGrid, clusters: GridClusters, **options):
    """Build abstraction ``kind`` from precomputed clusters (to share reachable sets across classes)."""
    if kind not in _BUILDERS:
        raise ValueError(f"unknown abstraction kind {kind!r}; expected one of {KINDS}")
    abstraction = _BUILDERS[kind].from_clusters(grid, clusters, **options)
    if kind == "imdp" and not abstraction.any_positive_lower():
        warnings.warn("IMDP: every lower transition bound is 0 (no reachable set of any cell, action and noise "
                      "cell lies inside one state), so the adversary may move all mass anywhere the upper bounds "
                      "allow and p_low is 0 except where they force mass into the goal. Finer noise cells or "
                      "coarser state cells help; the 2I-MDP, MI-MDP and SMDP keep more of the reachable sets' "
                      "information; for additive noise (System.additive), bounds='direct' integrates it "
                      "exactly.", stacklevel=2)
    return abstraction


def abstract(system: System, state_grid: StateGrid, noise_grid: NoiseGrid | None, kind: str = "smdp", *,
             method: str = "both", policy=None, progress: bool = False, mesh=None, bounds: str = "lemma1",
             **options):
    """Abstract ``system`` on the partitions into an uncertain MDP of class ``kind``.

    Args:
        system: the stochastic system.
        state_grid: the phi-conservative state partition S (with reach/avoid labels).
        noise_grid: the partition C of W (not used by ``bounds="direct"``: pass it or ``None``).
        kind: ``"imdp"``, ``"2imdp"`` (option ``block``: coarse block shape in cells),
            ``"mimdp"`` (options ``extra_clusters``, ``lp_backend="highs"|"clarabel"``,
            ``screen_actions``, ``freeze_multipliers``, see ``MIMDP.from_clusters``) or ``"smdp"``
            (option ``encoding``: ``"boxes"``, ``"members"``, ``"structured"`` for a
            ``System.additive`` with one nonzero per row of B: O(R A K n) memory instead of
            O(R A C n), see ``SMDP.structured``; or ``"auto"``, the default: structured where it
            applies and halves the memory (``structured.pays_off``), else boxes).
        method: reachable-set enclosure: ``"natural"``, ``"centered"`` or ``"both"`` (direct
            bounds: the enclosure of g over a cell).
        policy: optional ``(N,)`` action index per cell: abstract only that action in each cell
            (``|A| = 1``), to verify a fixed controller with ``verify(abstraction)``.
        progress: show a progress bar over the reachable-set chunks.
        mesh: optional ``jax.sharding.Mesh`` (``smdpjax.sharding.row_mesh()``): the reachable sets
            are computed with the rows split across its devices, and the abstraction is returned
            sharded (``smdpjax.sharding.shard_abstraction``), so that synthesis runs on all of them.
        bounds: ``"lemma1"`` (default: Lemma 1 over the noise partition, every class) or
            ``"direct"`` (``kind="imdp"`` only; a system declared with ``System.additive``, B a
            diagonal or a permutation times a diagonal, Gaussian or Uniform noise): the IMDP's
            bounds integrate the noise exactly per cell (``smdpjax.abstraction.direct``; options
            ``threshold`` (default 1e-12: successors with a larger upper bound are listed, every other
            state gets ``[0, upper_rest]``, ``upper_rest <= threshold``) and ``entries_per_chunk``).
            The direct bounds are computed on the default device; ``mesh`` only shards the result.

    Returns:
        An abstraction PyTree (``IMDP``, ``TwoLayerIMDP``, ``MIMDP``, ``SMDP``), ready for
        ``smdpjax.synthesize``. An IMDP none of whose lower transition bounds is positive (no
        reachable box inside one cell: the partitions are too coarse for Lemma 1) comes with a
        ``UserWarning``, since its p_low is then 0 almost everywhere.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown abstraction kind {kind!r}; expected one of {KINDS}")
    if bounds not in ("lemma1", "direct"):
        raise ValueError(f"unknown bounds {bounds!r}; expected 'lemma1' (Lemma 1 over the noise partition) or "
                         f"'direct' (direct integration of additive noise, kind='imdp')")
    if bounds == "direct":
        if kind != "imdp":
            raise ValueError(f"bounds='direct' builds an IMDP (kind='imdp'), got kind={kind!r}")
        abstraction = direct_imdp(system, state_grid, method=method, policy=policy, progress=progress, **options)
    elif kind == "smdp" and (options.get("encoding") == "structured" or (
            options.get("encoding", "auto") == "auto" and pays_off(system, state_grid, noise_grid))):
        abstraction = SMDP.structured(system, state_grid, noise_grid, method=method, policy=policy,
                                      progress=progress, mesh=mesh)
    else:
        clusters = compute_grid_clusters(system, state_grid, noise_grid, method=method, policy=policy,
                                         progress=progress, mesh=mesh, compact=kind == "smdp")
        abstraction = build(kind, state_grid, clusters, **options)
    if mesh is None:
        return abstraction
    from ..sharding import shard_abstraction
    return shard_abstraction(abstraction, mesh)


__all__ = ["abstract", "build", "direct_imdp", "KINDS", "IMDP", "CompactIMDP", "SMDP", "TwoLayerIMDP", "MIMDP", "AbstractionMixin",
           "GridClusters", "IndexBoxes", "compute_grid_clusters", "cluster_members", "index_boxes", "interval_min"]
