"""Building the IMDP's Lemma 1 bounds: from index boxes (``box_bounds``) vs from member lists.

For each Table 1 IMDP row given, computes the clusters once, then times side by side in one
process (median of ``--repeats`` warm runs after a compiling one; a mode whose first run took
over ``--cold-cap`` seconds is reported cold and not repeated):

* ``boxes``: ``IMDP.from_clusters`` (difference arrays over each row's window, exact fixed-point
  sums rounded outward; what ``abstract`` uses),
* ``members``: the member-list construction it replaced (expand every cluster to its cells with
  ``cluster_members``, then ``IMDP.from_members``: a sort of each row's C x K members and float
  sums; still the traceable path of ``smdpjax.gradients``),

and checks that both list the same successors with bounds within 1e-14.

    python -m benchmarks.lemma1_build [--rows 1,5,9,13,33,37] [--repeats 3] [--out results/lemma1_build.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp

from smdpjax.abstraction import compute_grid_clusters
from smdpjax.abstraction.clusters import cluster_members, max_lengths
from smdpjax.abstraction.imdp import IMDP

from .common import environment, median, timed, write_json
from .paper_table1 import parse_rows, row_spec
from .table1 import case_study


def by_members(grid, clusters):
    members = cluster_members(grid, clusters.boxes, max_lengths(clusters.boxes))
    return IMDP.from_members(members, clusters.prob, clusters.prob_rest, clusters.rows, grid.state_labels)


def measure(fn, repeats: int, cold_cap: float):
    result, runs = timed(fn, 0)
    if repeats > 0 and runs[0] <= cold_cap:
        result, warm = timed(fn, repeats)
        return result, median(warm), runs + warm, True
    return result, runs[0], runs, False


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", default="1,5,9,13,33,37", help="IMDP rows of Table 1")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cold-cap", type=float, default=60.0)
    parser.add_argument("--out", type=Path, default=Path("results/lemma1_build.json"))
    args = parser.parse_args(argv)
    results = []
    print(f"{'row':>4} {'system':12} {'rows x A':>10} {'C':>5} {'width':>6} {'boxes s':>9} {'members s':>10} "
          f"{'ratio':>7} {'max |diff|':>11}")
    for row in parse_rows(args.rows):
        spec = row_spec(row)
        if spec.kind != "imdp":
            parser.error(f"row {row} is a {spec.kind} row, not an IMDP one")
        study = case_study(spec, False)
        grid = study.state_grid
        clusters = compute_grid_clusters(study.system, grid, study.noise_grid, policy=study.controller,
                                         method=study.reach_method)
        jax.block_until_ready(clusters.boxes.start)
        new, t_new, runs_new, warm_new = measure(lambda: IMDP.from_clusters(grid, clusters), args.repeats,
                                                 args.cold_cap)
        old, t_old, runs_old, warm_old = measure(lambda: by_members(grid, clusters), args.repeats, args.cold_cap)
        same_lists = new.successors.shape == old.successors.shape and bool(jnp.all(new.successors == old.successors))
        diff = max(float(jnp.max(jnp.abs(new.lower - old.lower))), float(jnp.max(jnp.abs(new.upper - old.upper))))
        r, a, width = new.successors.shape
        c = clusters.boxes.start.shape[2]
        results.append(dict(row=row, system=spec.system, rows=r, actions=a, noise_cells=c, width=width,
                            boxes_s=t_new, boxes_runs=runs_new, boxes_warm=warm_new,
                            members_s=t_old, members_runs=runs_old, members_warm=warm_old,
                            same_successors=same_lists, max_bound_difference=diff))
        print(f"{row:4d} {spec.system:12} {r * a:10d} {c:5d} {width:6d} {t_new:9.2f} {t_old:10.2f} "
              f"{t_old / t_new:6.1f}x {diff:11.1e}" + ("" if same_lists else "  SUCCESSORS DIFFER"), flush=True)
        write_json(args.out, dict(environment=environment(), repeats=args.repeats, rows=results))  # after each row
        if not same_lists or diff > 1e-14:
            raise SystemExit(f"row {row}: the two constructions disagree")
        new = old = clusters = None  # free this row before building the next
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
