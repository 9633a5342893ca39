"""How the SMDP pipeline scales with the number of cells, from ~10^4 cells up to what fits.

Systems (``--systems``): ``2d`` the 2-D unicycle (``case_studies.unicycle_2d``, 8 actions,
12x12 + 1 noise cells), ``3d`` the 3-D friction unicycle (``unicycle_3d``, 10 actions, 6x6 + 1),
``4d`` the planar double integrator (``double_integrator_4d``, 25 actions, 2x2 + 1); ``--noise-cells``
changes the noise cells per axis. Each size (total cells ``--sizes``, or the ladder 1e4, 3e4,
1e5, 3e5, 6e5, 1e6 up to ``--max-cells``; ``round(size^(1/n))`` cells per dimension) runs in its own
subprocess, so that its peak resident memory (``ru_maxrss`` of the child) is its own. Per size:

* cells, rows (non-terminal cells), actions, noise cells |C| (with the remainder) and boxes
  ``rows x actions x C_b`` (the stored clusters; the remainder cell is not stored);
* T_abs: ``smdpjax.abstract(..., kind="smdp", encoding=--encoding)``, and T_syn:
  ``smdpjax.synthesize`` (``--tol``), each timed to ``jax.block_until_ready``; the first run,
  compilation included, unless it took less than ``--rerun-below`` seconds: then the median of
  ``--repeats`` further runs;
* iterations: ``Solution.iterations + evaluation_iterations`` (greedy backups, strategy sweeps
  and evaluation backups), and T_syn per iteration;
* one full greedy backup ``max_a q(s, a)`` (``SMDP.q_values(v, "min")``, jitted as in
  ``benchmarks/smdp_backup.py``), median of ``--backup-repeats`` after a warm-up, and its cost
  per box in ns;
* peak RSS of the child, stored bytes (``abstraction.nbytes``), mean and max p_low over the
  non-terminal cells.

A size whose estimated peak exceeds ``--max-memory-gb``, that runs past ``--time-limit-min``
or that fails ends its system's ladder (larger sizes would too). An encoding that the library does
not offer for a system (``--encoding structured`` needs ``System.additive``, which only the 4-D
system is) is reported as not available. Prints a
table and the log-log slopes (least squares over the completed sizes) of time per backup, cost per
box and peak RSS against cells; writes ``--out`` (JSON) and, beside it (or ``--figure``), a
log-log figure of the three with the slopes in the legends (``--no-plot``: none).

    python -m benchmarks.scaling --systems 2d,3d,4d [--max-cells 1.1e6] [--max-memory-gb 8]
        [--encoding auto] [--sizes 1e4,1e5] [--time-limit-min 10] [--figure docs/results/figures/scaling.png]
    python -m benchmarks.scaling --replot results/scaling.json     # the table and figure again, no runs
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .common import argument_parser, median, rss_bytes, write_result

SYSTEMS = {"2d": ("unicycle_2d", 2, 12), "3d": ("unicycle_3d", 3, 6), "4d": ("double_integrator_4d", 4, 2)}
LADDER = (1e4, 3e4, 1e5, 3e5, 6e5, 1e6)
ENCODINGS = ("auto", "boxes", "members", "structured")
ROOT = Path(__file__).resolve().parent.parent
# What a child holds besides the boxes: the Python process with JAX and XLA's code.
BASE_BYTES = 0.4e9


def case_study(system: str, cells: int, noise_cells: int):
    """The ``CaseStudy`` of ``system`` (a key of ``SYSTEMS``) with ``cells`` per dimension."""
    from smdpjax import case_studies

    if system == "2d":
        return case_studies.unicycle_2d(cells, noise_cells)
    if system == "3d":
        return case_studies.unicycle_3d(noise_cells, cells)
    if system == "4d":
        return case_studies.double_integrator_4d(cells, noise_cells)
    raise ValueError(f"unknown system {system!r}; expected one of {tuple(SYSTEMS)}")


def cells_per_dimension(system: str, size: float) -> int:
    """``round(size^(1/n))``, at least 2."""
    n = SYSTEMS[system][1]
    return max(2, int(round(size ** (1.0 / n))))


def estimate_bytes(n: int, boxes: float, cells: int) -> float:
    """Estimated peak bytes of a child: the base process, the stored boxes twice (the chunks and
    their concatenation: ``2 n`` ints of 1 or 2 bytes and a sink flag each) and what synthesis
    adds per box, about ``18 n + 12`` bytes (measured: 4-D, 25 actions, 20^4 cells: 31 bytes per
    box after ``abstract``, 100 after ``synthesize``), at most a few backup blocks of
    ``smdp.BACKUP_BLOCK_BYTES`` (a backup takes the rows in blocks)."""
    from smdpjax.abstraction.smdp import BACKUP_BLOCK_BYTES

    stored = 2 * n * (1 if cells <= 127 else 2) + 1
    return boxes * 2 * stored + min(boxes * (18 * n + 12), 4 * BACKUP_BLOCK_BYTES) + BASE_BYTES


def unavailable(exc: Exception) -> bool:
    """Whether ``exc`` from ``abstract`` says that the encoding is not offered (for this system)."""
    text = str(exc).lower()
    named = "encoding" in text or "structured" in text
    return isinstance(exc, (ValueError, TypeError, NotImplementedError)) and named


# ----------------------------------------------------------------------------- child

def run_size(spec: dict, record_path: Path) -> dict:
    """Abstract, synthesize and time one backup of ``spec`` in this process; the record is
    rewritten after every stage (a parent that kills us keeps what was done)."""
    import jax
    import jax.numpy as jnp

    import smdpjax as sj

    record = dict(spec, status="running", stage="setup", rss_start_bytes=rss_bytes())

    def save(stage, **fields):
        record.update(fields, stage=stage, rss_peak_bytes=rss_bytes())
        record_path.write_text(json.dumps(record, indent=2, default=float))

    study = case_study(spec["system"], spec["cells_per_dim"], spec["noise_cells_per_axis"])
    grid, noise = study.state_grid, study.noise_grid
    rows, actions, bounded = int(grid.nonterminal.size), study.num_actions, noise.num_bounded
    save("abstraction", cells=grid.num_cells, rows=rows, actions=actions, noise_cells=noise.num_cells,
         noise_bounded=bounded, boxes=rows * actions * bounded)
    encoding = spec["encoding"]
    if encoding not in ("auto", "boxes", "members"):
        # an encoding this smdpjax may not offer (yet), or not for this system: try it on a tiny
        # grid first rather than after the clusters of the full one
        try:
            jax.block_until_ready(case_study(spec["system"], 4, 2).abstract("smdp", encoding=encoding))
        except Exception as exc:  # noqa: BLE001: re-raised unless it is the encoding
            if not unavailable(exc):
                raise
            save("done", status="unavailable", error=f"{type(exc).__name__}: {exc}")
            return record

    def abstract():
        return jax.block_until_ready(study.abstract("smdp", encoding=encoding))

    abstraction, t_abs, abs_runs = _timed(abstract, spec)
    save("synthesis", t_abs_s=t_abs, t_abs_runs=abs_runs, bytes=abstraction.nbytes, abstraction=repr(abstraction),
         encoding_used=abstraction.encoding, rss_abstraction_bytes=rss_bytes())

    def solve():
        solution = sj.synthesize(abstraction, tol=spec["tol"])
        jax.block_until_ready(solution.lower)
        return solution

    solution, t_syn, syn_runs = _timed(solve, spec)
    iterations = solution.iterations + solution.evaluation_iterations
    lower = np.asarray(solution.lower)[np.asarray(abstraction.rows)]
    save("backup", t_syn_s=t_syn, t_syn_runs=syn_runs, iterations=solution.iterations,
         evaluation_iterations=solution.evaluation_iterations, backups=iterations, converged=solution.converged,
         t_syn_per_iteration_s=t_syn / max(iterations, 1), p_low_mean=float(lower.mean()),
         p_low_max=float(lower.max()), gap=solution.gap, rss_synthesis_bytes=rss_bytes())
    solution = None

    backup = jax.jit(lambda smdp, v: smdp.q_values(v, "min").max(axis=1))
    v = jnp.asarray(np.random.default_rng(0).uniform(size=abstraction.num_states))
    jax.block_until_ready(backup(abstraction, v))  # compile
    times = []
    for _ in range(max(1, spec["backup_repeats"])):
        start = time.perf_counter()
        jax.block_until_ready(backup(abstraction, v))
        times.append(time.perf_counter() - start)
    t_backup = median(times)
    save("done", status="ok", t_backup_s=t_backup, t_backup_runs=times,
         ns_per_box=1e9 * t_backup / max(record["boxes"], 1))
    return record


def _timed(fn, spec):
    """``(result, seconds, runs)``: the first run (compilation included), or, where it took less
    than ``rerun_below`` seconds, the median of ``repeats`` further runs (the previous result
    dropped first, so that the peak memory is one run's)."""
    start = time.perf_counter()
    result = fn()
    first = time.perf_counter() - start
    if spec["repeats"] <= 0 or first >= spec["rerun_below"]:
        return result, first, [first]
    runs = []
    for _ in range(spec["repeats"]):
        result = None
        start = time.perf_counter()
        result = fn()
        runs.append(time.perf_counter() - start)
    return result, median(runs), runs


def child_main(spec_json: str, record: str) -> None:
    path = Path(record)
    spec = json.loads(spec_json)
    try:
        run_size(spec, path)
    except Exception as exc:  # noqa: BLE001: recorded for the parent, which goes on
        done = json.loads(path.read_text()) if path.exists() else dict(spec)
        done.update(status="error", error=f"{type(exc).__name__}: {exc}", rss_peak_bytes=rss_bytes())
        path.write_text(json.dumps(done, indent=2, default=float))
        raise


# ----------------------------------------------------------------------------- parent

def run_child(spec: dict, limit_s: float, workdir: Path) -> dict:
    """Run ``spec`` in a subprocess with a wall-clock limit; its record, with ``status`` ``ok``,
    ``unavailable``, ``error`` or ``timeout``, and ``elapsed_s``."""
    path = workdir / f"{spec['system']}_{spec['cells_per_dim']}.json"
    path.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "benchmarks.scaling", "--child", json.dumps(spec), "--record", str(path)]
    start = time.perf_counter()
    child = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        output, _ = child.communicate(timeout=limit_s)
        timed_out = False
    except subprocess.TimeoutExpired:
        child.kill()
        output, _ = child.communicate()
        timed_out = True
    record = json.loads(path.read_text()) if path.exists() else dict(spec, status="error", error="")
    record["elapsed_s"] = time.perf_counter() - start
    if timed_out:
        record.update(status="timeout", error=f"ran past {limit_s:.0f} s in stage {record.get('stage', 'setup')!r}")
    elif child.returncode != 0:
        oom = ", most likely out of memory" if child.returncode == -9 else ""
        killed = f" (killed by signal {-child.returncode}{oom})" if child.returncode < 0 else ""
        record.update(status="error", error=(record.get("error") or "exit status %d" % child.returncode) + killed,
                      log=(output or "")[-3000:])
    return record


def sizes_for(args) -> list[float]:
    if args.sizes:
        sizes = [float(s) for s in args.sizes.split(",") if s.strip()]
        if not sizes or any(s < 1 for s in sizes):
            raise ValueError(f"--sizes must be positive cell counts, got {args.sizes!r}")
        return sorted(sizes)
    return [s for s in LADDER if s <= args.max_cells]


def parse_noise_cells(text: str) -> dict:
    """``"2d:12,4d:3"`` -> ``{"2d": 12, "4d": 3}`` over the defaults."""
    cells = {name: default for name, (_, _, default) in SYSTEMS.items()}
    for item in filter(None, (s.strip() for s in (text or "").split(","))):
        name, _, value = item.partition(":")
        if name not in SYSTEMS or not value.isdigit() or int(value) < 1:
            raise ValueError(f"--noise-cells entries are system:count with a system in {tuple(SYSTEMS)}, got {item!r}")
        cells[name] = int(value)
    return cells


def run_ladder(system: str, args, noise_cells: int, workdir: Path) -> list[dict]:
    """Every size of ``system`` in increasing order, until one does not fit or fails."""
    name, n, _ = SYSTEMS[system]
    records, seen = [], set()
    for size in sizes_for(args):
        cells = cells_per_dimension(system, size)
        if cells in seen:
            continue
        seen.add(cells)
        study = case_study(system, cells, noise_cells)
        rows = int(study.state_grid.nonterminal.size)
        boxes = rows * study.num_actions * study.noise_grid.num_bounded
        spec = dict(system=system, case_study=name, n=n, cells_per_dim=cells, noise_cells_per_axis=noise_cells,
                    encoding=args.encoding, tol=args.tol, repeats=args.repeats, rerun_below=args.rerun_below,
                    backup_repeats=args.backup_repeats, estimate_bytes=estimate_bytes(n, boxes, cells))
        label = f"{system} {cells}^{n} = {cells ** n} cells, {boxes:.3g} boxes"
        if spec["estimate_bytes"] > args.max_memory_gb * 1e9:
            note = (f"estimated {spec['estimate_bytes'] / 1e9:.1f} GB exceeds --max-memory-gb {args.max_memory_gb:g}")
            print(f"{label}: skipped, {note}", flush=True)
            records.append(dict(spec, cells=cells ** n, rows=rows, actions=study.num_actions,
                                noise_cells=study.noise_grid.num_cells, boxes=boxes, status="skipped", error=note))
            break
        print(f"{label}: running (estimate {spec['estimate_bytes'] / 1e9:.1f} GB) ...", flush=True)
        record = run_child(spec, args.time_limit_min * 60.0, workdir)
        records.append(record)
        print(f"  {summary(record)}", flush=True)
        if record["status"] != "ok":
            break
    return records


def summary(r: dict) -> str:
    if r["status"] != "ok":
        return f"{r['status']}: {r.get('error', '')}".strip()[:400]
    return (f"T_abs {r['t_abs_s']:.2f} s, T_syn {r['t_syn_s']:.2f} s ({r['backups']} backups), backup "
            f"{r['t_backup_s']:.3g} s = {r['ns_per_box']:.2f} ns/box, peak RSS {r['rss_peak_bytes'] / 2 ** 30:.2f} GiB")


def slope(records: list[dict], key: str, min_cells: float = 0):
    """Least-squares slope of log(key) against log(cells) over the completed sizes with at least
    ``min_cells`` cells (None with fewer than two)."""
    points = [(r["cells"], r[key]) for r in records
              if r.get("status") == "ok" and r.get(key, 0) > 0 and r["cells"] >= min_cells]
    if len(points) < 2 or len({x for x, _ in points}) < 2:
        return None
    x, y = np.log(np.array(points, dtype=float)).T
    return float(np.polyfit(x, y, 1)[0])


# Slopes are also fitted from about 10^5 cells on (316^2 = 99 856 counts), where fixed costs no
# longer dominate and the 4-D range-minimum table has left the regime of one lookup per box.
LARGE_CELLS = 9e4
FITTED = (("t_backup_s", "time per backup"), ("ns_per_box", "cost per box"), ("rss_peak_bytes", "peak RSS"),
          ("t_syn_per_iteration_s", "T_syn per iteration"), ("t_abs_s", "T_abs"))


def encoding_of(r: dict) -> str:
    """The encoding the abstraction used (``"auto"`` resolves to one), from the record."""
    if r.get("encoding_used"):
        return r["encoding_used"]
    found = re.search(r"encoding=(\w+)", r.get("abstraction", ""))
    return found.group(1) if found else ""


def table(records: list[dict]) -> str:
    header = (f"{'sys':3} {'cells':>9} {'rows':>9} {'|A|':>3} {'|C|':>4} {'boxes':>9} {'enc':>10} {'T_abs s':>8} "
              f"{'T_syn s':>8} {'iters':>6} {'s/iter':>8} {'backup s':>9} {'ns/box':>7} {'RSS GiB':>7} "
              f"{'stored MB':>9} {'p_low':>6}  status")
    lines = [header, "-" * len(header)]
    for r in records:
        cells, rows = r.get("cells", r["cells_per_dim"] ** r["n"]), r.get("rows", 0)
        head = (f"{r['system']:3} {cells:9d} {rows:9d} {r.get('actions', 0):3d} {r.get('noise_cells', 0):4d} "
                f"{r.get('boxes', 0):9.3g} {encoding_of(r):>10}")
        if r["status"] == "ok":
            lines.append(f"{head} {r['t_abs_s']:8.2f} {r['t_syn_s']:8.2f} {r['backups']:6d} "
                         f"{r['t_syn_per_iteration_s']:8.3g} {r['t_backup_s']:9.3g} {r['ns_per_box']:7.2f} {r['rss_peak_bytes'] / 2 ** 30:7.2f} "
                         f"{r['bytes'] / 1e6:9.1f} {r['p_low_mean']:6.3f}  ok")
        else:
            t_abs = f"{r['t_abs_s']:8.2f}" if "t_abs_s" in r else f"{'':8}"
            lines.append(f"{head} {t_abs} {'':8} {'':6} {'':8} {'':9} {'':7} {'':7} {'':9} {'':6}  {r['status']}")
    return "\n".join(lines)


def plot(records: list[dict], slopes: dict, path: Path, large: dict | None = None):
    """Log-log panels of time per backup, cost per box and peak RSS against cells, one line per
    system, the fitted slopes in the legend (over all sizes and, from ``large``, over the sizes
    from ~10^5 cells). Returns the path, or None without matplotlib."""
    try:
        import matplotlib
    except ImportError:
        print("matplotlib is not installed (pip install -e \".[dev]\" or \".[plot]\"): no figure drawn")
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("t_backup_s", "time per backup (s)", 1.0), ("ns_per_box", "cost per box per backup (ns)", 1.0),
              ("rss_peak_bytes", "peak RSS (GiB)", 2.0 ** -30))
    colors = {"2d": "tab:blue", "3d": "tab:orange", "4d": "tab:green"}
    fig, axes = plt.subplots(1, len(panels), figsize=(17, 5), constrained_layout=True)
    drawn = False
    for ax, (key, label, scale) in zip(axes, panels):
        for system in SYSTEMS:
            ok = sorted((r["cells"], r[key] * scale) for r in records if r["system"] == system and r["status"] == "ok")
            if not ok:
                continue
            drawn = True
            s = slopes.get(system, {}).get(key)
            s_large = (large or {}).get(system, {}).get(key)
            fit = f", slope {s:.2f}" if s is not None else ""
            fit += f" ({s_large:.2f} from 1e5)" if s_large is not None else ""
            ax.plot(*zip(*ok), "o-", color=colors[system], label=f"{system} ({SYSTEMS[system][0]}){fit}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("cells")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8, loc="best")
    if not drawn:
        plt.close(fig)
        return None
    fig.suptitle("SMDP scaling: one greedy backup, its cost per (row x action x noise cell) box, and peak memory")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None):
    parser = argument_parser(__doc__, "scaling", repeats=1, tol=1e-6,
                             repeats_help="timed runs of T_abs and T_syn after the first, where the first took less "
                                          "than --rerun-below seconds (median reported); 0: the first run only")
    parser.add_argument("--systems", default="2d,3d,4d", help=f"comma-separated, from {', '.join(SYSTEMS)}")
    parser.add_argument("--sizes", default=None, help="comma-separated total cell counts (default: the ladder "
                        f"{', '.join(f'{s:g}' for s in LADDER)} up to --max-cells)")
    parser.add_argument("--max-cells", type=float, default=1.1e6, help="largest size of the default ladder")
    parser.add_argument("--max-memory-gb", type=float, default=8.0,
                        help="skip a size (and the larger ones) whose estimated peak memory exceeds this")
    parser.add_argument("--time-limit-min", type=float, default=10.0, help="wall-clock limit per size (minutes)")
    parser.add_argument("--encoding", default="auto", choices=ENCODINGS,
                        help="SMDP encoding (abstract(..., encoding=))")
    parser.add_argument("--noise-cells", default="", help="noise cells per axis, e.g. '2d:12,3d:6,4d:2' (the defaults)")
    parser.add_argument("--rerun-below", type=float, default=30.0,
                        help="repeat T_abs and T_syn (--repeats) only where the first run took less (seconds)")
    parser.add_argument("--backup-repeats", type=int, default=3, help="timed backups after a warm-up (median)")
    parser.add_argument("--figure", type=Path, default=None, help="figure path (default: --out with .png)")
    parser.add_argument("--no-plot", action="store_true", help="do not draw the figure")
    parser.add_argument("--replot", type=Path, default=None,
                        help="run nothing: print the table and slopes of this earlier JSON result and draw its figure")
    parser.add_argument("--child", default=None, help=argparse_suppress())
    parser.add_argument("--record", default=None, help=argparse_suppress())
    args = parser.parse_args(argv)
    if args.child is not None:
        return child_main(args.child, args.record)

    systems = [s.strip() for s in args.systems.split(",") if s.strip()]
    unknown = [s for s in systems if s not in SYSTEMS]
    if unknown or not systems:
        parser.error(f"--systems: unknown {unknown or systems}; expected a comma-separated subset of "
                     f"{', '.join(SYSTEMS)}")
    try:
        noise_cells = parse_noise_cells(args.noise_cells)
        sizes_for(args)
    except ValueError as exc:
        parser.error(str(exc))
    if args.max_memory_gb <= 0 or args.time_limit_min <= 0:
        parser.error("--max-memory-gb and --time-limit-min must be positive")

    if args.replot is not None:
        records = json.loads(args.replot.read_text())["rows"]
        systems = [s for s in SYSTEMS if any(r["system"] == s for r in records)]
    else:
        records = []
        with tempfile.TemporaryDirectory(prefix="smdpjax-scaling-") as workdir:
            for system in systems:
                records += run_ladder(system, args, noise_cells[system], Path(workdir))
    fit = lambda min_cells: {system: {key: slope([r for r in records if r["system"] == system], key, min_cells)
                                      for key, _ in FITTED} for system in systems}
    slopes, large = fit(0), fit(LARGE_CELLS)
    print()
    print(table(records))
    for title, fits in (("over the completed sizes", slopes), (f"from {LARGE_CELLS:.0f} cells", large)):
        print(f"\nlog-log slopes against cells (least squares {title}):")
        for system in systems:
            text = ", ".join(f"{label} {fits[system][key]:.2f}" for key, label in FITTED
                             if fits[system][key] is not None)
            print(f"  {system}: {text or 'fewer than two completed sizes'}")
    if args.replot is None:
        write_result("scaling", args, rows=records, slopes=slopes, slopes_from_1e5=large)
        print(f"wrote {args.out}")
    if not args.no_plot:
        default = (args.replot if args.replot is not None else args.out).with_suffix(".png")
        figure = plot(records, slopes, args.figure or default, large)
        if figure is not None:
            print(f"wrote {figure}")
    return records


def argparse_suppress():
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    main()
