"""MI-MDP synthesis with the LPs' last optimal bases re-priced against HiGHS at every LP.

For each Table 1 MI-MDP row the clusters are computed once; then the MI-MDP is built and
``study.solve`` (T_syn as Table 1 times it, a fresh build each time so that both start without
warm starts) runs alternately with re-pricing (``reprice_bases=True``, the default) and without,
``--repeats`` times each, in one process, so that both see the same load. Reports the medians of
T_syn and of the LP wall time, the HiGHS solves and re-priced LPs of the last run, their ratios,
and the largest difference of the bounds.

    python -m benchmarks.mimdp_reprice --rows 3,35 [--repeats 1]
"""

from __future__ import annotations

import time

import jax
import numpy as np

from .common import argument_parser, median, row_clusters, write_result

VARIANTS = {"repriced": True, "HiGHS every LP": False}


def measure(row: int, repeats: int) -> dict:
    from smdpjax.abstraction import build

    study, clusters = row_clusters(row, "mimdp")
    times = {name: [] for name in VARIANTS}
    lp_times = {name: [] for name in VARIANTS}
    stats, solutions = {}, {}
    for _ in range(max(1, repeats)):
        for name, reprice in VARIANTS.items():
            mimdp = build("mimdp", study.state_grid, clusters, lp_backend="highs", reprice_bases=reprice)
            start = time.perf_counter()
            solutions[name] = jax.block_until_ready(study.solve(mimdp))
            times[name].append(time.perf_counter() - start)
            lp_times[name].append(float(mimdp.lps.stats["solve_seconds"]))
            stats[name] = dict(solved=int(mimdp.lps.stats["Optimal"]), repriced=int(mimdp.lps.stats["repriced"]))
    ours, theirs = solutions["repriced"], solutions["HiGHS every LP"]
    diff = max(float(np.max(np.abs(np.asarray(getattr(ours, f)) - np.asarray(getattr(theirs, f)))))
               for f in ("lower", "upper", "lower_optimal"))
    return dict(row=row, states=study.state_grid.num_states, actions=study.num_actions,
                t_syn_repriced_s=median(times["repriced"]), t_syn_highs_s=median(times["HiGHS every LP"]),
                lp_repriced_s=median(lp_times["repriced"]), lp_highs_s=median(lp_times["HiGHS every LP"]),
                solves_repriced=stats["repriced"]["solved"], repriced=stats["repriced"]["repriced"],
                solves_highs=stats["HiGHS every LP"]["solved"], t_syn_runs=times, lp_runs=lp_times,
                iterations=int(ours.iterations), max_bound_difference=diff,
                same_policy=bool(np.array_equal(np.asarray(ours.policy), np.asarray(theirs.policy))))


def main(argv=None):
    parser = argument_parser(__doc__, "mimdp_reprice", repeats=1)
    parser.add_argument("--rows", default="3,35", help="Table 1 MI-MDP rows")
    args = parser.parse_args(argv)
    results = []
    print(f"{'row':>4} {'T_syn repriced':>15} {'every LP':>9} {'ratio':>6} {'LP s':>8} {'every LP':>9} {'ratio':>6} "
          f"{'HiGHS solves':>13} {'repriced':>9} {'every LP':>9} {'max diff':>9}")
    for row in (int(r) for r in args.rows.split(",")):
        r = measure(row, args.repeats)
        results.append(r)
        print(f"{row:>4} {r['t_syn_repriced_s']:>15.2f} {r['t_syn_highs_s']:>9.2f} "
              f"{r['t_syn_highs_s'] / r['t_syn_repriced_s']:>5.2f}x {r['lp_repriced_s']:>8.2f} {r['lp_highs_s']:>9.2f} "
              f"{r['lp_highs_s'] / max(r['lp_repriced_s'], 1e-9):>5.2f}x {r['solves_repriced']:>13} "
              f"{r['repriced']:>9} {r['solves_highs']:>9} {r['max_bound_difference']:>9.1e}", flush=True)
    print("wrote", write_result("mimdp_reprice", args, rows=results))


if __name__ == "__main__":
    main()
