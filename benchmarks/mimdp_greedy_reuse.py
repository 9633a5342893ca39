"""MI-MDP synthesis whose first strategy sweeps reuse the greedy backup's multipliers, against a refreeze.

    python -m benchmarks.mimdp_greedy_reuse --rows 3 --repeats 3

After each greedy backup of the optimization (``value_iteration.optimize_lower``), the first
round of strategy sweeps can freeze the multipliers that backup solved for the strategy's actions
(``REUSE_GREEDY_MULTIPLIERS = True``, the default) instead of solving the strategy's LPs again.
For each Table 1 MI-MDP row the clusters are computed once; then, ``--repeats`` rounds, each mode
builds a fresh MI-MDP (no warm starts carried over) and runs ``study.solve`` (T_syn as Table 1
times it), the two modes alternating in one process so that both see the same load. Reports the
medians of T_syn and of the LP wall time, the LP calls and HiGHS solves of the last run, and the
largest difference of the bounds between the modes.
"""

from __future__ import annotations

import time

import jax
import numpy as np

from .common import argument_parser, median, row_clusters, write_result

MODES = {"reuse": True, "refreeze": False}


def measure(row: int, repeats: int) -> dict:
    from smdpjax.abstraction import build
    from smdpjax.synthesis import value_iteration

    study, clusters = row_clusters(row, "mimdp")
    times = {name: [] for name in MODES}
    lp_times = {name: [] for name in MODES}
    stats, solutions = {}, {}
    default = value_iteration.REUSE_GREEDY_MULTIPLIERS
    try:
        for _ in range(max(1, repeats)):
            for name, reuse in MODES.items():
                value_iteration.REUSE_GREEDY_MULTIPLIERS = reuse  # read when the loop is traced
                mimdp = build("mimdp", study.state_grid, clusters, lp_backend="highs")  # a new model: a new trace
                start = time.perf_counter()
                solutions[name] = jax.block_until_ready(study.solve(mimdp))
                times[name].append(time.perf_counter() - start)
                lp_times[name].append(float(mimdp.lps.stats["solve_seconds"]))
                stats[name] = dict(calls=int(mimdp.lps.stats["calls"]), solves=int(mimdp.lps.stats["Optimal"]),
                                   repriced=int(mimdp.lps.stats["repriced"]))
    finally:
        value_iteration.REUSE_GREEDY_MULTIPLIERS = default
    ours, theirs = solutions["reuse"], solutions["refreeze"]
    diff = max(float(np.max(np.abs(np.asarray(getattr(ours, f)) - np.asarray(getattr(theirs, f)))))
               for f in ("lower", "upper", "lower_optimal"))
    return dict(row=row, states=study.state_grid.num_states, actions=study.num_actions, runs_s=times,
                lp_runs_s=lp_times, t_syn_s={n: median(t) for n, t in times.items()},
                lp_s={n: median(t) for n, t in lp_times.items()}, stats=stats,
                backups={n: int(s.iterations) + int(s.evaluation_iterations) for n, s in solutions.items()},
                max_bound_difference=diff)


def main(argv=None):
    parser = argument_parser(__doc__, "mimdp_greedy_reuse", repeats=3)
    parser.add_argument("--rows", default="3", help="Table 1 MI-MDP rows")
    args = parser.parse_args(argv)
    results = []
    print(f"{'row':>4} {'mode':9} {'T_syn s':>8} {'LP s':>7} {'LP calls':>9} {'HiGHS':>7} {'repriced':>9} "
          f"{'backups':>8} {'max diff':>9}")
    for row in (int(r) for r in args.rows.split(",")):
        r = measure(row, args.repeats)
        results.append(r)
        for name in MODES:
            s = r["stats"][name]
            print(f"{row:>4} {name:9} {r['t_syn_s'][name]:>8.2f} {r['lp_s'][name]:>7.2f} {s['calls']:>9} "
                  f"{s['solves']:>7} {s['repriced']:>9} {r['backups'][name]:>8} {r['max_bound_difference']:>9.1e}",
                  flush=True)
    print("wrote", write_result("mimdp_greedy_reuse", args, rows=results))


if __name__ == "__main__":
    main()
