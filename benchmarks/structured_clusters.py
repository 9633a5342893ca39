"""Stored index boxes vs structured clusters (additive noise) for the SMDP: memory, T_abs, backup.

For each case, the SMDP is built twice from the same system: ``encoding="boxes"`` (one index
box per (cell, action, noise cell)) and ``encoding="structured"`` (per-dimension pieces, formed
into boxes inside the backup). Both must give identical backups (checked). Reported: stored
bytes, T_abs (warm, medians of ``--repeats``), one jitted backup ``max_a q(s, a)`` (median), and
synthesis (one warm run).

Cases: IMPaCT's 2-D robot (441 actions, additive N(0, 0.75 I)) at 40x40 cells with 10x10 noise
cells and at 80x80 with 20x20; a 3-D additive system (unicycle drift with noise on all three
axes, heading periodic) at 30^3 cells with 5^3 noise cells.

    python -m benchmarks.structured_clusters [--repeats 5] [--cases robot40,robot80,additive3d]
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import smdpjax as sj

from .common import argument_parser, median, timed, write_result


def _additive_3d():
    def g(x, u):
        return jnp.array([x[0] + 0.1 * u[0] * jnp.cos(x[2]), x[1] + 0.1 * u[0] * jnp.sin(x[2]), x[2] + 0.1 * u[1]])
    actions = [[v, om] for v in (0.5, 1.5) for om in (-6.0, -3.0, 0.0, 3.0, 6.0)]
    system = sj.System.additive(g, [0.01, 0.01, 0.05], actions=actions, noise=sj.Gaussian([0, 0, 0], [1, 1, 1]))
    grid = sj.StateGrid([0, 0, 0], [1, 1, 2 * np.pi], 30, periodic=[False, False, True],
                        reach=[([0.7, 0.7, 0], [1.0, 1.0, 2 * np.pi])], avoid=[([0.4, 0.3, 0], [0.6, 0.7, 2 * np.pi])])
    return system, grid, sj.NoiseGrid.ball([0, 0, 0], 3.0, 5)


def cases():
    from smdpjax.case_studies import robot_2d as robot
    return {
        "robot40": lambda: (lambda s: (s.system, s.state_grid, s.noise_grid))(robot(40, 10)),
        "robot80": lambda: (lambda s: (s.system, s.state_grid, s.noise_grid))(robot(80, 20)),
        "additive3d": _additive_3d,
    }


def run_case(name, make, repeats):
    system, grid, noise = make()
    backup = jax.jit(lambda smdp, v: smdp.q_values(v, "min").max(axis=1))
    v = jnp.asarray(np.random.default_rng(0).uniform(size=grid.num_states))
    out, rows = {}, []
    for encoding in ("boxes", "structured"):
        build = lambda: sj.abstract(system, grid, noise, "smdp", method="natural", encoding=encoding)
        smdp, t_abs = timed(build, repeats)
        value, t_backup = timed(lambda: backup(smdp, v), repeats)
        out[encoding] = np.asarray(value)
        start = time.perf_counter()
        solution = jax.block_until_ready(sj.synthesize(smdp))
        t_syn = time.perf_counter() - start
        rows.append(dict(case=name, encoding=encoding, states=grid.num_states, actions=system.num_actions,
                         noise_cells=noise.num_bounded, bytes=smdp.nbytes, t_abs_s=median(t_abs),
                         backup_ms=1e3 * median(t_backup), t_syn_s=t_syn, iterations=int(solution.iterations),
                         repr=repr(smdp)))
        smdp = None
    if not np.array_equal(out["boxes"], out["structured"]):
        raise AssertionError(f"{name}: the two encodings give different backups")
    return rows


def main(argv=None):
    parser = argument_parser(__doc__, "structured_clusters", repeats=5)
    parser.add_argument("--cases", default="robot40,robot80,additive3d")
    args = parser.parse_args(argv)
    table = cases()
    results = []
    print(f"{'case':>11} {'encoding':>10} {'MB':>8} {'T_abs s':>8} {'backup ms':>9} {'T_syn s':>8} {'iters':>5}")
    for name in args.cases.split(","):
        for r in run_case(name, table[name], args.repeats):
            results.append(r)
            print(f"{r['case']:>11} {r['encoding']:>10} {r['bytes'] / 1e6:>8.1f} {r['t_abs_s']:>8.3f} "
                  f"{r['backup_ms']:>9.2f} {r['t_syn_s']:>8.2f} {r['iterations']:>5}", flush=True)
    print(f"wrote {write_result('structured_clusters', args, results=results)}")


if __name__ == "__main__":
    main()
