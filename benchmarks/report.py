"""Speed and memory against the paper, per Table 1 row, for one or more result directories.

    python -m benchmarks.report --results results/table1 [results/table1_gpu ...] [--out results/report.md]

Each directory holds ``benchmarks.table1`` row files from one machine (say this CPU and a GPU).
For every row: our T_abs, T_syn, T_abs + T_syn and memory next to the paper's, with the ratios
paper / ours (how many times faster / smaller). Below the table, the issue's targets for the SMDP
rows: T_abs + T_syn at least 50x below the paper's on a CPU and 1000x on a GPU, memory below the
paper's on every row; each is checked on the rows that have results.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .paper_table1 import KIND_NAMES, PAPER, TO, row_spec
from .table1 import load_results

TARGETS = {"cpu": 50.0, "gpu": 1000.0}


def _ratio(paper, ours):
    if paper in (None, TO) or ours is None or ours <= 0:
        return None
    return paper / ours


def _cell(value, fmt="{:.2f}"):
    if value is None:
        return "-"
    if fmt == "x":
        return f"{value:.0f}x" if value >= 10 else f"{value:.2g}x"
    return fmt.format(value)


def rows_of(results_dir: Path):
    results = load_results(results_dir)
    table = []
    for row in sorted(results):
        r, p, spec = results[row], PAPER[row], row_spec(row)
        ok = r.get("status") == "ok"
        backend = r.get("environment", {}).get("backend", "?")
        paper_total = None if p.t_syn_min == TO else (p.t_abs_min + p.t_syn_min) * 60
        ours_total = r["t_abs_s"] + r["t_syn_s"] if ok else None
        table.append(dict(row=row, kind=spec.kind, system=spec.system, backend=backend, status=r.get("status"),
                          quick=r.get("quick", False), t_abs=r.get("t_abs_s"), t_syn=r.get("t_syn_s") if ok else None,
                          total=ours_total, memory_mb=r["memory_bytes"] / 1e6 if "memory_bytes" in r else None,
                          paper_abs=p.t_abs_min * 60, paper_syn=None if p.t_syn_min == TO else p.t_syn_min * 60,
                          paper_total=paper_total, paper_memory_mb=p.memory_gb * 1e3,
                          time_limit=r.get("time_limit_min")))
    return table


def render(dirs) -> str:
    out = []
    for results_dir in dirs:
        table = rows_of(Path(results_dir))
        if not table:
            continue
        backend = table[0]["backend"]
        out.append(f"### {results_dir} ({backend})\n")
        out.append("| # | class | system | T_abs s (paper) | x | T_syn s (paper) | x | total s (paper) | x | "
                   "memory MB (paper) | x smaller |")
        out.append("|" + "---|" * 11)
        for t in table:
            status = t["status"]
            syn = _cell(t["t_syn"]) if status == "ok" else (f"TO ({t['time_limit']:g} min)" if status == TO else status)
            quick = " (quick)" if t["quick"] else ""
            out.append(
                f"| {t['row']} | {KIND_NAMES[t['kind']]} | {t['system']}{quick} | {_cell(t['t_abs'])} "
                f"({_cell(t['paper_abs'])}) | {_cell(_ratio(t['paper_abs'], t['t_abs']), 'x')} | {syn} "
                f"({_cell(t['paper_syn']) if t['paper_syn'] is not None else 'TO'}) | "
                f"{_cell(_ratio(t['paper_syn'], t['t_syn']), 'x')} | {_cell(t['total'])} "
                f"({_cell(t['paper_total']) if t['paper_total'] is not None else 'TO'}) | "
                f"{_cell(_ratio(t['paper_total'], t['total']), 'x')} | {_cell(t['memory_mb'])} "
                f"({_cell(t['paper_memory_mb'])}) | {_cell(_ratio(t['paper_memory_mb'], t['memory_mb']), 'x')} |")
        smdp = [t for t in table if t["kind"] == "smdp" and t["status"] == "ok" and not t["quick"]]
        target = TARGETS["gpu" if backend == "gpu" else "cpu"]
        if smdp:
            speedups = [_ratio(t["paper_total"], t["total"]) for t in smdp]
            met = sum(s >= target for s in speedups)
            out.append(f"\nSMDP rows: T_abs + T_syn speed-up over the paper min {min(speedups):.0f}x, median "
                       f"{np.median(speedups):.0f}x, max {max(speedups):.0f}x; target {target:.0f}x met on {met} of "
                       f"{len(smdp)} rows (met: {', '.join(str(t['row']) for t, x in zip(smdp, speedups) if x >= target) or 'none'}; "
                       f"not met: {', '.join(str(t['row']) for t, x in zip(smdp, speedups) if x < target) or 'none'}).")
        full = [t for t in table if t["memory_mb"] is not None and not t["quick"]]
        if full:
            below = [t["row"] for t in full if t["memory_mb"] < t["paper_memory_mb"]]
            above = [t["row"] for t in full if t["memory_mb"] >= t["paper_memory_mb"]]
            out.append(f"Memory below the paper's on {len(below)} of {len(full)} rows"
                       + (f"; not on rows {above}." if above else "."))
        out.append("")
    return "\n".join(out)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, nargs="+", default=[Path("results/table1")])
    parser.add_argument("--out", type=Path, default=Path("results/report.md"))
    args = parser.parse_args(argv)
    text = render(args.results)
    if not text.strip():
        parser.error(f"no row results in {[str(d) for d in args.results]}: run python -m benchmarks.table1 first")
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
