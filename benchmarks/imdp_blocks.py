"""The IMDP's and 2I-MDP's inner problems a block of rows at a time against all rows at once.

For each Table 1 row (IMDP, 2I-MDP, or the MI-MDP's relaxation) the abstraction is built once,
then ``study.solve`` (T_syn as Table 1 times it) runs alternately with the rows in blocks (``imdp_compact.inner_blocks``, the
default) and with all rows at once (``block_rows=0``), ``--repeats`` times each after a compiling
run, in one process, so that both see the same load. Reports the medians, their ratio, the
largest difference of the bounds, and one ``q_values`` call of each (median of ``--repeats``).

    python -m benchmarks.imdp_blocks --rows 13,37 [--repeats 3] [--budget 524288]
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from .common import argument_parser, median, write_result


def with_blocks(abstraction, budget: int | None):
    """``abstraction`` (a compact IMDP, a 2I-MDP, or an MI-MDP's relaxation) blocked for
    ``budget`` slots a block (``None``: the library's default; 0: all rows at once)."""
    from smdpjax.abstraction.imdp_compact import CompactIMDP, block_fields
    from smdpjax.abstraction.twolayer import TwoLayerIMDP

    def blocked(a):
        if budget is None:
            return a
        if isinstance(a, TwoLayerIMDP):  # its met pairs per block change with the blocks
            return a.with_block_budget(budget)
        rows = a.list_rows or a.num_rows
        slots = a.num_chunks * a.chunk / rows  # per row and action, as the class counts them
        return dataclasses.replace(a, **block_fields(np.asarray(a.chunk_row), rows, a.num_actions, slots, budget))

    if isinstance(abstraction, (CompactIMDP, TwoLayerIMDP)):
        return blocked(abstraction)
    return dataclasses.replace(abstraction, relaxation=blocked(abstraction.relaxation))


def measure(row: int, repeats: int, budget: int | None) -> dict:
    from smdpjax.abstraction import build, compute_grid_clusters

    from .paper_table1 import row_spec
    from .table1 import case_study

    spec = row_spec(row)
    study = case_study(spec, False)
    clusters = compute_grid_clusters(study.system, study.state_grid, study.noise_grid, policy=study.controller,
                                     method=study.reach_method)
    abstraction = build(spec.kind, study.state_grid, clusters)
    variants = {"blocked": with_blocks(abstraction, budget), "all rows": with_blocks(abstraction, 0)}
    imdp = lambda a: a if not hasattr(a, "relaxation") else a.relaxation  # what q_values times
    v = jax.numpy.asarray(np.random.default_rng(0).random(abstraction.num_states))
    solve_times, call_times, solutions = {k: [] for k in variants}, {k: [] for k in variants}, {}
    call = jax.jit(lambda a, w: a.q_values(w, "min"))  # the abstraction an argument, as synthesize has it
    for name, a in variants.items():  # compile
        solutions[name] = jax.block_until_ready(study.solve(a))
        jax.block_until_ready(call(imdp(a), v))
    for _ in range(repeats):
        for name, a in variants.items():
            start = time.perf_counter()
            solutions[name] = jax.block_until_ready(study.solve(a))
            solve_times[name].append(time.perf_counter() - start)
            start = time.perf_counter()
            jax.block_until_ready(call(imdp(a), v))
            call_times[name].append(time.perf_counter() - start)
    blocked, whole = solutions["blocked"], solutions["all rows"]
    diff = max(float(np.max(np.abs(np.asarray(blocked.lower) - np.asarray(whole.lower)))),
               float(np.max(np.abs(np.asarray(blocked.upper) - np.asarray(whole.upper)))))
    b = imdp(variants["blocked"])
    return dict(row=row, kind=spec.kind, rows=b.num_rows, actions=b.num_actions, chunks=b.num_chunks, chunk=b.chunk,
                block_rows=b.block_rows, block_chunks=b.block_chunks, iterations=int(blocked.iterations),
                t_syn_blocked_s=median(solve_times["blocked"]), t_syn_all_s=median(solve_times["all rows"]),
                q_values_blocked_s=median(call_times["blocked"]), q_values_all_s=median(call_times["all rows"]),
                t_syn_runs=solve_times, q_values_runs=call_times, max_bound_difference=diff)


def main(argv=None):
    parser = argument_parser(__doc__, "imdp_blocks", repeats=3)
    parser.add_argument("--rows", default="13,37", help="Table 1 rows (IMDP, 2I-MDP or MI-MDP)")
    parser.add_argument("--budget", type=int, default=None, help="slots a block (default: the library's)")
    args = parser.parse_args(argv)
    results = []
    print(f"{'row':>4} {'kind':>6} {'blocks':>12} {'T_syn blocked':>14} {'all rows':>9} {'ratio':>6} "
          f"{'q_values':>9} {'all rows':>9} {'ratio':>6} {'max diff':>9}")
    for row in (int(r) for r in args.rows.split(",")):
        r = measure(row, args.repeats, args.budget)
        results.append(r)
        print(f"{row:>4} {r['kind']:>6} {r['block_rows']:>5}x{r['block_chunks']:<6} {r['t_syn_blocked_s']:>14.3f} "
              f"{r['t_syn_all_s']:>9.3f} {r['t_syn_all_s'] / r['t_syn_blocked_s']:>5.2f}x "
              f"{r['q_values_blocked_s']:>9.4f} {r['q_values_all_s']:>9.4f} "
              f"{r['q_values_all_s'] / r['q_values_blocked_s']:>5.2f}x {r['max_bound_difference']:>9.1e}", flush=True)
    print("wrote", write_result("imdp_blocks", args, rows=results))


if __name__ == "__main__":
    main()
