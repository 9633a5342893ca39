"""Labelling of cells by regions: exact set tests on half-open cells, checked by brute force."""

import jax
import numpy as np
import pytest

import smdpjax as sj
from smdpjax import specification as sp
from smdpjax.specification.regions import cell_membership


def brute_force(grid, region):
    """Cells x boxes, dimension by dimension: candidate coordinates are every face, bound and the
    midpoints between them, so each 1-D intersection is decided exactly."""
    inside = np.ones((grid.num_cells, region.low.shape[0]), bool)
    meets = np.ones_like(inside)
    cells = np.arange(grid.num_cells)
    lo, hi = (np.asarray(b) for b in grid.cell_bounds(cells))
    last = np.asarray(grid.upper_attained(cells))
    for d in range(grid.n):
        coords = np.unique(np.concatenate([grid.edges[d], region.low[:, d], region.high[:, d]]))
        coords = np.unique(np.concatenate([coords, (coords[1:] + coords[:-1]) / 2]))
        in_cell = (coords[None] >= lo[:, d, None]) & ((coords[None] < hi[:, d, None]) |
                                                      (last[:, d, None] & (coords[None] == hi[:, d, None])))
        for j in range(region.low.shape[0]):
            a, b = region.low[j, d], region.high[j, d]
            in_box = ((coords >= a) & (coords <= b)) if region.closed else ((coords > a) & (coords < b))
            meets[:, j] &= np.any(in_cell & in_box[None], axis=1)
            inside[:, j] &= ~np.any(in_cell & ~in_box[None], axis=1)
    return inside.any(axis=1), meets.any(axis=1)


@pytest.mark.parametrize("closed", [True, False])
def test_exact_membership_matches_brute_force(closed):
    grid = sj.StateGrid([0, 0], [1, 1.5], [10, 7])
    boxes = [([0.2, 0.3], [0.5, 0.6]), ([0.33, 0.0], [0.7, 1.5]), ([0.9, 1.2], [1.0, 1.5]), ([0.0, 0.0], [0.1, 0.1])]
    for box in boxes:
        region = sp.Region([box], closed=closed)
        got = cell_membership(grid, region)
        want = brute_force(grid, region)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
    region = sp.Region(boxes, closed=closed)
    inside, meets = cell_membership(grid, region)
    assert np.all(inside <= meets)


def test_interior_faces_match_the_grids_own_labels():
    reach, avoid = [([0.8, 0.8], [1.0, 1.0])], [([0.4, 0.3], [0.6, 0.7]), ([0.75, 0.5], [0.9, 0.65])]
    grid = sj.StateGrid([0, 0], [1, 1], 30, reach=reach, avoid=avoid)
    two = {}
    for faces in ("interior", "exact"):
        on = sp.reach_avoid_of(grid, faces=faces).on(grid, warn=False)
        two[faces] = on.labelling.count > 1
        letters = on.labelling.letters
        inside_reach = np.all(letters & 1, axis=1)
        maybe_avoid = np.any(letters & 2, axis=1)
        np.testing.assert_array_equal(inside_reach, grid.labels == sj.REACH)  # closed boxes: same either way
        np.testing.assert_array_equal(maybe_avoid, grid.labels == sj.AVOID)
        assert on.mixed_cells.size == 9  # the second obstacle ends at 0.65 and 0.9, mid-cell
        if faces == "interior":
            np.testing.assert_array_equal(two[faces], on.labelling.mixed)
    # exact faces: the obstacles' lower faces also belong to safe points of the avoid cells
    assert np.all(two["interior"] <= two["exact"]) and two["exact"].sum() > two["interior"].sum()


def test_mixed_cells_warn_and_points_carry_a_possible_letter():
    grid = sj.StateGrid([0, 0], [1, 1], 10)
    spec = sp.Specification(sp.reach_avoid_dfa(), {"reach": [([0.75, 0.75], [1.0, 1.0])],
                                                   "avoid": sp.Region([([0.33, 0.3], [0.6, 0.68])], closed=False)})
    with pytest.warns(UserWarning, match=r"^\d+ of 100 cells lie partly inside"):
        on = spec.on(grid)
    assert 0 < on.mixed_cells.size < 40
    x = sj.uniform_in_cells(grid, np.arange(100), 50, jax.random.PRNGKey(3))
    cells = np.repeat(np.arange(100), 50)
    letters = np.asarray(on.point_letters(x))
    possible = on.labelling.letters[cells]
    assert np.all(np.any(possible == letters[:, None], axis=1))
    corner = np.array([[0.75, 0.75], [0.33, 0.5], [0.34, 0.5]])  # closed reach face; open avoid face; inside
    np.testing.assert_array_equal(np.asarray(on.point_letters(corner)), [1, 0, 2])
