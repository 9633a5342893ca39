"""Reproduce the paper's Table 1: every row, side by side with the paper's numbers.

    python -m benchmarks.table1 --rows 1-40 --out results/table1 [--time-limit 30] [--quick]

Each row runs in its own process (so a row past ``--time-limit`` minutes is stopped and marked TO,
as the paper marks rows past its 360 minutes), and writes ``row_NN.json`` (metrics, stage times,
checks) and ``row_NN.npz`` (p_low, p_up, optimal p_low, policy) as soon as it finishes. Rows with
a result file are skipped, so an interrupted run resumes where it stopped (``--force`` reruns).
At the end, ``table1.md`` is rendered from all result files in ``--out``: each measured value
beside the paper's, the speed-up for times, and two checks per row:

* Monte Carlo: P_avg (``--trajectories`` runs from each of ``--initial`` cells S_0) lies in
  [p_low_avg - tol, p_up_avg + tol] with tol a 4-sigma binomial band; also counted per cell.
* Theorem 3: optimal lower bounds ordered cell by cell, SMDP >= MI-MDP >= IMDP and
  2I-MDP >= IMDP, among the rows of one configuration that have run (largest violation shown).

Times: T_abs is reachable sets + building the class (each row computes its own reachable sets,
as the paper's per-class times do); T_syn is synthesis (or verification of the look-up table).
Each stage runs once to compile, then ``--repeats`` more times, and the median of those warm runs
is reported; a stage whose first run took over ``--cold-cap`` seconds is not repeated and its
cold time (compilation included, a few seconds at most) is reported instead, so big rows do not
cost twice. Every row's JSON has all the runs and says which.

``--quick`` shrinks every system (2-D at 20x20 with 6x6 noise cells, 3-D at 8^3 cells with half
the noise cells, rooms at 6 cells and 2x2 noise cells per axis beyond two rooms, 10 initial cells x 100 runs) for
smoke tests; its results are not comparable to the paper and are marked so.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from .paper_table1 import KIND_NAMES, PAPER, TO, parse_rows, row_spec

STAGES = ("reachable sets", "abstraction", "synthesis", "Monte Carlo", "done")


def case_study(spec, quick: bool):
    """The ``CaseStudy`` of a row (at the quick scale if asked)."""
    from smdpjax import case_studies

    if spec.system == "unicycle_2d":
        return case_studies.unicycle_2d(20, 6) if quick else case_studies.unicycle_2d(spec.value)
    if spec.system == "unicycle_3d":
        return case_studies.unicycle_3d(spec.value // 2, cells=8) if quick else case_studies.unicycle_3d(spec.value)
    if quick and spec.value > 2:
        return case_studies.temperature(spec.value, cells=6, noise_cells=2)
    return case_studies.temperature(spec.value)


def timed_stage(fn, repeats: int, cold_cap: float):
    """``(result, seconds reported, all runs, warm?)``: median of ``repeats`` warm runs after a
    compiling one, or the cold run alone if it took longer than ``cold_cap`` seconds."""
    import jax

    start = time.perf_counter()
    result = jax.block_until_ready(fn())
    runs = [time.perf_counter() - start]
    if repeats <= 0 or runs[0] > cold_cap:
        return result, runs[0], runs, False
    warm = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = jax.block_until_ready(fn())
        warm.append(time.perf_counter() - start)
    return result, float(np.median(warm)), runs + warm, True


# ----------------------------------------------------------------------------- one row (child)

def run_row(row: int, args) -> dict:
    """Run one row in this process; writes partial results after every stage."""
    import jax

    import smdpjax as sj
    from smdpjax.abstraction import build, compute_grid_clusters

    from .common import binomial_tolerance, environment, monte_carlo

    spec = row_spec(row)
    study = case_study(spec, args.quick)
    out = Path(args.out)
    result = dict(row=row, system=spec.system, kind=spec.kind, parameter=spec.parameter, value=spec.value,
                  reach_method=study.reach_method,
                  quick=bool(args.quick), status="running", stage=STAGES[0], n=study.state_grid.n,
                  states=study.state_grid.num_states, actions=study.num_actions, noise_cells=study.noise_grid.num_cells,
                  objective=study.objective, horizon=study.horizon, time_limit_min=args.time_limit,
                  repeats=args.repeats, environment=environment(), started=time.strftime("%Y-%m-%d %H:%M:%S"))

    def save(stage=None, **fields):
        result.update(fields)
        if stage is not None:
            result["stage"] = stage
        _write(out / f"row_{row:02d}.partial.json", result)

    save()
    policy = study.controller
    stage = lambda fn: timed_stage(fn, args.repeats, args.cold_cap)
    clusters, t_reach, runs, warm = stage(lambda: compute_grid_clusters(study.system, study.state_grid,
                                                                        study.noise_grid, policy=policy,
                                                                        method=study.reach_method,
                                                                        compact=spec.kind == "smdp"))
    save(STAGES[1], t_reach_s=t_reach, t_reach_runs=runs, t_reach_warm=warm)
    options = {"lp_backend": args.lp_backend} if spec.kind == "mimdp" else {}
    abstraction, t_build, runs, warm = stage(lambda: build(spec.kind, study.state_grid, clusters, **options))
    lps = getattr(abstraction, "lps", None)  # the MI-MDP's host LP data, outside the memory metric
    save(STAGES[2], t_build_s=t_build, t_build_runs=runs, t_build_warm=warm, t_abs_s=t_reach + t_build,
         memory_bytes=abstraction.nbytes, abstraction=repr(abstraction),
         lp_data_bytes=None if lps is None else lps.data_nbytes)
    solution, t_syn, runs, warm = stage(lambda: study.solve(abstraction, tol=args.tol))
    lower, upper = np.asarray(solution.lower), np.asarray(solution.upper)
    cells = sj.metrics.initial_cells(study.state_grid, min(args.initial, study.state_grid.nonterminal.size), seed=0)
    p_low, p_up = sj.metrics.average_bounds(solution, cells)
    np.savez_compressed(out / f"row_{row:02d}.npz", lower=lower, upper=upper,
                        lower_optimal=np.asarray(solution.lower_optimal), policy=np.asarray(solution.policy),
                        initial_cells=cells)
    save(STAGES[3], t_syn_s=t_syn, t_syn_runs=runs, t_syn_warm=warm, e_avg=sj.metrics.average_error(solution, study.state_grid),
         p_low_avg=p_low, p_up_avg=p_up, iterations=solution.iterations,
         evaluation_iterations=solution.evaluation_iterations, converged=solution.converged,
         upper_change=solution.upper_change, gap=solution.gap)

    sat, undecided = monte_carlo(study.system, study.state_grid, study.closed_loop_policy(solution), cells,
                                 args.trajectories, seed=7, max_steps=study.max_steps, objective=study.objective)
    p_mc = float(sat.mean())
    tol = float(binomial_tolerance(p_mc, sat.size * args.trajectories))
    cell_tol = binomial_tolerance(sat, args.trajectories)
    cell_ok = (sat >= lower[cells] - cell_tol) & (sat <= upper[cells] + cell_tol)
    save(STAGES[4], status="ok", p_mc_avg=p_mc, mc_tolerance=tol, mc_in_bounds=bool(p_low - tol <= p_mc <= p_up + tol),
         mc_cells_in_bounds=int(cell_ok.sum()), mc_cells=int(cell_ok.size), mc_undecided=int(undecided),
         initial_cells=int(len(cells)), trajectories=args.trajectories)
    _write(out / f"row_{row:02d}.json", result)
    (out / f"row_{row:02d}.partial.json").unlink()
    return result


def _write(path: Path, payload: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(payload, indent=2, default=float))
    os.replace(tmp, path)


# ----------------------------------------------------------------------------- runner (parent)

def run_all(rows, args) -> None:
    from tqdm.auto import tqdm

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    todo = [r for r in rows if args.force or not _done(out, r, args.quick)]
    skipped = len(rows) - len(todo)
    if skipped:
        print(f"{skipped} row(s) already in {out} (use --force to rerun)")
    interactive = sys.stderr.isatty()
    bar = tqdm(todo, unit="row", desc="Table 1", disable=not interactive)
    for row in bar:
        spec = row_spec(row)
        label = f"row {row} {spec.system} {KIND_NAMES[spec.kind]} {spec.parameter}={spec.value}"
        bar.set_description(label)
        if not interactive:
            print(label, flush=True)
        _run_child(row, args, out, bar)
    bar.close()


def _done(out: Path, row: int, quick: bool) -> bool:
    path = out / f"row_{row:02d}.json"
    return path.exists() and json.loads(path.read_text()).get("quick") == quick


def _run_child(row: int, args, out: Path, bar) -> None:
    cmd = [sys.executable, "-m", "benchmarks.table1", "--worker", str(row), "--out", str(out), "--tol", str(args.tol),
           "--repeats", str(args.repeats), "--cold-cap", str(args.cold_cap), "--initial", str(args.initial), "--trajectories", str(args.trajectories),
           "--lp-backend", args.lp_backend, "--time-limit", str(args.time_limit)] + (["--quick"] if args.quick else [])
    partial = out / f"row_{row:02d}.partial.json"
    partial.unlink(missing_ok=True)
    limit = args.time_limit * 60.0
    start = time.perf_counter()
    with open(out / f"row_{row:02d}.log", "w") as log:
        child = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=Path(__file__).resolve().parent.parent)
        while child.poll() is None:
            elapsed = time.perf_counter() - start
            stage = json.loads(partial.read_text()).get("stage", "starting") if partial.exists() else "starting"
            bar.set_postfix_str(f"{stage}, {elapsed:.0f} s")
            if elapsed > limit:
                child.kill()
                child.wait()
                break
            time.sleep(0.5)
    if (out / f"row_{row:02d}.json").exists() and child.returncode == 0:
        return
    record = json.loads(partial.read_text()) if partial.exists() else dict(row=row, quick=bool(args.quick))
    timed_out = time.perf_counter() - start > limit
    record.update(status=TO if timed_out else "error", elapsed_s=time.perf_counter() - start,
                  time_limit_min=args.time_limit)
    if not timed_out:
        record["error"] = (out / f"row_{row:02d}.log").read_text()[-2000:]
        if child.returncode is not None and child.returncode < 0:  # e.g. SIGKILL from the OOM killer
            record["error"] += (f"\nkilled by signal {-child.returncode}"
                                + (" (most likely out of memory)" if child.returncode == -9 else ""))
    _write(out / f"row_{row:02d}.json", record)
    partial.unlink(missing_ok=True)
    bar.write(f"row {row}: {record['status']} in stage {record.get('stage', 'starting')!r} after "
              f"{record['elapsed_s']:.0f} s")


# ----------------------------------------------------------------------------- report

def load_results(out: Path) -> dict[int, dict]:
    results = {}
    for path in sorted(Path(out).glob("row_*.json")):
        if path.name.endswith(".partial.json"):
            continue
        record = json.loads(path.read_text())
        results[int(record["row"])] = record
    return results


def order_checks(out: Path, results: dict[int, dict], tol: float = 1e-4) -> dict[int, float]:
    """Largest violation of the Theorem 3 ordering of optimal lower bounds, per row, against the
    other rows of its configuration that have results (NaN where there is nothing to compare).

    Unbounded-horizon values stop at a tolerance below their fixed points, so violations up to
    ``tol`` are convergence, not unsoundness; finite-horizon values are exact.
    """
    above = {"2imdp": ("imdp",), "mimdp": ("imdp",), "smdp": ("mimdp", "imdp", "2imdp")}
    violations = {}
    for row, record in results.items():
        if record.get("status") != "ok":
            continue
        spec = row_spec(row)
        mine = np.load(out / f"row_{row:02d}.npz")["lower_optimal"]
        worst = np.nan
        for other, other_record in results.items():
            other_spec = row_spec(other)
            if other == row or other_spec.group != spec.group or other_record.get("status") != "ok":
                continue
            if other_record.get("quick") != record.get("quick"):
                continue
            theirs = np.load(out / f"row_{other:02d}.npz")["lower_optimal"]
            if other_spec.kind in above.get(spec.kind, ()):
                gap = float(np.max(theirs - mine))
            elif spec.kind in above.get(other_spec.kind, ()):
                gap = float(np.max(mine - theirs))
            else:
                continue
            worst = gap if np.isnan(worst) else max(worst, gap)
        violations[row] = worst
    return violations


def _fmt(value, digits=3):
    if value is None:
        return "-"
    if isinstance(value, str):
        return value
    if value != 0 and (abs(value) < 10 ** -digits or abs(value) >= 1e5):
        return f"{value:.1e}"
    return f"{value:.{digits}f}"


def render(out: Path, order_tol: float = 1e-4) -> str:
    results = load_results(out)
    violations = order_checks(out, results, order_tol)
    lines = [
        "| # | system | n | class | \\|S\\| | \\|A\\| | \\|C\\| | e_avg (paper) | T_abs s (paper) | speed-up | "
        "T_syn s (paper) | speed-up | memory MB (paper) | p_low_avg (paper) | p_up_avg (paper) | P_avg (paper) | "
        "MC in bounds | Thm 3 order |",
        "|" + "---|" * 18,
    ]
    for row in sorted(results):
        r, p = results[row], PAPER[row]
        spec = row_spec(row)
        status = r.get("status")
        paper_abs, paper_syn = p.t_abs_min * 60, p.t_syn_min if p.t_syn_min == TO else p.t_syn_min * 60
        t_abs = r.get("t_abs_s")
        t_syn = r.get("t_syn_s") if status == "ok" else (f"TO ({r.get('time_limit_min'):g} min)" if status == TO
                                                          else status)
        cold_abs = "" if r.get("t_reach_warm", True) and r.get("t_build_warm", True) else "*"
        cold_syn = "" if r.get("t_syn_warm", True) else "*"
        speed = lambda ours, paper: ("-" if not isinstance(ours, float) or isinstance(paper, str)
                                     else f"{paper / ours:.0f}x" if paper / ours >= 10 else f"{paper / ours:.1f}x")
        mc = "-"
        if status == "ok":
            mc = (f"{'yes' if r['mc_in_bounds'] else 'NO'} (+-{r['mc_tolerance']:.2g}; "
                  f"{r['mc_cells_in_bounds']}/{r['mc_cells']} cells)")
        gap = violations.get(row, np.nan)
        order = "-" if np.isnan(gap) else (f"ok ({gap:.1e})" if gap <= order_tol else f"VIOLATED by {gap:.1e}")
        quick = " (quick)" if r.get("quick") else ""
        lines.append(
            f"| {row} | {spec.system}{quick} | {r.get('n', '-')} | {KIND_NAMES[spec.kind]} | {r.get('states', '-')} | "
            f"{r.get('actions', '-')} | {r.get('noise_cells', '-')} | {_fmt(r.get('e_avg'))} ({_fmt(p.e_avg)}) | "
            f"{_fmt(t_abs, 2)}{cold_abs} ({_fmt(paper_abs, 2)}) | {speed(t_abs, paper_abs)} | "
            f"{_fmt(t_syn, 2)}{cold_syn} ({_fmt(paper_syn, 2)}) | {speed(r.get('t_syn_s') if status == 'ok' else None, paper_syn)} | "
            f"{_fmt(r['memory_bytes'] / 1e6, 2) if 'memory_bytes' in r else '-'} ({_fmt(p.memory_gb * 1e3, 2)}) | "
            f"{_fmt(r.get('p_low_avg'))} ({_fmt(p.p_low_avg)}) | {_fmt(r.get('p_up_avg'))} ({_fmt(p.p_up_avg)}) | "
            f"{_fmt(r.get('p_mc_avg'))} ({_fmt(p.p_mc_avg)}) | {mc} | {order} |")
    text = "\n".join(lines) + "\n"
    env = next((r["environment"] for r in results.values() if "environment" in r), {})
    text += (f"\nMeasured with jax {env.get('jax', '?')} on {env.get('backend', '?')} ({env.get('cpus', '?')} CPUs); "
             "paper values in parentheses (MATLAB, one i7 thread, minutes converted to seconds, GB to MB); "
             "* = a single cold run (JIT compilation included), otherwise the median of warm runs. "
             "Reconstructed case studies (see shared/benchmarks.md): compare sizes, times, memory and the ordering "
             "of e_avg, not exact probabilities.\n")
    (Path(out) / "table1.md").write_text(text)
    return text


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", default="1-40", help="rows of Table 1, e.g. 1-16,20,29-32")
    parser.add_argument("--kinds", default=None, help="only these classes, e.g. smdp,imdp")
    parser.add_argument("--out", type=Path, default=Path("results/table1"))
    parser.add_argument("--time-limit", type=float, default=30.0, help="minutes per row before it is marked TO")
    parser.add_argument("--quick", action="store_true", help="small partitions for smoke tests")
    parser.add_argument("--force", action="store_true", help="rerun rows that already have results")
    parser.add_argument("--repeats", type=int, default=1, help="warm runs per stage after the compiling one (median)")
    parser.add_argument("--cold-cap", type=float, default=120.0,
                        help="seconds: a stage whose first run took longer is not repeated (cold time reported)")
    parser.add_argument("--initial", type=int, default=100, help="|S_0|")
    parser.add_argument("--trajectories", type=int, default=1000, help="Monte Carlo runs per initial cell")
    parser.add_argument("--tol", type=float, default=1e-6, help="value-iteration tolerance")
    parser.add_argument("--lp-backend", default="highs", choices=("clarabel", "highs"), help="MI-MDP LP solver")
    parser.add_argument("--render-only", action="store_true", help="only rebuild table1.md from the result files")
    parser.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.quick and args.initial == 100 and args.trajectories == 1000:
        args.initial, args.trajectories = 10, 100
    if args.worker is not None:
        run_row(args.worker, args)
        return
    if args.time_limit <= 0:
        parser.error("--time-limit must be positive")
    rows = parse_rows(args.rows)
    if args.kinds:
        kinds = set(args.kinds.split(","))
        unknown = kinds - set(KIND_NAMES)
        if unknown:
            parser.error(f"unknown classes {sorted(unknown)}; expected some of {sorted(KIND_NAMES)}")
        rows = [r for r in rows if row_spec(r).kind in kinds]
    if not args.render_only:
        run_all(rows, args)
    print(render(args.out))
    print(f"wrote {args.out / 'table1.md'}")


if __name__ == "__main__":
    main()
