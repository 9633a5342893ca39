"""The case studies' choice of reachable-set enclosure costs no tightness where it is made."""

import dataclasses
import importlib

import jax
import numpy as np
import pytest

from smdpjax.abstraction import compute_grid_clusters
from smdpjax.case_studies import temperature, unicycle_2d, unicycle_3d

temperature_model = importlib.import_module("smdpjax.case_studies.temperature")


def index_boxes(study, method):
    clusters = compute_grid_clusters(study.system, study.state_grid, study.noise_grid, method=method,
                                     policy=study.controller)
    return [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(clusters.boxes)]


@pytest.mark.parametrize("study", [unicycle_2d(30), unicycle_3d(noise_cells=6, cells=12)], ids=["2d", "3d"])
def test_natural_enclosures_give_the_same_index_boxes_on_the_unicycles(study):
    assert study.reach_method == "natural"
    natural, both = index_boxes(study, "natural"), index_boxes(study, "both")
    assert all(np.array_equal(a, b) for a, b in zip(natural, both))


@pytest.mark.parametrize("rooms", [1, 2, 3])
def test_temperature_dynamics_is_the_textbook_model(rooms):
    study = temperature(rooms)
    keys = jax.random.split(jax.random.PRNGKey(rooms), 3)
    x = jax.random.uniform(keys[0], (500, rooms), minval=17.5, maxval=22.0)
    u = study.system.actions[jax.random.randint(keys[1], (500,), 0, 2 ** rooms)]
    w = 0.03 * jax.random.normal(keys[2], (500, rooms))
    np.testing.assert_allclose(jax.vmap(temperature_model.dynamics)(x, u, w),
                               jax.vmap(temperature_model.textbook_dynamics)(x, u, w), rtol=1e-14, atol=0)


@pytest.mark.parametrize("rooms", [2, 3])
def test_temperature_natural_enclosures_are_the_tightest(rooms):
    study = temperature(rooms, cells=8 if rooms == 3 else 12)
    assert study.reach_method == "natural"
    natural, both = index_boxes(study, "natural"), index_boxes(study, "both")
    assert all(np.array_equal(a, b) for a, b in zip(natural, both))
    # and the arrangement matters: the textbook form's enclosures are wider (in total) or equal
    textbook = dataclasses.replace(study, system=dataclasses.replace(study.system,
                                                                     dynamics=temperature_model.textbook_dynamics))
    for method in ("natural", "both"):
        loose = index_boxes(textbook, method)
        assert np.all(loose[1] >= natural[1]) and loose[1].sum() > natural[1].sum()


def test_abstract_uses_the_controller_and_the_method():
    study = temperature(2)
    smdp = study.abstract("smdp")
    assert smdp.num_actions == 1 and smdp.num_states == study.state_grid.num_states
