"""The pipeline on the 2-D unicycle (30x30 cells, 8 actions, 12x12 + 1 noise cells).

Prints, for every abstraction class (each built from the same partitions and reachable-set
method): e_avg, abstraction and synthesis time (medians over ``--repeats`` runs after a
compiling warm-up), memory, p_low/p_up averages over 100 initial cells, and the Monte Carlo check
(1000 trajectories per initial cell). Writes the results to ``--out`` (JSON) and, beside it, a
figure (``core_2d.png`` for the default ``--out``): each class's p_low heat map with a few
closed-loop trajectories of its refined controller (as the paper's Fig. 2); ``--no-plot`` skips
it, and it is skipped with a message where matplotlib is not installed (the ``dev`` and ``plot``
extras have it).

    python -m benchmarks.core_2d [--kinds imdp,smdp] [--cells 30] [--repeats 3] [--trajectories 1000] [--no-plot]
"""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np

import smdpjax as sj

from .common import argument_parser, binomial_tolerance, median, monte_carlo, timed, write_result


def unicycle_2d(x, u, w):
    """x' = x + dt (v (cos th_a, sin th_a) + w), dt = 0.1, v = 1."""
    return x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)


def problem(cells: int = 30):
    system = sj.System(unicycle_2d, actions=(np.arange(8) * np.pi / 4)[:, None],
                       noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], cells, reach=[([0.8, 0.8], [1.0, 1.0])],
                        avoid=[([0.40, 0.30], [0.60, 0.70]), ([0.75, 0.50], [0.90, 0.65])])
    noise = sj.NoiseGrid.ball([0.0, 0.0], 2.1, 12)
    return system, grid, noise


def main(argv=None):
    parser = argument_parser(__doc__, "core_2d", repeats=3, tol=1e-6,
                             repeats_help="timed runs per stage after a warm-up (median reported); 0: time the first run")
    parser.add_argument("--kinds", default="imdp,smdp",
                        help="comma-separated abstraction classes (imdp, 2imdp, mimdp, smdp); default: the quick pair")
    parser.add_argument("--cells", type=int, default=30, help="grid cells per dimension")
    parser.add_argument("--lp-backend", default="highs", choices=("clarabel", "highs"),
                        help="LP solver for the MI-MDP's multipliers")
    parser.add_argument("--initial", type=int, default=100, help="initial cells |S_0|")
    parser.add_argument("--trajectories", type=int, default=1000, help="Monte Carlo runs per initial cell")
    parser.add_argument("--no-plot", action="store_true", help="do not draw the figure")
    args = parser.parse_args(argv)

    system, grid, noise = problem(args.cells)
    print(f"{system!r}\n{grid!r}\n{noise!r}\n")
    cells = sj.metrics.initial_cells(grid, args.initial, seed=0)
    rows, solutions = [], {}
    for kind in args.kinds.split(","):
        options = {"lp_backend": args.lp_backend} if kind == "mimdp" else {}
        abstraction, t_abs = timed(lambda: sj.abstract(system, grid, noise, kind, **options), args.repeats)
        solution, t_syn = timed(lambda: sj.synthesize(abstraction, tol=args.tol), args.repeats)
        solutions[kind] = solution
        p_low, p_up = sj.metrics.average_bounds(solution, cells)
        sat, undecided = monte_carlo(system, grid, solution.policy, cells, args.trajectories, seed=7, max_steps=1000)
        p_mc = float(sat.mean())
        tol = float(binomial_tolerance(p_mc, args.trajectories * len(cells)))
        per_cell_ok = bool(np.all((sat >= np.asarray(solution.lower)[cells] - binomial_tolerance(sat, args.trajectories))
                                  & (sat <= np.asarray(solution.upper)[cells] + binomial_tolerance(sat, args.trajectories))))
        rows.append(dict(kind=kind, states=grid.num_states, actions=system.num_actions, noise_cells=noise.num_cells,
                         e_avg=sj.metrics.average_error(solution, grid), t_abs_s=median(t_abs), t_abs_runs=t_abs,
                         t_syn_s=median(t_syn), t_syn_runs=t_syn, memory_bytes=abstraction.nbytes,
                         iterations=solution.iterations, evaluation_iterations=solution.evaluation_iterations,
                         p_low_avg=p_low, p_up_avg=p_up, p_mc_avg=p_mc, mc_tolerance=tol,
                         mc_in_bounds=bool(p_low - tol <= p_mc <= p_up + tol), mc_per_cell_in_bounds=per_cell_ok,
                         mc_undecided=int(undecided)))

    header = (f"{'class':6} {'|S|':>5} {'|A|':>3} {'|C|':>4} {'e_avg':>7} {'T_abs s':>8} {'T_syn s':>8} "
              f"{'mem MB':>7} {'iters':>9} {'p_low':>6} {'p_up':>6} {'P_mc':>6}  MC in [p_low, p_up]")
    print(header)
    print("-" * len(header))
    for r in rows:
        print(f"{r['kind']:6} {r['states']:5d} {r['actions']:3d} {r['noise_cells']:4d} {r['e_avg']:7.4f} "
              f"{r['t_abs_s']:8.3f} {r['t_syn_s']:8.3f} {r['memory_bytes'] / 1e6:7.2f} "
              f"{r['iterations']:4d}+{r['evaluation_iterations']:<4d} {r['p_low_avg']:6.3f} {r['p_up_avg']:6.3f} "
              f"{r['p_mc_avg']:6.3f}  {'yes' if r['mc_in_bounds'] else 'NO'} (avg, +-{r['mc_tolerance']:.4f}); "
              f"per cell: {'yes' if r['mc_per_cell_in_bounds'] else 'NO'}")
    if args.out.exists():  # keep rows of other classes from earlier runs
        import json
        earlier = [r for r in json.loads(args.out.read_text()).get("rows", []) if r["kind"] not in args.kinds.split(",")]
        rows = earlier + rows
    write_result("core_2d", args, rows=rows)
    print(f"\nwrote {args.out}")
    if not args.no_plot:
        figure = plot(system, grid, solutions, cells, args.out.with_suffix(".png"))
        if figure is not None:
            print(f"wrote {figure}")
    return rows


def plot(system, grid, solutions: dict, cells, path: Path, trajectories: int = 8):
    """p_low heat maps of ``solutions`` (class -> ``Solution``), one panel per class, with
    ``trajectories`` closed-loop runs from the centres of the same initial cells in every panel;
    written to ``path``. Returns the path, or ``None`` (with a message) without matplotlib."""
    try:
        import matplotlib
    except ImportError:
        print("matplotlib is not installed (pip install -e \".[dev]\" or \".[plot]\"): no figure drawn")
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .paper_table1 import KIND_NAMES
    from .table1_figures import p_low_panel

    starts = np.random.default_rng(0).choice(np.asarray(cells), min(trajectories, len(cells)), replace=False)
    x0 = np.asarray(grid.cell_centers(starts))
    fig, axes = plt.subplots(1, len(solutions), figsize=(4.2 * len(solutions), 4), squeeze=False)
    for i, (ax, (kind, solution)) in enumerate(zip(axes[0], solutions.items())):
        image = p_low_panel(ax, grid, solution.lower, system, solution.policy, x0, steps=150)
        if i:
            ax.set_ylabel("")
        mean = float(np.asarray(solution.lower)[:-1][grid.nonterminal].mean())
        ax.set_title(f"{KIND_NAMES.get(kind, kind)}: mean p_low {mean:.3f}")
    fig.colorbar(image, ax=axes[0].tolist(), shrink=0.85, label="$\\underline{p}$")
    fig.suptitle(f"2-D unicycle, {'x'.join(map(str, grid.cells.tolist()))} cells: p_low and closed-loop "
                 "trajectories (white: satisfied, red: not)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


if __name__ == "__main__":
    main()
