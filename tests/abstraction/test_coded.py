"""Coded float arrays (``abstraction.coded``): exact, used only where smaller, and the classes
that store their bounds coded give the values of the plain arrays."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.abstraction import compute_grid_clusters
from smdpjax.abstraction.coded import Coded, decoded, encode, map_entries


@pytest.mark.parametrize("distinct, code_dtype", [(1, np.uint8), (256, np.uint8), (257, np.uint16),
                                                  (65536, np.uint16)])
def test_encode_is_exact_and_as_narrow_as_the_values_allow(distinct, code_dtype):
    rng = np.random.default_rng(distinct)
    values = rng.uniform(0, 1, distinct)
    x = rng.permutation(np.concatenate([values, rng.choice(values, 300_000 - distinct)])).reshape(600, 500)
    if distinct > 256:  # uint16 codes only on request
        assert encode(jnp.asarray(x)).dtype == np.float64 and not isinstance(encode(jnp.asarray(x)), Coded)
    coded = encode(jnp.asarray(x), max_codes=1 << 16)
    assert isinstance(coded, Coded) and coded.codes.dtype == code_dtype and coded.table.shape == (distinct,)
    assert coded.shape == x.shape and coded.dtype == x.dtype
    np.testing.assert_array_equal(np.asarray(coded.decode()), x)  # bit for bit
    assert coded.codes.nbytes + coded.table.nbytes < x.nbytes
    pick = lambda a: a[::7, 3:9]
    np.testing.assert_array_equal(np.asarray(decoded(map_entries(coded, pick))), x[::7, 3:9])


def test_encode_leaves_arrays_it_cannot_shrink():
    rng = np.random.default_rng(0)
    many = jnp.asarray(rng.uniform(0, 1, 70_000))  # more distinct values than uint16 codes
    assert encode(many) is many
    small = jnp.asarray(rng.uniform(0, 1, 3))  # the table would outweigh the codes' saving
    assert encode(small) is small
    ints = jnp.arange(1000) % 3
    assert encode(ints) is ints
    assert decoded(ints) is ints
    with pytest.raises(ValueError, match="at most 65536"):
        encode(many, max_codes=1 << 17)
    few = jnp.asarray(np.repeat([0.25, 0.5], 5000))
    assert isinstance(encode(few), Coded)
    assert jax.jit(lambda a: encode(a) is a)(few)  # traced: left as it is


@pytest.mark.parametrize("distinct", [3, 300])
def test_encode_of_a_small_array_sorts_it_once_bit_for_bit(distinct):
    from smdpjax.abstraction import coded

    values = np.concatenate([np.arange(1, distinct - 2) / 7, [0.0, -0.0, np.nan]])
    x = np.random.default_rng(distinct).permutation(np.repeat(values, 4)).reshape(-1, 2)
    assert x.size <= coded._SAMPLES[0]  # the one-sort path
    got = encode(jnp.asarray(x), max_codes=1 << 16)
    assert isinstance(got, Coded) and got.table.shape == (distinct,) and got.shape == x.shape
    assert got.codes.dtype == (np.uint8 if distinct <= 256 else np.uint16)
    np.testing.assert_array_equal(np.asarray(got.decode()).view(np.uint64), x.view(np.uint64))
    if distinct > 256:  # more values than uint8 codes: left as it is by default
        assert not isinstance(encode(jnp.asarray(x)), Coded)


def _drift(x, u, w):
    return x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)


@pytest.mark.parametrize("kind", ["imdp", "2imdp"])
def test_classes_store_coded_upper_bounds_and_give_the_plain_values(kind, assert_same_q_values):
    system = sj.System(_drift, actions=(np.arange(4) * np.pi / 2)[:, None], noise=sj.Uniform([-1, -1], [1, 1]))
    grid = sj.StateGrid([0, 0], [1, 1], 10, reach=[([0.7, 0.7], [1, 1])])
    noise = sj.NoiseGrid.box([-1, -1], [1, 1], 4)  # equal cells: few distinct Lemma 1 bounds
    abstraction = sj.abstract(system, grid, noise, kind)
    assert isinstance(abstraction.chunk_upper, Coded) and abstraction.chunk_upper.codes.dtype == np.uint8
    plain = dataclasses.replace(abstraction, chunk_upper=abstraction.chunk_upper.decode())
    assert abstraction.nbytes < plain.nbytes
    np.testing.assert_array_equal(np.asarray(abstraction.upper), np.asarray(plain.upper))
    rng = np.random.default_rng(1)
    strategy = jnp.asarray(rng.integers(0, abstraction.num_actions, abstraction.num_rows), jnp.int32)
    values = [jnp.asarray(rng.uniform(0, 1, grid.num_states)).at[-1].set(0.0) for _ in range(2)]
    assert_same_q_values(abstraction, plain, values, strategy, atol=0.0)
    a, b = sj.synthesize(abstraction), sj.synthesize(plain)
    np.testing.assert_array_equal(np.asarray(a.lower), np.asarray(b.lower))
    np.testing.assert_array_equal(np.asarray(a.upper), np.asarray(b.upper))


@pytest.mark.parametrize("lookup", ["numpy", "hash", "levels", "search"])
@pytest.mark.parametrize("distinct", [3, 300])
def test_encode_completes_the_sampled_table_bit_for_bit(distinct, lookup, monkeypatch):
    from smdpjax.abstraction import coded

    monkeypatch.setattr(coded, "_SAMPLES", (4, 64))  # samples that miss most values
    if lookup != "numpy":  # the compiled pass over every entry
        monkeypatch.setattr(coded, "_HOST_LOOKUP", 0)
    if lookup == "levels":  # 1 024 slots: 300 values need several levels of hashes
        monkeypatch.setattr(coded, "_HASH_BITS", 10)
        assert distinct < 300 or len(coded._hash_levels(np.arange(300, dtype=np.uint64) * 7919)) > 1
    if lookup == "search":  # no hash separates them: a binary search
        monkeypatch.setattr(coded, "_MULTIPLIERS", ())
    monkeypatch.setattr(coded, "_search_codes" if lookup in ("hash", "levels") else "_hash_codes", None)
    values = np.concatenate([np.arange(1, distinct - 2) / 7, [0.0, -0.0, np.nan]])
    x = np.random.default_rng(distinct).permutation(np.repeat(values, 50))
    got = encode(jnp.asarray(x), max_codes=1 << 16)
    assert isinstance(got, Coded) and got.table.shape == (distinct,)
    np.testing.assert_array_equal(np.asarray(got.decode()).view(np.uint64), x.view(np.uint64))
