"""Gradients of the guarantee (mean p_low) through the fixed point, against central finite differences.

The system is a small 2-D unicycle (10x10 cells, 8 headings, 6x6 noise cells + remainder) with
a walled-in corner whose cells have p_low = 0 under every strategy, so the adjoint's pinning of
zero-valued states is exercised. Finite differences recompute the cluster structure at theta +- h
and check that it did not change: there the frozen-structure gradient is the true derivative.
"""

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax import gradients as G
from smdpjax.partition.noise_grid import ball_edges, warped_ball_edges

K = 6  # noise cells per axis
REL = 1e-4  # required relative agreement with finite differences


def unicycle(x, u, w):
    return x + 0.2 * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + 0.1 * w


def make_system(noise=None):
    return sj.System(unicycle, actions=(np.arange(8) * np.pi / 4)[:, None],
                     noise=noise or sj.Gaussian([0.0, 0.0], [0.3, 0.3]))


GRID = sj.StateGrid([0, 0], [1, 1], 10, reach=[([0.7, 0.7], [1.0, 1.0])],
                    avoid=[([0.0, 0.2], [0.6, 0.6]), ([0.2, 0.0], [0.6, 0.2])])  # walls around [0, .2]^2
TRAP = np.array([0, 1, 10, 11])  # the four cells of [0, 0.2]^2: enclosed, p_low = 0
CELLS = np.asarray(GRID.nonterminal)[::2]
SYSTEM = make_system()

BALL = dict(mean=jnp.array([0.05, -0.03]), std=jnp.array(0.3), center=jnp.array([0.02, -0.01]),
            radius=jnp.array(1.2))
_E = jnp.array([-1.2, -0.75, -0.33, 0.02, 0.31, 0.7, 1.25])
EDGES = dict(mean=jnp.array([0.0, 0.0]), std=jnp.array(0.3), edges=(_E, _E + 0.013))


def edges_of(theta):
    return theta["edges"] if "edges" in theta else ball_edges(theta["center"], theta["radius"], K)


def objective(theta, structure, kind, tol=1e-13):
    noise = sj.Gaussian(theta["mean"], theta["std"])
    return G.guarantee(structure, noise, edges_of(theta), CELLS, kind=kind, tol=tol)


def structure_at(theta):
    return G.cluster_structure(SYSTEM, GRID, G.noise_grid_of(edges_of(theta)))


grad_jit = jax.jit(jax.grad(objective), static_argnames=("kind", "tol"))


@pytest.fixture(scope="module")
def structures():
    return {"ball": structure_at(BALL), "edges": structure_at(EDGES)}


def central_difference(theta, index, structure, kind):
    """(f(theta + h e_i) - f(theta - h e_i)) / 2h with the structure recomputed at theta +- h."""
    flat, unravel = jax.flatten_util.ravel_pytree(theta)
    h = 1e-5 * max(abs(float(flat[index])), 0.1)
    values = []
    for sign in (1.0, -1.0):
        shifted = unravel(flat.at[index].add(sign * h))
        moved = structure_at(shifted)
        assert moved.same_as(structure), f"the structure changes within +-{h:g} of parameter {index}"
        values.append(float(objective(shifted, moved, kind)))
    return (values[0] - values[1]) / (2 * h)


def flat_index(theta, name, i=0, axis=None):
    """Position of theta[name][i] (or theta["edges"][axis][i]) in ravel_pytree order (sorted keys)."""
    offset = 0
    for key in sorted(theta):
        if key == name:
            if axis is not None:
                return offset + sum(int(e.size) for e in theta[key][:axis]) + i
            return offset + i
        offset += sum(int(leaf.size) for leaf in jax.tree_util.tree_leaves(theta[key]))
    raise KeyError(name)


CASES = [  # (theta, parameter, element, axis)
    ("ball", "std", 0, None),
    ("ball", "mean", 1, None),
    ("ball", "radius", 0, None),
    ("ball", "center", 0, None),
    ("edges", "edges", 3, 0),  # inner boundaries of the non-uniform grid, both axes
    ("edges", "edges", 5, 1),
    ("edges", "edges", 0, 0),  # an outer face (moves the remainder too)
]


@pytest.mark.parametrize("kind", ["smdp", "imdp"])
@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-{c[1]}[{c[3]},{c[2]}]" if c[3] is not None
                         else f"{c[0]}-{c[1]}[{c[2]}]")
def test_gradient_matches_central_differences(structures, kind, case):
    which, name, i, axis = case
    theta = BALL if which == "ball" else EDGES
    structure = structures[which]
    grad, _ = jax.flatten_util.ravel_pytree(grad_jit(theta, structure, kind))  # jax.grad under jax.jit
    index = flat_index(theta, name, i, axis)
    fd = central_difference(theta, index, structure, kind)
    ad = float(grad[index])
    assert abs(fd) > 1e-4, "pick a parameter the guarantee depends on"
    assert abs(ad - fd) <= REL * abs(fd), f"{kind} {name}: autodiff {ad:.10e} vs finite difference {fd:.10e}"


def test_value_and_zero_states(structures):
    """The forward value is synthesize's optimal p_low, the trapped cells have p_low = 0, and the
    derivative of their values is exactly 0 (pinned in the adjoint)."""
    structure = structures["ball"]
    prob, rest = sj.partition.cell_probabilities(sj.Gaussian(BALL["mean"], BALL["std"]), edges_of(BALL), True)
    for kind in ("smdp", "imdp"):
        abstraction = structure.abstraction(prob, rest, kind)
        v = G.robust_lower(abstraction)
        reference = sj.synthesize(abstraction, tol=1e-12).lower_optimal
        np.testing.assert_allclose(np.asarray(v), np.asarray(reference), atol=1e-9)
        assert np.all(np.asarray(v)[TRAP] == 0.0) and np.all(np.asarray(v)[CELLS] >= 0)
        assert float(v[CELLS].mean()) > 0.3

        def trapped(theta):
            p, r = sj.partition.cell_probabilities(sj.Gaussian(theta["mean"], theta["std"]), edges_of(theta), True)
            return G.robust_lower(structure.abstraction(p, r, kind))[TRAP].sum()

        g, _ = jax.flatten_util.ravel_pytree(jax.grad(trapped)(BALL))
        assert np.all(np.asarray(g) == 0.0)


def test_translation_invariance(structures):
    """Moving the noise mean and the grid center together leaves every P_W(c) unchanged, so the
    two gradients are opposite: a structural check that needs no finite differences."""
    g = grad_jit(BALL, structures["ball"], "smdp")
    np.testing.assert_allclose(np.asarray(g["center"]), -np.asarray(g["mean"]), rtol=1e-8, atol=1e-12)


def test_grad_is_the_same_with_and_without_jit(structures):
    eager = jax.grad(objective)(EDGES, structures["edges"], "smdp")
    jitted = grad_jit(EDGES, structures["edges"], "smdp")
    for a, b in zip(jax.tree_util.tree_leaves(eager), jax.tree_util.tree_leaves(jitted)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-14)


def test_warped_edges_are_differentiable_and_uniform_at_zero(structures):
    """``warped_ball_edges`` (the tuning parametrization) is ``ball_edges`` at zero logits, and the
    chain rule through it matches differentiating the edges directly."""
    logits = (jnp.zeros(K), jnp.zeros(K))
    for a, b in zip(warped_ball_edges(BALL["center"], BALL["radius"], logits), edges_of(BALL)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-14)
    structure = structures["ball"]

    def by_logits(z):
        edges = warped_ball_edges(BALL["center"], BALL["radius"], z)
        return G.guarantee(structure, sj.Gaussian(BALL["mean"], BALL["std"]), edges, CELLS)

    g_logits = jax.grad(by_logits)(logits)
    g_edges = jax.grad(lambda e: G.guarantee(structure, sj.Gaussian(BALL["mean"], BALL["std"]), e, CELLS))(
        edges_of(BALL))
    _, pull = jax.vjp(lambda z: warped_ball_edges(BALL["center"], BALL["radius"], z), logits)
    expected = pull(g_edges)[0]
    for a, b in zip(g_logits, expected):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-14)


def test_dynamics_parameters_have_zero_gradient_between_structure_changes():
    """A parameter of the dynamics enters only through the reachable boxes: while the structure
    stays the same the guarantee does not move at all (its derivative is 0, as documented)."""
    prob, rest = sj.partition.cell_probabilities(sj.Gaussian(BALL["mean"], BALL["std"]), edges_of(BALL), True)
    values, structures = [], []
    for gain in (0.2 - 1e-7, 0.2, 0.2 + 1e-7):
        system = sj.System(lambda x, u, w, g=gain: x + g * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + 0.1 * w,
                           actions=SYSTEM.actions, noise=SYSTEM.noise)
        structures.append(G.cluster_structure(system, GRID, G.noise_grid_of(edges_of(BALL))))
        values.append(float(G.mean_lower(structures[-1].abstraction(prob, rest), CELLS)))
    assert structures[0].same_as(structures[1]) and structures[2].same_as(structures[1])
    assert values[0] == values[1] == values[2]


def test_from_members_equals_from_clusters():
    """The traceable constructors rebuild exactly the abstractions ``abstract`` builds."""
    noise = sj.NoiseGrid.ball([0.0, 0.0], 1.2, K)
    clusters = sj.abstraction.compute_grid_clusters(SYSTEM, GRID, noise)
    structure = G.ClusterStructure.from_clusters(GRID, clusters)
    for kind in ("smdp", "imdp"):
        # the frozen structure holds member lists: compare with that encoding of the SMDP
        built = sj.abstraction.build(kind, GRID, clusters, **({"encoding": "members"} if kind == "smdp" else {}))
        built = built.padded() if kind == "imdp" else built  # the traceable IMDP is the padded one
        rebuilt = jax.jit(lambda s, p, r: s.abstraction(p, r, kind))(structure, clusters.prob, clusters.prob_rest)
        for a, b in zip(jax.tree_util.tree_leaves(built), jax.tree_util.tree_leaves(rebuilt)):
            assert a.dtype == b.dtype and a.shape == b.shape
            if jnp.issubdtype(a.dtype, jnp.integer):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
            elif kind == "smdp":  # the same sums; XLA may fuse "+ P(rest)" differently under jit (1 ulp)
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-15, atol=0)
            else:  # float sums (traceable) against exact fixed-point sums rounded outward (box_bounds)
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-14, atol=1e-16)


def test_padding_changes_no_value(structures):
    structure = structures["edges"]
    padded = structure.padded(structure.members.shape[-1] + 3, structure.width + 5)
    assert padded.members.shape[-1] == structure.members.shape[-1] + 3
    for kind in ("smdp", "imdp"):
        np.testing.assert_allclose(float(objective(EDGES, padded, kind, 1e-10)),
                                   float(objective(EDGES, structure, kind, 1e-10)), rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match="pad"):
        structure.padded(1)


def test_bad_kind_and_mismatched_edges(structures):
    with pytest.raises(ValueError, match="kind"):
        structures["ball"].abstraction(jnp.ones(K * K) / K**2, 0.0, "mimdp")
    with pytest.raises(ValueError, match="bounded noise cells"):
        G.guarantee(structures["ball"], sj.Gaussian([0.0, 0.0], 0.3), ball_edges(jnp.zeros(2), 1.0, 3), CELLS)
