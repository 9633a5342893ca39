"""Batched sweep versus a Python loop: 64 noise standard deviations on the 2-D unicycle.

The cluster structure does not depend on the noise distribution, so it is computed once; then
for every std the noise-cell probabilities and the synthesis (p_low with its strategy, then p_up
under it) run either in one jitted, vmapped call (``smdpjax.sweep.batched_synthesis``, for
several chunk sizes) or in a Python loop of ``abstraction.with_probabilities`` + ``synthesize``.
Times are medians over ``--repeats`` interleaved rounds after a compiling warm-up. Also reports the loop that
re-abstracts every value from scratch (``sj.abstract`` + ``sj.synthesize``), what a script
without the structure/probability split does.

    python -m benchmarks.sweep [--cells 20] [--noise-cells 12] [--values 64] [--kind smdp] [--batch-sizes 64 8 1]

On a CPU the Bellman backups (gathers) do not get cheaper per value when batched, and a vmapped
loop runs every value for the slowest one's iteration count, so expect the batched call to win
only on small abstractions (where per-call overhead dominates) or on an accelerator.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import smdpjax as sj
from smdpjax import gradients
from smdpjax import sweep as sweeps
from smdpjax.partition import cell_probabilities

from .common import environment, median, timed, write_json
from .core_2d import problem


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cells", type=int, default=20, help="grid cells per dimension")
    parser.add_argument("--noise-cells", type=int, default=12, help="noise cells per axis (ball r_W = 2.1)")
    parser.add_argument("--values", type=int, default=64, help="number of std values")
    parser.add_argument("--low", type=float, default=0.2)
    parser.add_argument("--high", type=float, default=0.4)
    parser.add_argument("--kind", default="smdp", choices=("smdp", "imdp"))
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[64, 8, 1],
                        help="values solved side by side in the batched call (chunks run in sequence)")
    parser.add_argument("--repeats", type=int, default=2, help="interleaved timing rounds")
    parser.add_argument("--tol", type=float, default=1e-6)
    parser.add_argument("--scratch", action="store_true", help="also time sj.abstract + synthesize per value")
    parser.add_argument("--out", type=Path, default=Path("results/sweep.json"))
    args = parser.parse_args(argv)

    system, grid, noise = problem(args.cells)
    noise = sj.NoiseGrid.ball([0.0, 0.0], 2.1, args.noise_cells)
    stds = jnp.linspace(args.low, args.high, args.values)
    structure, t_structure = timed(lambda: gradients.cluster_structure(system, grid, noise), 1)
    print(f"{grid!r}\n{noise!r}\n{structure!r} (structure: {median(t_structure):.2f} s)\n")
    edges = tuple(jnp.asarray(e) for e in noise.edges)
    mean = jnp.asarray(system.noise.mean())

    def probabilities(std):  # one value -> (P_W(c), P_W(rest)); the same object every call
        return cell_probabilities(sj.Gaussian(mean, std), edges, noise.remainder)

    template = structure.abstraction(*probabilities(stds[0]), args.kind)

    def loop():
        out = []
        for std in stds:
            abstraction = template.with_probabilities(*probabilities(std)) if args.kind == "smdp" else \
                structure.abstraction(*probabilities(std), args.kind)
            out.append(sj.synthesize(abstraction, tol=args.tol))
        return [s.lower for s in out], out

    def batched(batch_size):
        return lambda: sweeps.batched_synthesis(structure, probabilities, stds, kind=args.kind, tol=args.tol,
                                                batch_size=batch_size)

    # Warm up (compile) every method, then time them in interleaved rounds, so that load from
    # other processes on a shared machine hits all of them alike.
    methods = {"loop": loop, **{b: batched(b) for b in args.batch_sizes}}
    outputs = {name: jax.block_until_ready(fn()) for name, fn in methods.items()}
    times = {name: [] for name in methods}
    for _ in range(args.repeats):
        for name, fn in methods.items():
            times[name].append(timed(fn, 1)[1][0])
    loop_lower, loop_solutions = outputs["loop"]
    t_loop = times["loop"]
    loop_lower = np.stack([np.asarray(v) for v in loop_lower])
    iterations = np.array([s.iterations + s.evaluation_iterations for s in loop_solutions])
    rows = []
    print(f"{'method':28} {'seconds':>8} {'loop / this':>11} {'max |p_low - loop|':>19} {'backups':>10}")
    print(f"{'python loop':28} {median(t_loop):8.2f} {1.0:11.2f} {0.0:19.2e} {int(iterations.sum()):10d}")
    for batch_size in args.batch_sizes:
        batch, t_batch = outputs[batch_size], times[batch_size]
        diff = float(np.abs(np.asarray(batch.lower) - loop_lower).max())
        per_value = np.asarray(batch.iterations + batch.evaluation_iterations)
        chunks = [per_value[i:i + batch_size] for i in range(0, per_value.size, batch_size)]
        work = int(sum(batch_size * c.max() for c in chunks))  # a vmapped loop runs to its slowest value
        ratio = median(t_loop) / median(t_batch)
        print(f"{'batched, batch_size=' + str(batch_size):28} {median(t_batch):8.2f} {ratio:11.2f} {diff:19.2e} "
              f"{work:10d}")
        rows.append(dict(batch_size=batch_size, seconds=median(t_batch), runs=t_batch, speedup_vs_loop=ratio,
                         max_abs_diff_lower=diff, backups_total=work))
    result = dict(benchmark="sweep", args={k: str(v) for k, v in vars(args).items()}, environment=environment(),
                  structure=repr(structure), loop_seconds=median(t_loop), loop_runs=t_loop,
                  loop_iterations_total=int(iterations.sum()), batched=rows,
                  stds=np.asarray(stds).tolist(), mean_lower=loop_lower[:, grid.nonterminal].mean(axis=1).tolist())
    if args.scratch:
        def scratch():
            out = []
            for std in np.asarray(stds):
                s = dataclasses.replace(system, noise=sj.Gaussian(np.asarray(mean), [std, std]))
                out.append(sj.synthesize(sj.abstract(s, grid, noise, args.kind), tol=args.tol).lower)
            return out
        _, t_scratch = timed(scratch, args.repeats)
        best = min(r["seconds"] for r in rows)
        print(f"{'loop, abstract from scratch':28} {median(t_scratch):8.2f} {median(t_scratch) / best:11.2f} "
              f"(vs the fastest batched call)")
        result.update(scratch_seconds=median(t_scratch), scratch_runs=t_scratch)
    write_json(args.out, result)
    print(f"\nwrote {args.out}")
    return result


if __name__ == "__main__":
    main()
