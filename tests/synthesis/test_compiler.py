"""How the backup loops are compiled (``smdpjax.synthesis.compiler``)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from smdpjax.synthesis.compiler import CPU_BACKUP_OPTIONS, backup_compiler_options, backup_jit


def block_sums(x):
    return x.reshape(-1, 27).sum(-1)


def test_options_only_on_the_cpu():
    assert backup_compiler_options("gpu") is None
    assert backup_compiler_options("cpu") in (None, CPU_BACKUP_OPTIONS)


def test_the_cpu_options_keep_short_reductions_in_xla():
    options = backup_compiler_options("cpu")
    x = jnp.arange(596 * 27.0)
    default = jax.jit(block_sums).lower(x).compile().as_text()
    if options is None or "ynn_fusion" not in default:
        pytest.skip("this XLA has no YNNPACK fusions (or not the option): nothing to turn off")
    assert "ynn_fusion" not in jax.jit(block_sums, compiler_options=options).lower(x).compile().as_text()


def test_backup_jit_at_top_level_inside_jit_and_under_vmap():
    @backup_jit(static_argnames=("scale",))
    def scaled_sums(x, scale: int):
        return scale * block_sums(x)

    x = jnp.asarray(np.random.default_rng(0).uniform(size=(3, 54)))
    expected = 2.0 * x.reshape(3, 2, 27).sum(-1)
    np.testing.assert_allclose(scaled_sums(x[0], scale=2), expected[0], rtol=1e-15)
    np.testing.assert_allclose(jax.jit(lambda y: scaled_sums(y, scale=2))(x[1]), expected[1], rtol=1e-15)
    np.testing.assert_allclose(jax.vmap(lambda y: scaled_sums(y, scale=2))(x), expected, rtol=1e-15)
