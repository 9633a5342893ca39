import jax
import numpy as np
import pytest
from scipy import stats

import smdpjax as sj


def test_gaussian_box_probability_matches_scipy():
    g = sj.Gaussian([0.4, -1.0], [0.5, 2.0])
    lo = np.array([[0.0, -3.0], [3.0, 5.0], [-9.0, -1.0]])
    hi = np.array([[1.0, 0.5], [4.0, 9.0], [-8.0, 0.0]])
    m, sd = np.array([0.4, -1.0]), np.array([0.5, 2.0])
    # reference on the tail side too (a cdf difference cancels in the far right tail)
    right = lo > m
    per_axis = np.where(right, stats.norm.sf(lo, m, sd) - stats.norm.sf(hi, m, sd),
                        stats.norm.cdf(hi, m, sd) - stats.norm.cdf(lo, m, sd))
    expect = np.prod(per_axis, axis=1)
    np.testing.assert_allclose(np.asarray(g.box_probability(lo, hi)), expect, rtol=1e-10, atol=1e-300)


def test_gaussian_far_tail_has_relative_accuracy():
    g = sj.Gaussian([0.0], [1.0])
    p = float(g.box_probability(np.array([8.0]), np.array([9.0])))
    assert p == pytest.approx(stats.norm.sf(8.0) - stats.norm.sf(9.0), rel=1e-9)
    assert p > 0


def test_gaussian_outside_probability_without_cancellation():
    g = sj.Gaussian([0.0, 0.0], [0.3, 0.3])
    out = float(g.outside_probability(np.array([-2.1, -2.1]), np.array([2.1, 2.1])))
    q = 2 * stats.norm.sf(7.0)
    assert out == pytest.approx(1 - (1 - q) ** 2, rel=1e-9)
    assert out > 0


def test_uniform_box_probability_is_volume_ratio():
    u = sj.Uniform([-1.0, 0.0], [1.0, 2.0])
    assert float(u.box_probability(np.array([-0.5, 0.0]), np.array([0.5, 1.0]))) == pytest.approx(0.25)
    assert float(u.box_probability(np.array([-5.0, 3.0]), np.array([5.0, 4.0]))) == 0.0


@pytest.mark.parametrize("dist", [sj.Gaussian([1.0, 2.0], [0.5, 0.1]), sj.Uniform([0.0, 0.0], [1.0, 3.0])])
def test_sampling_matches_box_probability(dist):
    samples = np.asarray(dist.sample(jax.random.PRNGKey(1), (20000,)))
    assert samples.shape == (20000, 2)
    lo, hi = np.array([0.8, 1.9]), np.array([1.5, 2.5])
    freq = np.mean(np.all((samples >= lo) & (samples <= hi), axis=1))
    p = float(dist.box_probability(lo, hi))
    assert abs(freq - p) < 5 * np.sqrt(p * (1 - p) / 20000) + 1e-3


@pytest.mark.parametrize("std", [0.0, -1.0, np.nan, np.inf])
def test_gaussian_rejects_non_positive_std(std):
    with pytest.raises(ValueError, match="std"):
        sj.Gaussian([0.0], [std])


def test_uniform_rejects_low_not_below_high():
    with pytest.raises(ValueError, match="low < high"):
        sj.Uniform([0.0, 1.0], [1.0, 1.0])


def test_gaussian_is_a_pytree_and_differentiable():
    def p(std):
        return sj.Gaussian([0.0], std).box_probability(np.array([-1.0]), np.array([1.0]))

    grad = jax.grad(lambda s: p(s[None]))(0.5)
    eps = 1e-6
    fd = (float(p(np.array([0.5 + eps]))) - float(p(np.array([0.5 - eps])))) / (2 * eps)
    assert float(grad) == pytest.approx(fd, rel=1e-6)
    leaves = jax.tree_util.tree_leaves(sj.Gaussian([0.0, 1.0], [1.0, 2.0]))
    assert len(leaves) == 2
