"""Synthesis on 1 versus several (forced CPU) devices: same results, and the wall times.

The device count is fixed when JAX starts, so every device count runs in its own child process
(``XLA_FLAGS=--xla_force_host_platform_device_count=D``, ``JAX_PLATFORMS=cpu``), one after the
other. With D > 1 the abstraction is built with ``abstract(..., mesh=row_mesh())`` (reachable
sets computed sharded, abstraction returned sharded). Times are medians over ``--repeats`` runs
after a compiling warm-up. Forced CPU devices share the machine's cores, so this measures the
overhead of the sharded program and checks its results, not a speed-up (that needs real devices).

    python -m benchmarks.sharding [--cells 30] [--kind smdp] [--devices 1,4] [--repeats 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

FIELDS = ("lower", "upper", "policy", "lower_optimal")


def child(args):
    import jax

    import smdpjax as sj
    from smdpjax.sharding import row_mesh

    from .common import median, timed
    from .core_2d import problem

    system, grid, noise = problem(args.cells)
    mesh = row_mesh() if len(jax.devices()) > 1 else None
    abstraction, t_abs = timed(lambda: sj.abstract(system, grid, noise, args.kind, mesh=mesh), args.repeats)
    out = {"devices": len(jax.devices()), "rows": abstraction.num_rows, "t_abs_s": median(t_abs),
           "t_abs_runs": t_abs}
    arrays = {}
    for name, horizon in (("unbounded", None), (f"horizon_{args.horizon}", args.horizon)):
        solution, t_syn = timed(lambda: sj.synthesize(abstraction, horizon=horizon, tol=args.tol), args.repeats)
        out[name] = {"t_syn_s": median(t_syn), "t_syn_runs": t_syn, "iterations": solution.iterations,
                     "evaluation_iterations": solution.evaluation_iterations,
                     "rounding_allowance": solution.rounding_allowance,
                     "lower_devices": len(solution.lower.sharding.device_set)}
        arrays.update({f"{name}/{f}": np.asarray(getattr(solution, f)) for f in FIELDS})
    np.savez(args.npz, **arrays)
    print("RESULT " + json.dumps(out))


def run_child(devices: int, args, npz: Path) -> dict:
    env = dict(os.environ, JAX_PLATFORMS="cpu",
               XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
               PYTHONPATH=os.pathsep.join(filter(None, [str(Path(__file__).resolve().parents[1]),
                                                        os.environ.get("PYTHONPATH")])))
    cmd = [sys.executable, "-m", "benchmarks.sharding", "--child", "--npz", str(npz), "--cells", str(args.cells),
           "--kind", args.kind, "--repeats", str(args.repeats), "--horizon", str(args.horizon), "--tol", str(args.tol)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"{devices}-device run failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def main(argv=None):
    from .common import argument_parser, write_result

    parser = argument_parser(__doc__, "sharding", repeats=2, tol=1e-6)
    parser.add_argument("--cells", type=int, default=30, help="grid cells per dimension (2-D unicycle)")
    parser.add_argument("--kind", default="smdp", help="abstraction class")
    parser.add_argument("--devices", default="1,4", help="comma-separated device counts; the first is the reference")
    parser.add_argument("--horizon", type=int, default=100, help="finite horizon timed besides the unbounded one")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--npz", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        return child(args)

    counts = [int(d) for d in args.devices.split(",")]
    runs, arrays = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for d in counts:
            npz = Path(tmp) / f"{d}.npz"
            runs.append(dict(run_child(d, args, npz), requested_devices=d))
            with np.load(npz) as data:
                arrays.append(dict(data))
    ref = arrays[0]
    tasks = ["unbounded", f"horizon_{args.horizon}"]
    for run, arr in zip(runs, arrays):
        for task in tasks:
            diffs = {f: float(np.max(np.abs(arr[f"{task}/{f}"].astype(float) - ref[f"{task}/{f}"].astype(float))))
                     for f in FIELDS if f != "policy"}
            run[task]["max_abs_diff_vs_first"] = diffs
            run[task]["identical_to_first"] = all(np.array_equal(arr[f"{task}/{f}"], ref[f"{task}/{f}"])
                                                  for f in FIELDS)
            run[task]["policy_equal_to_first"] = bool(np.array_equal(arr[f"{task}/policy"], ref[f"{task}/policy"]))
            run[task]["within_rounding_allowance"] = max(diffs.values()) <= 2 * runs[0][task]["rounding_allowance"]

    header = (f"{'devices':>7} {'rows':>5} {'T_abs s':>8} " + " ".join(f"{'T_syn ' + t + ' s':>20}" for t in tasks)
              + "  iterations   same policy  max |diff| (lower, upper)")
    print(f"{args.kind} on the 2-D unicycle, {args.cells}x{args.cells} cells, forced CPU devices "
          f"({os.cpu_count()} cores)\n")
    print(header)
    print("-" * len(header))
    for run in runs:
        u = run["unbounded"]
        diff = max(run[t]["max_abs_diff_vs_first"]["lower"] for t in tasks), \
            max(run[t]["max_abs_diff_vs_first"]["upper"] for t in tasks)
        print(f"{run['devices']:7d} {run['rows']:5d} {run['t_abs_s']:8.2f} "
              + " ".join(f"{run[t]['t_syn_s']:20.2f}" for t in tasks)
              + f"  {u['iterations']:4d}+{u['evaluation_iterations']:<5d}  "
              + f"{'yes' if all(run[t]['policy_equal_to_first'] for t in tasks) else 'NO':>11}  "
              + f"{diff[0]:.1e}, {diff[1]:.1e}")
    write_result("sharding", args, runs=runs)
    print(f"\nwrote {args.out}")
    return runs


if __name__ == "__main__":
    main()
