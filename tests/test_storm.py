"""Storm as a peer: DRN export/import of the IMDP, and Storm's robust value iteration on it.

The DRN tests need no Storm. The others (``stormpy``, the ``storm`` extra) check on three small
systems (2-D damped unicycle with an obstacle and Gaussian noise, 1-D linear with Gaussian noise,
2-D linear with bounded uniform noise) that Storm's ``Pmax=? [ !"avoid" U<=K "reach" ]`` equals
our K-step bounds within 1e-9 at every state: ROBUST on the abstraction equals p_low of
``synthesize``, and on the single-action abstraction of a strategy ROBUST / COOPERATIVE equal
``verify``'s lower / upper bounds (COOPERATIVE on the full model maximizes over strategies too,
which is compared with a max-max value iteration).
"""

import io

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax import storm
from smdpjax.partition import AVOID, NONTERMINAL, REACH

HORIZONS = (1, 5, 20)
TOL = 1e-9


def damped_unicycle(x, u, w):  # heading u[0], contracting towards the unit circle
    return 0.6 * x + 0.5 * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + 0.02 * w


def linear(x, u, w):
    return 0.5 * x + u + w


def linear_1d(x, u, w):
    return 0.8 * x + u + w


def unicycle_gaussian():
    system = sj.System(damped_unicycle, actions=(np.arange(8) * np.pi / 4)[:, None],
                       noise=sj.Gaussian([0, 0], [1.0, 1.0]))
    grid = sj.StateGrid([-1, -1], [1, 1], 8, reach=[([0.5, 0.5], [1, 1])], avoid=[([-0.25, 0.0], [0.25, 0.5])])
    return system, grid, sj.NoiseGrid.ball([0, 0], 3.5, 6)


def line_gaussian():
    system = sj.System(linear_1d, actions=np.array([[-0.6], [0.0], [0.6]]), noise=sj.Gaussian([0.0], [0.05]))
    grid = sj.StateGrid([-2.0], [2.0], 16, reach=[([1.5], [2.0])], avoid=[([-2.0], [-1.5])])
    return system, grid, sj.NoiseGrid.ball([0.0], 0.15, 6)


def plane_uniform():
    system = sj.System(linear, actions=np.array([[0, 0], [0.5, 0], [0, 0.5], [0.5, 0.5], [-0.5, 0]]),
                       noise=sj.Uniform([-0.05, -0.05], [0.05, 0.05]))
    grid = sj.StateGrid([-1, -1], [1, 1], 8, reach=[([0.5, 0.5], [1, 1])], avoid=[([-0.25, 0.0], [0.0, 0.5])])
    return system, grid, sj.NoiseGrid.box([-0.05, -0.05], [0.05, 0.05], 3)


SYSTEMS = {"unicycle_gaussian": unicycle_gaussian, "line_gaussian": line_gaussian, "plane_uniform": plane_uniform}


@pytest.fixture(scope="module", params=list(SYSTEMS))
def imdp(request):
    system, grid, noise = SYSTEMS[request.param]()
    return sj.abstract(system, grid, noise, "imdp", method="natural")


def dense(imdp):
    """``(R, A, N+1)`` lower and upper bounds of every state, listed or not."""
    succ, n = np.asarray(imdp.successors).astype(np.int64), imdp.num_states
    lo = np.zeros(succ.shape[:2] + (n + 1,))
    up = np.full(succ.shape[:2] + (n + 1,), float(imdp.upper_rest))
    r, a, _ = np.indices(succ.shape)
    lo[r, a, succ] = np.asarray(imdp.lower)
    up[r, a, succ] = np.asarray(imdp.upper)
    return lo[..., :n], np.where(up[..., :n] > 0, up[..., :n], 0.0)


def assert_same_imdp(a, b):
    np.testing.assert_array_equal(np.asarray(a.labels), np.asarray(b.labels))
    np.testing.assert_array_equal(np.asarray(a.rows), np.asarray(b.rows))
    assert float(a.upper_rest) == float(b.upper_rest)
    for x, y in zip(dense(a), dense(b)):
        np.testing.assert_array_equal(x, y)  # bit for bit


# ---------------------------------------------------------------- DRN (no Storm needed)

def tiny(rest):
    """Cells 0, 1 (1 is a reach cell) and the sink 2; cell 0 has two actions."""
    return sj.IMDP(successors=jnp.array([[[0, 1, 3], [1, 2, 3]]], jnp.int16),
                   lower=jnp.array([[[0.25, 0.5, 0.0], [0.1, 0.0, 0.0]]]),
                   upper=jnp.array([[[0.5, 0.75, 0.0], [1.0, 0.9, 0.0]]]) + rest * np.array([1, 1, 0]),
                   upper_rest=jnp.asarray(rest), rows=jnp.array([0], jnp.int32),
                   labels=jnp.array([NONTERMINAL, REACH, AVOID], jnp.int8))


def test_drn_text_of_a_tiny_imdp():
    text = storm.drn_string(tiny(0.0))
    assert text.splitlines()[2:] == [
        "@type: MDP", "@value_type: double-interval", "@parameters", "", "@reward_models", "", "@nr_states", "3",
        "@nr_choices", "4", "@model",
        "state 0", "\taction 0", "\t\t0 : [0.25, 0.5]", "\t\t1 : [0.5, 0.75]",
        "\taction 1", "\t\t1 : [0.1, 1.0]", "\t\t2 : [0.0, 0.9]",
        "state 1 reach", "\taction 0", "\t\t1 : [1, 1]",
        "state 2 avoid", "\taction 0", "\t\t2 : [1, 1]"]
    assert_same_imdp(storm.from_drn(io.StringIO(text)), tiny(0.0))


def test_drn_round_trip_with_an_unlisted_remainder():
    rest = 0.1 + 1e-17 * 3  # needs all 17 digits
    text = storm.drn_string(tiny(rest))
    assert f"\t\t2 : [0, {rest!r}]" in text.splitlines()  # the unlisted sink of action 0, written out
    back = storm.from_drn(io.StringIO(text))
    assert_same_imdp(back, tiny(rest))
    with pytest.raises(ValueError, match="does not list every state"):
        storm.from_drn(io.StringIO(text.replace(f"\t\t2 : [0, {rest!r}]\n", "", 1)))


# ---------------------------------------------------------------- Storm (stormpy)

@pytest.fixture(scope="module")
def stormpy():
    return pytest.importorskip("stormpy")


def storm_model_of(imdp, tmp_path, name="imdp.drn"):
    path = tmp_path / name
    storm.to_drn(imdp, path)
    return storm.storm_model(path)


def test_storm_reads_the_intervals_bit_for_bit(stormpy, imdp, tmp_path):
    model = storm_model_of(imdp, tmp_path)
    lo, up = dense(imdp)
    matrix, rows = model.transition_matrix, np.asarray(imdp.rows)
    assert model.nr_states == imdp.num_states
    for r, s in enumerate(rows):
        first = matrix.get_row_group_start(int(s))
        for a in range(imdp.num_actions):
            got_lo, got_up = np.zeros(imdp.num_states), np.zeros(imdp.num_states)
            for entry in matrix.get_row(first + a):
                got_lo[entry.column], got_up[entry.column] = entry.value.lower(), entry.value.upper()
            np.testing.assert_array_equal(got_lo, lo[r, a])
            np.testing.assert_array_equal(got_up, up[r, a])


@jax.jit
def max_max_step(imdp, v):
    return v.at[imdp.rows].set(imdp.q_values(v, "max").max(axis=1))


def max_max(imdp, horizon):
    """K-step optimum when the strategy and the adversary both maximize (Storm's COOPERATIVE Pmax)."""
    v = imdp.initial_values()
    for _ in range(horizon):
        v = max_max_step(imdp, v)
    return np.asarray(v)


def test_storm_robust_equals_our_lower_bound(stormpy, imdp, tmp_path):
    model = storm_model_of(imdp, tmp_path)
    nontrivial = False
    for horizon in HORIZONS:
        sol = sj.synthesize(imdp, horizon=horizon)
        robust = storm.storm_values(model, horizon)
        lower = np.asarray(sol.lower)
        nontrivial |= bool(np.any((lower > 0.01) & (lower < 0.99)))
        assert np.max(np.abs(robust - lower)) <= TOL
        assert np.all(lower <= robust + 1e-12)  # ours is a sound lower bound (rounding allowance)
        assert sol.rounding_allowance < 1e-11
        cooperative = storm.storm_values(model, horizon, cooperative=True)
        assert np.max(np.abs(cooperative - max_max(imdp, horizon))) <= TOL
    assert nontrivial  # the comparison is not only about 0 and 1


def test_storm_on_our_strategy_equals_our_bounds(stormpy, imdp, tmp_path):
    """Robust and cooperative values of the single-action IMDP of a strategy equal verify()'s."""
    rows = np.asarray(imdp.rows)
    gap = 0.0
    for horizon in HORIZONS:
        policy = np.asarray(sj.synthesize(imdp, horizon=horizon).policy[0])  # a stationary strategy
        bounds = sj.verify(imdp, policy, horizon=horizon)
        single = imdp.restrict(jnp.asarray(policy[rows], jnp.int32))
        model = storm_model_of(single, tmp_path, f"policy{horizon}.drn")
        lower, upper = np.asarray(bounds.lower), np.asarray(bounds.upper)
        robust = storm.storm_values(model, horizon)
        cooperative = storm.storm_values(model, horizon, cooperative=True)
        assert np.max(np.abs(robust - lower)) <= TOL
        assert np.max(np.abs(cooperative - upper)) <= TOL
        assert np.all(lower <= robust + 1e-12) and np.all(upper >= cooperative - 1e-12)
        gap = max(gap, float(np.max(upper - lower)))
    assert gap > 1e-3  # the two values differ


def test_drn_round_trip(imdp, tmp_path):
    path = tmp_path / "imdp.drn"
    storm.to_drn(imdp, path, reach_label="goal", avoid_label="bad")
    back = storm.from_drn(path, reach_label="goal", avoid_label="bad")
    assert_same_imdp(back, imdp)
    for horizon in HORIZONS[1:2]:  # compiled already by the Storm tests when they run
        ours, again = sj.synthesize(imdp, horizon=horizon), sj.synthesize(back, horizon=horizon)
        np.testing.assert_allclose(np.asarray(again.lower), np.asarray(ours.lower), rtol=0, atol=1e-14)
        np.testing.assert_allclose(np.asarray(again.upper), np.asarray(ours.upper), rtol=0, atol=1e-14)
