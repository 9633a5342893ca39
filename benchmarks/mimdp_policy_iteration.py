"""MI-MDP synthesis by policy iteration against value iteration, side by side.

    python -m benchmarks.mimdp_policy_iteration --rows 3 --repeats 3

For each Table 1 MI-MDP row the clusters are computed once; then, ``--repeats`` rounds, each
method builds a fresh MI-MDP (HiGHS, no warm starts carried over) and runs ``synthesize(...,
method=...)`` at ``--tol`` (T_syn as Table 1 times it, compilation included), the methods
alternating in one process so that both see the same load. Reports the medians of T_syn and of
the LP wall time, the LP calls, HiGHS solves and re-priced LPs, the greedy backups (and the
adversary's linear solves) of the optimization and the evaluation's backups of the last run,
the mean certified p_low and p_up, and the largest differences of the bounds between the methods
(``lower`` of policy iteration minus value iteration's: its smallest and largest entry).
"""

from __future__ import annotations

import time

import jax
import numpy as np

from .common import argument_parser, median, row_clusters, write_result

METHODS = ("policy_iteration", "value_iteration")


def measure(row: int, repeats: int, tol: float) -> dict:
    from smdpjax import synthesize
    from smdpjax.abstraction import build
    from smdpjax.synthesis import policy_iteration

    study, clusters = row_clusters(row, "mimdp")
    if study.controller is not None:
        raise ValueError(f"row {row} verifies a fixed controller: nothing to optimize")
    times = {name: [] for name in METHODS}
    lp_times = {name: [] for name in METHODS}
    stats, solutions, steps = {}, {}, {}
    optimize = policy_iteration.optimize

    def counting(*args, **kwargs):  # the adversary's linear solves of the last run
        found = optimize(*args, **kwargs)
        steps["policy_iteration"] = None if found is None else int(found[3])
        return found

    policy_iteration.optimize = counting
    try:
        for _ in range(max(1, repeats)):
            for name in METHODS:
                mimdp = build("mimdp", study.state_grid, clusters, lp_backend="highs")
                start = time.perf_counter()
                solutions[name] = jax.block_until_ready(synthesize(mimdp, tol=tol, method=name))
                times[name].append(time.perf_counter() - start)
                lp_times[name].append(float(mimdp.lps.stats["solve_seconds"]))
                stats[name] = dict(calls=int(mimdp.lps.stats["calls"]), solves=int(mimdp.lps.stats["Optimal"]),
                                   repriced=int(mimdp.lps.stats["repriced"]))
    finally:
        policy_iteration.optimize = optimize
    pi, vi = solutions["policy_iteration"], solutions["value_iteration"]
    diff = np.asarray(pi.lower) - np.asarray(vi.lower)
    return dict(row=row, states=study.state_grid.num_states, actions=study.num_actions, tol=tol, runs_s=times,
                lp_runs_s=lp_times, t_syn_s={n: median(t) for n, t in times.items()},
                lp_s={n: median(t) for n, t in lp_times.items()}, stats=stats,
                iterations={n: int(s.iterations) for n, s in solutions.items()},
                evaluation_iterations={n: int(s.evaluation_iterations) for n, s in solutions.items()},
                adversary_solves=steps.get("policy_iteration"),
                converged={n: bool(s.converged) for n, s in solutions.items()},
                p_low_mean={n: float(np.mean(np.asarray(s.lower))) for n, s in solutions.items()},
                p_up_mean={n: float(np.mean(np.asarray(s.upper))) for n, s in solutions.items()},
                lower_difference=(float(diff.min()), float(diff.max())),
                upper_difference=float(np.max(np.abs(np.asarray(pi.upper) - np.asarray(vi.upper)))),
                same_policy=bool(np.array_equal(np.asarray(pi.policy), np.asarray(vi.policy))))


def main(argv=None):
    parser = argument_parser(__doc__, "mimdp_policy_iteration", repeats=3, tol=1e-6)
    parser.add_argument("--rows", default="3", help="Table 1 MI-MDP rows (with a synthesized controller)")
    args = parser.parse_args(argv)
    results = []
    print(f"{'row':>4} {'method':17} {'T_syn s':>8} {'LP s':>7} {'calls':>6} {'HiGHS':>7} {'repriced':>9} "
          f"{'iters':>6} {'eval':>5} {'p_low mean':>12} {'p_up mean':>10}")
    for row in (int(r) for r in args.rows.split(",")):
        r = measure(row, args.repeats, args.tol)
        results.append(r)
        for name in METHODS:
            s = r["stats"][name]
            print(f"{row:>4} {name:17} {r['t_syn_s'][name]:>8.2f} {r['lp_s'][name]:>7.2f} {s['calls']:>6} "
                  f"{s['solves']:>7} {s['repriced']:>9} {r['iterations'][name]:>6} "
                  f"{r['evaluation_iterations'][name]:>5} {r['p_low_mean'][name]:>12.9f} {r['p_up_mean'][name]:>10.7f}",
                  flush=True)
        low, high = r["lower_difference"]
        print(f"     p_low (policy - value iteration) in [{low:.1e}, {high:.1e}], |d p_up| <= "
              f"{r['upper_difference']:.1e}, adversary solves {r['adversary_solves']}, same strategy "
              f"{r['same_policy']}", flush=True)
    print("wrote", write_result("mimdp_policy_iteration", args, rows=results))


if __name__ == "__main__":
    main()
