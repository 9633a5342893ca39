import numpy as np
import pytest

import smdpjax as sj


def test_ball_probabilities_sum_to_one():
    ng = sj.NoiseGrid.ball([0.0, 0.0], 2.1, 12)
    assert ng.num_bounded == 144 and ng.num_cells == 145 and ng.remainder
    p, rest = ng.probabilities(sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
    assert p.shape == (144,)
    assert abs(float(p.sum()) + float(rest) - 1.0) < 1e-12
    assert 0 < float(rest) < 1e-10


def test_ball_off_center_and_3d_noise():
    ng = sj.NoiseGrid.ball([0.4, 0.0], 2.0, [6, 6])
    p, rest = ng.probabilities(sj.Gaussian([0.4, 0.0], [0.5, 0.5]))
    assert ng.num_cells == 37
    assert abs(float(p.sum()) + float(rest) - 1.0) < 1e-12
    assert float(rest) > 1e-5  # 4 sigma per axis: a real remainder


def test_box_grid_uniform_exact():
    ng = sj.NoiseGrid.box([-1.0], [1.0], 5)
    p, rest = ng.probabilities(sj.Uniform([-1.0], [1.0]))
    np.testing.assert_allclose(np.asarray(p), 0.2, rtol=1e-14)
    assert float(rest) == 0.0
    lo, hi = ng.boxes()
    np.testing.assert_allclose(np.asarray(lo)[:, 0], [-1, -0.6, -0.2, 0.2, 0.6], atol=1e-15)


def test_cells_c_order():
    ng = sj.NoiseGrid.box([0, 0], [2, 3], [2, 3])
    lo, hi = (np.asarray(b) for b in ng.boxes())
    np.testing.assert_allclose(lo[:4], [[0, 0], [0, 1], [0, 2], [1, 0]])
    np.testing.assert_allclose(hi[-1], [2, 3])


def test_bounded_grid_must_cover_support():
    with pytest.raises(ValueError, match="does not cover"):
        sj.NoiseGrid.box([-1.0], [1.0], 4).probabilities(sj.Gaussian([0.0], [1.0]))
    with pytest.raises(ValueError, match="does not cover"):
        sj.NoiseGrid.box([-1.0], [0.5], 4).probabilities(sj.Uniform([-1.0], [1.0]))
    with pytest.raises(ValueError, match="dimension"):
        sj.NoiseGrid.box([-1.0], [1.0], 4).probabilities(sj.Uniform([-1.0, 0], [1.0, 1]))


@pytest.mark.parametrize("make, match", [
    (lambda: sj.NoiseGrid.ball([0.0], 0.0, 3), "radius"),
    (lambda: sj.NoiseGrid.ball([0.0], -1.0, 3), "radius"),
    (lambda: sj.NoiseGrid.ball([0.0], 1.0, 0), "positive"),
    (lambda: sj.NoiseGrid.box([0.0], [0.0], 3), "low < high"),
    (lambda: sj.NoiseGrid.from_edges([[0.0, 1.0, 0.5]], remainder=True), "increasing"),
])
def test_bad_noise_grids_are_rejected(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_nonuniform_edges():
    ng = sj.NoiseGrid.from_edges([[-1.0, -0.2, 0.1, 1.0]], remainder=False)
    p, _ = ng.probabilities(sj.Uniform([-1.0], [1.0]))
    np.testing.assert_allclose(np.asarray(p), [0.4, 0.15, 0.45], rtol=1e-13)
