"""The LP data of ``lp.ClusterLPs``, built for all LPs at once (``LPTable``), against a per-LP
construction written out directly from the surrogate LP of the module docstring."""

import numpy as np
import pytest

from smdpjax.abstraction.lp import ClusterLPs, LPTable


def per_lp_reference(succ, lower, upper, rest, slots, clo, cup, num_states, max_buckets=16):
    """Every LP's data, one LP at a time (the construction before ``LPTable``)."""
    width = succ.shape[1]
    lps = []
    for p in range(succ.shape[0]):
        listed = succ[p] < num_states
        cap = np.where(listed, upper[p] - lower[p], 0.0)
        low = np.where(listed, lower[p], 0.0)
        n_unlisted = num_states - listed.sum()
        if rest > 0:
            b = min(n_unlisted, min(max_buckets, int(np.ceil(1.0 / rest - 1e-9))))
            b = 0 if n_unlisted * rest <= 1e-6 else b
            has_rest = n_unlisted > b
        else:
            b, has_rest = 0, False
        free = 1.0 - low.sum()
        var_slots = np.flatnonzero(listed & (cap > 0))
        var_of_slot = np.full(width, -1)
        var_of_slot[var_slots] = np.arange(var_slots.size)
        caps = np.concatenate([cap[var_slots], np.full(b, rest), [(n_unlisted - b) * rest] if has_rest else []])
        cost_src = np.concatenate([var_slots, width + np.arange(b), [width + b] if has_rest else []])
        rows, ptr, var, los, his = [], [0], [], [], []
        for j in range(slots.shape[1]):
            members = [int(s) for s in slots[p, j] if s < width]
            fixed, room = low[members].sum(), cap[members].sum()
            ids = [int(var_of_slot[s]) for s in members if var_of_slot[s] >= 0]
            use_lo = clo[p, j] - fixed > 1e-12 and ids
            use_hi = max(cup[p, j] - fixed, 0.0) < min(room, free) - 1e-12 and ids
            if use_lo or use_hi:
                rows.append(j)
                var += ids
                ptr.append(len(var))
                los.append(min(clo[p, j] - fixed, room) if use_lo else -np.inf)
                his.append(max(cup[p, j] - fixed, 0.0) if use_hi else np.inf)
        lps.append(dict(caps=caps, cost_src=cost_src, free_mass=free, cluster=np.array(rows, int),
                        ptr=np.array(ptr), var=np.array(var, int), lo=np.array(los), hi=np.array(his)))
    return lps


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("rest", [0.0, 0.004, 0.2])
def test_lp_table_equals_the_per_lp_construction(seed, rest, random_lps):
    args = random_lps(seed, rest)
    lps = ClusterLPs(*args)
    reference = per_lp_reference(*args)
    assert isinstance(lps._lps, LPTable) and len(lps._lps) == len(reference)
    assert sum(r["cluster"].size for r in reference) > 0 and sum(r["caps"].size for r in reference) > 0
    for p, (got, want) in enumerate(zip(lps._lps, reference)):
        assert got.keys() == want.keys()
        for key in want:
            np.testing.assert_array_equal(np.asarray(got[key]), np.asarray(want[key]), err_msg=f"LP {p} {key}")
    np.testing.assert_array_equal(lps.num_vars, [r["caps"].size for r in reference])
    sides = [int(np.isfinite(r["lo"]).sum() + np.isfinite(r["hi"]).sum()) for r in reference]
    np.testing.assert_array_equal(lps.num_cluster_rows, sides)
    assert lps.nnz == sum(3 * r["caps"].size + 2 * r["var"].size for r in reference)


def test_lp_table_concatenates_blocks_with_empty_lps():
    """Blocks whose LPs have no variables or no cluster rows keep every LP's pieces in place."""
    def table(caps_per_lp, rows_per_lp, members_per_row):
        caps = np.concatenate([np.full(c, float(i)) for i, c in enumerate(caps_per_lp)])
        start = lambda counts: np.concatenate([[0], np.cumsum(counts)])
        rows = int(sum(rows_per_lp))
        return LPTable(caps=caps, cost_src=np.arange(caps.size, dtype=np.int32), var_start=start(caps_per_lp),
                       free_mass=np.arange(len(caps_per_lp), dtype=float), cluster=np.arange(rows, dtype=np.int32),
                       lo=np.zeros(rows), hi=np.ones(rows), row_start=start(rows_per_lp),
                       var=np.arange(int(sum(members_per_row))), member_start=start(members_per_row))

    a, b = table([2, 0, 3], [1, 0, 2], [2, 1, 3]), table([0, 4], [0, 1], [4])
    both = LPTable.concatenate([a, b])
    assert len(both) == 5
    for got, want in zip(both, [*a, *b]):
        for key in want:
            np.testing.assert_array_equal(np.asarray(got[key]), np.asarray(want[key]), err_msg=key)
    assert both[3]["caps"].size == 0 and both[3]["cluster"].size == 0 and both[4]["ptr"].tolist() == [0, 4]


@pytest.mark.parametrize("rest", [0.0, 0.2])
def test_highs_model_arrays_are_the_lps_rows_written_out(rest, random_lps):
    """``_highs_model`` slices the flat table (and shared constant arrays); its arrays are LP
    ``p``'s written out from ``table[p]``: ``n`` variables in [0, caps], the equality row at
    ``free_mass``, then each cluster row's members, row-wise with unit coefficients."""
    lps = ClusterLPs(*random_lps(3, rest), backend="highs")
    rng = np.random.default_rng(0)
    for p, lp in enumerate(lps._lps):
        n, k = lp["caps"].size, lp["cluster"].size
        cost = rng.random(n)
        want = (n, 1 + k, n + lp["var"].size, 2, 1, 0.0, cost, np.zeros(n), lp["caps"],
                np.concatenate([[lp["free_mass"]], lp["lo"]]), np.concatenate([[lp["free_mass"]], lp["hi"]]),
                np.concatenate([[0], n + lp["ptr"]]).astype(np.int32),
                np.concatenate([np.arange(n), lp["var"]]).astype(np.int32), np.ones(n + lp["var"].size),
                np.zeros(n, np.int32))
        got = lps._highs_model(p, cost)
        assert len(got) == len(want)
        for i, (g, w) in enumerate(zip(got, want)):
            g, w = np.asarray(g), np.asarray(w)
            assert g.dtype == w.dtype, (p, i)
            np.testing.assert_array_equal(g, w, err_msg=f"LP {p} argument {i}")
    big = lps._model_constants(4 * lps._model_constants(1)["ones"].size)  # grows, stays read-only
    assert not big["ones"].flags.writeable and big["arange"][-1] == big["arange"].size - 1
