"""Batched synthesis over parameter values and the structure-grouping sweep, against synthesize."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax import gradients as G
from smdpjax import sweep as S
from smdpjax.partition import cell_probabilities
from smdpjax.partition.noise_grid import ball_edges

TOL = 1e-6


def unicycle(x, u, w):
    return x + 0.2 * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + 0.1 * w


SYSTEM = sj.System(unicycle, actions=(np.arange(8) * np.pi / 4)[:, None], noise=sj.Gaussian([0.0, 0.0], [0.3, 0.3]))
GRID = sj.StateGrid([0, 0], [1, 1], 10, reach=[([0.7, 0.7], [1.0, 1.0])], avoid=[([0.40, 0.30], [0.60, 0.70])])
NOISE = sj.NoiseGrid.ball([0.0, 0.0], 1.2, 4)
EDGES = tuple(jnp.asarray(e) for e in NOISE.edges)
STDS = jnp.array([0.22, 0.27, 0.3, 0.36, 0.41])


def std_probabilities(std):
    return cell_probabilities(sj.Gaussian(jnp.zeros(2), std), EDGES, True)


def reference(std, kind, noise_grid=NOISE):
    system = dataclasses.replace(SYSTEM, noise=sj.Gaussian([0.0, 0.0], [float(std)] * 2))
    return sj.synthesize(sj.abstract(system, GRID, noise_grid, kind), tol=TOL)


@pytest.fixture(scope="module")
def structure():
    return G.cluster_structure(SYSTEM, GRID, NOISE)


def assert_matches(batch, solutions):
    for name in ("lower", "upper", "lower_optimal"):
        expected = np.stack([np.asarray(getattr(s, name)) for s in solutions])
        np.testing.assert_allclose(np.asarray(getattr(batch, name)), expected, rtol=0, atol=1e-12, err_msg=name)
    assert np.all(np.asarray(batch.converged))
    assert np.all(np.asarray(batch.rounding_allowance) > 0)


@pytest.mark.parametrize("kind", ["smdp", "imdp"])
@pytest.mark.parametrize("batch_size", [None, 2])  # the platform's choice; vmapped chunks of 2, the last one padded
def test_batched_synthesis_matches_synthesize(structure, kind, batch_size):
    batch = S.batched_synthesis(structure, std_probabilities, STDS, kind=kind, tol=TOL, batch_size=batch_size)
    assert len(batch) == STDS.shape[0] and batch.lower.shape == (STDS.shape[0], GRID.num_states)
    solutions = [reference(s, kind) for s in STDS]
    assert_matches(batch, solutions)
    np.testing.assert_array_equal(np.asarray(batch.iterations), [s.iterations for s in solutions])
    mean_lower = np.asarray(batch.lower)[:, GRID.nonterminal].mean(axis=1)
    assert np.all(np.diff(mean_lower) < 0), "more noise, lower guarantee on this system"


def test_strategy_choice(structure):
    """On a CPU the values run one after the other (batch_size 1: lax.map, no vmap), elsewhere
    vmapped chunks within the memory budget; by default the platform of the structure's arrays."""
    budget = S.auto_batch_size(structure)
    assert S.choose_batch_size(structure, 64, "cpu") == 1
    assert S.choose_batch_size(structure, 64, "gpu") == min(64, budget)
    assert S.choose_batch_size(structure, 3, "tpu") == min(3, budget)
    expected = 1 if jax.default_backend() == "cpu" else min(5, budget)
    assert S.choose_batch_size(structure, 5) == expected


@pytest.mark.parametrize("kind", ["smdp", "imdp"])
def test_sequential_equals_vmapped(structure, kind):
    """Every strategy gives the same results: values one after the other (``batch_size=1``, the
    CPU default) and all of them vmapped side by side."""
    sequential = S.batched_synthesis(structure, std_probabilities, STDS, kind=kind, tol=TOL, batch_size=1)
    vmapped = S.batched_synthesis(structure, std_probabilities, STDS, kind=kind, tol=TOL, batch_size=STDS.shape[0])
    for name in ("lower", "upper", "lower_optimal", "rounding_allowance"):
        np.testing.assert_allclose(np.asarray(getattr(sequential, name)), np.asarray(getattr(vmapped, name)),
                                   rtol=0, atol=1e-15, err_msg=name)
    for name in ("policy", "iterations", "evaluation_iterations", "converged"):
        np.testing.assert_array_equal(np.asarray(getattr(sequential, name)), np.asarray(getattr(vmapped, name)),
                                      err_msg=name)


def test_solve_is_synthesize(structure):
    prob, rest = std_probabilities(0.3)
    abstraction = structure.abstraction(prob, rest)
    mine, theirs = S.solve(abstraction, 1e-6), sj.synthesize(abstraction, tol=1e-6)
    for name in ("lower", "upper", "lower_optimal", "policy"):
        np.testing.assert_array_equal(np.asarray(getattr(mine, name)), np.asarray(getattr(theirs, name)))
    assert int(mine.iterations) == theirs.iterations
    assert float(mine.rounding_allowance) == pytest.approx(theirs.rounding_allowance, rel=1e-12)


def test_sweep_groups_values_by_structure():
    """r_W values 1.2 and 1.2 + 1e-9 give the same clusters (different probabilities), 1.6 other ones."""
    radii = [1.2, 1.6, 1.2 + 1e-9]

    def problem(radius):
        return SYSTEM, GRID, sj.NoiseGrid.from_edges([np.asarray(e) for e in ball_edges(jnp.zeros(2), radius, 4)],
                                                     True)

    result = S.sweep(problem, radii, tol=TOL)
    assert result.group.tolist() == [0, 1, 0] and len(result.structures) == 2
    assert not result.structures[0].same_as(result.structures[1])
    solutions = [reference(0.3, "smdp", problem(r)[2]) for r in radii]
    assert_matches(result.solution, solutions)
    assert result.mean_lower(GRID.nonterminal).shape == (3,)


def test_sweep_with_a_probability_function_reuses_one_structure():
    calls = []

    def problem(std):
        calls.append(std)
        return dataclasses.replace(SYSTEM, noise=sj.Gaussian([0.0, 0.0], [std, std])), GRID, NOISE

    result = S.sweep(problem, [0.25, 0.35], probabilities=std_probabilities, kind="imdp", tol=TOL)
    assert len(result.structures) == 1 and result.group.tolist() == [0, 0] and len(calls) == 2
    assert_matches(result.solution, [reference(0.25, "imdp"), reference(0.35, "imdp")])


def test_errors(structure):
    with pytest.raises(ValueError, match="tol"):
        S.batched_synthesis(structure, std_probabilities, STDS, tol=0.0)
    with pytest.raises(ValueError, match="kind"):
        S.batched_synthesis(structure, std_probabilities, STDS, kind="mimdp")
    with pytest.raises(ValueError, match="at least one"):
        S.sweep(lambda v: (SYSTEM, GRID, NOISE), [])
