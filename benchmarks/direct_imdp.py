"""Direct IMDP bounds (``bounds="direct"``) against the Lemma 1 IMDP and the SMDP on additive noise.

Problems (``--problems``):

* ``unicycle``: the 2-D unicycle of ``smdpjax.case_studies.unicycle_2d`` at 30 x 30, declared
  additive (g = x + 0.1 (cos th, sin th), B = 0.1 I, w ~ N(0, 0.3^2 I)); noise partition of the
  Lemma 1 classes: ball radius 2.1, 12 x 12 + remainder.
* ``robot``: IMPaCT's robot (``smdpjax.case_studies.robot_2d``): 40 x 40 cells, 441 actions,
  w ~ N(0, 0.75 I); noise ball radius 4 sigma, 10 x 10 + remainder.
* ``integrator4d``: a 4-D single integrator x' = x + 0.45 u + B w on [-1.5, 1.5]^4 with 6^4
  cells (width 0.5), u in {-1, 0, 1}^4 (81 actions), B = diag(0.075, 0.12, 0.075, 0.12),
  w ~ N(0, I); reach the centre box [-0.5, 0.5]^4, avoid x_1 in (0.5, 1.5), x_2 in (-0.5, 0.5);
  noise ball radius 4, 4 cells per axis + remainder.

Per class (``--kinds``: ``direct``, ``imdp``, ``smdp``): e_avg, p_low averaged over the non-terminal
cells and over ``--initial`` initial cells, p_up, T_abs and T_syn (``--repeats 0``: the first run,
compilation included; else the median of warm runs), memory (``abstraction.nbytes``), the peak
resident memory of the process while the class was built and solved, the successor width K, the
throughput of the direct construction ((s, a, s') bounds listed per second of T_abs, and window
entries computed per second), and the Monte Carlo check (``--trajectories`` per initial cell).

    python -m benchmarks.direct_imdp [--problems unicycle,robot] [--kinds direct,imdp,smdp]
        [--robot-threshold 1e-6] [--threshold 1e-12] [--repeats 0] [--trajectories 1000]

Rows of other (problem, class) pairs already in ``--out`` are kept, so the classes can be run in
separate processes (the robot's Lemma 1 classes need several GB each).
"""

from __future__ import annotations

import threading
import time

import jax
import jax.numpy as jnp
import numpy as np

import smdpjax as sj
from smdpjax.case_studies import robot_2d, unicycle_2d

from .common import argument_parser, binomial_tolerance, median, monte_carlo, timed, write_result

GAIN_4D = 0.45


def unicycle_drift(x, u):
    """g(x, u) = x + 0.1 (cos u, sin u): the unicycle's step without its noise 0.1 w."""
    return x + 0.1 * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])])


def integrator_drift(x, u):
    """g(x, u) = x + 0.45 u."""
    return x + GAIN_4D * u


def problem(name: str):
    """``(system, grid, noise_grid, reach_method)`` of a benchmark problem."""
    if name.startswith("unicycle"):  # unicycle (30x30), unicycle45, unicycle60, unicycle75: Table 1's grids
        study = unicycle_2d(int(name[len("unicycle"):] or 30))
        system = sj.System.additive(unicycle_drift, 0.1, actions=study.system.actions, noise=study.system.noise)
        return system, study.state_grid, study.noise_grid, study.reach_method
    if name == "robot":
        study = robot_2d()
        return study.system, study.state_grid, study.noise_grid, study.reach_method
    if name == "integrator4d":
        actions = np.stack(np.meshgrid(*[np.array([-1.0, 0.0, 1.0])] * 4, indexing="ij"), axis=-1).reshape(-1, 4)
        system = sj.System.additive(integrator_drift, [0.075, 0.12, 0.075, 0.12], actions=actions,
                                    noise=sj.Gaussian(np.zeros(4), np.ones(4)))
        grid = sj.StateGrid(np.full(4, -1.5), np.full(4, 1.5), 6, reach=[(np.full(4, -0.5), np.full(4, 0.5))],
                            avoid=[([0.5, -0.5, -1.5, -1.5], [1.5, 0.5, 1.5, 1.5])])
        return system, grid, sj.NoiseGrid.ball(np.zeros(4), 4.0, 4), "natural"
    raise ValueError(f"unknown problem {name!r}; expected unicycle, robot or integrator4d")


class PeakMemory:
    """Largest resident set size (bytes) of this process while the block runs (Linux; else None)."""

    def __enter__(self):
        self.peak, self._stop = None, threading.Event()
        try:
            self._page = 4096
            self.peak = self._rss()
        except OSError:
            return self
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def _rss(self):
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * self._page

    def _watch(self):
        while not self._stop.wait(0.02):
            self.peak = max(self.peak, self._rss())

    def __exit__(self, *exc):
        self._stop.set()
        if self.peak is not None:
            self._thread.join()
            self.peak = max(self.peak, self._rss())
        return False


def run_class(name, kind, system, grid, noise, method, args, cells):
    threshold = args.robot_threshold if name == "robot" else args.threshold
    repeats = args.repeats
    if kind == "direct":
        build = lambda: sj.abstract(system, grid, None, "imdp", bounds="direct", method=method, threshold=threshold)
    else:
        build = lambda: sj.abstract(system, grid, noise, kind, method=method)
    with PeakMemory() as peak:
        abstraction, t_abs = timed(build, repeats)
        solution, t_syn = timed(lambda: sj.synthesize(abstraction, tol=args.tol), repeats)
    nt = grid.nonterminal
    p_low, p_up = sj.metrics.average_bounds(solution, cells)
    row = dict(problem=name, kind=kind, states=grid.num_states, actions=system.num_actions,
               noise_cells=None if kind == "direct" else noise.num_cells,
               threshold=threshold if kind == "direct" else None,
               e_avg=sj.metrics.average_error(solution, grid), p_low_nt=float(np.asarray(solution.lower)[nt].mean()),
               p_low_avg=p_low, p_up_avg=p_up, t_abs_s=median(t_abs), t_abs_runs=t_abs, t_syn_s=median(t_syn),
               t_syn_runs=t_syn, memory_bytes=abstraction.nbytes, peak_rss_bytes=peak.peak,
               iterations=solution.iterations, evaluation_iterations=solution.evaluation_iterations, repeats=repeats)
    if kind in ("direct", "imdp"):
        row["successors"] = int(abstraction.successors.shape[-1])
        row["upper_rest"] = float(abstraction.upper_rest)
    if kind == "direct":
        listed = int(np.sum(np.asarray(abstraction.successors) < grid.num_states))
        row["bounds_listed"] = listed
        row["bounds_per_s"] = listed / row["t_abs_s"]
    if args.trajectories > 0:
        sat, undecided = monte_carlo(system, grid, solution.policy, cells, args.trajectories, seed=7, max_steps=1000)
        p_mc = float(sat.mean())
        tol = float(binomial_tolerance(p_mc, args.trajectories * len(cells)))
        row.update(p_mc_avg=p_mc, mc_tolerance=tol, mc_in_bounds=bool(p_low - tol <= p_mc <= p_up + tol),
                   mc_undecided=int(undecided))
    return row


def main(argv=None):
    parser = argument_parser(__doc__, "direct_imdp", repeats=0, tol=1e-6,
                             repeats_help="timed runs per stage after a warm-up (median reported); 0: time the "
                                          "first run, compilation included")
    parser.add_argument("--problems", default="unicycle,robot", help="comma-separated: unicycle (30x30), unicycle45, unicycle60, unicycle75, robot, integrator4d")
    parser.add_argument("--kinds", default="direct,imdp,smdp", help="comma-separated: direct, imdp, smdp")
    parser.add_argument("--threshold", type=float, default=1e-12,
                        help="listing threshold of the direct IMDP (every problem but the robot)")
    parser.add_argument("--robot-threshold", type=float, default=1e-6,
                        help="listing threshold of the direct IMDP on the robot (1e-6 keeps it under 4 GB)")
    parser.add_argument("--initial", type=int, default=100, help="initial cells |S_0|")
    parser.add_argument("--trajectories", type=int, default=1000, help="Monte Carlo runs per initial cell (0: none)")
    args = parser.parse_args(argv)

    rows = []
    for name in args.problems.split(","):
        system, grid, noise, method = problem(name)
        print(f"{name}: {system!r}\n  {grid!r}\n  {noise!r}", flush=True)
        cells = sj.metrics.initial_cells(grid, args.initial, seed=0)
        for kind in args.kinds.split(","):
            if kind not in ("direct", "imdp", "smdp"):
                raise ValueError(f"unknown kind {kind!r}; expected direct, imdp or smdp")
            start = time.perf_counter()
            rows.append(run_class(name, kind, system, grid, noise, method, args, cells))
            print(f"  {kind}: done in {time.perf_counter() - start:.1f} s", flush=True)
            jax.clear_caches()

    header = (f"{'problem':12} {'class':6} {'|S|':>5} {'|A|':>4} {'K':>4} {'e_avg':>8} {'p_low':>7} {'p_low0':>7} "
              f"{'T_abs s':>8} {'T_syn s':>8} {'mem MB':>8} {'peak MB':>8} {'bounds/s':>9} {'P_mc':>6}  MC ok")
    print("\n" + header)
    print("-" * len(header))
    for r in rows:
        rate = f"{r['bounds_per_s']:9.2e}" if "bounds_per_s" in r else f"{'':9}"
        peak = f"{r['peak_rss_bytes'] / 1e6:8.0f}" if r["peak_rss_bytes"] else f"{'':8}"
        mc = (f"{r['p_mc_avg']:6.3f}  {'yes' if r['mc_in_bounds'] else 'NO'}" if "p_mc_avg" in r else "")
        print(f"{r['problem']:12} {r['kind']:6} {r['states']:5d} {r['actions']:4d} {r.get('successors', ''):>4} "
              f"{r['e_avg']:8.5f} {r['p_low_nt']:7.4f} {r['p_low_avg']:7.4f} {r['t_abs_s']:8.2f} {r['t_syn_s']:8.2f} "
              f"{r['memory_bytes'] / 1e6:8.1f} {peak} {rate} {mc}")
    print("\np_low: mean over the non-terminal cells; p_low0: over the initial cells; K: successors per (s, a); "
          "peak MB: resident memory of the process while the class was built and solved")
    if args.out.exists():  # keep the rows of other (problem, class) pairs from earlier runs
        import json
        done = {(r["problem"], r["kind"]) for r in rows}
        rows = [r for r in json.loads(args.out.read_text()).get("rows", [])
                if (r.get("problem"), r.get("kind")) not in done] + rows
    write_result("direct_imdp", args, rows=rows)
    print(f"wrote {args.out}")
    return rows


if __name__ == "__main__":
    main()
