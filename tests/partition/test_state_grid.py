import numpy as np
import pytest

import smdpjax as sj
from smdpjax.partition import AVOID, NONTERMINAL, REACH


def unicycle_grid(cells=30):
    return sj.StateGrid([0, 0], [1, 1], cells, reach=[([0.8, 0.8], [1.0, 1.0])],
                        avoid=[([0.4, 0.3], [0.6, 0.7]), ([0.75, 0.5], [0.9, 0.65])])


def test_labels_and_counts():
    g = unicycle_grid()
    assert g.num_cells == 900 and g.num_states == 901 and g.sink == 900
    assert np.sum(g.labels == REACH) == 36  # 6 x 6 cells in [0.8, 1]^2, edges aligned with the grid
    # obstacle [0.4,0.6]x[0.3,0.7] covers cells 12..17 x 9..20 exactly (faces are not overlaps)
    centers = np.asarray(g.cell_centers())
    inside = (centers[:, 0] > 0.4) & (centers[:, 0] < 0.6) & (centers[:, 1] > 0.3) & (centers[:, 1] < 0.7)
    assert np.all(g.labels[inside] == AVOID)
    assert np.sum(inside) == 6 * 12
    # [0.75,0.9]x[0.5,0.65]: 0.75 = 22.5 cells, so cells 22..26 x 15..19 overlap it
    assert np.sum(g.labels == AVOID) == 72 + 5 * 5
    assert g.state_labels[-1] == AVOID
    assert g.nonterminal.size == 900 - 36 - 97


def test_locate_c_order_and_outside():
    g = sj.StateGrid([0, 0], [1, 2], [4, 2])
    pts = np.array([[0.1, 0.1], [0.1, 1.5], [0.9, 0.1], [1.0, 2.0], [-0.01, 0.5], [0.5, 2.01], [np.nan, 0.5]])
    np.testing.assert_array_equal(np.asarray(g.locate(pts)), [0, 1, 6, 7, -1, -1, -1])


def test_locate_agrees_with_cell_bounds():
    g = sj.StateGrid([-1, 0, 2], [1, 3, 2.5], [5, 7, 3])
    rng = np.random.default_rng(0)
    x = rng.uniform([-1, 0, 2], [1, 3, 2.5], size=(5000, 3))
    idx = np.asarray(g.locate(x))
    lo, hi = (np.asarray(b) for b in g.cell_bounds(idx))
    assert np.all((x >= lo - 1e-12) & (x <= hi + 1e-12))


def test_periodic_dimension_wraps():
    g = sj.StateGrid([0, 0], [1, 2 * np.pi], [2, 8], periodic=[False, True])
    a = np.asarray(g.locate(np.array([[0.2, 0.1], [0.2, 0.1 + 2 * np.pi], [0.2, 0.1 - 4 * np.pi]])))
    assert a[0] == a[1] == a[2] == 0
    assert int(g.locate(np.array([0.2, -0.1]))) == 7  # just below 0 wraps to the last heading cell
    assert "periodic=[1]" in repr(g)


@pytest.mark.parametrize("kwargs, match", [
    (dict(low=[0, 0], high=[1, 1], cells=[3, 0]), "positive"),
    (dict(low=[0, 0], high=[1, 1], cells=[3, -2]), "positive"),
    (dict(low=[0, 1], high=[1, 1], cells=3), "low < high"),
    (dict(low=[0, 0], high=[1, 1, 1], cells=3), "length 2"),
    (dict(low=[0, 0], high=[1, 1], cells=[2, 2, 2]), "length 2"),
    (dict(low=[0, np.nan], high=[1, 1], cells=3), "finite"),
    (dict(low=[0, 0], high=[1, 1], cells=3, reach=[([0.5, 0.5], [1.2, 1.0])]), "not inside"),
    (dict(low=[0, 0], high=[1, 1], cells=3, reach=[([0.5, 0.5], [0.9, 0.9])], avoid=[([0.6, 0.6], [0.7, 0.7])]),
     "overlaps"),
    (dict(low=[0, 0], high=[1, 1], cells=3, avoid=[([0.6, 0.6], [0.5, 0.7])]), "low < high"),
])
def test_bad_grids_are_rejected(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        sj.StateGrid(**kwargs)


def test_true_sets_for_simulation():
    g = unicycle_grid()
    pts = np.array([[0.9, 0.9], [0.5, 0.5], [1.2, 0.5], [0.1, 0.1]])
    np.testing.assert_array_equal(np.asarray(g.in_reach(pts)), [True, False, False, False])
    np.testing.assert_array_equal(np.asarray(g.in_avoid(pts)), [False, True, True, False])
    assert int(np.sum(g.labels == NONTERMINAL)) == g.nonterminal.size
