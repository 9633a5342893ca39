"""Shared helpers for benchmark scripts: command lines, timing medians, JSON output, Monte Carlo checks.

Every script starts its command line from ``argument_parser`` (its docstring as the help text,
``--out results/<name>.json``, and ``--repeats`` / ``--tol`` where it times runs or iterates to a
tolerance) and writes its results with ``write_result`` (``benchmark``, ``args`` and
``environment`` first, then the script's own fields).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import numpy as np

import smdpjax as sj


def timed(fn, repeats: int):
    """Run ``fn`` ``repeats`` times (after one warm-up that compiles); return (result, [seconds]).

    ``repeats=0`` times the single first call, compilation included (for stages too slow to repeat).
    """
    if repeats == 0:
        start = time.perf_counter()
        result = jax.block_until_ready(fn())
        return result, [time.perf_counter() - start]
    result = jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return result, times


def alternating(calls: dict, repeats: int) -> dict:
    """``{name: [seconds]}``: every call of ``calls`` (``name -> fn``, compiled already) timed once
    per round, ``max(1, repeats)`` rounds, so that all of them see the same machine load."""
    times = {name: [] for name in calls}
    for _ in range(max(1, repeats)):
        for name, call in calls.items():
            start = time.perf_counter()
            jax.block_until_ready(call())
            times[name].append(time.perf_counter() - start)
    return times


def median(xs):
    return float(statistics.median(xs))


def monte_carlo(system, grid, policy, cells, per_cell: int, seed: int, max_steps: int,
                objective: str = "reach_avoid"):
    """``(satisfied, undecided)``: the empirical satisfaction per initial cell ``(len(cells),)`` of
    ``per_cell`` runs from uniform points in each, under the look-up table ``policy (N + 1,)``
    (keys ``seed`` for the starts, ``seed + 1`` for the runs), and the runs left undecided."""
    controller = sj.Controller(grid, policy)
    x0 = sj.uniform_in_cells(grid, cells, per_cell, jax.random.PRNGKey(seed))
    res = sj.simulate(system, controller, x0, jax.random.PRNGKey(seed + 1), max_steps=max_steps,
                      objective=objective)
    return np.asarray(res.satisfied).reshape(len(cells), per_cell).mean(axis=1), res.undecided


def row_clusters(row: int, kind: str | None = None):
    """``(study, clusters)`` of Table 1 row ``row``: its case study and the clusters of its
    reachable sets; with ``kind``, a ``ValueError`` unless the row is of that class."""
    from smdpjax.abstraction import compute_grid_clusters

    from .paper_table1 import row_spec
    from .table1 import case_study

    spec = row_spec(row)
    if kind is not None and spec.kind != kind:
        raise ValueError(f"row {row} is not {'an' if kind[0] in 'aeimos' else 'a'} {kind_name(kind)} row")
    study = case_study(spec, False)
    return study, compute_grid_clusters(study.system, study.state_grid, study.noise_grid, policy=study.controller,
                                        method=study.reach_method)


def kind_name(kind: str) -> str:
    return {"imdp": "IMDP", "2imdp": "2I-MDP", "mimdp": "MI-MDP", "smdp": "SMDP"}[kind]


def rss_bytes() -> int:
    """Peak resident memory of this process (``ru_maxrss`` is in KiB on Linux)."""
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def binomial_tolerance(p, n, sigmas: float = 4.0):
    """Half-width of a ``sigmas``-standard-deviation band for averaged binomial frequencies."""
    return sigmas * np.sqrt(np.maximum(p * (1 - p), 1e-4) / n)


def environment() -> dict:
    """What a timing depends on beyond the code: versions of JAX and of the numerical packages
    (the MI-MDP's LP solvers among them), the processor and the number of CPUs."""
    return {"jax": jax.__version__, "backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()],
            "python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count(),
            "cpu_model": _cpu_model(), "packages": _package_versions(SOLVER_PACKAGES)}


SOLVER_PACKAGES = ("jaxlib", "numpy", "scipy", "highspy", "clarabel", "cvxpy")


def _package_versions(names) -> dict:
    from importlib import metadata

    versions = {}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def _cpu_model() -> str:
    """The processor's name (``/proc/cpuinfo`` on Linux, else ``platform.processor()``)."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def write_json(path: Path, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2, default=float))


def argument_parser(doc: str, name: str, *, repeats: int | None = None, repeats_help: str | None = None,
                    tol: float | None = None) -> argparse.ArgumentParser:
    """The command line every benchmark script starts from.

    Args:
        doc: the script's module docstring, shown verbatim by ``--help``.
        name: the script's name; ``--out`` defaults to ``results/<name>.json``.
        repeats: add ``--repeats`` with this default (timed runs; the median is reported).
        repeats_help: its help text.
        tol: add ``--tol`` (the solvers' stopping tolerance) with this default.
    """
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path(f"results/{name}.json"), help="JSON results file")
    if repeats is not None:
        parser.add_argument("--repeats", type=int, default=repeats,
                            help=repeats_help or "timed runs after a compiling warm-up (median reported)")
    if tol is not None:
        parser.add_argument("--tol", type=float, default=tol, help="value iteration's stopping tolerance")
    return parser


def arguments(args: argparse.Namespace) -> dict:
    """The parsed command line as strings, for the JSON record."""
    return {k: str(v) for k, v in vars(args).items()}


def write_result(name: str, args: argparse.Namespace, **payload) -> Path:
    """Write ``{"benchmark": name, "args": ..., "environment": ..., **payload}`` to ``args.out``
    (``payload`` may replace ``environment``, e.g. to add a peer tool's version); returns the path."""
    write_json(args.out, {"benchmark": name, "args": arguments(args), "environment": environment(), **payload})
    return args.out
