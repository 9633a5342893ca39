"""One case study end to end with Monte Carlo checks as in Table 1: abstract, solve, simulate.

Builds a case study of ``smdpjax.case_studies`` with keyword arguments (``--study
temperature:rooms=5,cells=10,noise_cells=3``), abstracts it (``--kind``, default ``smdp``), solves
it (``CaseStudy.solve``: synthesis for reach-avoid, verification of the fixed controller for
safety), then simulates ``--trajectories`` runs from uniform points in each of ``--initial`` cells
drawn from the non-terminal cells (``metrics.initial_cells``, seed 0) under the closed-loop
controller, and checks, as ``benchmarks/table1.py`` does, that each cell's empirical frequency lies
in ``[p_low - tol, p_up + tol]`` with ``tol`` a 4-sigma binomial band. Reports T_abs, T_syn
(first runs, compilation included), stored and peak resident memory, mean p_low / p_up over the
initial cells and the non-terminal cells, and the Monte Carlo counts.

    python -m benchmarks.case_study_mc --study temperature:rooms=5,cells=10,noise_cells=3
    python -m benchmarks.case_study_mc --study double_integrator_4d:cells=24 --initial 50
"""

from __future__ import annotations

import time

import jax
import numpy as np

import smdpjax as sj
from smdpjax import case_studies

from .common import argument_parser, binomial_tolerance, monte_carlo, rss_bytes, write_result


def parse_study(text: str):
    """``"name:key=value,key=value"`` -> the case study (values parsed as int, float or string)."""
    name, _, rest = text.partition(":")
    names = [n for n in case_studies.__all__ if n != "CaseStudy"]
    if name not in names:
        raise SystemExit(f"unknown case study {name!r}; one of {', '.join(names)}")
    constructor = getattr(case_studies, name)
    options = {}
    for item in filter(None, rest.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--study options are key=value, got {item!r}")
        for parse in (int, float):
            try:
                options[key] = parse(value)
                break
            except ValueError:
                continue
        else:
            options[key] = value
    return constructor(**options)


def run(study, kind: str, initial: int, trajectories: int, tol: float) -> dict:
    start = time.perf_counter()
    abstraction = jax.block_until_ready(study.abstract(kind))
    t_abs = time.perf_counter() - start
    start = time.perf_counter()
    solution = jax.block_until_ready(study.solve(abstraction, tol=tol))
    t_syn = time.perf_counter() - start
    lower, upper = np.asarray(solution.lower), np.asarray(solution.upper)
    grid = study.state_grid
    cells = sj.metrics.initial_cells(grid, min(initial, grid.nonterminal.size), seed=0)
    sat, undecided = monte_carlo(study.system, grid, study.closed_loop_policy(solution), cells, trajectories,
                                 seed=7, max_steps=study.max_steps, objective=study.objective)
    band = binomial_tolerance(sat, trajectories)
    inside = (sat >= lower[cells] - band) & (sat <= upper[cells] + band)
    nt = grid.nonterminal
    return {"study": repr(study), "kind": kind, "abstraction": repr(abstraction), "t_abs_s": t_abs,
            "t_syn_s": t_syn, "stored_mb": abstraction.nbytes / 1e6, "peak_rss_gib": rss_bytes() / 2**30,
            "p_low_initial": float(lower[cells].mean()), "p_up_initial": float(upper[cells].mean()),
            "p_mc_initial": float(sat.mean()), "p_low_nonterminal": float(lower[nt].mean()),
            "p_low_min": float(lower[nt].min()), "p_low_max": float(lower[nt].max()),
            "p_up_nonterminal": float(upper[nt].mean()), "mc_cells_in_bounds": int(inside.sum()),
            "mc_cells": int(inside.size), "trajectories": trajectories, "mc_undecided": int(undecided),
            "worst_excess": float(np.max(np.maximum(lower[cells] - sat, sat - upper[cells])))}


def main(argv=None):
    parser = argument_parser(__doc__, "case_study_mc", tol=1e-6)
    parser.add_argument("--study", required=True, help="name:key=value,... of a smdpjax.case_studies constructor")
    parser.add_argument("--kind", default="smdp", choices=["imdp", "2imdp", "mimdp", "smdp"])
    parser.add_argument("--initial", type=int, default=100, help="initial cells (Table 1: 100)")
    parser.add_argument("--trajectories", type=int, default=400, help="runs per initial cell")
    args = parser.parse_args(argv)
    study = parse_study(args.study)
    print(study, flush=True)
    result = run(study, args.kind, args.initial, args.trajectories, args.tol)
    for key, value in result.items():
        print(f"{key:>20}: {value:.4g}" if isinstance(value, float) else f"{key:>20}: {value}")
    print(f"wrote {write_result('case_study_mc', args, **result)}")
    return result


if __name__ == "__main__":
    main()
