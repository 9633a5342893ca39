"""MI-MDP synthesis with and without the SMDP screen (``MIMDP.screen``), side by side.

Builds one Table 1 MI-MDP row's clusters once, then for each mode builds the MI-MDP (HiGHS
multipliers) and solves the row once as Table 1 does (``synthesize``, or ``verify`` of the
look-up table on the temperature rows; cold: compilation included, as the table reports MI-MDP
rows), printing T_syn, the backups, the LPs solved and skipped, and how far the bounds of the two
modes are apart (they should agree to LP accuracy). The screen skips the LPs of rows whose IMDP
and SMDP values meet, and in greedy backups those of actions that cannot be the best.

    python -m benchmarks.mimdp_screen [--row 3] [--modes screen,plain] [--out results/mimdp_screen.json]
"""

from __future__ import annotations

import time

import numpy as np

import smdpjax as sj
from smdpjax.abstraction import build, compute_grid_clusters

from .common import argument_parser, write_result
from .paper_table1 import row_spec
from .table1 import case_study


def main(argv=None):
    parser = argument_parser(__doc__, "mimdp_screen", tol=1e-6)
    parser.add_argument("--row", type=int, default=3, help="an MI-MDP row of Table 1")
    parser.add_argument("--modes", default="screen,plain", help="comma-separated: screen, plain")
    args = parser.parse_args(argv)
    spec = row_spec(args.row)
    if spec.kind != "mimdp":
        parser.error(f"row {args.row} is a {spec.kind} row, not an MI-MDP one")
    study = case_study(spec, False)
    clusters = compute_grid_clusters(study.system, study.state_grid, study.noise_grid, policy=study.controller,
                                     method=study.reach_method)
    nonterminal = np.asarray(study.state_grid.nonterminal)
    runs, bounds = {}, {}
    print(f"{'mode':8} {'T_syn s':>8} {'backups':>8} {'eval':>6} {'LPs solved':>11} {'skipped':>9} {'e_avg':>10}")
    for mode in args.modes.split(","):
        if mode not in ("screen", "plain"):
            parser.error(f"unknown mode {mode!r}")
        mimdp = build("mimdp", study.state_grid, clusters, lp_backend="highs", screen_actions=mode == "screen")
        start = time.perf_counter()
        solution = study.solve(mimdp, tol=args.tol)
        seconds = time.perf_counter() - start
        stats = mimdp.lps.stats
        solved = int(sum(v for k, v in stats.items() if k not in ("skipped", "calls") and isinstance(v, int)))
        runs[mode] = dict(t_syn_s=seconds, iterations=solution.iterations,
                          evaluation_iterations=solution.evaluation_iterations, lps_solved=solved,
                          lps_skipped=int(stats.get("skipped", 0)),
                          e_avg=float(sj.metrics.average_error(solution, study.state_grid)))
        bounds[mode] = (np.asarray(solution.lower), np.asarray(solution.upper))
        r = runs[mode]
        print(f"{mode:8} {seconds:8.1f} {r['iterations']:8d} {r['evaluation_iterations']:6d} {solved:11d} "
              f"{r['lps_skipped']:9d} {r['e_avg']:10.6f}", flush=True)
    if len(bounds) == 2:
        (lo_a, up_a), (lo_b, up_b) = bounds.values()
        diff = max(np.abs(lo_a - lo_b)[nonterminal].max(), np.abs(up_a - up_b)[nonterminal].max())
        print(f"max |difference| of p_low, p_up between the modes: {diff:.2e}")
        runs["max_bound_difference"] = float(diff)
    write_result("mimdp_screen", args, row=args.row, runs=runs)


if __name__ == "__main__":
    main()
