"""From (system, state grid, noise grid) to the index boxes of every cluster q_{s,a,c}.

This is the one place where reachable sets are computed; every abstraction class is built from
its output, so all four classes share the same reachable sets (as the paper's comparison needs).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..partition import NoiseGrid, StateGrid
from ..reach import reachable_boxes
from ..system import System
from .clusters import IndexBoxes, decode_boxes, dimension_codes, small_int, snapping_end

# Reachable boxes per chunk: bounds peak memory (a few hundred MB of float64 temporaries).
BOXES_PER_CHUNK = 1 << 19


@dataclasses.dataclass(frozen=True)
class GridClusters:
    """Index boxes of all clusters of the non-terminal rows, and the noise cell probabilities.

    Attributes:
        rows: ``(R,)`` flat indices of the non-terminal cells the abstraction has transitions for.
        boxes: ``IndexBoxes`` with leading shape ``(R, A, C_b)``.
        prob: ``(C_b,)`` P_W of the bounded noise cells.
        prob_rest: P_W of the remainder cell (0 for bounded noise); its cluster is all of S.
        noise_shape: ``(K_1, ..., K_m)`` the bounded noise cells as a C-order product grid
            (``NoiseGrid.shape``), or ``None`` (Lemma 1's sums then take no product form).
    """

    rows: np.ndarray
    boxes: IndexBoxes
    prob: jax.Array
    prob_rest: jax.Array
    noise_shape: tuple | None = None


def validate(system: System, grid: StateGrid, noise_grid: NoiseGrid) -> np.ndarray:
    """Check everything that can be checked cheaply; return the non-terminal rows."""
    if not isinstance(system, System):
        raise TypeError(f"system must be a smdpjax.System, got {type(system).__name__}")
    if not isinstance(grid, StateGrid):
        raise TypeError(f"state_grid must be a smdpjax.StateGrid, got {type(grid).__name__}")
    if not isinstance(noise_grid, NoiseGrid):
        raise TypeError(f"noise_grid must be a smdpjax.NoiseGrid, got {type(noise_grid).__name__}")
    noise_grid.check_covers(system.noise)
    rows = grid.nonterminal
    if rows.size == 0:
        raise ValueError(f"{grid!r} has no non-terminal cell: every cell is a reach or avoid cell")
    probe = np.asarray(grid.cell_centers(rows[np.linspace(0, rows.size - 1, min(rows.size, 64)).astype(int)]))
    system.check_against(grid.n, probe)
    actions = np.asarray(system.actions, np.float64)
    if np.any((actions != 0) & (np.abs(actions) < np.finfo(np.float64).tiny)):
        raise ValueError("actions contain subnormal numbers (below 2.2e-308 in magnitude), which XLA on the CPU "
                         "reads as 0; round them to 0")
    return rows


def policy_actions(system: System, grid: StateGrid, rows: np.ndarray, policy=None) -> np.ndarray:
    """The inputs to abstract: ``(A, m)`` all actions, or with a fixed ``policy`` (``(N,)``
    action index per cell) ``(R, 1, m)``, the policy's action of each row. Checks the policy."""
    actions = np.asarray(system.actions)
    if policy is None:
        return actions
    policy = np.asarray(policy)
    if policy.shape not in ((grid.num_cells,), (grid.num_states,)) or not np.issubdtype(policy.dtype, np.integer):
        raise ValueError(f"policy must be ({grid.num_cells},) integer action indices, got {policy.shape} "
                         f"{policy.dtype}")
    if np.any(policy < 0) or np.any(policy >= system.num_actions):
        raise ValueError(f"policy entries must lie in [0, {system.num_actions})")
    return actions[policy[rows]][:, None, :]


def compute_grid_clusters(system: System, grid: StateGrid, noise_grid: NoiseGrid, *, method: str = "both",
                          policy=None, progress: bool = False, mesh=None, compact: bool = False,
                          structured: bool | None = None) -> GridClusters:
    """Reachable boxes of all (non-terminal cell, action, bounded noise cell) triples, snapped to
    index boxes on ``grid``. Raises ValueError if the dynamics give NaN bounds anywhere.

    ``policy``: optional ``(N,)`` action index per cell (a fixed controller, e.g. a look-up
    table). Only that action is abstracted in each cell, so the abstraction has ``|A| = 1``
    (action 0 of a row is the policy's action): the way to verify a given controller cheaply.

    ``mesh``: optional ``jax.sharding.Mesh`` (``smdpjax.sharding.row_mesh()``): each chunk of rows
    is split across its devices, which compute their rows' reachable sets. The result is the
    same, on the default device.

    ``compact``: store starts and lengths in the smallest integer type that holds the grid's
    cells (``int8`` up to 127 cells per dimension, then ``int16``), chunk by chunk, instead of
    ``int32``: 7 instead of 25 bytes per box in 3-D, and no int32 copy of all boxes ever exists
    (what ``abstract(..., kind="smdp")`` asks for; the SMDP stores them so).

    ``structured``: enclose only one noise cell per cell index along each noise axis and assemble
    the boxes from per-dimension pieces (``smdpjax.abstraction.structured``; the same boxes bit
    for bit, 4-7x faster), for a ``System.additive`` with one nonzero per row of B. ``None``
    (default): where ``structured.pays_off``; ``False``: enclose every box.
    """
    rows = validate(system, grid, noise_grid)
    actions = policy_actions(system, grid, rows, policy)
    prob, prob_rest = noise_grid.probabilities(system.noise)
    w_lo, w_hi = noise_grid.boxes()
    box_dtype = small_int(int(np.max(grid.cells))) if compact else jnp.int32
    per_row = (1 if policy is not None else system.num_actions) * noise_grid.num_bounded
    _require_memory(grid, rows.size, per_row, np.dtype(box_dtype).itemsize)
    from .structured import expanded_boxes, pays_off, structured_clusters

    if structured or (structured is None and pays_off(system, grid, noise_grid)):
        _, pieces, _, _ = structured_clusters(system, grid, noise_grid, method=method, policy=policy, progress=progress,
                                              mesh=mesh)
        return GridClusters(rows=rows, boxes=expanded_boxes(pieces, np.dtype(box_dtype).name), prob=prob,
                            prob_rest=prob_rest, noise_shape=noise_grid.shape)
    decode = functools.partial(_decode, dtype=np.dtype(box_dtype).name)
    boxes = snapped_boxes(system, grid, rows, actions, w_lo, w_hi, decode, method=method, progress=progress,
                          mesh=mesh)
    return GridClusters(rows=rows, boxes=boxes, prob=prob, prob_rest=prob_rest, noise_shape=noise_grid.shape)


def snapped_boxes(system: System, grid: StateGrid, rows: np.ndarray, actions, w_lo, w_hi, decode, *,
                  method: str = "both", progress: bool = False, mesh=None):
    """The chunked reachable-set stage: ``decode(codes)`` of the `dimension_codes` ``(n, R_c, A,
    C)`` of every chunk of ``rows``, concatenated along rows (``decode`` returns a PyTree whose
    leaves lead with the chunk's rows). ``actions``: from `policy_actions`; ``w_lo, w_hi: (C, d)``
    the noise boxes. Raises ValueError if the dynamics give NaN bounds anywhere."""
    if method not in ("natural", "centered", "both"):
        raise ValueError(f"unknown reachable-set method {method!r}; expected 'natural', 'centered' or 'both'")
    per_row = (1 if actions.ndim == 3 else actions.shape[0]) * w_lo.shape[0]
    chunk = int(max(1, min(rows.size, BOXES_PER_CHUNK // per_row)))
    place, on_mesh = (lambda a: a), contextlib.nullcontext
    if mesh is not None:
        from ..sharding import padded_rows, row_sharding
        chunk = padded_rows(chunk, mesh)  # whole rows per device
        split = row_sharding(mesh)
        place = functools.partial(jax.device_put, device=split)
        if hasattr(jax, "set_mesh"):  # trace under the mesh: constants then match the inputs'
            on_mesh = functools.partial(jax.set_mesh, split.mesh)  # shardings (no `reshard` ops)
    run = _chunk_fn(system.dynamics, grid, method, bool(system.noise.has_density))
    starts = range(0, rows.size, chunk)
    if progress:
        from tqdm.auto import tqdm
        starts = tqdm(starts, desc="reachable sets", unit="chunk")
    parts, nan_rows = [], []
    for start in starts:
        idx = rows[start:start + chunk]
        padded = np.concatenate([idx, np.full(chunk - idx.size, idx[-1])])  # one compiled shape
        x_lo, x_hi = place(grid.cell_bounds(padded))
        x_open = place(~grid.upper_attained(padded))
        row_actions = actions if actions.ndim == 2 else place(actions[np.minimum(np.arange(start, start + chunk),
                                                                                 rows.size - 1)])
        with on_mesh():
            codes, has_nan = run(x_lo, x_hi, x_open, row_actions, w_lo, w_hi)
        boxes = decode(codes)
        if mesh is not None or idx.size < chunk:
            trim = (lambda a: a[:idx.size]) if mesh is None else (lambda a: np.asarray(a)[:idx.size])  # gathered
            boxes, has_nan = jax.tree.map(trim, boxes), has_nan[:idx.size]
        parts.append(boxes)
        nan_rows.append(np.asarray(has_nan))
    nan_rows = np.concatenate(nan_rows)
    if nan_rows.any():
        cell = int(rows[np.flatnonzero(nan_rows)[0]])
        lo, hi = (np.asarray(b) for b in grid.cell_bounds(cell))
        raise ValueError(f"the reachable-set bounds of cell {cell} (box {lo.tolist()}..{hi.tolist()}) are NaN: "
                         f"the dynamics are undefined somewhere on that cell or its noise cells")
    if len(parts) == 1 and mesh is None:
        return parts[0]
    return jax.tree.map(lambda *a: jnp.concatenate(a), *parts)  # one array on the default device


def _require_memory(grid: StateGrid, rows: int, per_row: int, int_bytes: int = 4) -> None:
    """Refuse clusters that would not fit: the index boxes of every (row, action, noise cell)
    (start and length per dimension, ``int_bytes`` each, a sink flag) twice (the chunks and their
    concatenation) plus one chunk's float64 temporaries."""
    from ..memory import require

    boxes = float(rows) * per_row
    stored = 2 * boxes * (2 * int_bytes * grid.n + 1)
    chunk = min(boxes, BOXES_PER_CHUNK) * grid.n * 8 * 8  # ends, flags, codes and the pieces between
    require(stored + chunk, f"the clusters of {rows} cells x {per_row} (action, noise cell) pairs "
            f"({boxes:.3g} reachable boxes)",
            "use a coarser state grid, fewer noise cells or actions, a fixed policy (policy=), structured "
            "clusters for additive noise (System.additive; abstract(..., 'smdp', encoding='structured') stores "
            "O(cells x actions x cells per noise axis)), or split the rows over several devices (mesh=)")


def _chunk_fn(dynamics, grid: StateGrid, method: str, noise_open: bool):
    """The compiled chunk computation, shared by every grid of the same geometry (a new
    ``StateGrid`` object with the same box, cells and periodicity does not recompile)."""
    geometry = (tuple(grid.low.tolist()), tuple(grid.high.tolist()), tuple(int(c) for c in grid.cells),
                tuple(bool(p) for p in grid.periodic))
    return _chunk_fn_for(dynamics, geometry, method, noise_open)


_decode = jax.jit(decode_boxes, static_argnames="dtype")


@functools.lru_cache(maxsize=32)
def _chunk_fn_for(dynamics, geometry: tuple, method: str, noise_open: bool):
    low, high, cells, periodic = geometry
    grid = StateGrid(np.array(low), np.array(high), np.array(cells), periodic=np.array(periodic))

    # Separate compiled programs, not one: XLA on the CPU fuses the elementwise interval arithmetic
    # into every consumer, so in one program each output of ``index_boxes`` (start, length,
    # sink) and the NaN test recomputed the reachable sets (an optimization barrier is dropped on
    # the CPU). Materializing the boxes in between costs a write and a read of them instead.
    # benchmarks/cpu_layouts.py (retired; figures in docs/performance.md; identical boxes): one program takes 2.0x as long on the 2-D
    # unicycle, 0.98x on the 3-D unicycle and 0.73-1.18x on the 4-room model (cheap affine
    # dynamics) across runs: the split pays where the dynamics are costly to enclose.
    periodic_dims = np.flatnonzero(grid.periodic)
    flat = jnp.asarray(~grid.periodic)

    @jax.jit
    def enclose(x_lo, x_hi, actions, w_lo, w_hi, x_high_open):
        lo, hi, hi_open = reachable_boxes(dynamics, x_lo, x_hi, actions, w_lo, w_hi, method=method,
                                          x_high_open=x_high_open, noise_open=noise_open)
        # Two outputs where the dimensions allow it (see ``snapping_end``), not three; each
        # dimension contiguous (the snapping reads them one at a time).
        hi = jnp.where(flat, snapping_end(hi, hi_open, grid.high), hi)
        return jnp.moveaxis(lo, -1, 0), jnp.moveaxis(hi, -1, 0), jnp.moveaxis(hi_open[..., periodic_dims], -1, 0)

    @jax.jit
    def codes(lo, hi, periodic_open):
        has_nan = jnp.any(jnp.isnan(lo) | jnp.isnan(hi), axis=(0, 2, 3))
        opens = [jnp.zeros(hi.shape[1:], bool)] * grid.n
        for i, d in enumerate(periodic_dims):
            opens[d] = periodic_open[i]
        return dimension_codes(grid, list(lo), list(hi), opens, normal_ends=True), has_nan

    def run(x_lo, x_hi, x_open, actions, w_lo, w_hi):
        return codes(*enclose(x_lo, x_hi, actions, w_lo, w_hi, x_open))

    return run
