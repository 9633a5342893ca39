"""Per-iteration cost of the MI-MDP inner problem on the 2-D unicycle (30x30, 8 actions, 12x12 + 1 noise cells).

Times ``MIMDP.q_values(v, "min")`` over all rows and actions (jitted; the LPs run on the host
through ``jax.pure_callback``, then the certified bound in JAX) for a few value-iteration steps
starting at the IMDP's pessimistic value (the warm start the synthesis uses), with the Clarabel
backend and, if ``highspy`` is installed, the warm-started HiGHS backend. Compares with naive
per-LP CVXPY loops (Clarabel backend, full N+1-state LP with every constraint written out),
timed on a subset of the LPs and extrapolated; checks the certified values against exact vertex
solutions (HiGHS dual simplex via scipy) on that subset; sweeps block size (LPs stacked per
Clarabel problem), threads and solver settings there.

    python -m benchmarks.mimdp_lp [--cells 30] [--subset 48] [--repeats 3] [--steps 4] [--out results/mimdp_lp.json]
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

import smdpjax as sj
from smdpjax.abstraction import compute_grid_clusters
from smdpjax.abstraction.lp import ClusterLPs
from smdpjax.abstraction.mimdp import MIMDP, certified_min

from .common import argument_parser, median, write_result
from .core_2d import problem


def naive_cvxpy(mimdp, v, lps, rebuild: bool):
    """Solve LPs ``lps`` (flat (row, action) indices) with CVXPY; returns (values, seconds per LP)."""
    import cvxpy as cp

    imdp, n = mimdp.relaxation, mimdp.num_states
    rest = float(imdp.upper_rest)
    a_count = mimdp.num_actions
    succ_all, lo_all, up_all = (np.asarray(x) for x in (imdp.successors, imdp.lower, imdp.upper))
    slots_all = np.asarray(mimdp.cluster_slots)
    clo_all, cup_all = np.asarray(mimdp.cluster_lower), np.asarray(mimdp.cluster_upper)

    def make(p, cost):
        r, a = divmod(int(p), a_count)
        succ, keep = succ_all[r, a], succ_all[r, a] < n
        lo, hi = np.zeros(n), np.full(n, rest)
        lo[succ[keep]], hi[succ[keep]] = lo_all[r, a][keep], up_all[r, a][keep]
        real = np.any(slots_all[r, a] < succ.size, axis=1)
        member = np.zeros((int(real.sum()), n))
        for j, s in enumerate(slots_all[r, a][real]):
            member[j, succ[s[s < succ.size]]] = 1.0
        g = cp.Variable(n)
        cons = [cp.sum(g) == 1, g >= lo, g <= hi, member @ g >= clo_all[r, a][real], member @ g <= cup_all[r, a][real]]
        return cp.Problem(cp.Minimize(cost @ g), cons)

    values, start = [], None
    if rebuild:  # what a straightforward implementation does every iteration
        start = time.perf_counter()
        for p in lps:
            prob = make(p, v)
            prob.solve(solver=cp.CLARABEL)
            values.append(prob.value)
    else:  # parametrized (DPP) problems built once, only the objective changes
        cost = cp.Parameter(n)
        probs = [make(p, cost) for p in lps]
        cost.value = v
        for prob in probs:  # first solve canonicalizes
            prob.solve(solver=cp.CLARABEL)
        start = time.perf_counter()
        for prob in probs:
            prob.solve(solver=cp.CLARABEL)
            values.append(prob.value)
    return np.array(values), (time.perf_counter() - start) / len(lps)


def vertex_reference(mimdp, w, lps):
    """Values of the full LPs ``lps`` (HiGHS dual simplex on all N+1 states; tight tolerances: at
    the default 1e-7 it returns vertices that violate cluster constraints by ~5e-8)."""
    from scipy.optimize import linprog

    imdp, n = mimdp.relaxation, mimdp.num_states
    rest = float(imdp.upper_rest)
    out = []
    for p in lps:
        r, a = divmod(int(p), mimdp.num_actions)
        succ = np.asarray(imdp.successors[r, a])
        keep = succ < n
        lo, hi = np.zeros(n), np.full(n, rest)
        lo[succ[keep]], hi[succ[keep]] = np.asarray(imdp.lower[r, a])[keep], np.asarray(imdp.upper[r, a])[keep]
        slots = np.asarray(mimdp.cluster_slots[r, a])
        real = np.any(slots < succ.size, axis=1)
        member = np.zeros((int(real.sum()), n))
        for j, s in enumerate(slots[real]):
            member[j, succ[s[s < succ.size]]] = 1.0
        clo, cup = np.asarray(mimdp.cluster_lower[r, a])[real], np.asarray(mimdp.cluster_upper[r, a])[real]
        res = linprog(w, A_ub=np.vstack([member, -member]), b_ub=np.r_[cup, -clo], A_eq=np.ones((1, n)), b_eq=[1.0],
                      bounds=list(zip(lo, hi)), method="highs-ds",
                      options=dict(primal_feasibility_tolerance=1e-10, dual_feasibility_tolerance=1e-10))
        out.append(res.fun)
    return np.array(out)


def resident_mb() -> float:
    """Resident memory of this process (Linux), MB."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * 4096 / 1e6
    except OSError:  # pragma: no cover
        return float("nan")


def iterate(mimdp, v, steps):
    """``steps`` value-iteration steps from ``v``; seconds of each ``q_values`` call (the first one
    also sets the solvers up)."""
    q = jax.jit(lambda m, x: m.q_values(x, "min"))
    rows = mimdp.rows
    times, values, iterates = [], [], []
    for _ in range(steps):
        iterates.append(np.asarray(v))
        start = time.perf_counter()
        out = jax.block_until_ready(q(mimdp, v))
        times.append(time.perf_counter() - start)
        values.append(np.asarray(out))
        v = v.at[rows].set(out.max(axis=1))
    return values, times, iterates


def main(argv=None):
    parser = argument_parser(__doc__, "mimdp_lp", repeats=3)
    parser.add_argument("--cells", type=int, default=30)
    parser.add_argument("--subset", type=int, default=48, help="LPs for the CVXPY loop and the sweeps")
    parser.add_argument("--steps", type=int, default=4, help="value-iteration steps timed per backend")
    parser.add_argument("--threads", type=int, default=None, help="LP threads (default: auto)")
    args = parser.parse_args(argv)

    system, grid, noise = problem(args.cells)
    print(f"{system!r}\n{grid!r}\n{noise!r}\n")
    clusters = compute_grid_clusters(system, grid, noise)
    start = time.perf_counter()
    mimdp = MIMDP.from_clusters(grid, clusters, threads=args.threads)
    t_build = time.perf_counter() - start
    imdp = mimdp.relaxation
    lps = mimdp.lps
    print(f"{mimdp!r}\n{lps!r}  (built in {t_build:.1f} s)")
    backends = {"clarabel": mimdp}
    try:
        import highspy  # noqa: F401
        flat = lambda a: np.asarray(a).reshape(lps.num_lps, *np.shape(a)[2:])
        highs = ClusterLPs(flat(imdp.successors), flat(imdp.lower), flat(imdp.upper), float(imdp.upper_rest),
                           flat(mimdp.cluster_slots), flat(mimdp.cluster_lower), flat(mimdp.cluster_upper),
                           grid.num_states, backend="highs", threads=lps.threads)
        backends["highs"] = dataclasses.replace(mimdp, lps=highs)
    except ImportError:
        print("highspy not installed: HiGHS backend skipped")

    # the value vector: the IMDP's pessimistic optimal value (the synthesis' warm start)
    v = jnp.asarray(sj.synthesize(imdp).lower_optimal)
    real_clusters = np.asarray(jnp.any(mimdp.cluster_slots < imdp.successors.shape[2], axis=-1)).sum(-1)
    sizes = dict(lp_count=int(lps.num_lps), clusters_per_row_mean=float(real_clusters.mean()),
                 clusters_per_row_max=int(real_clusters.max()),
                 variables_mean=float(lps.num_vars.mean()), variables_max=int(lps.num_vars.max()),
                 constraints_mean=float(lps.num_rows.mean()), constraints_max=int(lps.num_rows.max()),
                 cluster_sides_mean=float(lps.num_cluster_rows.mean()),
                 cluster_sides_max=int(lps.num_cluster_rows.max()),
                 highs_rows_mean=float(np.mean([1 + lp["cluster"].size for lp in lps._lps])),
                 reference_variables=grid.num_states,
                 reference_constraints_mean=float(1 + 2 * grid.num_states + 2 * real_clusters.mean()),
                 nnz_total=int(lps.nnz), memory_bytes=int(mimdp.nbytes), imdp_memory_bytes=int(imdp.nbytes))

    # full size: every row and action, a few value-iteration steps from the warm start
    q_im = np.asarray(jax.jit(lambda m, x: m.q_values(x, "min"))(imdp, v))
    full = {}
    q_first = None
    for name, model in backends.items():
        model.lps.stats.clear()
        before = resident_mb()
        values, times, iterates = iterate(model, v, args.steps)
        host_mb = resident_mb() - before
        stats = dict(model.lps.stats)
        q_first = values[0] if q_first is None else q_first
        lam = np.asarray(model.multipliers(v, model.lp_index))
        full[name] = dict(first_call_s=times[0], later_calls_s=times[1:], per_iteration_s=median(times[1:]),
                          per_lp_ms=median(times[1:]) / lps.num_lps * 1e3, threads=model.lps.threads,
                          host_solver_memory_mb=host_mb,
                          setup_s=stats.get("setup_seconds", 0.0),
                          statuses={k: x for k, x in stats.items() if k[0].isupper()},
                          gain_over_imdp_max=float((values[0] - q_im).max()),
                          gain_over_imdp_mean=float((values[0] - q_im).mean()),
                          below_imdp_min=float((values[0] - q_im).min()),
                          diff_to_first_backend=float(np.abs(values[0] - q_first).max()),
                          multipliers_clipped=int((lam > mimdp.multiplier_cap).sum()),
                          multipliers_max=float(lam.max()))
    q_mi = q_first

    # subset: naive CVXPY loops, an exact (vertex) reference, and the sweeps
    rng = np.random.default_rng(0)
    ids = np.sort(rng.choice(lps.num_lps, min(args.subset, lps.num_lps), replace=False)).astype(np.int64)
    w = np.asarray(v)
    ref_cvxpy, t_rebuild = naive_cvxpy(mimdp, w, ids, rebuild=True)
    _, t_dpp = naive_cvxpy(mimdp, w, ids, rebuild=False)
    exact = vertex_reference(mimdp, w, ids)
    naive = dict(rebuild_per_lp_ms=t_rebuild * 1e3, rebuild_extrapolated_s=t_rebuild * lps.num_lps,
                 dpp_per_lp_ms=t_dpp * 1e3, dpp_extrapolated_s=t_dpp * lps.num_lps,
                 max_abs_diff_cvxpy_vs_vertex=float(np.abs(ref_cvxpy - exact).max()))

    r_idx, a_idx = np.divmod(ids, mimdp.num_actions)
    pick = lambda x: jnp.asarray(np.asarray(x)[r_idx, a_idx])
    bound = jax.jit(certified_min, static_argnums=9)
    certify = lambda lam: np.asarray(bound(
        v, pick(imdp.successors), pick(imdp.lower), pick(imdp.upper), imdp.upper_rest, pick(mimdp.cluster_slots),
        pick(mimdp.cluster_lower), pick(mimdp.cluster_upper), jnp.asarray(lam), mimdp.multiplier_cap))
    base = dict(lps.settings)
    configs = [("clarabel", 1, 1, {}), ("clarabel", 4, 1, {}), ("clarabel", 16, 1, {}), ("clarabel", 64, 1, {}),
               ("clarabel", 1, 2, {}), ("clarabel", 1, 1, {"iterative_refinement_enable": True}),
               ("clarabel", 1, 1, {"direct_solve_method": "faer"}),
               ("clarabel", 1, 1, {"tol_gap_abs": 1e-6, "tol_gap_rel": 1e-6, "tol_feas": 1e-6})]
    if "highs" in backends:
        configs += [("highs", 1, 1, {})]
    sweep = []
    for backend, block, threads, settings in configs:
        model = lps if backend == "clarabel" else backends["highs"].lps
        model.block_size, model.threads = block, threads
        if backend == "clarabel":
            model.settings = {**base, **settings}
        model.reset()
        start = time.perf_counter()
        lam = model.multipliers(w, ids, direction=1)  # builds the solvers (cold solve)
        t_cold = time.perf_counter() - start
        g = certify(lam)
        model.stats.clear()
        times = []
        for k in range(args.repeats):  # the next value-iteration iterates (HiGHS warm starts)
            start = time.perf_counter()
            model.multipliers(iterates[1 + k % (len(iterates) - 1)], ids, direction=1)
            times.append(time.perf_counter() - start)
        sweep.append(dict(backend=backend, block_size=block, threads=threads, settings=settings,
                          per_lp_ms=median(times) / ids.size * 1e3, first_call_per_lp_ms=t_cold / ids.size * 1e3,
                          max_below_exact=float((exact - g).max()), max_above_exact=float((g - exact).max()),
                          statuses={k: x for k, x in model.stats.items() if k[0].isupper()}))

    print()
    print(f"LPs per iteration: {sizes['lp_count']} ((row, action) pairs); clusters per row "
          f"{sizes['clusters_per_row_mean']:.1f} (max {sizes['clusters_per_row_max']})")
    print(f"surrogate LP per row: {sizes['variables_mean']:.1f} variables (max {sizes['variables_max']}); "
          f"{sizes['cluster_sides_mean']:.1f} cluster sides after dropping implied ones (max "
          f"{sizes['cluster_sides_max']}); Clarabel form {sizes['constraints_mean']:.1f} constraint rows (max "
          f"{sizes['constraints_max']}), HiGHS form {sizes['highs_rows_mean']:.1f} ranged rows + variable bounds")
    print(f"reference LP per row: {sizes['reference_variables']} variables, "
          f"{sizes['reference_constraints_mean']:.0f} constraints (incl. variable bounds)")
    print(f"memory: MI-MDP {sizes['memory_bytes'] / 1e6:.1f} MB "
          f"(IMDP inside: {sizes['imdp_memory_bytes'] / 1e6:.1f} MB); "
          f"build {t_build:.1f} s\n")
    header = f"{'q_values(v, min), all rows and actions':58} {'per LP ms':>10} {'per iteration s':>16}"
    print(header)
    print("-" * len(header))
    print(f"{'CVXPY, problem rebuilt per LP (naive), extrapolated':58} {naive['rebuild_per_lp_ms']:10.2f} "
          f"{naive['rebuild_extrapolated_s']:16.1f}")
    print(f"{'CVXPY, parametrized (DPP) problems, extrapolated':58} {naive['dpp_per_lp_ms']:10.2f} "
          f"{naive['dpp_extrapolated_s']:16.1f}")
    for name, f in full.items():
        label = f"{name} direct + JAX certificate, measured ({f['threads']} threads)"
        print(f"{label:58} {f['per_lp_ms']:10.2f} {f['per_iteration_s']:16.1f}   "
              f"(first call {f['first_call_s']:.1f} s incl. setup; later {['%.1f' % t for t in f['later_calls_s']]}; "
              f"host solver memory +{f['host_solver_memory_mb']:.0f} MB)")
    print(f"\nsweep on {ids.size} LPs (LP part only; first call at v, then the next iterates):")
    for s_ in sweep:
        label = f"{s_['backend']}, block {s_['block_size']}, threads {s_['threads']}, {s_['settings'] or 'defaults'}"
        print(f"  {label:78} {s_['per_lp_ms']:7.3f} ms/LP (first {s_['first_call_per_lp_ms']:.2f})  certified "
              f"below exact by <= {s_['max_below_exact']:.1e}, above by <= {s_['max_above_exact']:.1e}  "
              f"{s_['statuses']}")
    print(f"\nCVXPY (Clarabel, default tolerances) vs vertex solutions: max |diff| "
          f"{naive['max_abs_diff_cvxpy_vs_vertex']:.1e}")
    for name, f in full.items():
        print(f"{name}: gain over the IMDP value max {f['gain_over_imdp_max']:.4f}, "
              f"mean {f['gain_over_imdp_mean']:.5f}; "
              f"min {f['below_imdp_min']:.1e}; differs from {next(iter(full))} by <= {f['diff_to_first_backend']:.1e}; "
              f"statuses {f['statuses']}; multipliers clipped {f['multipliers_clipped']} "
              f"(max {f['multipliers_max']:.3f})")
    write_result("mimdp_lp", args, load_average=list(__import__("os").getloadavg()), build_seconds=t_build,
                 sizes=sizes, full=full, naive_cvxpy=naive, sweep=sweep)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
