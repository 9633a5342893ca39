"""The 2I-MDP's count table: what it costs to build and what it saves in each kind of backup.

For each Table 1 2I-MDP row the abstraction is built once; then, alternately in one process
(medians of ``--repeats`` warm runs):

* the count table ``(N + 1) x (B + 2)`` (``twolayer.block_ranking(..., count_table=True)``) built
  by the sequential pass the CPU uses and by the cumulative sum an accelerator uses;
* one backup with every action and one with a fixed strategy (``q_values``, the two kinds of
  backup the synthesis runs), each with the count table and with a binary search in every block's
  ranks instead, and what ``wants_count_table`` picks for it.

Reports the times and the largest difference of the values (none: the same counts either way).

    python -m benchmarks.count_table --rows 18,38 [--repeats 3]
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import numpy as np

from .common import alternating, argument_parser, median, row_clusters, write_result


@contextlib.contextmanager
def _setting(name: str, value):
    from smdpjax.abstraction import twolayer

    saved = getattr(twolayer, name)
    setattr(twolayer, name, value)
    try:
        yield
    finally:
        setattr(twolayer, name, saved)


def measure(row: int, repeats: int) -> dict:
    from smdpjax.abstraction import build, twolayer

    study, clusters = row_clusters(row, "2imdp")
    tl = build("2imdp", study.state_grid, clusters)
    rng = np.random.default_rng(row)
    v = jnp.asarray(rng.uniform(0, 1, tl.num_states)).at[-1].set(0.0)
    strategy = jnp.asarray(rng.integers(0, tl.num_actions, tl.num_rows), jnp.int32)
    calls, values = {}, {}
    for name, on_cpu in (("table, sequential", True), ("table, cumulative sum", False)):
        table = jax.jit(lambda w: twolayer.block_ranking(w, tl.cells_of, count_table=True)["count"])
        with _setting("_on_cpu", lambda on_cpu=on_cpu: on_cpu):
            values[name] = np.asarray(table(v))
        calls[name] = lambda f=table: f(v)
    for kind, actions in (("every action", None), ("strategy", strategy)):
        for name, reads in (("table", 0), ("binary search", None)):
            backup = jax.jit(lambda w, actions=actions: tl.q_values(w, "min", actions))
            with _setting("COUNT_TABLE_READS", reads) if reads is not None else _setting("COUNT_TABLE_MAX", 0):
                values[f"{kind}/{name}"] = np.asarray(backup(v))
            calls[f"{kind}/{name}"] = lambda f=backup: f(v)
    times = alternating(calls, repeats)
    same_table = bool(np.array_equal(values["table, sequential"], values["table, cumulative sum"]))
    diff = max(float(np.max(np.abs(values[f"{kind}/table"] - values[f"{kind}/binary search"])))
               for kind in ("every action", "strategy"))
    lists = tl.num_rows * tl.num_block_slots
    picks = {kind: twolayer.wants_count_table(tl.num_states, tl.cells_of.shape[0], lists * n)
             for kind, n in (("every action", tl.num_actions), ("strategy", 1))}
    return dict(row=row, states=tl.num_states, blocks=int(tl.cells_of.shape[0]), actions=tl.num_actions,
                table_entries=int(values["table, sequential"].size), same_table=same_table,
                max_value_difference=diff, picks_table=picks,
                **{name.replace(", ", "_").replace("/", "_").replace(" ", "_") + "_s": median(t)
                   for name, t in times.items()},
                runs=times)


def main(argv=None):
    parser = argument_parser(__doc__, "count_table", repeats=3)
    parser.add_argument("--rows", default="18,38", help="Table 1 2I-MDP rows")
    args = parser.parse_args(argv)
    results = []
    print(f"{'row':>4} {'table entries':>14} {'sequential':>11} {'cumsum':>8} {'every action: table':>20} "
          f"{'search':>8} {'strategy: table':>16} {'search':>8} {'picks':>12} {'max diff':>9}")
    for row in (int(r) for r in args.rows.split(",")):
        r = measure(row, args.repeats)
        results.append(r)
        picks = "/".join("table" if r["picks_table"][k] else "search" for k in ("every action", "strategy"))
        print(f"{row:>4} {r['table_entries']:>14,} {r['table_sequential_s']:>11.4f} {r['table_cumulative_sum_s']:>8.4f} "
              f"{r['every_action_table_s']:>20.3f} {r['every_action_binary_search_s']:>8.3f} "
              f"{r['strategy_table_s']:>16.3f} {r['strategy_binary_search_s']:>8.3f} {picks:>12} "
              f"{r['max_value_difference']:>9.1e}", flush=True)
    print("wrote", write_result("count_table", args, rows=results))


if __name__ == "__main__":
    main()
