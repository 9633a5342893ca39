"""Bad input is refused with a clear message before any heavy work."""

import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj


def ok(x, u, w):
    return x + 0.1 * u + 0.05 * w


GRID = sj.StateGrid([0, 0], [1, 1], 5, reach=[([0.8, 0.8], [1, 1])])
NOISE = sj.NoiseGrid.box([-1, -1], [1, 1], 2)
UNIFORM = sj.Uniform([-1, -1], [1, 1])


def system(dynamics=ok, actions=((1.0, 0.0), (0.0, 1.0)), noise=UNIFORM):
    return sj.System(dynamics, actions=np.array(actions), noise=noise)


def test_unknown_kind():
    with pytest.raises(ValueError, match="unknown abstraction kind 'mdp'"):
        sj.abstract(system(), GRID, NOISE, "mdp")


def test_unknown_reach_method():
    with pytest.raises(ValueError, match="reachable-set method"):
        sj.abstract(system(), GRID, NOISE, "smdp", method="taylor")


def test_dynamics_returning_nan():
    def bad(x, u, w):
        return jnp.where(x[0] > 0.5, jnp.nan, 1.0) * x

    with pytest.raises(ValueError, match="NaN/inf"):
        sj.abstract(system(bad), GRID, NOISE, "smdp")


def test_dynamics_returning_inf_with_log():
    def bad(x, u, w):
        return x + jnp.log(x[0] - x[0])  # -inf everywhere

    with pytest.raises(ValueError, match="NaN/inf"):
        sj.abstract(system(bad), GRID, NOISE, "imdp")


def test_dynamics_with_wrong_output_shape():
    with pytest.raises(ValueError, match=r"must return shape \(2,\)"):
        sj.abstract(system(lambda x, u, w: jnp.concatenate([x, w])), GRID, NOISE, "smdp")


def test_dynamics_failing_on_shapes():
    with pytest.raises(ValueError, match="failed"):
        sj.abstract(system(lambda x, u, w: x @ jnp.ones((3, 2))), GRID, NOISE, "smdp")


def test_actions_shape_and_values():
    with pytest.raises(ValueError, match="actions"):
        sj.System(ok, actions=np.zeros((2, 2, 2)), noise=UNIFORM)
    with pytest.raises(ValueError, match="actions"):
        sj.System(ok, actions=np.zeros((0, 2)), noise=UNIFORM)
    with pytest.raises(ValueError, match="finite"):
        sj.System(ok, actions=[[np.nan, 0.0]], noise=UNIFORM)
    with pytest.raises(TypeError, match="Distribution"):
        sj.System(ok, actions=[[1.0, 0.0]], noise=(0.0, 1.0))
    with pytest.raises(TypeError, match="callable"):
        sj.System(3, actions=[[1.0, 0.0]], noise=UNIFORM)


def test_noise_dimension_mismatch():
    with pytest.raises(ValueError, match="dimension"):
        sj.abstract(system(), GRID, sj.NoiseGrid.box([-1], [1], 2), "smdp")


def test_gaussian_noise_on_bounded_grid():
    with pytest.raises(ValueError, match="NoiseGrid.ball"):
        sj.abstract(system(noise=sj.Gaussian([0, 0], [1, 1])), GRID, NOISE, "smdp")


def test_grid_without_nonterminal_cells():
    grid = sj.StateGrid([0, 0], [1, 1], 2, reach=[([0, 0], [1, 1])])
    with pytest.raises(ValueError, match="no non-terminal cell"):
        sj.abstract(system(), grid, NOISE, "smdp")


def test_argument_types():
    with pytest.raises(TypeError, match="StateGrid"):
        sj.abstract(system(), NOISE, NOISE, "smdp")
    with pytest.raises(TypeError, match="System"):
        sj.abstract(ok, GRID, NOISE, "smdp")


def test_imdp_warns_when_every_lower_bound_is_zero():
    # noise of width 0.2 per cell on cells of width 0.2: no reachable box fits inside one cell
    wide = system(lambda x, u, w: x + 0.1 * u + 0.2 * w)
    with pytest.warns(UserWarning, match="every lower transition bound is 0"):
        imdp = sj.abstract(wide, GRID, NOISE, "imdp")
    assert float(imdp.lower.max()) == 0.0
    # the same grid with narrow noise has lower bounds, and says nothing
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        narrow = sj.abstract(system(lambda x, u, w: 0.5 * x + 0.21 + 0.001 * w), GRID, NOISE, "imdp")
    assert float(narrow.lower.max()) > 0.0
