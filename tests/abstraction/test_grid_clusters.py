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


def test_compact_boxes_are_the_int32_boxes_in_the_smallest_type():
    system = sj.System(drift, actions=np.array([[1.0, 0.0], [0.0, -1.0]]), noise=sj.Gaussian([0, 0], [0.3, 0.3]))
    noise = sj.NoiseGrid.ball([0, 0], 1.0, 3)
    for cells, dtype in ((12, np.int8), ([130, 3], np.int16)):
        grid = sj.StateGrid([0, 0], [1, 1], cells, reach=[([0.75, 0.75], [1, 1])])
        wide = compute_grid_clusters(system, grid, noise, method="natural")
        small = compute_grid_clusters(system, grid, noise, method="natural", compact=True)
        assert wide.boxes.start.dtype == np.int32 and small.boxes.start.dtype == dtype
        assert small.boxes.length.dtype == dtype
        for field in ("start", "length", "sink"):
            np.testing.assert_array_equal(np.asarray(getattr(small.boxes, field)), np.asarray(getattr(wide.boxes, field)))
        smdp = sj.abstraction.build("smdp", grid, small)
        assert smdp.clusters.start is small.boxes.start  # stored as computed, not copied
        reference = sj.abstraction.build("smdp", grid, wide)
        assert smdp.nbytes == reference.nbytes and smdp.clusters.spec == reference.clusters.spec
        v = np.random.default_rng(0).random(grid.num_states)
        np.testing.assert_array_equal(np.asarray(smdp.q_values(v)), np.asarray(reference.q_values(v)))
    assert sj.abstract(system, grid, noise, "smdp", method="natural").clusters.start.dtype == np.int16
