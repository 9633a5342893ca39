"""DFA specifications with the other tools: Storm (product DRN), gradients, sweeps."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax import gradients as G
from smdpjax import specification as sp
from smdpjax import storm
from smdpjax.partition.noise_grid import ball_edges
from smdpjax.specification.storm import product_drn, product_drn_string
from smdpjax.specification.structure import ProductStructure


def damped_unicycle(x, u, w):
    return 0.6 * x + 0.5 * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + 0.02 * w


SYSTEM = sj.System(damped_unicycle, actions=(np.arange(8) * np.pi / 4)[:, None], noise=sj.Gaussian([0, 0], [1.0, 1.0]))
NOISE = sj.NoiseGrid.ball([0, 0], 3.5, 6)
GRID = sj.StateGrid([-1, -1], [1, 1], 8)
SPEC = sp.sequence({"a": [([-1.0, 0.5], [-0.5, 1.0])], "b": [([0.5, -1.0], [1.0, -0.5])]},
                   avoid=[([-0.25, 0.0], [0.25, 0.5])]).on(GRID)
HORIZONS = (1, 5, 20)


@pytest.fixture(scope="module")
def imdp():
    return sj.abstract(SYSTEM, GRID, NOISE, "imdp", method="natural")


def test_product_drn_text(imdp):
    text = product_drn_string(imdp, SPEC)
    lines = text.splitlines()
    size = GRID.num_states
    assert int(lines[lines.index("@nr_states") + 1]) == SPEC.num_dfa_states * size
    assert f"state {2 * size} reach" in lines  # (done, cell 0)
    assert f"state {3 * size} avoid" in lines  # (fail, cell 0): a trap
    with pytest.raises(ValueError, match="acceptance"):
        product_drn_string(imdp, sp.safety([([-0.25, 0.0], [0.25, 0.5])]).on(GRID))


def test_storm_robust_value_iteration_on_the_product(imdp, tmp_path):
    pytest.importorskip("stormpy")
    path = tmp_path / "product.drn"
    product_drn(imdp, SPEC, path)
    model = storm.storm_model(path)
    nontrivial = False
    for horizon in HORIZONS:
        sol = sj.synthesize_product(imdp, SPEC, horizon=horizon)
        lower = np.asarray(sol.flat.lower)
        robust = storm.storm_values(model, horizon)
        assert np.max(np.abs(robust - lower)) <= 1e-9
        assert np.all(lower <= robust + 1e-12)
        nontrivial |= bool(np.any((lower > 0.01) & (lower < 0.99)))
        # Storm's cooperative value maximizes over strategies too: above our p_up of one strategy
        cooperative = storm.storm_values(model, horizon, cooperative=True)
        assert np.all(np.asarray(sol.flat.upper) <= cooperative + 1e-9)
    assert nontrivial


def test_gradients_of_a_dfa_guarantee_match_finite_differences():
    edges = ball_edges(jnp.zeros(2), 3.5, 6)
    structure = G.cluster_structure(SYSTEM, GRID, G.noise_grid_of(edges))
    ps = ProductStructure.of(structure, SPEC)
    starts = SPEC.start_states([27, 36, 9, 54])

    def f(theta):
        noise = sj.Gaussian(theta["mean"], theta["std"])
        return G.guarantee(ps, noise, edges, starts, tol=1e-12)

    theta = {"mean": jnp.array([0.05, -0.02]), "std": jnp.array([1.0, 1.1])}
    value, grad = jax.value_and_grad(f)(theta)
    assert 0.05 < float(value) < 0.99
    h = 1e-5
    for name in ("mean", "std"):
        for i in range(2):
            up = {**theta, name: theta[name].at[i].add(h)}
            down = {**theta, name: theta[name].at[i].add(-h)}
            fd = (f(up) - f(down)) / (2 * h)
            assert abs(float(grad[name][i]) - float(fd)) <= 1e-4 + 1e-3 * abs(float(fd)), (name, i, grad, fd)
    # the forward value is the product's optimal lower bound
    prob, rest = sj.partition.cell_probabilities(sj.Gaussian(theta["mean"], theta["std"]), edges, True)
    sol = sj.synthesize(ps.abstraction(prob, rest), tol=1e-12)
    assert abs(float(value) - float(np.asarray(sol.lower_optimal)[starts].mean())) < 1e-8


def test_sweep_over_a_dfa_specification():
    from smdpjax.sweep import sweep

    stds = [0.8, 1.0, 1.2]

    def problem(std):
        system = sj.System(damped_unicycle, actions=SYSTEM.actions, noise=sj.Gaussian([0, 0], [std, std]))
        return system, GRID, NOISE

    result = sweep(problem, stds, specification=SPEC, tol=1e-8)
    q, size = SPEC.num_dfa_states, GRID.num_states
    lower = np.asarray(result.lower).reshape(len(stds), q, size)
    for k, std in enumerate(stds):
        system, grid, noise = problem(std)
        smdp = sj.abstract(system, grid, noise, "smdp")
        ref = sj.synthesize_product(smdp, SPEC, tol=1e-8)
        np.testing.assert_allclose(lower[k], np.asarray(ref.lower), atol=1e-9)
    starts = SPEC.start_states([27, 36])
    means = result.mean_lower(starts)
    assert means[0] > means[-1]  # less noise, a better guarantee
