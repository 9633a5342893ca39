"""Our K-step IMDP synthesis and Storm's robust value iteration on the same model, side by side.

For the 2-D unicycle of ``core_2d`` (Gaussian noise: the remainder noise cell makes every state a
possible successor, so the exported rows are dense; and a bounded-noise variant, uniform on
[-0.63, 0.63]^2 = +-2.1 sigma, whose rows list only the states the reachable sets meet), the
IMDP is exported to Storm's DRN format and built in Storm once (timed separately, as is our JIT
compile), then, alternating in one run, ``smdpjax.synthesize(imdp, horizon=K)`` (p_low with its
strategy and p_up under it) and Storm's ``Pmax=? [ !"avoid" U<=K "reach" ]`` with
``uncertainty_resolution_mode=ROBUST`` (p_low only), and ``synthesize(imdp, horizon=K,
upper=False)``, which computes what Storm's query computes (p_low and its strategy). Reports
medians, the transitions of the model (entries with a nonzero upper bound, as Storm counts them),
transition-updates per second (transitions x K / seconds) and the ratios, and checks that the
p_low values agree within 1e-9.

    python -m benchmarks.storm_peer [--cells 20,30] [--noise gaussian,uniform] [--horizon 100] [--repeats 3]

Needs ``stormpy`` (``pip install -e ".[storm]"``).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

import smdpjax as sj
from smdpjax import storm

from .common import argument_parser, environment, write_result
from .core_2d import problem

UNIFORM_HALF_WIDTH = 0.63  # 2.1 standard deviations of the Gaussian of core_2d


def case(cells: int, noise_kind: str):
    system, grid, noise = problem(cells)
    if noise_kind == "uniform":
        lo, hi = [-UNIFORM_HALF_WIDTH] * 2, [UNIFORM_HALF_WIDTH] * 2
        system = sj.System(system.dynamics, actions=system.actions, noise=sj.Uniform(lo, hi))
        noise = sj.NoiseGrid.box(lo, hi, 12)
    elif noise_kind != "gaussian":
        raise ValueError(f"unknown noise {noise_kind!r}")
    return system, grid, noise


def add_model_options(parser, horizon_help: str) -> None:
    """``--cells``, ``--noise`` and ``--horizon``: the models (and steps) of this benchmark."""
    parser.add_argument("--cells", default="20,30", help="comma-separated grid sizes per dimension")
    parser.add_argument("--noise", default="gaussian,uniform", help="gaussian (dense rows) and/or uniform (bounded)")
    parser.add_argument("--horizon", type=int, default=100, help=horizon_help)


def models(args):
    """``(cells, noise kind)`` of every model the options name, in order."""
    return [(int(c), kind) for c in args.cells.split(",") for kind in args.noise.split(",")]


def timed_once(fn):
    start = time.perf_counter()
    result = jax.block_until_ready(fn())
    return result, time.perf_counter() - start


def run_case(cells: int, noise_kind: str, horizon: int, repeats: int, workdir: Path) -> dict:
    system, grid, noise = case(cells, noise_kind)
    imdp, t_abs = timed_once(lambda: sj.abstract(system, grid, noise, "imdp"))
    path = workdir / f"unicycle_{cells}_{noise_kind}.drn"
    _, t_export = timed_once(lambda: storm.to_drn(imdp, path))
    size_mb = path.stat().st_size / 1e6
    model, t_build = timed_once(lambda: storm.storm_model(path))
    path.unlink()
    transitions = int(model.nr_transitions)
    listed = int(np.sum((np.asarray(imdp.successors) < imdp.num_states) & (np.asarray(imdp.upper) > 0)))

    ours = lambda: sj.synthesize(imdp, horizon=horizon)
    lean = lambda: sj.synthesize(imdp, horizon=horizon, upper=False)
    theirs = lambda: storm.storm_values(model, horizon)
    solution, t_compile = timed_once(ours)  # JIT compile + first run
    lean_solution, _ = timed_once(lean)
    values, t_storm_first = timed_once(theirs)
    t_ours, t_lean, t_storm = [], [], []
    for _ in range(repeats):  # alternate, so that all three see the same machine load
        solution, t = timed_once(ours)
        t_ours.append(t)
        lean_solution, t = timed_once(lean)
        t_lean.append(t)
        values, t = timed_once(theirs)
        t_storm.append(t)
    diff = float(max(np.max(np.abs(values - np.asarray(solution.lower))),
                     np.max(np.abs(values - np.asarray(lean_solution.lower)))))
    ours_s, lean_s, storm_s = statistics.median(t_ours), statistics.median(t_lean), statistics.median(t_storm)
    return dict(case=f"unicycle {cells}x{cells}, {noise_kind}", cells=cells, noise=noise_kind,
                states=imdp.num_states, rows=imdp.num_rows, actions=imdp.num_actions,
                upper_rest=float(imdp.upper_rest), transitions=transitions, listed_successors=listed,
                horizon=horizon, t_abstract_s=t_abs, t_export_s=t_export, drn_mb=size_mb,
                t_storm_build_s=t_build, t_ours_compile_s=t_compile, t_storm_first_s=t_storm_first,
                t_ours_runs=t_ours, t_lower_only_runs=t_lean, t_storm_runs=t_storm, t_ours_s=ours_s,
                t_lower_only_s=lean_s, t_storm_s=storm_s,
                ours_updates_per_s=transitions * horizon / ours_s, storm_updates_per_s=transitions * horizon / storm_s,
                lower_only_updates_per_s=transitions * horizon / lean_s, speedup=storm_s / ours_s,
                speedup_lower_only=storm_s / lean_s, max_abs_diff_p_low=diff, agree_1e_9=bool(diff <= 1e-9))


def table(rows) -> str:
    lines = ["| model | states | transitions | K | Storm build s | ours s | ours p_low only s | Storm s "
             "| ours Mupd/s | Storm Mupd/s | ours / Storm speed | p_low only / Storm speed | max abs diff p_low |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['states']} | {r['transitions']:,} | {r['horizon']} | "
                     f"{r['t_storm_build_s']:.2f} | {r['t_ours_s']:.3f} | {r['t_lower_only_s']:.3f} | "
                     f"{r['t_storm_s']:.3f} | {r['ours_updates_per_s'] / 1e6:.1f} | "
                     f"{r['storm_updates_per_s'] / 1e6:.1f} | {r['speedup']:.2f}x | {r['speedup_lower_only']:.2f}x | "
                     f"{r['max_abs_diff_p_low']:.1e} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argument_parser(__doc__, "storm_peer", repeats=3, repeats_help="timed runs of each tool (median reported)")
    add_model_options(parser, horizon_help="K of the bounded until")
    args = parser.parse_args(argv)
    import stormpy

    rows = []
    with tempfile.TemporaryDirectory() as workdir:
        for cells, noise_kind in models(args):
            row = run_case(cells, noise_kind, args.horizon, args.repeats, Path(workdir))
            rows.append(row)
            print(f"{row['case']}: {row['rows']} rows x {row['actions']} actions, {row['transitions']:,} "
                  f"transitions ({row['listed_successors']:,} listed in our arrays), DRN {row['drn_mb']:.0f} MB "
                  f"(export {row['t_export_s']:.1f} s), Storm build {row['t_storm_build_s']:.1f} s, "
                  f"our compile+first run {row['t_ours_compile_s']:.1f} s", flush=True)
    print()
    print(table(rows))
    print("\nours: p_low (max over actions of the robust inner problem) and p_up under the strategy, per step; "
          "ours p_low only (upper=False) and Storm: p_low and its strategy. Medians of alternating runs in one "
          "process.")
    write_result("storm_peer", args, environment={**environment(), "stormpy": stormpy.__version__}, rows=rows)
    print(f"wrote {args.out}")
    return rows


if __name__ == "__main__":
    main()
