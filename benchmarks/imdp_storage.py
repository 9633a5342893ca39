"""Padded vs compact IMDP storage on Table 1 rows: bytes, one backup, synthesis, where a backup's time goes.

For each row (an IMDP row of Table 1, or any row: its clusters give the IMDP of Lemma 1), the
IMDP is built padded to the widest list (``IMDP``) and compact (``CompactIMDP``: lists in
fixed-width chunks, sparse lower bounds); both must give the same backups to 1e-14 (checked).
Reported: stored bytes, the chunk layout, one jitted backup ``max_a q(s, a)`` (median of
``--repeats``, the two side by side), one warm synthesis each, and for the compact one the
parts of a backup timed alone: the sort of the values (``value_ranking``), the gathers of ranks
and values into the chunks, and the bisection.

    python -m benchmarks.imdp_storage [--rows 1,13,17,37] [--repeats 5]
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import smdpjax as sj
from smdpjax.abstraction import IMDP, CompactIMDP, compute_grid_clusters
from smdpjax.abstraction.imdp import value_ranking

from .common import argument_parser, median, timed, write_result
from .paper_table1 import row_spec
from .table1 import case_study


def _parts(compact: CompactIMDP, v, repeats):
    """Median ms of the pieces of one compact backup, each jitted alone."""
    sort = jax.jit(value_ranking)
    gathers = jax.jit(lambda c, v: (value_ranking(v)[0].at[c.chunk_succ].get(mode="fill", fill_value=0),
                                    v.at[c.chunk_succ].get(mode="fill", fill_value=0.0)))
    _, t_sort = timed(lambda: sort(v), repeats)
    _, t_gather = timed(lambda: gathers(compact, v), repeats)
    return 1e3 * median(t_sort), 1e3 * median(t_gather)


def run_row(row: int, repeats: int) -> dict:
    spec = row_spec(row)
    study = case_study(spec, quick=False)
    clusters = compute_grid_clusters(study.system, study.state_grid, study.noise_grid, policy=study.controller,
                                     method=study.reach_method)
    padded = IMDP.from_clusters(study.state_grid, clusters)
    compact = CompactIMDP.from_imdp(padded)
    clusters = None
    backup = jax.jit(lambda a, v: a.q_values(v, "min").max(axis=1))
    v = jnp.asarray(np.random.default_rng(0).uniform(size=study.state_grid.num_states)).at[-1].set(0.0)
    times = {"padded": [], "compact": []}
    values = {}
    for name, a in (("padded", padded), ("compact", compact)):
        values[name] = np.asarray(backup(a, v))  # compile
    for _ in range(repeats):  # side by side
        for name, a in (("padded", padded), ("compact", compact)):
            start = time.perf_counter()
            jax.block_until_ready(backup(a, v))
            times[name].append(time.perf_counter() - start)
    diff = float(np.abs(values["padded"] - values["compact"]).max())
    if diff > 1e-14:
        raise AssertionError(f"row {row}: compact and padded backups differ by {diff}")
    syn = {}
    for name, a in (("padded", padded), ("compact", compact)):
        jax.block_until_ready(study.solve(a))  # compile
        start = time.perf_counter()
        solution = jax.block_until_ready(study.solve(a))
        syn[name] = (time.perf_counter() - start, int(solution.iterations))
    t_sort, t_gather = _parts(compact, v, repeats)
    return dict(row=row, system=spec.system, states=study.state_grid.num_states, actions=study.num_actions,
                padded_bytes=padded.nbytes, compact_bytes=compact.nbytes, width=compact.width, chunk=compact.chunk,
                chunks=compact.num_chunks, lower_pairs=compact.num_lower,
                padded_backup_ms=1e3 * median(times["padded"]), compact_backup_ms=1e3 * median(times["compact"]),
                padded_syn_s=syn["padded"][0], compact_syn_s=syn["compact"][0], iterations=syn["compact"][1],
                sort_ms=t_sort, gather_ms=t_gather, max_difference=diff, repr=repr(compact))


def main(argv=None):
    parser = argument_parser(__doc__, "imdp_storage", repeats=5)
    parser.add_argument("--rows", default="1,13,17,37")
    args = parser.parse_args(argv)
    results = []
    print(f"{'row':>3} {'|S|':>6} {'padded MB':>9} {'compact MB':>10} {'W x C':>12} {'L':>2} "
          f"{'backup ms pad/cmp':>18} {'sort ms':>7} {'gather ms':>9} {'T_syn s pad/cmp':>16}")
    for row in (int(r) for r in args.rows.split(",")):
        r = run_row(row, args.repeats)
        results.append(r)
        print(f"{row:>3} {r['states']:>6} {r['padded_bytes'] / 1e6:>9.1f} {r['compact_bytes'] / 1e6:>10.1f} "
              f"{r['chunk']:>4} x {r['chunks']:<6} {r['lower_pairs']:>2} "
              f"{r['padded_backup_ms']:>8.2f}/{r['compact_backup_ms']:<8.2f} {r['sort_ms']:>7.2f} "
              f"{r['gather_ms']:>9.2f} {r['padded_syn_s']:>7.2f}/{r['compact_syn_s']:<7.2f}", flush=True)
    print(f"wrote {write_result('imdp_storage', args, results=results)}")


if __name__ == "__main__":
    main()
