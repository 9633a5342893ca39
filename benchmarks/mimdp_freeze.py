"""MI-MDP synthesis with frozen multipliers in the strategy sweeps against an LP per row at every sweep.

    python -m benchmarks.mimdp_freeze --sizes 30 --repeats 2

For each 2-D unicycle size (the Table 1 system, ``size x size`` cells), the MI-MDP (HiGHS) is
built twice from the same reachable sets: with ``freeze_multipliers=True`` (the default; 32
sweeps per greedy backup with the multipliers refrozen every 8, ``value_iteration``) and
``False`` (8 sweeps, each solving one LP per row, the previous behaviour). Each is synthesized
once to compile and warm HiGHS's bases, then ``--repeats`` more times; the table gives the median
of those, the LPs solved and the backups of the first run, and the largest difference of
p_low / p_up between the two (both are sound; they stop at ``--tol`` from different sides of
the iteration). Writes ``--out`` (JSON).
"""

from __future__ import annotations


import jax
import numpy as np

from smdpjax import case_studies, synthesize
from smdpjax.abstraction import build, compute_grid_clusters

from .common import argument_parser, median, timed, write_result


def _lps_solved(mimdp) -> int:
    stats = mimdp.lps.stats
    return int(sum(count for status, count in stats.items() if status in ("Optimal", "Solved", "AlmostSolved")))


def main(argv=None):
    parser = argument_parser(__doc__, "mimdp_freeze", repeats=2,
                             repeats_help="timed runs per mode after the first (median reported)", tol=1e-6)
    parser.add_argument("--sizes", default="30", help="comma-separated cells per axis of the 2-D unicycle")
    args = parser.parse_args(argv)
    results = []
    print(f"{'size':>4} {'|S|':>6} {'mode':8} {'median s':>9} {'runs s':>20} {'LPs':>8} {'backups':>8} "
          f"{'max |d p_low|':>13} {'max |d p_up|':>12}")
    for size in (int(s) for s in args.sizes.split(",")):
        study = case_studies.unicycle_2d(size)
        clusters = compute_grid_clusters(study.system, study.state_grid, study.noise_grid, method=study.reach_method)
        runs, sols = {}, {}
        for mode, freeze in (("frozen", True), ("LP each", False)):
            mimdp = build("mimdp", study.state_grid, clusters, lp_backend="highs", freeze_multipliers=freeze)
            first = jax.block_until_ready(synthesize(mimdp, tol=args.tol))
            lps_first = _lps_solved(mimdp)
            sols[mode], times = first, []
            for _ in range(args.repeats):  # the first run was the warm-up: each of these is timed
                sols[mode], (seconds,) = timed(lambda: synthesize(mimdp, tol=args.tol), 0)
                times.append(seconds)
            runs[mode] = dict(runs_s=times, median_s=median(times) if times else None, lps_first_run=lps_first,
                              backups=int(first.iterations) + int(first.evaluation_iterations))
        d_low = float(np.max(np.abs(np.asarray(sols["frozen"].lower) - np.asarray(sols["LP each"].lower))))
        d_up = float(np.max(np.abs(np.asarray(sols["frozen"].upper) - np.asarray(sols["LP each"].upper))))
        for mode, r in runs.items():
            shown = " ".join(f"{t:.1f}" for t in r["runs_s"])
            med = f"{r['median_s']:9.1f}" if r["median_s"] is not None else f"{'-':>9}"
            print(f"{size:4d} {study.state_grid.num_states:6d} {mode:8} {med} {shown:>20} {r['lps_first_run']:8d} "
                  f"{r['backups']:8d} {d_low:13.1e} {d_up:12.1e}", flush=True)
        results.append(dict(size=size, states=study.state_grid.num_states, runs=runs, max_diff_lower=d_low,
                            max_diff_upper=d_up))
        write_result("mimdp_freeze", args, repeats=args.repeats, tol=args.tol, sizes=results)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
