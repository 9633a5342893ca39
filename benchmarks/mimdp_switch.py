"""MI-MDP synthesis with one of its switches on (the default) and off, side by side.

    python -m benchmarks.mimdp_switch --switch greedy_reuse --rows 3 --repeats 3

The switches (module constants; the first two are read when the synthesis is traced):

* ``greedy_reuse`` (``value_iteration.REUSE_GREEDY_MULTIPLIERS``): value iteration's first round of
  strategy sweeps after a greedy backup freezes the multipliers that backup solved for the
  strategy's actions, instead of solving the strategy's LPs again (``--method value_iteration``);
* ``greedy_screen`` (``policy_iteration.SCREEN_BY_STRATEGY_VALUE``): policy iteration's greedy
  backups solve only the LPs of actions whose screen value exceeds the strategy's value, not
  those of the current actions, instead of every action that could be a row's best;
* ``reprice_after_pivots`` (``lp.REPRICE_AFTER_PIVOTS``, read at every LP call): a large basis
  that HiGHS reached by pivoting is re-priced at the next call, instead of only one from which
  HiGHS took no simplex iteration;
* ``presolve`` (``lp.PRESOLVE``, read when a solver thread sets up its HiGHS instance): HiGHS
  presolves the LPs it solves from no basis (its own default; "on" here is the mode that is not
  the library's default).

For each Table 1 MI-MDP row the clusters are computed once; then, ``--repeats`` rounds, each mode
builds a fresh MI-MDP (no warm starts carried over) and runs ``synthesize`` with ``--method``, the two
modes alternating in one process so that both see the same load. A switch read when the loop is
traced needs a new model per run, so its T_syn includes the compilation; a host-side switch
(``reprice_after_pivots``, ``presolve``) uses one model, compiled by a first run not counted, and drops its LP
solvers and warm starts before each run (``ClusterLPs.reset``): T_syn as Table 1's warm runs time it. Reports the
medians of T_syn and of the LP wall time, the LP calls, HiGHS solves, re-priced LPs and adversary
steps (``worst_case_transitions`` calls) of the last run, and the largest difference of the bounds
between the modes.
"""

from __future__ import annotations

import time

import jax
import numpy as np

from .common import argument_parser, median, row_clusters, write_result

MODES = {"on": True, "off": False}
# switch: (module, flag, read on the host at every call)
SWITCHES = {"greedy_reuse": ("smdpjax.synthesis.value_iteration", "REUSE_GREEDY_MULTIPLIERS", False),
            "greedy_screen": ("smdpjax.synthesis.policy_iteration", "SCREEN_BY_STRATEGY_VALUE", False),
            "reprice_after_pivots": ("smdpjax.abstraction.lp", "REPRICE_AFTER_PIVOTS", True),
            "presolve": ("smdpjax.abstraction.lp", "PRESOLVE", True)}


def measure(row: int, repeats: int, switch: str, method: str | None) -> dict:
    import importlib

    from smdpjax.abstraction import build

    study, clusters = row_clusters(row, "mimdp")
    times = {name: [] for name in MODES}
    lp_times = {name: [] for name in MODES}
    stats, solutions = {}, {}
    module_name, flag, on_host = SWITCHES[switch]
    module = importlib.import_module(module_name)
    default = getattr(module, flag)
    from smdpjax import synthesize
    from smdpjax.abstraction.mimdp import MIMDP

    steps = [0]
    worst_case_transitions = MIMDP.worst_case_transitions

    def counted(self, *args, **kwargs):
        steps[0] += 1
        return worst_case_transitions(self, *args, **kwargs)

    solve = lambda model: jax.block_until_ready(synthesize(model, horizon=study.horizon, objective=study.objective,
                                                           method=method))
    if on_host:
        shared = build("mimdp", study.state_grid, clusters, lp_backend="highs")
        solve(shared)  # compiles; not counted
    MIMDP.worst_case_transitions = counted
    try:
        for _ in range(max(1, repeats)):
            for name, on in MODES.items():
                setattr(module, flag, on)
                if on_host:
                    mimdp = shared
                    mimdp.lps.reset()  # no warm starts carried over
                    before = dict(mimdp.lps.stats)
                else:  # read when the loop is traced: a new model, a new trace
                    mimdp = build("mimdp", study.state_grid, clusters, lp_backend="highs")
                    before = {}
                steps[0] = 0
                start = time.perf_counter()
                solutions[name] = solve(mimdp)
                times[name].append(time.perf_counter() - start)
                spent = lambda key: mimdp.lps.stats[key] - before.get(key, 0)
                lp_times[name].append(float(spent("solve_seconds")))
                stats[name] = dict(calls=int(spent("calls")), solves=int(spent("Optimal")), repriced=int(spent("repriced")),
                                   steps=steps[0])
    finally:
        setattr(module, flag, default)
        MIMDP.worst_case_transitions = worst_case_transitions
    ours, theirs = solutions["on"], solutions["off"]
    diff = max(float(np.max(np.abs(np.asarray(getattr(ours, f)) - np.asarray(getattr(theirs, f)))))
               for f in ("lower", "upper", "lower_optimal"))
    return dict(row=row, switch=switch, states=study.state_grid.num_states, actions=study.num_actions, runs_s=times,
                lp_runs_s=lp_times, t_syn_s={n: median(t) for n, t in times.items()},
                lp_s={n: median(t) for n, t in lp_times.items()}, stats=stats,
                backups={n: int(s.iterations) + int(s.evaluation_iterations) for n, s in solutions.items()},
                max_bound_difference=diff)


def main(argv=None):
    parser = argument_parser(__doc__, "mimdp_switch", repeats=3)
    parser.add_argument("--rows", default="3", help="Table 1 MI-MDP rows")
    parser.add_argument("--switch", choices=sorted(SWITCHES), required=True)
    parser.add_argument("--method", choices=("policy_iteration", "value_iteration"), default=None,
                        help="synthesis method (default: value iteration for greedy_reuse, else policy iteration)")
    args = parser.parse_args(argv)
    results = []
    print(f"{'row':>4} {'mode':9} {'T_syn s':>8} {'LP s':>7} {'LP calls':>9} {'HiGHS':>7} {'repriced':>9} "
          f"{'steps':>6} {'backups':>8} {'max diff':>9}")
    for row in (int(r) for r in args.rows.split(",")):
        method = args.method or ("value_iteration" if args.switch == "greedy_reuse" else "policy_iteration")
        r = measure(row, args.repeats, args.switch, method)
        results.append(r)
        for name in MODES:
            s = r["stats"][name]
            print(f"{row:>4} {name:9} {r['t_syn_s'][name]:>8.2f} {r['lp_s'][name]:>7.2f} {s['calls']:>9} "
                  f"{s['solves']:>7} {s['repriced']:>9} {s['steps']:>6} {r['backups'][name]:>8} {r['max_bound_difference']:>9.1e}",
                  flush=True)
    print("wrote", write_result(f"mimdp_switch_{args.switch}", args, rows=results))


if __name__ == "__main__":
    main()
