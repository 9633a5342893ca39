"""Achieved memory bandwidth of one SMDP Bellman backup on the largest Table 1 rows.

    python -m benchmarks.bandwidth [--rows 16,28,40] [--peak-gbs 3350] [--out results/bandwidth.json]

One backup is ``max_a sum_c P_W(c) min_{s' in q(s,a,c)} v(s')`` for every row (index-box
clusters, range minima from a sparse table rebuilt from ``v``). The bytes it *must* touch are the
cluster encoding (start, length, sink of every (s, a, c)), ``v`` and the new values; the sparse
table adds its levels (written once, then gathered 2^n times per cluster, mostly from cache).
We report both byte counts over the median backup time, and the ratio of the card's peak
bandwidth to the achieved one on the compulsory bytes ("x from the bound": 1 would be
bandwidth-bound; the target is within 3x). ``--peak-gbs`` defaults to the H100 SXM's 3350 GB/s
on a GPU named H100, 4800 on an H200, and is left out on a CPU.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import smdpjax as sj
from smdpjax.abstraction import build, compute_grid_clusters

from .common import argument_parser, write_result
from .paper_table1 import parse_rows, row_spec
from .table1 import case_study

PEAK_GBS = {"H100": 3350.0, "H200": 4800.0}


def _peak(default):
    if default is not None:
        return default
    device = jax.devices()[0]
    name = getattr(device, "device_kind", "")
    return next((gbs for key, gbs in PEAK_GBS.items() if key in name), None)


def measure(row: int, repeats: int, quick: bool = False) -> dict:
    spec = row_spec(row)
    study = case_study(spec, quick)
    clusters = compute_grid_clusters(study.system, study.state_grid, study.noise_grid, policy=study.controller)
    smdp = build("smdp", study.state_grid, clusters)
    if smdp.encoding != "boxes":
        raise RuntimeError(f"row {row}: expected the index-box encoding, got {smdp.encoding}")

    @jax.jit
    def backup(smdp, v):  # the abstraction is an argument: as a closed-over constant XLA would fold it
        return v.at[smdp.rows].set(smdp.q_values(v, "min").max(axis=1))

    @jax.jit
    def fused_backup(smdp, v):  # q_values without its optimization barrier: XLA may fuse the sum
        worst = smdp.clusters.extreme(v, True)
        return v.at[smdp.rows].set((worst @ smdp.prob + smdp.prob_rest * v.min()).max(axis=1))

    smdp = jax.device_put(smdp)
    v = jax.device_put(jnp.asarray(np.random.default_rng(0).uniform(size=smdp.num_states)))

    def median_time(fn):
        jax.block_until_ready(fn(smdp, v))
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            jax.block_until_ready(fn(smdp, v))
            times.append(time.perf_counter() - start)
        return float(np.median(times)), times

    seconds, times = median_time(backup)
    fused_seconds, _ = median_time(fused_backup)
    c = smdp.clusters
    encoding_bytes = c.start.nbytes + c.length.nbytes + c.sink.nbytes + smdp.prob.nbytes
    value_bytes = 2 * smdp.num_states * 8
    levels = int(np.prod([int(np.floor(np.log2(max(m, 1)))) + 1 for m in c.spec.max_lengths]))
    table_bytes = 2 * levels * (smdp.num_states - 1) * 8  # each level written and read once at least
    compulsory = encoding_bytes + value_bytes
    return dict(row=row, system=spec.system, states=smdp.num_states, rows=smdp.num_rows, actions=smdp.num_actions,
                noise_cells=int(smdp.prob.shape[0]), max_box=list(c.spec.max_lengths), table_levels=levels,
                backup_ms=seconds * 1e3, backup_runs_ms=[t * 1e3 for t in times], fused_backup_ms=fused_seconds * 1e3, compulsory_bytes=int(compulsory),
                with_table_bytes=int(compulsory + table_bytes),
                achieved_gbs=compulsory / seconds / 1e9, achieved_with_table_gbs=(compulsory + table_bytes) / seconds / 1e9)


def main(argv=None):
    parser = argument_parser(__doc__, "bandwidth", repeats=20, repeats_help="timed backups (median reported)")
    parser.add_argument("--rows", default="16,28,40", help="Table 1 SMDP rows")
    parser.add_argument("--peak-gbs", type=float, default=None, help="the device's memory bandwidth, GB/s")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    peak = _peak(args.peak_gbs)
    results = []
    print(f"{'row':>3} {'system':12} {'|S|':>6} {'R x A x C_b':>18} {'ms/backup':>9} {'MB compulsory':>13} "
          f"{'GB/s':>7} {'GB/s w/ table':>13} {'x from bound':>12} {'ms no barrier':>13}")
    for row in parse_rows(args.rows):
        r = measure(row, args.repeats, args.quick)
        r["peak_gbs"] = peak
        r["x_from_bound"] = peak / r["achieved_gbs"] if peak else None
        results.append(r)
        shape = f"{r['rows']}x{r['actions']}x{r['noise_cells']}"
        bound = f"{r['x_from_bound']:.1f}x" if peak else "-"
        print(f"{row:3d} {r['system']:12} {r['states']:6d} {shape:>18} {r['backup_ms']:9.3f} "
              f"{r['compulsory_bytes'] / 1e6:13.1f} {r['achieved_gbs']:7.1f} {r['achieved_with_table_gbs']:13.1f} "
              f"{bound:>12} {r['fused_backup_ms']:13.3f}", flush=True)
    write_result("bandwidth", args, peak_gbs=peak, rows=results)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
