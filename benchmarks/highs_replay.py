"""HiGHS options on the exact sequence of solves of an MI-MDP synthesis, replayed side by side.

    python -m benchmarks.highs_replay --rows 3 --options '[{"presolve": "on"}, {}]' --repeats 3

For each Table 1 MI-MDP row, one synthesis (``lp_backend="highs"``, one LP thread) is run while
every HiGHS solve is captured: the LP (the arrays ``ClusterLPs`` passes to ``Highs.passModel``) and
which LP and adversary direction it is. The captured solves are then replayed in the same order,
once per option set and ``--repeats`` rounds with the option sets alternating: a fresh ``Highs``
instance per replay (the library's settings, then the option set), each LP warm-started from the
basis of its own previous solve in that replay, as ``ClusterLPs`` does. Only the solver's work
is timed (``passModel``, ``setBasis``, ``run``, ``getBasis``), not the re-pricing or the JAX
backups around it. Reports the median time per option set, the simplex iterations, and the
largest difference of the optimal values from the first option set's.

Needs ``highspy``.
"""

from __future__ import annotations

import json
import time

import numpy as np

from .common import argument_parser, median, row_clusters, write_result


def capture(row: int) -> tuple[list, dict]:
    """``([(lp, direction, passModel arguments)], settings)``: every HiGHS solve of one synthesis of
    ``row``, in order, and the HiGHS options the library set (``ClusterLPs.settings``)."""
    import jax

    from smdpjax import synthesize
    from smdpjax.abstraction import build
    from smdpjax.abstraction.lp import ClusterLPs

    study, clusters = row_clusters(row, "mimdp")
    mimdp = build("mimdp", study.state_grid, clusters, lp_backend="highs")
    mimdp.lps.threads = 1  # the solves in one order
    solves = []
    solve = ClusterLPs._solve_highs

    def captured(self, p, direction, cost, out):
        model = tuple(np.array(a) if isinstance(a, np.ndarray) else a for a in self._highs_model(p, cost))
        solves.append((int(p), direction, model))
        return solve(self, p, direction, cost, out)

    ClusterLPs._solve_highs = captured
    try:
        jax.block_until_ready(synthesize(mimdp, horizon=study.horizon, objective=study.objective))
    finally:
        ClusterLPs._solve_highs = solve
    return solves, mimdp.lps.settings


def replay(solves, settings: dict, options: dict):
    """``(seconds, iterations, optimal values)`` of the solves in order, each LP from its last basis."""
    from smdpjax.abstraction.lp import new_highs

    h = new_highs({**settings, **options})  # as ClusterLPs sets up its solvers
    bases, values, iterations = {}, np.empty(len(solves)), 0
    start = time.perf_counter()
    for i, (p, direction, model) in enumerate(solves):
        h.passModel(*model)
        basis = bases.get((p, direction))
        if basis is not None:
            h.setBasis(basis)
        h.run()
        bases[(p, direction)] = h.getBasis()
        info = h.getInfo()
        values[i], iterations = info.objective_function_value, iterations + info.simplex_iteration_count
    return time.perf_counter() - start, iterations, values


def measure(row: int, option_sets: list, repeats: int) -> list:
    """One result per option set: median seconds over ``repeats`` alternating rounds, iterations and
    the largest optimal-value difference from the first set's (the last round's)."""
    solves, settings = capture(row)
    times = [[] for _ in option_sets]
    results = [None] * len(option_sets)
    for _ in range(max(1, repeats)):
        for k, options in enumerate(option_sets):
            seconds, iterations, values = replay(solves, settings, options)
            times[k].append(seconds)
            results[k] = (iterations, values)
    reference = results[0][1]
    return [dict(row=row, options=options, solves=len(solves), seconds=median(times[k]), runs=times[k],
                 iterations=int(results[k][0]), max_value_diff=float(np.max(np.abs(results[k][1] - reference))))
            for k, options in enumerate(option_sets)]


def main(argv=None):
    parser = argument_parser(__doc__, "highs_replay", repeats=3, repeats_help="rounds, option sets alternating")
    parser.add_argument("--rows", default="3", help="comma-separated MI-MDP rows of Table 1")
    parser.add_argument("--options", default='[{"presolve": "on"}, {}]',
                        help="JSON list of HiGHS option sets (each on top of the library's settings)")
    args = parser.parse_args(argv)
    option_sets = json.loads(args.options)
    if not isinstance(option_sets, list) or not all(isinstance(o, dict) for o in option_sets) or not option_sets:
        parser.error("--options must be a JSON list of objects, e.g. '[{}, {\"presolve\": \"on\"}]'")
    rows = []
    print(f"{'row':>4} {'options':40s} {'solves':>7} {'seconds':>8} {'iterations':>10} {'max diff':>9}")
    for row in (int(r) for r in args.rows.split(",")):
        for r in measure(row, option_sets, args.repeats):
            rows.append(r)
            print(f"{row:4d} {json.dumps(r['options']):40s} {r['solves']:7d} {r['seconds']:8.2f} {r['iterations']:10d} "
                  f"{r['max_value_diff']:9.1e}", flush=True)
    write_result("highs_replay", args, rows=rows)
    print(f"wrote {args.out}")
    return rows


if __name__ == "__main__":
    main()
