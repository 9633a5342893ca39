"""Where the time of the IMDP's finite-horizon synthesis goes, on the models of ``storm_peer``.

For each model (the 2-D unicycle of ``core_2d`` at ``--cells``, Gaussian or bounded noise, the
compact IMDP that ``abstract(..., "imdp")`` returns), ``--horizon`` steps of each stage run as one
jitted ``lax.scan`` whose carry is the value vector (so nothing is hoisted out of the loop), and
the median over ``--repeats`` runs is reported per step:

* ``sort``: the one global sort of the values per backup (``imdp.value_ranking``: argsort, ranks,
  sorted values, prefix sums);
* ``inner``: the inner problems of every (row, action) with the ranking computed once outside the
  loop (``imdp_compact.chunked_interval_min``: the gathers of ranks and values, the bisection over
  ranks and the final sums);
* ``sums``: the same with the bisection left loop-invariant (XLA runs it once, before the loop):
  the gathers of the values and the final sums; ``inner - sums`` is the bisection;
* ``q_values``: both, as ``CompactIMDP.q_values(v, "min")`` computes them;
* ``backup``: a full greedy backup as ``synthesize(horizon=K, upper=False)`` runs it (q-values,
  max and argmax over actions, the rows written back);
* ``synthesize``: ``synthesize(imdp, horizon=K, upper=False)`` itself (the backups, the strategy
  array and ``Solution``'s host work: widening, expanding the policy, the gap).

``backup - q_values`` is the max/argmax/scatter; ``synthesize - backup`` is what runs outside the
loop. Prints a table and writes ``--out`` (JSON).

    python -m benchmarks.imdp_breakdown [--cells 20,30] [--noise gaussian,uniform] [--horizon 100] [--repeats 5]
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import smdpjax as sj
from smdpjax.abstraction.imdp import value_ranking
from smdpjax.abstraction.imdp_compact import chunked_interval_min
from smdpjax.abstraction.range_min import loop_variant_zero

from .common import argument_parser, environment, median, timed, write_result
from .storm_peer import add_model_options, case, models

STAGES = ("sort", "sums", "inner", "q_values", "backup", "synthesize")


def stage_loops(imdp, horizon: int):
    """``{stage: jitted fn(v0) -> v}`` running ``horizon`` steps of each stage."""
    rows = imdp.rows

    def write_back(v, q):
        return v.at[rows].set(q.max(axis=1))

    def sort_step(v, _):
        rank, w_sorted, prefix = value_ranking(v)
        return w_sorted[rank] + 0.0 * prefix[-1], None  # the values again, through the sort's outputs

    def inner_loop(v0, hoist_bisection: bool):
        rank, w_sorted, prefix = value_ranking(v0)  # once: the loop times the inner problems alone

        def step(v, _):
            # the ranks through a zero that XLA cannot fold keep the bisection in the loop; without
            # it the bisection depends on nothing the loop changes and runs once, before it
            ranking = (rank if hoist_bisection else rank + loop_variant_zero(v), w_sorted, prefix)
            q = chunked_interval_min(v, ranking, imdp.chunk_succ, imdp.chunk_upper, imdp.chunk_row,
                                     imdp.lower_succ, imdp.lower_value, imdp.upper_rest)
            return write_back(v, q), None

        return jax.lax.scan(step, v0, None, length=horizon)[0]

    def q_step(v, _):
        return write_back(v, imdp.q_values(v, "min")), None

    def backup_step(v, _):
        q = imdp.greedy_q_values(v)
        return write_back(v, q), jnp.argmax(q, axis=1).astype(jnp.int32)

    scan = lambda step: jax.jit(lambda v0: jax.lax.scan(step, v0, None, length=horizon)[0])
    return {"sort": scan(sort_step), "sums": jax.jit(lambda v0: inner_loop(v0, True)),
            "inner": jax.jit(lambda v0: inner_loop(v0, False)), "q_values": scan(q_step),
            "backup": scan(backup_step),
            "synthesize": lambda v0: sj.synthesize(imdp, horizon=horizon, upper=False).lower}


def run_case(cells: int, noise_kind: str, horizon: int, repeats: int) -> dict:
    system, grid, noise = case(cells, noise_kind)
    imdp = jax.block_until_ready(sj.abstract(system, grid, noise, "imdp"))
    v0 = imdp.initial_values("reach_avoid")
    seconds = {}
    for name, fn in stage_loops(imdp, horizon).items():
        _, times = timed(lambda: fn(v0), repeats)
        seconds[name] = median(times)
    per_step_ms = {name: 1e3 * s / horizon for name, s in seconds.items()}
    return dict(case=f"unicycle {cells}x{cells}, {noise_kind}", cells=cells, noise=noise_kind,
                rows=imdp.num_rows, actions=imdp.num_actions, chunks=imdp.num_chunks, chunk_width=imdp.chunk,
                lower_pairs=imdp.num_lower, horizon=horizon, seconds=seconds, per_step_ms=per_step_ms)


def table(rows) -> str:
    lines = ["| model | rows x actions | chunks x width | " + " | ".join(f"{s} ms/step" for s in STAGES)
             + " | bisection share of q_values | sort share | outside the loop |",
             "| --- | ---: | ---: | " + " | ".join("---:" for _ in STAGES) + " | ---: | ---: | ---: |"]
    for r in rows:
        ms = r["per_step_ms"]
        lines.append(f"| {r['case']} | {r['rows']} x {r['actions']} | {r['chunks']} x {r['chunk_width']} | "
                     + " | ".join(f"{ms[s]:.3f}" for s in STAGES)
                     + f" | {(ms['inner'] - ms['sums']) / ms['q_values']:.0%} | {ms['sort'] / ms['q_values']:.0%}"
                     f" | {1 - ms['backup'] / ms['synthesize']:.0%} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argument_parser(__doc__, "imdp_breakdown", repeats=5, repeats_help="timed runs per stage (median)")
    add_model_options(parser, horizon_help="steps per timed loop")
    args = parser.parse_args(argv)
    rows = []
    for cells, noise_kind in models(args):
        rows.append(run_case(cells, noise_kind, args.horizon, args.repeats))
        print(f"{rows[-1]['case']}: " + ", ".join(f"{k} {v:.3f} ms" for k, v in rows[-1]["per_step_ms"].items()),
              flush=True)
    print()
    print(table(rows))
    write_result("imdp_breakdown", args, environment=environment(), rows=rows)
    print(f"wrote {args.out}")
    return rows


if __name__ == "__main__":
    main()
