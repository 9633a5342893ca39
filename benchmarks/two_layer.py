"""The 2I-MDP's inner problem per backup: block-sorted prefix sums vs the per-slot bisection.

For each Table 1 2I-MDP row given, builds the abstraction once, then times one robust backup
(``q_values`` against the minimizing adversary, every action) side by side in one process,
median of ``--repeats`` warm runs after a compiling one:

* ``sorted``: ``twolayer.two_layer_min`` (what synthesis uses): each block's cells sorted once
  per call, every row's capacities put in that order and prefix-summed, then O(T log S) per
  bisection step,
* ``per-slot``: the implementation it replaced (below, kept here as the reference): every
  bisection step sums over all T x S slots of every row, and two sorts of every row's slots per
  call for the fill costs at the block bounds,

and checks that both give the same values within 1e-12. Also times the prefix sums over the
last axis of the row's (R, A, T, S) capacities both ways (``jnp.cumsum`` vs a product with a
triangular matrix, what ``twolayer._prefix_sums`` picks for S <= 128).

    python -m benchmarks.two_layer [--rows 2,6,10,34,38] [--repeats 3] [--out results/two_layer.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from smdpjax.abstraction import build, compute_grid_clusters
from smdpjax.abstraction.twolayer import two_layer_min

from .common import environment, median, timed, write_json
from .paper_table1 import parse_rows, row_spec
from .table1 import case_study


def per_slot_two_layer_min(w, blocks, block_lower, block_upper, lower, upper, cells_of, upper_rest):
    """The previous ``two_layer_min``: O(T S) per bisection step (same results)."""
    n_states = w.shape[0]
    order = jnp.argsort(w, stable=True)
    rank = jnp.zeros(n_states, jnp.int32).at[order].set(jnp.arange(n_states, dtype=jnp.int32))
    w_sorted = w[order]
    block_min_rank = jnp.min(rank.at[cells_of].get(mode="fill", fill_value=n_states), axis=-1)
    sorted_min_rank = jnp.sort(block_min_rank)
    block_prefix = jnp.concatenate([jnp.zeros(1), jnp.cumsum(w_sorted[jnp.minimum(sorted_min_rank, n_states - 1)])])
    cells = cells_of.at[blocks].get(mode="fill", fill_value=n_states)
    valid = cells < n_states
    r = jnp.where(valid, rank.at[cells].get(mode="fill", fill_value=n_states), n_states)
    w_i = jnp.where(valid, w.at[cells].get(mode="fill", fill_value=0.0), 0.0)
    lo = jnp.where(valid, lower, 0.0)
    cap = jnp.where(valid, upper - lower, 0.0)
    met = blocks < cells_of.shape[0]
    sum_l = lo.sum(-1)
    floor = jnp.where(met, jnp.maximum(block_lower, sum_l), 0.0)
    ceil = jnp.where(met, jnp.minimum(block_upper, sum_l + cap.sum(-1)), 0.0)
    base = (lo * w_i).sum(-1)

    def fill_cost(amount):
        by_rank = jnp.argsort(r, axis=-1)
        cap_s = jnp.take_along_axis(cap, by_rank, -1)
        w_s = jnp.take_along_axis(w_i, by_rank, -1)
        before = jnp.cumsum(cap_s, -1) - cap_s
        return jnp.sum(jnp.clip(amount[..., None] - before, 0.0, cap_s) * w_s, -1)

    f_floor = base + fill_cost(floor - sum_l)
    f_ceil = base + fill_cost(ceil - sum_l)
    met_min_rank = jnp.where(met, jnp.min(r, axis=-1), n_states)

    def mass_and_cost(k):
        offered = r < k[..., None, None]
        free = sum_l + jnp.sum(jnp.where(offered, cap, 0.0), -1)
        m = jnp.clip(free, floor, ceil)
        cost = jnp.where(free < floor, f_floor,
                         jnp.where(free > ceil, f_ceil, base + jnp.sum(jnp.where(offered, cap * w_i, 0.0), -1)))
        cost = jnp.where(met, cost, 0.0)
        n_all = jnp.searchsorted(sorted_min_rank, k, side="left")
        met_offered = met_min_rank < k[..., None]
        n_met = jnp.sum(met_offered, -1)
        w_met = jnp.sum(jnp.where(met_offered, w_sorted[jnp.minimum(met_min_rank, n_states - 1)], 0.0), -1)
        return m.sum(-1) + upper_rest * (n_all - n_met), cost.sum(-1) + upper_rest * (block_prefix[n_all] - w_met)

    def bisect(_, bounds):
        lo_k, hi_k = bounds
        mid = (lo_k + hi_k) // 2
        enough = mass_and_cost(mid)[0] >= 1.0
        return jnp.where(enough, lo_k, mid + 1), jnp.where(enough, mid, hi_k)

    zeros = jnp.zeros(blocks.shape[:-1], jnp.int32)
    _, k_star = jax.lax.fori_loop(0, int(n_states).bit_length(), bisect, (zeros, zeros + n_states))
    j = jnp.maximum(k_star - 1, 0)
    mass_j, cost_j = mass_and_cost(j)
    return jnp.where(k_star > 0, cost_j + (1.0 - mass_j) * w_sorted[j], mass_and_cost(zeros)[1])


def _backup(solver):
    @jax.jit
    def run(tl, v):
        return solver(v, tl.blocks, tl.block_lower, tl.block_upper, tl.lower, tl.upper, tl.cells_of, tl.upper_rest)
    return run


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", default="2,6,10,34,38", help="2I-MDP rows of Table 1")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("results/two_layer.json"))
    args = parser.parse_args(argv)
    results = []
    print(f"{'row':>4} {'system':12} {'rows x A':>9} {'T':>4} {'S':>4} {'sorted s':>9} {'per-slot s':>11} {'ratio':>6} "
          f"{'cumsum s':>9} {'matmul s':>9} {'max |diff|':>11}")
    cumsum = jax.jit(lambda x: jnp.cumsum(x, -1))
    matmul = jax.jit(lambda x: jnp.matmul(x, jnp.triu(jnp.ones((x.shape[-1],) * 2, x.dtype)),
                                          precision=jax.lax.Precision.HIGHEST))
    for row in parse_rows(args.rows):
        spec = row_spec(row)
        if spec.kind != "2imdp":
            parser.error(f"row {row} is a {spec.kind} row, not a 2I-MDP one")
        study = case_study(spec, False)
        clusters = compute_grid_clusters(study.system, study.state_grid, study.noise_grid, policy=study.controller,
                                         method=study.reach_method)
        tl = jax.block_until_ready(build("2imdp", study.state_grid, clusters))
        clusters = None
        v = jnp.asarray(np.random.default_rng(row).uniform(0.0, 1.0, tl.num_states)).at[-1].set(0.0)
        timings = {}
        values = {}
        for name, solver in (("sorted", two_layer_min), ("per-slot", per_slot_two_layer_min)):
            fn = _backup(solver)
            values[name], timings[name] = timed(lambda: fn(tl, v), args.repeats)
        cap = tl.upper - tl.lower
        _, cumsum_runs = timed(lambda: cumsum(cap), args.repeats)
        _, matmul_runs = timed(lambda: matmul(cap), args.repeats)
        cap = None
        diff = float(jnp.max(jnp.abs(values["sorted"] - values["per-slot"])))
        r, a, t, s = tl.lower.shape
        t_new, t_old = median(timings["sorted"]), median(timings["per-slot"])
        results.append(dict(row=row, system=spec.system, rows=r, actions=a, blocks_met=t, cells_per_block=s,
                            fine_layer_bytes=int(tl.lower.nbytes + tl.upper.nbytes),
                            sorted_runs=timings["sorted"], per_slot_runs=timings["per-slot"], sorted_s=t_new,
                            per_slot_s=t_old, cumsum_runs=cumsum_runs, matmul_runs=matmul_runs,
                            max_difference=diff))
        print(f"{row:4d} {spec.system:12} {r * a:9d} {t:4d} {s:4d} {t_new:9.3f} {t_old:11.3f} {t_old / t_new:5.1f}x "
              f"{median(cumsum_runs):9.3f} {median(matmul_runs):9.3f} {diff:11.1e}", flush=True)
        write_json(args.out, dict(environment=environment(), repeats=args.repeats, rows=results))  # after each row
        if diff > 1e-12:
            raise SystemExit(f"row {row}: the two solvers disagree")
        tl = values = None
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
