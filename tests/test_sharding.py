"""Several devices: sharded abstractions give the one-device results.

The device count is fixed when JAX starts, and this process must keep its single device, so two
child processes run the same small problem side by side: one on a single CPU device, one on 4
forced CPU devices (``XLA_FLAGS=--xla_force_host_platform_device_count=4``) with every
abstraction built and solved sharded. Each writes its arrays and a JSON summary; the tests below
compare them.

Abstractions and reachable sets must be equal bit for bit. Solutions are compared up to float
rounding: XLA:CPU's dot and fused reductions round a row's sum differently depending on how many
rows the kernel gets (on one device too: ``q_values`` of a 19-row slice can differ in the last
bit from the same rows of the whole array), and a device holds a quarter of the rows. Both
results are within ``rounding_allowance`` of the exact values, so they differ by at most twice
that (measured: IMDP 0, 2I-MDP 4e-16, SMDP 9e-19), with the same iteration counts and the same
strategies except at actions tied up to the tolerance (exact ties are broken by the last bit).
The MI-MDP's LP multipliers (an interior-point solver) respond to such last-bit changes of the
costs, which moves its certified bounds by up to ~5e-11 and may break near-ties differently.
"""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
# smdp: index boxes (the members encoding shards the same leaves); smdp-structured: the same system
# declared additive, with per-dimension pieces of the boxes
KINDS = ("imdp", "2imdp", "smdp", "mimdp", "smdp-structured")
HORIZON = 6

CHILD = textwrap.dedent(r'''
    import json, sys
    import jax, jax.numpy as jnp, numpy as np
    import smdpjax as sj
    from smdpjax.abstraction import compute_grid_clusters
    from smdpjax.sharding import row_mesh, shard_abstraction, unshard_abstraction

    sharded, out_dir, horizon = sys.argv[1] == "many", sys.argv[2], int(sys.argv[3])

    def dynamics(x, u, w):  # steps of about one cell, so the lower bounds are not all 0
        return x + 0.12 * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + 0.1 * w

    system = sj.System(dynamics, actions=(np.arange(4) * np.pi / 2)[:, None],
                       noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    additive = sj.System.additive(lambda x, u: x + 0.12 * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]), 0.1,
                                  actions=system.actions, noise=system.noise)
    grid = sj.StateGrid([0, 0], [1, 1], 10, reach=[([0.6, 0.6], [1.0, 1.0])],
                        avoid=[([0.3, 0.0], [0.5, 0.5])])  # 74 non-terminal rows: 2 padding copies
    noise = sj.NoiseGrid.ball([0.0, 0.0], 2.1, 6)
    mesh = row_mesh() if sharded else None
    info = {"devices": len(jax.devices()), "kinds": {}}
    arrays = {}

    def save(prefix, tree):
        for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
            arrays[prefix + jax.tree_util.keystr(path)] = np.asarray(leaf)

    def save_solution(prefix, s):
        save(prefix, {f: getattr(s, f) for f in ("lower", "upper", "policy", "lower_optimal")})
        return [s.iterations, s.evaluation_iterations, s.converged, s.rounding_allowance]

    clusters = compute_grid_clusters(system, grid, noise, mesh=mesh)
    save("clusters", (clusters.rows, clusters.boxes))
    if sharded:
        info["axis_types"] = [str(t) for t in mesh.axis_types]
    kinds = list(KINDS)
    try:
        import clarabel  # noqa: F401
    except ImportError:
        kinds.remove("mimdp")
    for kind in kinds:
        res = {}
        options = {"encoding": kind.split("-")[1]} if "-" in kind else {}
        if kind == "mimdp":  # interior point: each LP solved from scratch, so the values do not
            options["lp_backend"] = "clarabel"  # depend on which device solved what before (HiGHS's warm bases do)
        a = sj.abstract(additive if kind == "smdp-structured" else system, grid, noise, kind.split("-")[0],
                        mesh=mesh, **options)
        res["num_rows"] = a.num_rows
        if sharded:
            # every per-row leaf in 4 equal shards, one per device; every other leaf on all 4
            split, copies = [], []
            for path, leaf in jax.tree_util.tree_leaves_with_path(a):
                devices = {s.device for s in leaf.addressable_shards}
                shapes = {s.data.shape for s in leaf.addressable_shards}
                if leaf.ndim and leaf.shape[0] == a.num_rows and not jax.tree_util.keystr(path).endswith("labels"):
                    split.append(len(devices) == 4 and shapes == {(a.num_rows // 4, *leaf.shape[1:])})
                else:
                    copies.append(len(devices) == 4 and shapes == {leaf.shape})
            res.update(split_leaves=len(split), all_split=all(split), all_replicated=all(copies))
            res["restricted_split"] = len(a.restrict(a.rows * 0).rows.sharding.device_set) == 4
            plain = unshard_abstraction(a)
            res["unsharded_rows"] = plain.num_rows
            same = lambda x, y: all(np.array_equal(np.asarray(p), np.asarray(q)) for p, q in
                                    zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)))
            res["reshard_equal"] = same(shard_abstraction(plain, mesh), a)
            save(kind + "/abstraction", plain)
        else:
            save(kind + "/abstraction", a)
        s = sj.synthesize(a)
        res["unbounded"] = save_solution(kind + "/unbounded", s)
        if not sharded:  # to tell near-ties of the strategy apart from real differences
            arrays[kind + "/q"] = np.asarray(a.q_values(s.lower_optimal))
            arrays[kind + "/rows"] = np.asarray(a.rows)
        res["solution_devices"] = len(s.lower.sharding.device_set)
        res["finite"] = save_solution(kind + "/finite", sj.synthesize(a, horizon=horizon))
        policy = np.arange(grid.num_states) % system.num_actions  # a fixed controller to verify
        res["verify"] = save_solution(kind + "/verify", sj.verify(a, policy))
        info["kinds"][kind] = res
    if sharded:  # a mesh from jax.make_mesh (explicit axes by default) is made automatic
        explicit = shard_abstraction(sj.abstract(system, grid, noise, "smdp"), jax.make_mesh((4,), ("rows",)))
        save("explicit", sj.synthesize(explicit).lower)
        # a coded array's table stays whole even when it has as many values as there are rows
        import dataclasses
        from smdpjax.abstraction.coded import Coded
        imdp = sj.abstract(system, grid, noise, "imdp")
        codes, table = imdp.chunk_upper.codes, imdp.chunk_upper.table
        wide = jnp.zeros(imdp.num_rows).at[:table.shape[0]].set(table)
        wide = shard_abstraction(dataclasses.replace(imdp, chunk_upper=Coded(codes=codes, table=wide)), mesh)
        info["coded_table"] = [wide.chunk_upper.table.shape[0] == imdp.num_rows,
                               wide.chunk_upper.table.sharding.is_fully_replicated]
    np.savez(out_dir + "/arrays.npz", **arrays)
    with open(out_dir + "/info.json", "w") as f:
        json.dump(info, f)
''').replace("list(KINDS)", repr(list(KINDS)))


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Both children, started together (they compile in parallel)."""
    base = dict(os.environ, JAX_PLATFORMS="cpu",
                PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    procs = {}
    for mode, flags in (("one", ""), ("many", "--xla_force_host_platform_device_count=4")):
        out = tmp_path_factory.mktemp(mode)
        env = dict(base, XLA_FLAGS=" ".join(filter(None, [os.environ.get("XLA_FLAGS", ""), flags])))
        proc = subprocess.Popen([sys.executable, "-c", CHILD, mode, str(out), str(HORIZON)], env=env, cwd=ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs[mode] = (proc, out)
    results = {}
    for mode, (proc, out) in procs.items():
        stdout, stderr = proc.communicate(timeout=900)
        assert proc.returncode == 0, f"{mode} child failed:\n{stdout[-3000:]}\n{stderr[-5000:]}"
        with np.load(out / "arrays.npz") as data:
            arrays = dict(data)
        results[mode] = (json.loads((out / "info.json").read_text()), arrays)
    return results


def _kind(runs, kind):
    if kind not in runs["many"][0]["kinds"]:
        pytest.skip(f"{kind} not run (clarabel missing)")
    assert kind in runs["one"][0]["kinds"]
    return runs["one"][0]["kinds"][kind], runs["many"][0]["kinds"][kind]


def _arrays(runs, prefix):
    one, many = (runs[m][1] for m in ("one", "many"))
    keys = sorted(k for k in one if k.startswith(prefix))
    assert keys and keys == sorted(k for k in many if k.startswith(prefix))
    return [(k, one[k], many[k]) for k in keys]


def test_four_devices_with_an_automatic_axis(runs):
    assert runs["one"][0]["devices"] == 1
    assert runs["many"][0]["devices"] == 4
    assert runs["many"][0]["axis_types"] and all("Auto" in t for t in runs["many"][0]["axis_types"])


def test_reachable_sets_on_the_mesh_equal_one_device(runs):
    for key, a, b in _arrays(runs, "clusters"):
        assert a.dtype == b.dtype and np.array_equal(a, b), key


@pytest.mark.parametrize("kind", KINDS)
def test_rows_are_padded_and_split_over_four_devices(runs, kind):
    one, many = _kind(runs, kind)
    assert one["num_rows"] % 4 != 0, "the problem must need padding"
    assert many["num_rows"] == -(-one["num_rows"] // 4) * 4 and many["unsharded_rows"] == one["num_rows"]
    assert many["split_leaves"] >= 2 and many["all_split"] and many["all_replicated"]
    assert many["restricted_split"] and many["solution_devices"] == 4


@pytest.mark.parametrize("kind", KINDS)
def test_abstraction_built_with_mesh_equals_one_device(runs, kind):
    _, many = _kind(runs, kind)
    assert many["reshard_equal"]
    for key, a, b in _arrays(runs, kind + "/abstraction"):
        assert a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b), key


@pytest.mark.parametrize("task", ["unbounded", "finite", "verify"])
@pytest.mark.parametrize("kind", KINDS)
def test_solutions_equal_to_one_device(runs, kind, task):
    one, many = _kind(runs, kind)
    if task == "unbounded":
        assert one[task][0] + one[task][1] > 10  # value iteration does real work here
    allowance = one[task][3]
    for key, a, b in _arrays(runs, f"{kind}/{task}"):
        if kind != "mimdp":
            if "policy" in key and task == "unbounded":
                _assert_near_ties(runs, kind, a, b)
            elif "policy" in key:
                assert np.array_equal(a, b), key
            else:
                np.testing.assert_allclose(b, a, rtol=0, atol=2 * allowance, err_msg=key)
        elif "policy" in key:
            assert np.mean(a != b) <= 0.05, key  # near-ties of the LP-certified values
        else:
            # LP solver tolerance, and for an unbounded horizon the value iteration's (1e-6): near-ties
            # of the LP-certified values may pick another strategy and stop elsewhere within tol
            atol = 1e-6 if task == "unbounded" else 1e-8
            np.testing.assert_allclose(b, a, rtol=0, atol=atol, err_msg=key)
    if kind != "mimdp":
        assert one[task][:3] == many[task][:3]  # iterations and convergence
    else:
        assert abs(one[task][0] - many[task][0]) <= 3 and abs(one[task][1] - many[task][1]) <= 3


def _assert_near_ties(runs, kind, policy_one, policy_many):
    """Stationary strategies may differ only where both actions are optimal up to the value
    iteration's tolerance: exact ties (symmetric actions get bit-identical Lemma 1 bounds) are
    broken by the last bit of a row's sum, which depends on how many rows a device holds."""
    arrays = runs["one"][1]
    q, rows = arrays[kind + "/q"], arrays[kind + "/rows"]
    differ = np.flatnonzero(policy_one[rows] != policy_many[rows])
    assert differ.size <= 0.05 * rows.size
    gap = np.abs(q[differ, policy_one[rows][differ]] - q[differ, policy_many[rows][differ]])
    assert np.all(gap <= 2e-6), gap  # 2 x the default tolerance (1e-6)


def test_coded_table_is_replicated_whatever_its_length(runs):
    assert runs["many"][0]["coded_table"] == [True, True]


def test_explicit_mesh_is_made_automatic(runs):
    one, many = runs["one"][1], runs["many"][1]
    np.testing.assert_allclose(many["explicit"], one["smdp/unbounded['lower']"], rtol=0,
                               atol=2 * runs["one"][0]["kinds"]["smdp"]["unbounded"][3])
