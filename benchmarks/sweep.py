"""Batched sweep versus a Python loop: 64 noise standard deviations on the 2-D unicycle.

The cluster structure does not depend on the noise distribution, so it is computed once; then
for every std the noise-cell probabilities and the synthesis (p_low with its strategy, then p_up
under it) run either in one jitted, vmapped call (``smdpjax.sweep.batched_synthesis``, for
several chunk sizes, and with the chunk size it picks by itself, ``batch_size=None``) or in a
Python loop of ``abstraction.with_probabilities`` + ``synthesize``. Times are medians over
``--repeats`` interleaved rounds after a compiling warm-up; every batched result is compared with
the loop's (p_low and p_up). ``--scratch`` also times the loop that re-abstracts every value from
scratch (``sj.abstract`` + ``sj.synthesize``), what a script without the structure/probability
split does.

    python -m benchmarks.sweep [--cells 20] [--noise-cells 12] [--values 64] [--kind smdp] [--batch-sizes 64 8]
                               [--repeats 5]

On a CPU the Bellman backups (gathers) do not get cheaper per value when batched, a vmapped loop
runs every value of a chunk for the slowest one's iteration count, and under ``vmap`` the
solver's conditionals run both branches: vmapped chunks are slower than the loop there, and
``batch_size=None`` picks ``1`` (the values one after the other inside one jitted program,
``lax.map``), which does the loop's work without its per-call overhead. On an accelerator it
picks vmapped chunks (``smdpjax.sweep.choose_batch_size``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

import smdpjax as sj
from smdpjax import gradients
from smdpjax import sweep as sweeps
from smdpjax.partition import cell_probabilities

from .common import argument_parser, median, timed, write_result
from .core_2d import problem


def main(argv=None):
    parser = argument_parser(__doc__, "sweep", repeats=5, repeats_help="interleaved timing rounds (median reported)",
                             tol=1e-6)
    parser.add_argument("--cells", type=int, default=20, help="grid cells per dimension")
    parser.add_argument("--noise-cells", type=int, default=12, help="noise cells per axis (ball r_W = 2.1)")
    parser.add_argument("--values", type=int, default=64, help="number of std values")
    parser.add_argument("--low", type=float, default=0.2)
    parser.add_argument("--high", type=float, default=0.4)
    parser.add_argument("--kind", default="smdp", choices=("smdp", "imdp"))
    parser.add_argument("--batch-sizes", type=int, nargs="*", default=[64, 8],
                        help="values solved side by side in the batched call (chunks run in sequence; 1: one "
                             "value after the other, no vmap), besides the size it picks itself")
    parser.add_argument("--scratch", action="store_true", help="also time sj.abstract + synthesize per value")
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

    chosen = sweeps.choose_batch_size(structure, int(stds.shape[0]))
    # Warm up (compile) every method, then time them in interleaved rounds, so that load from
    # other processes on a shared machine hits all of them alike.
    methods = {"loop": loop, "auto": batched(None), **{b: batched(b) for b in args.batch_sizes if b != chosen}}
    outputs = {name: jax.block_until_ready(fn()) for name, fn in methods.items()}
    times = {name: [] for name in methods}
    for _ in range(args.repeats):
        for name, fn in methods.items():
            times[name].append(timed(fn, 1)[1][0])
    loop_lower, loop_solutions = outputs["loop"]
    t_loop = times["loop"]
    loop_lower = np.stack([np.asarray(v) for v in loop_lower])
    loop_upper = np.stack([np.asarray(s.upper) for s in loop_solutions])
    iterations = np.array([s.iterations + s.evaluation_iterations for s in loop_solutions])
    rows = []
    print(f"{'method':36} {'median s':>8} {'runs s':>26} {'loop / this':>11} {'max |d p_low|':>13} "
          f"{'max |d p_up|':>12} {'backups':>8}")
    runs = lambda ts: " ".join(f"{t:.2f}" for t in ts)
    print(f"{'python loop':36} {median(t_loop):8.2f} {runs(t_loop):>26} {1.0:11.2f} {0.0:13.1e} {0.0:12.1e} "
          f"{int(iterations.sum()):8d}")
    for name in methods:
        if name == "loop":
            continue
        batch_size = chosen if name == "auto" else name
        batch, t_batch = outputs[name], times[name]
        d_lower = float(np.abs(np.asarray(batch.lower) - loop_lower).max())
        d_upper = float(np.abs(np.asarray(batch.upper) - loop_upper).max())
        per_value = np.asarray(batch.iterations + batch.evaluation_iterations)
        chunks = [per_value[i:i + batch_size] for i in range(0, per_value.size, batch_size)]
        work = int(sum(batch_size * c.max() for c in chunks))  # a vmapped loop runs to its slowest value
        ratio = median(t_loop) / median(t_batch)
        label = (f"batched, auto (batch_size={chosen})" if name == "auto" else f"batched, batch_size={batch_size}")
        if batch_size == 1:
            label += ", lax.map"
        print(f"{label:36} {median(t_batch):8.2f} {runs(t_batch):>26} {ratio:11.2f} {d_lower:13.1e} {d_upper:12.1e} "
              f"{work:8d}")
        rows.append(dict(method=str(name), batch_size=batch_size, seconds=median(t_batch), runs=t_batch,
                         speedup_vs_loop=ratio, max_abs_diff_lower=d_lower, max_abs_diff_upper=d_upper,
                         backups_total=work))
    result = dict(structure=repr(structure), chosen_batch_size=chosen, loop_seconds=median(t_loop), loop_runs=t_loop,
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
    write_result("sweep", args, **result)
    print(f"\nwrote {args.out}")
    return result


if __name__ == "__main__":
    main()
