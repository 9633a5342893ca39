"""Two CPU layout choices, each against the alternative it replaced, side by side in one run.

1. Reachable sets: ``compute_grid_clusters`` encloses in one compiled program and snaps the boxes
   to index boxes in a second (``grid_clusters._chunk_fn_for``), against one program doing both
   (where XLA on the CPU recomputes the interval arithmetic in each consumer). Table 1 rows 8
   (2-D unicycle), 28 (3-D unicycle) and 40 (4 rooms), first ``--rows`` rows of each; the boxes
   must be identical.
2. IMDP inner problem: ``interval_min`` sums short successor lists column by column
   (``imdp._EXPLICIT_COLUMNS``), against the reduction over the K axis, in ``synthesize(imdp,
   horizon=100)`` on the models of ``storm_peer`` (the results must be identical to 1e-12).
3. MI-MDP inner problem: ``mimdp.interval_min_rows`` finds the threshold cost without sorting
   each row's shifted costs, against the per-row sort it replaced (``sorted_threshold_min``
   below), on the interval polytopes of Table 1 rows 3 (2-D, 30x30, |C| = 145) and 23 (3-D,
   |C| = 65, first ``--rows`` cells), with costs ``w(s') - shift`` as the LP multipliers make
   them; the new values must never exceed the old (exact) ones and stay within 1e-8.

    python -m benchmarks.cpu_layouts [--rows 4096] [--repeats 7]

Prints medians of alternating runs and writes ``results/cpu_layouts.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import smdpjax as sj
from smdpjax.abstraction import grid_clusters, imdp as imdp_module
from smdpjax.abstraction.grid_clusters import compute_grid_clusters
from smdpjax.abstraction.mimdp import interval_min_rows
from smdpjax.abstraction.clusters import index_boxes
from smdpjax.reach import reachable_boxes

from .common import environment, median, write_json
from .paper_table1 import row_spec
from .storm_peer import case
from .table1 import case_study


def alternate(fns: dict, repeats: int) -> dict:
    """Median seconds of each function, the functions called in turn ``repeats`` times."""
    for fn in fns.values():
        jax.block_until_ready(fn())
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - start)
    return {name: median(ts) for name, ts in times.items()}


def reach_programs(row: int, rows: int, repeats: int) -> dict:
    study = case_study(row_spec(row), quick=False)
    grid, noise, system = study.state_grid, study.noise_grid, study.system
    cells = grid.nonterminal[:rows]
    x_lo, x_hi = grid.cell_bounds(cells)
    w_lo, w_hi = noise.boxes()
    actions = np.asarray(system.actions)
    if study.controller is not None:
        actions = actions[np.asarray(study.controller)[cells]][:, None, :]
    two = grid_clusters._chunk_fn(system.dynamics, grid, study.reach_method)

    @jax.jit
    def one(x_lo, x_hi, actions, w_lo, w_hi):
        lo, hi = reachable_boxes(system.dynamics, x_lo, x_hi, actions, w_lo, w_hi, study.reach_method)
        return index_boxes(grid, lo, hi), jnp.any(jnp.isnan(lo) | jnp.isnan(hi), axis=(1, 2, 3))

    args = (x_lo, x_hi, actions, w_lo, w_hi)
    same = all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(two(*args)),
                                                       jax.tree_util.tree_leaves(one(*args))))
    times = alternate({"two programs": lambda: two(*args), "one program": lambda: one(*args)}, repeats)
    return dict(row=row, method=study.reach_method, rows=int(cells.size), identical=bool(same), **times)


def inner_layout(cells: int, noise_kind: str, repeats: int) -> dict:
    system, grid, noise = case(cells, noise_kind)
    imdp = sj.abstract(system, grid, noise, "imdp")
    width = int(imdp.successors.shape[-1])
    v0 = imdp.initial_values()

    def solver(explicit: int):
        # a fresh trace per layout: the threshold is read while tracing
        original = imdp_module._EXPLICIT_COLUMNS
        imdp_module._EXPLICIT_COLUMNS = explicit
        try:
            compiled = jax.jit(functools.partial(sj.synthesis.value_iteration.finite_horizon.__wrapped__,
                                                 horizon=100)).lower(imdp, v0).compile()
        finally:
            imdp_module._EXPLICIT_COLUMNS = original
        return lambda: compiled(imdp, v0)

    columns, reduction = solver(width), solver(0)
    a, b = jax.block_until_ready(columns()), jax.block_until_ready(reduction())
    diff = float(max(np.max(np.abs(np.asarray(x) - np.asarray(y))) for x, y in zip(a[:2], b[:2])))
    times = alternate({"columns": columns, "reduction": reduction}, repeats)
    return dict(model=f"{cells}x{cells} {noise_kind}", successors=width, max_abs_diff=diff, **times)


def sorted_threshold_min(w, w_listed, succ, lower, upper, upper_rest):
    """The replaced ``interval_min_rows``: exact threshold by a second bisection over each row's
    sorted listed costs (the per-row sort is what it costs)."""
    n = w.shape[0]
    w_sorted = jnp.sort(w)
    prefix = jnp.concatenate([jnp.zeros(1, w.dtype), jnp.cumsum(w_sorted)])
    listed = succ < n
    own = jnp.where(listed, w.at[succ].get(mode="fill", fill_value=0.0), 0.0)
    cost, lo = jnp.where(listed, w_listed, 0.0), jnp.where(listed, lower, 0.0)
    cap = jnp.where(listed, upper - lower, 0.0)

    def mass(t, strict):
        below = (cost < t[..., None]) if strict else (cost <= t[..., None])
        own_below = (own < t[..., None]) if strict else (own <= t[..., None])
        count = jnp.searchsorted(w_sorted, t, side="left" if strict else "right")
        unlisted = count - jnp.sum(listed & own_below, axis=-1)
        return lo.sum(-1) + jnp.sum(jnp.where(below, cap, 0.0), axis=-1) + upper_rest * unlisted

    def smallest_enough(values, size):
        def step(_, bounds):
            mid = (bounds[0] + bounds[1]) // 2
            enough = mass(values(jnp.minimum(mid, size - 1)), False) >= 1.0
            return jnp.where(enough, bounds[0], mid + 1), jnp.where(enough, mid, bounds[1])

        zeros = jnp.zeros(cost.shape[:-1], jnp.int32)
        return jax.lax.fori_loop(0, int(size).bit_length(), step, (zeros, zeros + size))[1]

    j_star = smallest_enough(lambda j: w_sorted[j], n)
    cost_sorted = jnp.sort(jnp.where(listed, cost, jnp.inf), axis=-1)
    k = cost.shape[-1]
    pick = lambda i: jnp.take_along_axis(cost_sorted, i[..., None], axis=-1)[..., 0]
    i_star = smallest_enough(pick, k)
    tau = jnp.minimum(jnp.where(j_star < n, w_sorted[jnp.minimum(j_star, n - 1)], jnp.inf),
                      jnp.where(i_star < k, pick(jnp.minimum(i_star, k - 1)), jnp.inf))
    tau = jnp.where(jnp.isfinite(tau), tau, jnp.maximum(w_sorted[-1], jnp.max(jnp.where(listed, cost, -jnp.inf), -1)))
    own_below = listed & (own < tau[..., None])
    count = jnp.searchsorted(w_sorted, tau, side="left")
    fill = jnp.sum(jnp.where(cost < tau[..., None], cap * cost, 0.0), axis=-1)
    fill_unlisted = upper_rest * (prefix[count] - jnp.sum(jnp.where(own_below, own, 0.0), axis=-1))
    return (lo * cost).sum(-1) + fill + fill_unlisted + jnp.maximum(1.0 - mass(tau, True), 0.0) * tau


def mimdp_threshold(row: int, rows: int, repeats: int) -> dict:
    study = case_study(row_spec(row), quick=False)
    clusters = compute_grid_clusters(study.system, study.state_grid, study.noise_grid, method=study.reach_method)
    clusters = dataclasses.replace(clusters, rows=clusters.rows[:rows],
                                   boxes=jax.tree.map(lambda a: a[:rows], clusters.boxes))
    imdp = sj.abstraction.build("imdp", study.state_grid, clusters)
    rng = np.random.default_rng(0)
    w = jnp.asarray(rng.uniform(0, 1, imdp.num_states))
    succ = imdp.successors
    # multipliers in [0, 1] on a few clusters per row shift the listed costs, ties included
    shift = jnp.asarray(rng.integers(0, 3, succ.shape) * rng.uniform(0, 0.5, succ.shape[:-1] + (1,)))
    w_listed = jnp.where(succ < w.shape[0], w.at[succ].get(mode="fill", fill_value=0.0) - shift, 0.0)
    args = (w, w_listed, succ, imdp.lower, imdp.upper, imdp.upper_rest)
    search, sort = jax.jit(interval_min_rows), jax.jit(sorted_threshold_min)
    new, old = np.asarray(search(*args)), np.asarray(sort(*args))
    times = alternate({"search": lambda: search(*args), "sort": lambda: sort(*args)}, repeats)
    return dict(row=row, rows=int(succ.shape[0] * succ.shape[1]), successors=int(succ.shape[-1]),
                max_abs_diff=float(np.max(np.abs(new - old))), never_above=bool(np.all(new <= old + 1e-12)), **times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=4096, help="state cells per reachable-set case")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", default="results/cpu_layouts.json")
    args = parser.parse_args(argv)

    reach = [reach_programs(row, args.rows, args.repeats) for row in (8, 28, 40)]
    print("| Table 1 row | method | rows | two programs s | one program s | ratio | identical |")
    print("| ---: | --- | ---: | ---: | ---: | ---: | --- |")
    for r in reach:
        print(f"| {r['row']} | {r['method']} | {r['rows']} | {r['two programs']:.4f} | {r['one program']:.4f} | "
              f"{r['one program'] / r['two programs']:.2f}x | {r['identical']} |")
    inner = [inner_layout(cells, kind, args.repeats) for cells in (20, 30) for kind in ("uniform", "gaussian")]
    print()
    print("| model | K | columns s | reduction s | ratio | max abs diff |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for r in inner:
        print(f"| {r['model']} | {r['successors']} | {r['columns']:.4f} | {r['reduction']:.4f} | "
              f"{r['reduction'] / r['columns']:.2f}x | {r['max_abs_diff']:.1e} |")
    threshold = [mimdp_threshold(row, args.rows, args.repeats) for row in (3, 23)]
    print()
    print("| Table 1 row | inner problems | K | search s | per-row sort s | ratio | max abs diff | never above |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    for r in threshold:
        print(f"| {r['row']} | {r['rows']} | {r['successors']} | {r['search']:.4f} | {r['sort']:.4f} | "
              f"{r['sort'] / r['search']:.2f}x | {r['max_abs_diff']:.1e} | {r['never_above']} |")
    print("\nratio: the replaced layout's time over the chosen one's (> 1: the choice is faster). "
          "The library picks columns for K <= 48 only.")
    write_json(Path(args.out), dict(reach=reach, inner=inner, threshold=threshold, repeats=args.repeats,
                                    environment=environment()))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
