"""Stored bytes of Table 1 abstractions against the paper's memory, without synthesis.

Each row (``--rows``, default every IMDP and 2I-MDP row) is abstracted as ``benchmarks/table1.py``
does (the row's case study and class, ``abstract``) in a child process of its own, and reported
with ``abstraction.nbytes`` (the metric of Table 1's memory column), the paper's figure, their
ratio, the MI-MDP's host-side LP data (``lps.data_nbytes``, reported apart as in Table 1), the
child's peak resident memory and T_abs (first run, compilation included).

    python -m benchmarks.abstraction_memory [--rows 1,2,5,6] [--out results/abstraction_memory.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

from .common import argument_parser, rss_bytes, write_result
from .paper_table1 import KIND_NAMES, PAPER, parse_rows, row_spec

IMDP_ROWS = ",".join(str(r) for r in range(1, 41) if (r - 1) % 4 in (0, 1))


def measure(row: int) -> dict:
    """Abstract one row in this process: ``{row, class, memory_mb, paper_mb, ...}``."""
    import jax

    from .table1 import case_study

    jax.config.update("jax_enable_x64", True)
    spec = row_spec(row)
    study = case_study(spec, quick=False)
    start = time.perf_counter()
    abstraction = jax.block_until_ready(study.abstract(spec.kind))
    t_abs = time.perf_counter() - start
    lps = getattr(abstraction, "lps", None)
    return {"row": row, "class": KIND_NAMES[spec.kind], "memory_mb": abstraction.nbytes / 1e6,
            "paper_mb": PAPER[row].memory_gb * 1e3, "ratio": abstraction.nbytes / 1e6 / (PAPER[row].memory_gb * 1e3),
            "lp_data_mb": None if lps is None else lps.data_nbytes / 1e6, "t_abs_s": t_abs,
            "peak_rss_gib": rss_bytes() / 2**30,
            "abstraction": repr(abstraction)}


def main(argv=None):
    parser = argument_parser(__doc__, "abstraction_memory")
    parser.add_argument("--rows", default=IMDP_ROWS, help="Table 1 rows, e.g. 1-4,17 (default: IMDP and 2I-MDP rows)")
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)  # one row, in this process
    args = parser.parse_args(argv)
    if args.child is not None:
        print(json.dumps(measure(args.child)))
        return None
    results = []
    print(f"{'row':>4} {'class':>7} {'MB':>9} {'paper MB':>9} {'ratio':>6} {'T_abs s':>8} {'peak GiB':>9}", flush=True)
    for row in parse_rows(args.rows):
        done = subprocess.run([sys.executable, "-m", "benchmarks.abstraction_memory", "--child", str(row)],
                              capture_output=True, text=True)
        if done.returncode != 0:
            results.append({"row": row, "error": done.stderr.strip().splitlines()[-1:]})
            print(f"{row:>4} failed: {results[-1]['error']}", flush=True)
            continue
        r = json.loads(done.stdout.strip().splitlines()[-1])
        results.append(r)
        print(f"{row:>4} {r['class']:>7} {r['memory_mb']:9.1f} {r['paper_mb']:9.0f} {r['ratio']:6.2f} "
              f"{r['t_abs_s']:8.2f} {r['peak_rss_gib']:9.2f}", flush=True)
    print(f"wrote {write_result('abstraction_memory', args, rows=results)}")
    return results


if __name__ == "__main__":
    main()
