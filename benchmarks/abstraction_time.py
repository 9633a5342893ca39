"""T_abs of Table 1 rows: `compute_grid_clusters` (reachable sets and index boxes) and `build`.

Medians of warm runs after a compiling one, wall and CPU seconds of the process (CPU time is
less sensitive to other jobs on a shared machine). With ``--trees A B ...`` each row is measured
in separate processes that import smdpjax from each git work tree in turn (make them with
``git worktree add /tmp/old <commit>``): side-by-side ratios of two versions of the code.

    python -m benchmarks.abstraction_time --rows 20,28,40
    python -m benchmarks.abstraction_time --rows 20,28,40 --trees /tmp/old .
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from .common import argument_parser, median, write_result


def tree_has_compact() -> bool:
    """Whether this process's smdpjax stores SMDP boxes compact from the start (4b44535 on)."""
    import inspect

    from smdpjax.abstraction import compute_grid_clusters

    return "compact" in inspect.signature(compute_grid_clusters).parameters


def measure(row: int, repeats: int) -> dict:
    """Medians over ``repeats`` warm runs of one row (in this process's smdpjax)."""
    import jax

    from smdpjax.abstraction import build, compute_grid_clusters

    from .paper_table1 import row_spec
    from .table1 import case_study

    spec = row_spec(row)
    study = case_study(spec, False)
    runs = []
    for _ in range(repeats + 1):
        wall, cpu = time.perf_counter(), time.process_time()
        options = {"compact": True} if spec.kind == "smdp" and tree_has_compact() else {}  # as abstract() does
        clusters = compute_grid_clusters(study.system, study.state_grid, study.noise_grid, method=study.reach_method,
                                         policy=study.controller, **options)
        jax.block_until_ready(clusters.boxes.start)
        mid_wall, mid_cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(build(spec.kind, study.state_grid, clusters))
        runs.append((mid_wall - wall, time.perf_counter() - mid_wall, mid_cpu - cpu, time.process_time() - mid_cpu))
    warm = runs[1:] or runs
    keys = ("reach_wall_s", "build_wall_s", "reach_cpu_s", "build_cpu_s")
    out = {k: median([r[i] for r in warm]) for i, k in enumerate(keys)}
    out.update(row=row, kind=spec.kind, t_abs_wall_s=out["reach_wall_s"] + out["build_wall_s"],
               t_abs_cpu_s=out["reach_cpu_s"] + out["build_cpu_s"])
    return out


def _in_tree(tree: str, row: int, repeats: int) -> dict:
    """``measure`` in a child process whose smdpjax comes from ``tree`` (the benchmark code from here)."""
    here = str(Path(__file__).resolve().parents[1])
    code = (f"import sys, json; sys.path.insert(0, {tree!r}); import smdpjax; sys.path.insert(0, {here!r}); "
            f"from benchmarks.abstraction_time import measure; print(json.dumps(measure({row}, {repeats})))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tree)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None):
    parser = argument_parser(__doc__, "abstraction_time", repeats=5)
    parser.add_argument("--rows", default="20,28,40", help="Table 1 rows, comma separated")
    parser.add_argument("--trees", nargs="*", default=None, help="git work trees to compare (separate processes)")
    args = parser.parse_args(argv)
    rows = [int(r) for r in args.rows.split(",")]
    trees = [str(Path(t).resolve()) for t in args.trees] if args.trees else [None]
    results = []
    print(f"{'row':>4} {'kind':>7} {'tree':>28} {'T_reach wall':>12} {'T_abs wall':>10} {'T_reach cpu':>11} "
          f"{'T_abs cpu':>9}")
    for row in rows:
        for tree in trees:
            r = measure(row, args.repeats) if tree is None else _in_tree(tree, row, args.repeats)
            r["tree"] = tree or "."
            results.append(r)
            print(f"{row:>4} {r['kind']:>7} {r['tree'][-28:]:>28} {r['reach_wall_s']:>12.3f} {r['t_abs_wall_s']:>10.3f} "
                  f"{r['reach_cpu_s']:>11.3f} {r['t_abs_cpu_s']:>9.3f}", flush=True)
    print(f"wrote {write_result('abstraction_time', args, results=results)}")


if __name__ == "__main__":
    main()
