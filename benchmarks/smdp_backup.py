"""One SMDP Bellman backup, index boxes + range minima vs padded member lists.

A backup is ``max_a q(s, a)`` with ``q = SMDP.q_values(v, "min")`` (Theorem 4: a min over every
cluster, a sum over noise cells), jitted with the abstraction as an argument; the time is the
median of ``--repeats`` runs after a compiling warm-up, on a fixed random value vector. Both
encodings are built from the same clusters and must give identical backups (checked).

Cases: the 2-D unicycle of ``core_2d`` at 30x30 and 75x75 cells (8 actions, 12x12 + 1 noise
cells), and the 3-D friction unicycle of shared/benchmarks.md section 2 at 30x30x30 (heading
periodic, 10 actions, 6x6 + 1 = 37 noise cells). The member lists of the 3-D case (and their
float64 gather temporaries) can exceed a small machine's memory: a case whose estimate exceeds
``--memory-limit-gb`` is skipped with a note.

    python -m benchmarks.smdp_backup [--quick] [--repeats 7] [--memory-limit-gb 6]
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import smdpjax as sj
from smdpjax.abstraction import SMDP, compute_grid_clusters
from smdpjax.abstraction.clusters import index_dtype, max_lengths

from .common import argument_parser, median, timed, write_result
from .core_2d import problem as unicycle_2d_problem


def friction_unicycle(x, u, w):
    """shared/benchmarks.md section 2: s = max(v_a - w1, 0); heading th periodic, dt = 0.1."""
    speed = jnp.maximum(u[0] - w[0], 0.0)
    return jnp.array([x[0] + 0.1 * speed * jnp.cos(x[2]), x[1] + 0.1 * speed * jnp.sin(x[2]),
                      x[2] + 0.1 * (u[1] + w[1])])


def unicycle_3d_problem(cells: int = 30, noise_cells: int = 6):
    actions = [[v, om] for v in (0.5, 1.5) for om in (-6.0, -3.0, 0.0, 3.0, 6.0)]
    system = sj.System(friction_unicycle, actions=actions, noise=sj.Gaussian([0.4, 0.0], [0.5, 0.5]))
    grid = sj.StateGrid([0, 0, 0], [1, 1, 2 * np.pi], cells, periodic=[False, False, True],
                        reach=[([0.7, 0.7, 0], [1.0, 1.0, 2 * np.pi])],
                        avoid=[([0.40, 0.30, 0], [0.60, 0.70, 2 * np.pi])])
    return system, grid, sj.NoiseGrid.ball([0.4, 0.0], 2.0, noise_cells)


def members_memory(grid, clusters) -> tuple[int, int]:
    """(bytes of the padded member lists, bytes of one backup's float64 gather of them)."""
    k = int(np.prod(max_lengths(clusters.boxes))) + 1
    count = int(np.prod(clusters.boxes.sink.shape)) * k
    return count * np.dtype(index_dtype(grid.num_states)).itemsize, count * 8


def run_case(name, system, grid, noise, repeats, limit_bytes):
    start = time.perf_counter()
    clusters = compute_grid_clusters(system, grid, noise)
    t_clusters = time.perf_counter() - start
    backup = jax.jit(lambda smdp, v: smdp.q_values(v, "min").max(axis=1))
    v = jnp.asarray(np.random.default_rng(0).uniform(size=grid.num_states))
    rows, results = [], {}
    for encoding in ("boxes", "members"):
        base = dict(case=name, states=grid.num_states, rows=int(clusters.rows.size), actions=system.num_actions,
                    noise_cells=noise.num_cells, encoding=encoding, clusters_s=t_clusters)
        if encoding == "members":
            stored, gathered = members_memory(grid, clusters)
            if stored + gathered > limit_bytes:
                note = (f"skipped: member lists {stored / 1e9:.2f} GB + gather temporaries {gathered / 1e9:.2f} GB "
                        f"exceed --memory-limit-gb {limit_bytes / 1e9:g}")
                print(f"  {name} members: {note}")
                rows.append(dict(base, skipped=note, bytes=stored))
                continue
        smdp = SMDP.from_clusters(grid, clusters, encoding=encoding)
        out, times = timed(lambda: backup(smdp, v), repeats)
        results[encoding] = np.asarray(out)
        rows.append(dict(base, bytes=smdp.nbytes, ms=1e3 * median(times), runs_ms=[1e3 * t for t in times],
                         repr=repr(smdp)))
        smdp = None  # free this encoding's arrays before building the next
    if len(results) == 2 and not np.array_equal(results["boxes"], results["members"]):
        raise AssertionError(f"{name}: the two encodings gave different backups")
    timed_rows = {r["encoding"]: r for r in rows if "ms" in r}
    if len(timed_rows) == 2:
        timed_rows["boxes"]["speedup_vs_members"] = timed_rows["members"]["ms"] / timed_rows["boxes"]["ms"]
    members = next(r for r in rows if r["encoding"] == "members")
    boxes = next(r for r in rows if r["encoding"] == "boxes")
    boxes["bytes_ratio_members"] = members["bytes"] / boxes["bytes"]
    return rows


def main(argv=None):
    parser = argument_parser(__doc__, "smdp_backup", repeats=7,
                             repeats_help="timed backups after the warm-up (median reported)")
    parser.add_argument("--quick", action="store_true", help="smaller sizes: 2-D at 30x30, 3-D at 15x15x15")
    parser.add_argument("--memory-limit-gb", type=float, default=6.0,
                        help="skip an encoding whose estimated memory exceeds this")
    args = parser.parse_args(argv)

    cases = [("2-D unicycle", unicycle_2d_problem, (30,) if args.quick else (30, 75)),
             ("3-D friction unicycle", unicycle_3d_problem, (15,) if args.quick else (30,))]
    rows = []
    for label, make, sizes in cases:
        for cells in sizes:
            system, grid, noise = make(cells)
            name = f"{label} {'x'.join(map(str, grid.cells.tolist()))}"
            print(f"{name}: {grid!r}, {noise!r}")
            rows += run_case(name, system, grid, noise, args.repeats, args.memory_limit_gb * 1e9)

    header = (f"{'case':32} {'|S|':>6} {'rows':>6} {'|A|':>3} {'|C|':>4} {'encoding':8} {'MB':>9} {'ms/backup':>10} "
              f"{'bytes x':>8} {'speedup':>8}")
    print()
    print(header)
    print("-" * len(header))
    for r in rows:
        ms = f"{r['ms']:10.2f}" if "ms" in r else f"{'skipped':>10}"
        ratio = f"{r['bytes_ratio_members']:8.1f}" if "bytes_ratio_members" in r else f"{'':8}"
        speedup = f"{r['speedup_vs_members']:8.2f}" if "speedup_vs_members" in r else f"{'':8}"
        print(f"{r['case']:32} {r['states']:6d} {r['rows']:6d} {r['actions']:3d} {r['noise_cells']:4d} "
              f"{r['encoding']:8} {r['bytes'] / 1e6:9.2f} {ms} {ratio} {speedup}")
    print("\nbytes x: member-list bytes / index-box bytes (the paper's memory metric, whole abstraction); "
          "speedup: member-list ms / index-box ms")
    write_result("smdp_backup", args, rows=rows)
    print(f"wrote {args.out}")
    return rows


if __name__ == "__main__":
    main()
