"""The reachable-set stage shared by every abstraction class (``compute_grid_clusters``)."""

import numpy as np

import smdpjax as sj
from smdpjax.abstraction import compute_grid_clusters
from smdpjax.abstraction.grid_clusters import _chunk_fn


def drift(x, u, w):
    return x + 0.1 * (u + w)


def test_grids_of_one_geometry_share_the_compiled_stage_and_give_the_same_boxes():
    system = sj.System(drift, actions=np.array([[1.0, 0.0], [0.0, 1.0]]), noise=sj.Uniform([-1, -1], [1, 1]))
    noise = sj.NoiseGrid.box([-1, -1], [1, 1], 3)
    first = sj.StateGrid([0, 0], [1, 1], 8, reach=[([0.75, 0.75], [1, 1])])
    # same box and cells, another specification: labels differ, geometry does not
    second = sj.StateGrid([0, 0], [1, 1], 8, reach=[([0.5, 0.75], [1, 1])], avoid=[([0, 0], [0.25, 0.25])])
    other = sj.StateGrid([0, 0], [1, 2], 8, reach=[([0.75, 0.75], [1, 1])])
    assert _chunk_fn(drift, first, "both", True) is _chunk_fn(drift, second, "both", True)
    assert _chunk_fn(drift, first, "both", True) is not _chunk_fn(drift, other, "both", True)
    assert _chunk_fn(drift, first, "both", True) is not _chunk_fn(drift, first, "natural", True)

    a = compute_grid_clusters(system, first, noise)
    b = compute_grid_clusters(system, second, noise)
    common = np.intersect1d(a.rows, b.rows)  # the rows both grids have
    ia, ib = np.searchsorted(a.rows, common), np.searchsorted(b.rows, common)
    for field in ("start", "length", "sink"):
        np.testing.assert_array_equal(np.asarray(getattr(a.boxes, field))[ia], np.asarray(getattr(b.boxes, field))[ib])
    assert np.asarray(a.prob).shape == (9,)
