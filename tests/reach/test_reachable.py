"""reachable_boxes: staged evaluation (intermediates stored per state / action / noise cell)."""
import re

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from smdpjax.case_studies.temperature import dynamics as temperature_dynamics  # noqa: E402
from smdpjax.case_studies.unicycle_3d import dynamics as unicycle_dynamics  # noqa: E402
from smdpjax.reach import reachable_boxes  # noqa: E402


def _switching(x, u, w):
    """Saturation, a data-dependent branch and a per-state transcendental term."""
    gain = jnp.where(x[0] > 0.5, 0.5, 1.0)
    return jnp.array([jnp.clip(x[0] + u[0] * w[0], 0.0, 1.0), x[1] + gain * jnp.exp(-x[0]) * (u[1] + w[1])])


def _random_problem(n, m, d, rng, rows=7, actions=3, cells=5):
    x_lo = rng.uniform(0.0, 1.0, (rows, n))
    x_hi = x_lo + rng.uniform(0.0, 0.2, (rows, n))
    u = rng.uniform(-1.0, 1.0, (actions, m))
    w_lo = rng.uniform(-0.3, 0.3, (cells, d))
    w_hi = w_lo + rng.uniform(0.0, 0.1, (cells, d))
    x_lo[0, 0] = x_hi[0, 0] = 0.5  # a degenerate interval on a switching point
    w_lo[0] = 0.0  # noise edges at exact zeros: exact bounds stay exact
    return x_lo, x_hi, u, w_lo, w_hi


CASES = [(unicycle_dynamics, 3, 2, 2), (temperature_dynamics, 3, 3, 3), (_switching, 2, 2, 2)]


@pytest.mark.parametrize("method", ["natural", "both"])
@pytest.mark.parametrize("case", range(len(CASES)))
def test_staged_bounds_equal_unstaged_bit_for_bit(case, method):
    dynamics, n, m, d = CASES[case]
    x_lo, x_hi, u, w_lo, w_hi = _random_problem(n, m, d, np.random.default_rng(case))
    x_open = np.random.default_rng(1).random(x_lo.shape) < 0.5
    runs = [jax.jit(lambda *a, s=s: reachable_boxes(dynamics, *a[:5], method=method, x_high_open=a[5], noise_open=True,
                                                      staged=s))(x_lo, x_hi, u, w_lo, w_hi, x_open) for s in (False, True)]
    for unstaged, staged in zip(*runs):
        assert unstaged.shape == (7, 3, 5, n)
        np.testing.assert_array_equal(np.asarray(staged), np.asarray(unstaged))
    closed = [jax.jit(lambda *a, s=s: reachable_boxes(dynamics, *a, method=method, staged=s))(x_lo, x_hi, u, w_lo, w_hi)
              for s in (False, True)]
    for unstaged, staged, with_flags in zip(*closed, runs[1]):
        np.testing.assert_array_equal(np.asarray(staged), np.asarray(unstaged))
        np.testing.assert_array_equal(np.asarray(staged), np.asarray(with_flags))  # flags do not move bounds


def test_staged_bounds_are_differentiable():
    x_lo, x_hi, u, w_lo, w_hi = _random_problem(3, 2, 2, np.random.default_rng(5))

    def width(x_high, staged):
        lo, hi = reachable_boxes(unicycle_dynamics, x_lo, x_high, u, w_lo, w_hi, method="both", staged=staged)
        return jnp.sum(hi - lo)

    staged, unstaged = (jax.grad(width)(jnp.asarray(x_hi), s) for s in (True, False))
    assert np.all(np.isfinite(staged)) and np.any(staged != 0)
    np.testing.assert_allclose(staged, unstaged, rtol=0, atol=0)


def _fusions_with_shape(hlo: str, shape: str) -> list[str]:
    """Bodies of the fused computations called by fusions whose output has ``shape``."""
    bodies = dict(re.findall(r"^%?([\w.\-]+) \(.*?\) -> .*? \{\n(.*?)^\}", hlo, flags=re.M | re.S))
    called = re.findall(r"= " + re.escape(shape) + r"\{[^}]*\} fusion\(.*?calls=%?([\w.\-]+)", hlo)
    assert called, f"no fusion of shape {shape}"
    return [bodies[c] for c in called]


def test_state_terms_are_computed_once_per_state():
    """Structural check of the compiled program (not a timing): the cos and sin of the heading
    interval are evaluated per state, never inside the loops over all (state, action, noise cell)
    triples, which is where XLA's CPU fusion put them before staging (2.6x slower on row 20)."""
    x_lo, x_hi, u, w_lo, w_hi = _random_problem(3, 2, 2, np.random.default_rng(2), rows=16, actions=4, cells=9)
    x_open = np.ones_like(x_lo, bool)
    for staged in (True, False):
        fn = jax.jit(lambda *a: reachable_boxes(unicycle_dynamics, *a[:5], method="natural", x_high_open=a[5],
                                                noise_open=True, staged=staged))
        hlo = fn.lower(x_lo, x_hi, u, w_lo, w_hi, x_open).compile().as_text()
        big = _fusions_with_shape(hlo, "f64[16,4,9,3]") + _fusions_with_shape(hlo, "pred[16,4,9,3]")
        per_triple = sum(body.count(" cosine(") + body.count(" sine(") for body in big)
        if staged:
            assert per_triple == 0
        else:  # the check sees the problem it guards against
            assert per_triple > 0
