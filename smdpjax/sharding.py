"""Abstractions and value iteration spread over several devices (GPUs, a TPU slice, CPU devices).

An abstraction's transitions are stored per row (one row per non-terminal cell): every PyTree
leaf with leading axis ``R`` (``SMDP`` cluster arrays, ``IMDP.successors/lower/upper``, ``rows``,
...) is split along that axis across the devices of a mesh, and everything else (``labels``, the
noise probabilities, the 2I-MDP's block table) is replicated. A Bellman backup gathers the value
vector ``v (N+1,)`` at arbitrary states, so ``v`` stays replicated: each device computes the
q-values of its own rows against its full copy of ``v``, and the new ``v`` is assembled with one
all-gather of the ``R`` row values per iteration (checked in the compiled HLO: one ``f64[R]``
all-gather per iteration, the loop carry holds the whole ``v`` and a quarter of the rows).

Why plain ``jit`` with shardings (XLA's partitioner) rather than ``shard_map``: the solver
(``smdpjax.synthesis``) and every abstraction class run unchanged, user-defined classes
included, and the partitioner follows the row sharding of the inputs through ``q_values`` by
itself. ``shard_map`` would give the same schedule but needs partition specs for every leaf of
every class, a hand-written all-gather, and a device-local view of ``rows`` in the solver. The
one hook, in ``synthesis.value_iteration._set_rows``, pins ``v`` to the replicated sharding at
each update, so the partitioner never splits the sorts, prefix sums and minima over ``v`` of the
IMDP and 2I-MDP inner problems (a split prefix sum would round differently).

Results equal one device's up to float rounding, not always bit for bit: XLA:CPU's dot and fused
reductions round a row's sum differently depending on how many rows one kernel call gets (the
same happens on one device for a slice of the rows). Both results lie within
``Solution.rounding_allowance`` of the exact values, which bounds any summation order, so the
sharded bounds are exactly as sound (``tests/test_sharding.py``: abstractions and reachable sets
equal bit for bit; solutions within an ulp or so, same strategies and iteration counts; the
MI-MDP's LP multipliers react to last-bit changes, which moves its certified values by ~1e-11).

Rows are padded to a multiple of the device count by repeating the last row: a copy computes
the same q-values as the original and writes the same value (and strategy entry) to the same
state (its ``rows`` entry), so the padding changes nothing. ``num_rows`` counts the copies. The
MI-MDP's LP multipliers come from a host callback, which XLA runs from one device (it gathers
the costs there and logs "involuntary full rematerialization" warnings at compile time); the
copies' LPs are solved once (``_DistinctLPs``).

The reachable sets can be computed on the mesh too: ``abstract(..., mesh=mesh)`` splits every
chunk of rows across the devices, then builds the class on the default device (the class
arrays are not built sharded) and shards it.

    mesh = row_mesh()                                  # all devices, one axis "rows"
    smdp = shard_abstraction(sj.abstract(system, grid, noise, "smdp"), mesh)
    solution = sj.synthesize(smdp)                     # the one-device solution
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["row_mesh", "shard_abstraction", "unshard_abstraction", "row_sharding", "replicated", "padded_rows",
           "GLOBAL_FIELDS"]

# Fields that are global even if their leading size happens to equal the row count R.
GLOBAL_FIELDS = frozenset({"labels", "cells_of", "prob", "prob_rest", "upper_rest",
                           "chunk_succ", "chunk_slot", "chunk_upper", "chunk_row",  # chunked lists: replicated
                           "table"})  # the values of a coded array (``abstraction.coded``)

_TRACER = getattr(jax.core, "Tracer", ())

try:  # jax >= 0.5: meshes carry axis types; the partitioner may only move "auto" axes itself
    from jax.sharding import AxisType
except ImportError:  # pragma: no cover - older jax: every mesh axis is automatic
    AxisType = None


def row_mesh(devices=None, axis_name: str = "rows") -> Mesh:
    """A 1-D mesh over ``devices`` (default: all of ``jax.devices()``) with an automatic axis.

    ``jax.make_mesh`` defaults to explicit axis types, under which the gathers of a backup raise
    ``ShardingTypeError``; this mesh lets XLA place the collectives.
    """
    devices = np.asarray(jax.devices() if devices is None else list(devices), dtype=object).reshape(-1)
    if devices.size == 0:
        raise ValueError("row_mesh needs at least one device")
    if AxisType is None:  # pragma: no cover
        return Mesh(devices, (axis_name,))
    return Mesh(devices, (axis_name,), axis_types=(AxisType.Auto,))


def _auto(mesh: Mesh) -> Mesh:
    """``mesh`` with every axis automatic (a mesh from ``jax.make_mesh`` has explicit axes)."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a jax.sharding.Mesh (e.g. smdpjax.sharding.row_mesh()), "
                        f"got {type(mesh).__name__}")
    if AxisType is None or all(t == AxisType.Auto for t in mesh.axis_types):
        return mesh
    return Mesh(mesh.devices, mesh.axis_names, axis_types=(AxisType.Auto,) * len(mesh.axis_names))


def row_sharding(mesh: Mesh) -> NamedSharding:
    """Leading axis split over all devices of ``mesh`` (all its axes), the rest replicated."""
    mesh = _auto(mesh)
    return NamedSharding(mesh, PartitionSpec(tuple(mesh.axis_names)))


def replicated(mesh: Mesh) -> NamedSharding:
    """A full copy on every device of ``mesh``."""
    return NamedSharding(_auto(mesh), PartitionSpec())


def padded_rows(num_rows: int, mesh: Mesh) -> int:
    """``num_rows`` rounded up to a multiple of the number of devices in ``mesh``."""
    return -(-int(num_rows) // mesh.size) * mesh.size


def shard_abstraction(abstraction, mesh: Mesh | None = None):
    """The same abstraction with its rows split across the devices of ``mesh``.

    Every leaf whose leading size is the row count ``R`` (except the fields in ``GLOBAL_FIELDS`` and
    the leaves inside them) is padded to a multiple of the device count by repeating its last row
    and placed with ``row_sharding(mesh)``; every other leaf is replicated. Works for any
    abstraction PyTree with a ``rows`` leaf (nested ones, such as the MI-MDP's ``relaxation``,
    included).

    Args:
        abstraction: from ``smdpjax.abstract`` (IMDP, TwoLayerIMDP, MIMDP, SMDP), with concrete
            arrays.
        mesh: default ``row_mesh()`` (all devices). A mesh with several axes splits the rows
            over all of them; explicit axis types are made automatic.

    Returns:
        An abstraction of the same class that ``synthesize``/``verify`` accept unchanged and that
        gives the same ``Solution`` as ``abstraction`` (up to float rounding, see the module
        docstring).
    """
    mesh = row_mesh() if mesh is None else _auto(mesh)
    rows = getattr(abstraction, "rows", None)
    if rows is None or np.ndim(rows) != 1:
        raise TypeError(f"expected an abstraction with a (R,) rows leaf, got {type(abstraction).__name__}")
    num_rows = int(np.shape(rows)[0])
    pad = padded_rows(num_rows, mesh) - num_rows
    split, copy = row_sharding(mesh), replicated(mesh)

    def place(path, leaf):
        names = {getattr(key, "name", None) for key in path}  # a coded field's codes and table too
        if isinstance(leaf, _TRACER):
            raise TypeError("shard_abstraction needs concrete arrays; call it outside jit/vmap")
        if np.ndim(leaf) >= 1 and np.shape(leaf)[0] == num_rows and not names & GLOBAL_FIELDS:
            if pad:
                host = np.asarray(leaf)  # pad on the host: the full array need not fit one device
                leaf = np.concatenate([host, np.repeat(host[-1:], pad, axis=0)])
            return jax.device_put(leaf, split)
        return jax.device_put(leaf, copy)

    sharded = jax.tree_util.tree_map_with_path(place, abstraction)
    if getattr(sharded, "backup_rows", 0) != 0:  # an SMDP: each device backs up its own rows at once
        sharded = dataclasses.replace(sharded, backup_rows=0)
    return _distinct_lps(_whole_rows(sharded))


def _whole_rows(abstraction):
    """``abstraction`` with every compact IMDP in it (the MI-MDP's relaxation too) solving all its
    rows at once: blocks of rows (``imdp_compact.inner_blocks``) would slice the rows that the
    devices split."""
    if not dataclasses.is_dataclass(abstraction):
        return abstraction
    changes = {f.name: _whole_rows(getattr(abstraction, f.name)) for f in dataclasses.fields(abstraction)
               if dataclasses.is_dataclass(getattr(abstraction, f.name))}
    if hasattr(abstraction, "strategy_blocks"):
        changes.update(block_rows=0, block_chunks=0, strategy_blocks=(0, 0))
        if hasattr(abstraction, "block_pairs"):
            changes.update(block_pairs=(0, 0))
    return dataclasses.replace(abstraction, **changes) if changes else abstraction


def unshard_abstraction(abstraction, device=None):
    """The inverse of ``shard_abstraction``: padding copies dropped, every leaf on ``device``
    (default: the default device, uncommitted, as ``abstract`` returns them).

    The copies are recognised by their ``rows`` entry: the non-terminal cells are distinct, so
    trailing repeats of the last row are padding.
    """
    rows = np.asarray(abstraction.rows)
    num_rows = rows.size
    while num_rows > 1 and rows[num_rows - 2] == rows[-1]:
        num_rows -= 1
    padded = rows.size

    def gather(path, leaf):
        names = {getattr(key, "name", None) for key in path}
        host = np.asarray(leaf)
        if host.ndim >= 1 and host.shape[0] == padded and not names & GLOBAL_FIELDS:
            host = host[:num_rows]
        return jnp.asarray(host) if device is None else jax.device_put(host, device)

    plain = jax.tree_util.tree_map_with_path(gather, abstraction)
    lps = getattr(plain, "lps", None)
    return dataclasses.replace(plain, lps=lps.inner) if isinstance(lps, _DistinctLPs) else plain


def _distinct_lps(abstraction):
    """Wrap an MI-MDP's host LP solver so the padding copies' LPs are solved once per call."""
    lps = getattr(abstraction, "lps", None)
    if lps is None or not hasattr(lps, "multipliers") or isinstance(lps, _DistinctLPs):
        return abstraction
    return dataclasses.replace(abstraction, lps=_DistinctLPs(lps))


class _DistinctLPs:
    """``ClusterLPs`` that solves each distinct LP of a call once.

    Padding repeats the last row, so the same LP ids arrive twice in one callback; solving them
    twice would disable ``ClusterLPs``'s thread pool (it runs only on distinct ids) and, with
    HiGHS, advance that LP's warm start twice. Distinct ids keep their first-seen order, which
    is the one-device order. Compared and hashed by identity, like ``ClusterLPs``.
    """

    def __init__(self, lps):
        self.inner = lps

    def multipliers(self, w, ids, direction: int = 0):
        ids = np.asarray(ids)
        flat = ids.reshape(-1)
        _, first, inverse = np.unique(flat, return_index=True, return_inverse=True)
        if first.size == flat.size:
            return self.inner.multipliers(w, ids, direction=direction)
        order = np.argsort(first, kind="stable")  # distinct ids in first-seen order
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        lam = self.inner.multipliers(w, flat[np.sort(first)], direction=direction)
        return lam[rank[inverse.reshape(-1)]].reshape(*ids.shape, *lam.shape[1:])

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def __repr__(self):
        return f"_DistinctLPs({self.inner!r})"
