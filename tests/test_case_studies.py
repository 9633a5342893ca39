"""The case studies' choice of reachable-set enclosure costs no tightness where it is made."""

import jax
import numpy as np
import pytest

from smdpjax.abstraction import compute_grid_clusters
from smdpjax.case_studies import temperature, unicycle_2d, unicycle_3d


def index_boxes(study, method):
    clusters = compute_grid_clusters(study.system, study.state_grid, study.noise_grid, method=method,
                                     policy=study.controller)
    return [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(clusters.boxes)]


@pytest.mark.parametrize("study", [unicycle_2d(30), unicycle_3d(noise_cells=6, cells=12)], ids=["2d", "3d"])
def test_natural_enclosures_give_the_same_index_boxes_on_the_unicycles(study):
    assert study.reach_method == "natural"
    natural, both = index_boxes(study, "natural"), index_boxes(study, "both")
    assert all(np.array_equal(a, b) for a, b in zip(natural, both))


def test_temperature_keeps_the_centred_form_because_it_tightens():
    study = temperature(2)
    assert study.reach_method == "both"
    natural, both = index_boxes(study, "natural"), index_boxes(study, "both")
    assert any(not np.array_equal(a, b) for a, b in zip(natural, both))


def test_abstract_uses_the_controller_and_the_method():
    study = temperature(2)
    smdp = study.abstract("smdp")
    assert smdp.num_actions == 1 and smdp.num_states == study.state_grid.num_states
