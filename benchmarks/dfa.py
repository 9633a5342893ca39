"""DFA specifications: the 2-D unicycle told to visit A, then B, avoiding the obstacles.

Part 1 (``--kinds``): for every abstraction class on ``smdpjax.case_studies.unicycle_2d_dfa``
(``--spec sequence`` or ``never_after``): T_abs, T_syn (synthesize_product, unbounded; medians
over ``--repeats`` runs after a compiling warm-up), memory, |Q| (and the live DFA states), e_avg
(mean p_up - p_low over the cells whose start is undecided), mean p_low, and a Monte Carlo check
judged by the DFA (``--trajectories`` per initial cell, 4-sigma band per cell).

Part 2 (``--targets``, SMDP): the issue's two targets, side by side in this process:

* synthesis time of the |Q|-state sequence DFA against the built-in reach-avoid synthesis of
  the same system and partitions (2-D 60x60 and the 3-D unicycle at 30^3), target <= 1.5 |Q|
  (runs interleaved, medians);
* reach-avoid written as the 3-state DFA against the built-in: max |difference| of p_low, p_up
  and the number of cells whose action differs (target 1e-12 and 0).

    python -m benchmarks.dfa [--kinds imdp,2imdp,mimdp,smdp] [--cells 20] [--targets] [--repeats 3]
"""

from __future__ import annotations

import time

import jax
import numpy as np

import smdpjax as sj
from smdpjax import specification as sp
from smdpjax.case_studies import unicycle_2d, unicycle_2d_dfa, unicycle_3d
from smdpjax.partition import NONTERMINAL

from .common import argument_parser, binomial_tolerance, median, timed, write_result


def start_labels(prod):
    """Label of every cell's start product state (its first possible letter)."""
    start = np.asarray(prod.tables.start)[:-1, 0]
    return np.asarray(prod.labels)[start]


def class_table(args):
    system, grid, noise, spec = unicycle_2d_dfa(args.cells, args.noise_cells, args.spec)
    on = spec.on(grid)
    print(f"{system!r}\n{grid!r}\n{noise!r}\n{on!r}\n")
    rows = []
    for kind in args.kinds.split(","):
        abstraction, t_abs = timed(lambda: sj.abstract(system, grid, noise, kind, method="natural"), args.repeats)
        sol, t_syn = timed(lambda: sj.synthesize_product(abstraction, on, tol=args.tol), args.repeats)
        prod = sj.synthesis.product(abstraction, on)
        undecided = np.flatnonzero(start_labels(prod) == NONTERMINAL)
        lo, up = np.asarray(sol.initial_lower)[undecided], np.asarray(sol.initial_upper)[undecided]
        rng = np.random.default_rng(0)
        cells = np.sort(rng.choice(undecided, size=min(args.initial, undecided.size), replace=False))
        controller = sp.ProductController(on, sol.policy)
        x0 = sj.uniform_in_cells(grid, cells, args.trajectories, jax.random.PRNGKey(7))
        mc = sp.simulate_product(system, controller, x0, jax.random.PRNGKey(8), max_steps=1000)
        freq = np.asarray(mc.satisfied).reshape(len(cells), args.trajectories).mean(axis=1)
        band = binomial_tolerance(freq, args.trajectories)
        ok = bool(np.all((freq >= np.asarray(sol.initial_lower)[cells] - band)
                         & (freq <= np.asarray(sol.initial_upper)[cells] + band)))
        rows.append(dict(kind=kind, states=grid.num_states, dfa_states=on.num_dfa_states,
                         live_dfa_states=len(prod.tables.live), product_rows=int(prod.rows.shape[0]),
                         t_abs_s=median(t_abs), t_abs_runs=t_abs, t_syn_s=median(t_syn), t_syn_runs=t_syn,
                         memory_bytes=abstraction.nbytes, e_avg=float(np.mean(up - lo)), p_low_avg=float(lo.mean()),
                         p_up_avg=float(up.mean()), iterations=sol.flat.iterations,
                         evaluation_iterations=sol.flat.evaluation_iterations, mc_avg=float(freq.mean()),
                         mc_per_cell_in_bounds=ok, mc_undecided=mc.undecided))
    header = (f"{'class':6} {'|S|':>5} {'|Q|':>4} {'live':>4} {'T_abs s':>8} {'T_syn s':>8} {'mem MB':>7} "
              f"{'e_avg':>7} {'p_low':>6} {'p_up':>6} {'P_mc':>6}  MC in bounds")
    print(header)
    print("-" * len(header))
    for r in rows:
        print(f"{r['kind']:6} {r['states']:5d} {r['dfa_states']:4d} {r['live_dfa_states']:4d} {r['t_abs_s']:8.2f} "
              f"{r['t_syn_s']:8.2f} {r['memory_bytes'] / 1e6:7.2f} {r['e_avg']:7.4f} {r['p_low_avg']:6.3f} "
              f"{r['p_up_avg']:6.3f} {r['mc_avg']:6.3f}  {r['mc_per_cell_in_bounds']}")
    return rows


def interleaved(runs: dict, repeats: int):
    """Time each function ``repeats`` times, alternating between them after one warm-up each, so
    that a shared machine's load falls on all of them alike: ``({name: result}, {name: [s]})``."""
    out = {name: jax.block_until_ready(fn()) for name, fn in runs.items()}
    times = {name: [] for name in runs}
    for _ in range(max(1, repeats)):
        for name, fn in runs.items():
            start = time.perf_counter()
            out[name] = jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - start)
    return out, times


def target_row(name, study, regions, repeats, tol):
    """Built-in reach-avoid, the 3-state reach-avoid DFA, and the sequence DFA on one problem."""
    system, ra_grid, noise = study.system, study.state_grid, study.noise_grid
    free = sj.StateGrid(ra_grid.low, ra_grid.high, ra_grid.cells, periodic=ra_grid.periodic)
    ra_abs = sj.abstract(system, ra_grid, noise, "smdp", method=study.reach_method)
    free_abs = sj.abstract(system, free, noise, "smdp", method=study.reach_method)
    seq = sp.sequence(regions, avoid=list(zip(*ra_grid.avoid_boxes))).on(free, warn=False)
    ra_dfa = sp.reach_avoid_of(ra_grid).on(ra_grid, warn=False)
    runs = {"ra": lambda: sj.synthesize(ra_abs, tol=tol), "ra_dfa": lambda: sj.synthesize_product(ra_abs, ra_dfa, tol=tol),
            "seq": lambda: sj.synthesize_product(free_abs, seq, tol=tol),
            "seq_vmap": lambda: sj.synthesize_product(free_abs, seq, tol=tol, batching="vmap"),
            "seq_map": lambda: sj.synthesize_product(free_abs, seq, tol=tol, batching="map")}
    out, times = interleaved(runs, repeats)
    (ref, t_ra), (as_dfa, t_ra_dfa), (sol, t_seq) = ((out[k], times[k]) for k in ("ra", "ra_dfa", "seq"))
    rows = np.asarray(ra_abs.rows)
    q = seq.num_dfa_states
    row = dict(problem=name, cells=int(ra_grid.num_cells), dfa_states=q,
               live_dfa_states=len(sj.synthesis.product(free_abs, seq).tables.live),
               t_reach_avoid_s=median(t_ra), t_reach_avoid_runs=t_ra,
               t_reach_avoid_dfa_s=median(t_ra_dfa), t_reach_avoid_dfa_runs=t_ra_dfa,
               t_sequence_s=median(t_seq), t_sequence_runs=t_seq,
               ratio_sequence=median(t_seq) / median(t_ra), target_ratio=1.5 * q,
               t_sequence_vmap_s=median(times["seq_vmap"]), t_sequence_map_s=median(times["seq_map"]),
               ratio_sequence_vmap=median(times["seq_vmap"]) / median(t_ra),
               ratio_sequence_map=median(times["seq_map"]) / median(t_ra),
               ratio_reach_avoid_dfa=median(t_ra_dfa) / median(t_ra), target_ratio_reach_avoid_dfa=1.5 * 3,
               max_diff_lower=float(np.max(np.abs(np.asarray(as_dfa.initial_lower) - np.asarray(ref.lower)))),
               max_diff_upper=float(np.max(np.abs(np.asarray(as_dfa.initial_upper) - np.asarray(ref.upper)))),
               policy_mismatches=int(np.sum(np.asarray(as_dfa.policy)[0, rows] != np.asarray(ref.policy)[rows])),
               iterations_reach_avoid=ref.iterations, iterations_sequence=sol.flat.iterations,
               mean_p_low_sequence=float(np.asarray(sol.initial_lower)[:-1].mean()))
    print(f"{name:14} |S|={row['cells']:6d}  T_RA={row['t_reach_avoid_s']:.3f}s  T_RA-as-DFA={row['t_reach_avoid_dfa_s']:.3f}s"
          f" ({row['ratio_reach_avoid_dfa']:.2f}x, target <= 4.5)  T_seq(|Q|={q})={row['t_sequence_s']:.3f}s "
          f"({row['ratio_sequence']:.2f}x, target <= {1.5 * q:.1f}; vmap {row['ratio_sequence_vmap']:.2f}x, map "
          f"{row['ratio_sequence_map']:.2f}x)  RA-as-DFA diffs: lower "
          f"{row['max_diff_lower']:.1e}, upper {row['max_diff_upper']:.1e}, actions {row['policy_mismatches']}")
    return row


def targets(args):
    two_pi = 2 * np.pi
    problems = [("2-D 60x60", unicycle_2d(60), {"a": [([0.1, 0.7], [0.3, 0.9])], "b": [([0.7, 0.1], [0.9, 0.3])]}),
                ("3-D 30^3", unicycle_3d(6, 30), {"a": [([0.1, 0.7, 0.0], [0.3, 0.9, two_pi])],
                                                   "b": [([0.7, 0.1, 0.0], [0.9, 0.3, two_pi])]})]
    return [target_row(name, study, regions, args.repeats, args.tol) for name, study, regions in problems]


def main(argv=None):
    parser = argument_parser(__doc__, "dfa", repeats=3, tol=1e-6)
    parser.add_argument("--kinds", default="imdp,2imdp,mimdp,smdp", help="classes of part 1 ('' skips it)")
    parser.add_argument("--cells", type=int, default=20, help="grid cells per dimension of part 1")
    parser.add_argument("--noise-cells", type=int, default=12, help="noise cells per axis of part 1")
    parser.add_argument("--spec", default="sequence", choices=("sequence", "never_after"))
    parser.add_argument("--initial", type=int, default=20, help="Monte Carlo initial cells")
    parser.add_argument("--trajectories", type=int, default=400, help="Monte Carlo runs per initial cell")
    parser.add_argument("--targets", action="store_true", help="run part 2 (SMDP, 2-D 60x60 and 3-D 30^3)")
    args = parser.parse_args(argv)
    classes = class_table(args) if args.kinds else []
    target_rows = targets(args) if args.targets else []
    path = write_result("dfa", args, classes=classes, targets=target_rows)
    print(f"\nwrote {path}")
    return {"classes": classes, "targets": target_rows}


if __name__ == "__main__":
    main()
