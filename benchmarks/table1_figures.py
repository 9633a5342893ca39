"""Figures of the paper, regenerated from ``benchmarks.table1`` result files.

    python -m benchmarks.table1_figures --results results/table1 --out results/figures

* ``fig2_unicycle_2d.png``: p_low heat map of each class with closed-loop trajectories, 2-D
  unicycle (the smallest grid with results; paper Fig. 2).
* ``fig5_unicycle_3d.png``: the same for the 3-D unicycle, sliced at a heading (paper Fig. 5).
* ``fig3_vs_states.png``, ``fig4_vs_noise_cells.png``, ``fig6_vs_rooms.png``: e_avg, T_abs, T_syn
  and memory against |S| (2-D rows), |C| (3-D rows) and n (temperature rows); ours solid, the
  paper's dashed, log scale for times and memory (paper Figs. 3, 4, 6).

Missing rows are skipped; a figure with nothing to show is not written. ``--table`` draws Figs.
3, 4, 6 from a rendered table instead (``docs/results/table1_cpu.md``: rows re-run at different
times, whose result files need not all be on this machine); the heat maps need result files.

    python -m benchmarks.table1_figures --table docs/results/table1_cpu.md --out docs/results/figures
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .paper_table1 import KIND_NAMES, KIND_ORDER, PAPER, ROWS, TO, row_spec
from .table1 import case_study, load_results

COLORS = {"imdp": "tab:blue", "2imdp": "tab:orange", "mimdp": "tab:green", "smdp": "tab:red"}


def _ok(results):
    return {row: r for row, r in results.items() if r.get("status") == "ok"}


def _trajectories(system, grid, policy, starts, steps, objective="reach_avoid", seed=3):
    import jax

    import smdpjax as sj

    controller = sj.Controller(grid, policy)
    sim = sj.simulate(system, controller, starts, jax.random.PRNGKey(seed), max_steps=steps,
                      objective=objective, return_trajectories=True)
    return np.asarray(sim.trajectories), np.asarray(sim.satisfied)


def _draw_boxes(ax, boxes, color, dims=(0, 1)):
    from matplotlib.patches import Rectangle

    lo, hi = boxes
    for a, b in zip(lo, hi):
        ax.add_patch(Rectangle((a[dims[0]], b[dims[1]] * 0 + a[dims[1]]), b[dims[0]] - a[dims[0]],
                               b[dims[1]] - a[dims[1]], fill=False, edgecolor=color, lw=1.5))


def p_low_panel(ax, grid, lower, system, policy, starts, *, objective="reach_avoid", steps=150, heading=None):
    """One heat map: ``lower`` ((N+1,) p_low) over the grid's first two axes (a slice at
    ``heading`` on a 3-D grid), avoid boxes white, reach boxes magenta, and closed-loop
    trajectories of ``policy``'s refined controller from the points ``starts`` ((B, n); white:
    satisfied, red: not). Returns the image (for a colour bar)."""
    lower = np.asarray(lower)[:-1].reshape(tuple(grid.cells))
    if grid.n == 3:
        k = int(np.clip(np.floor((heading - grid.low[2]) / grid.width[2]), 0, grid.cells[2] - 1))
        lower = lower[:, :, k]
    image = ax.imshow(lower.T, origin="lower", extent=(grid.low[0], grid.high[0], grid.low[1], grid.high[1]),
                      vmin=0, vmax=1, cmap="viridis")
    _draw_boxes(ax, grid.avoid_boxes, "white")
    _draw_boxes(ax, grid.reach_boxes, "magenta")
    traj, ok = _trajectories(system, grid, policy, starts, steps, objective)
    for b in range(traj.shape[1]):
        ax.plot(traj[:, b, 0], traj[:, b, 1], color="white" if ok[b] else "red", lw=1)
        ax.plot(traj[0, b, 0], traj[0, b, 1], "o", color="white", ms=3)
    ax.set_xlabel("$p_x$")
    ax.set_ylabel("$p_y$")
    return image


def heat_maps(results_dir: Path, results: dict, system: str, out: Path, heading: float = np.pi / 4):
    """One panel per class of the first configuration of ``system`` with results."""
    import matplotlib.pyplot as plt

    rows = sorted(r for r in _ok(results) if row_spec(r).system == system)
    if not rows:
        return None
    group = row_spec(rows[0]).group
    rows = [r for r in rows if row_spec(r).group == group]
    quick = results[rows[0]].get("quick", False)
    study = case_study(row_spec(rows[0]), quick)
    grid = study.state_grid
    fig, axes = plt.subplots(1, len(rows), figsize=(4.2 * len(rows), 4), squeeze=False)
    rng = np.random.default_rng(0)
    for i, (ax, row) in enumerate(zip(axes[0], rows)):
        data = np.load(results_dir / f"row_{row:02d}.npz")
        starts = data["initial_cells"][rng.choice(len(data["initial_cells"]), min(8, len(data["initial_cells"])),
                                                  replace=False)]
        x0 = np.array(grid.cell_centers(starts))
        if grid.n == 3:
            x0[:, 2] = heading
        image = p_low_panel(ax, grid, data["lower"], study.system, data["policy"], x0, objective=study.objective,
                            steps=150, heading=heading)
        if i:
            ax.set_ylabel("")
        spec = row_spec(row)
        ax.set_title(f"row {row}: {KIND_NAMES[spec.kind]}\nmean p_low {data['lower'][:-1][grid.labels == 0].mean():.3f}")
    fig.colorbar(image, ax=axes[0].tolist(), shrink=0.85, label="$\\underline{p}$")
    slice_note = f", heading slice th = {heading:.2f}" if grid.n == 3 else ""
    fig.suptitle(f"{system}: p_low and closed-loop trajectories (white: satisfied, red: not){slice_note}")
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out


def metric_plots(results: dict, system: str, xkey: str, xlabel: str, out: Path):
    """e_avg, T_abs, T_syn, memory against the varied size, per class; paper dashed."""
    import matplotlib.pyplot as plt

    rows = sorted(r for r in results if row_spec(r).system == system)
    ok = _ok(results)
    if not any(r in ok for r in rows):
        return None
    metrics = (("e_avg", "e_avg", 1.0, False), ("t_abs_s", "T_abs (s)", 60.0, True),
               ("t_syn_s", "T_syn (s)", 60.0, True), ("memory_bytes", "memory (MB)", 1e3, True))
    paper_key = {"e_avg": "e_avg", "t_abs_s": "t_abs_min", "t_syn_s": "t_syn_min", "memory_bytes": "memory_gb"}
    fig, axes = plt.subplots(1, 4, figsize=(18, 3.8))
    for ax, (key, label, paper_scale, log) in zip(axes, metrics):
        for kind in KIND_ORDER:
            mine = [(results[r][xkey], results[r][key] / (1e6 if key == "memory_bytes" else 1))
                    for r in rows if r in ok and row_spec(r).kind == kind and key in results[r]]
            theirs = [(_paper_x(r, xkey), getattr(PAPER[r], paper_key[key]) * paper_scale)
                      for r in ROWS if row_spec(r).system == system and row_spec(r).kind == kind
                      and getattr(PAPER[r], paper_key[key]) not in (None, TO)]
            if mine:
                ax.plot(*zip(*mine), "o-", color=COLORS[kind], label=f"{KIND_NAMES[kind]} (ours)")
            if theirs:
                ax.plot(*zip(*theirs), "s--", color=COLORS[kind], alpha=0.5, label=f"{KIND_NAMES[kind]} (paper)")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(label)
        if log:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=2)
    quick = " (quick scale: not comparable to the paper)" if any(results[r].get("quick") for r in rows if r in results) else ""
    fig.suptitle(f"{system}: metrics against {xlabel}{quick}")
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out


def results_from_table(path: Path) -> dict[int, dict]:
    """The metrics of Figs. 3, 4, 6 per row from a table ``benchmarks.table1`` rendered (markdown:
    ``| # | system | n | class | |S| | |A| | |C| | e_avg (paper) | T_abs s (paper) | speed-up |
    T_syn s (paper) | speed-up | memory MB (paper) | ...``); a ``*`` (single cold run) is dropped."""
    first = lambda cell: float(cell.split()[0].rstrip("*"))
    results = {}
    for line in Path(path).read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 13 or not cells[0].isdigit():
            continue
        try:
            results[int(cells[0])] = dict(status="ok", n=int(cells[2]), states=int(cells[4]),
                                          noise_cells=int(cells[6]), e_avg=first(cells[7]), t_abs_s=first(cells[8]),
                                          t_syn_s=first(cells[10]), memory_bytes=first(cells[12]) * 1e6)
        except ValueError:  # a row that did not finish (no numbers)
            continue
    return results


def _paper_x(row: int, xkey: str):
    """The paper's value of the varied size for a row (what our full-scale rows use too)."""
    spec = row_spec(row)
    if xkey == "states":
        return spec.value ** 2 + 1
    if xkey == "noise_cells":
        return spec.value ** 2 + 1
    return spec.value


def main(argv=None):
    import matplotlib

    matplotlib.use("Agg")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, default=Path("results/table1"))
    parser.add_argument("--out", type=Path, default=Path("results/figures"))
    parser.add_argument("--heading", type=float, default=np.pi / 4, help="heading slice of the 3-D heat maps")
    parser.add_argument("--table", type=Path, help="draw Figs. 3, 4, 6 from this rendered table (no heat maps)")
    args = parser.parse_args(argv)
    results = results_from_table(args.table) if args.table else load_results(args.results)
    if not results:
        parser.error(f"no rows in {args.table}" if args.table else
                     f"no row_*.json in {args.results}: run python -m benchmarks.table1 first")
    args.out.mkdir(parents=True, exist_ok=True)
    written = [] if args.table else [
        heat_maps(args.results, results, "unicycle_2d", args.out / "fig2_unicycle_2d.png"),
        heat_maps(args.results, results, "unicycle_3d", args.out / "fig5_unicycle_3d.png", args.heading),
    ]
    written += [
        metric_plots(results, "unicycle_2d", "states", "|S|", args.out / "fig3_vs_states.png"),
        metric_plots(results, "unicycle_3d", "noise_cells", "|C|", args.out / "fig4_vs_noise_cells.png"),
        metric_plots(results, "temperature", "n", "n (rooms)", args.out / "fig6_vs_rooms.png"),
    ]
    for path in written:
        if path is not None:
            print(f"wrote {path}")
    return [p for p in written if p is not None]


if __name__ == "__main__":
    main()
