"""The certified warm start of the strategy's pessimistic evaluation (``synthesize``)."""

import jax.numpy as jnp
import numpy as np
import pytest

import smdpjax as sj
from smdpjax.partition import AVOID, NONTERMINAL, REACH
from smdpjax.synthesis import _pessimistic, _warm_start
from smdpjax.synthesis.value_iteration import WARM_MARGINS, warm_margins


def idle_or_gamble():
    """Cell 0: action 0 stays put (probability 1), action 1 reaches cell 1 (a reach cell) or the
    sink 2 with probability 1/2 each. Values: 0 under action 0, 1/2 under action 1."""
    return sj.IMDP(successors=jnp.array([[[0, 3], [1, 2]]], jnp.int16),
                   lower=jnp.array([[[1.0, 0.0], [0.5, 0.5]]]), upper=jnp.array([[[1.0, 0.0], [0.5, 0.5]]]),
                   upper_rest=jnp.asarray(0.0), rows=jnp.array([0], jnp.int32),
                   labels=jnp.array([NONTERMINAL, REACH, AVOID], jnp.int8))


def test_an_idling_strategy_gets_no_credit_from_the_guess():
    """Under action 0 the guess 1/2 is a fixed point of the backup (so 'v <= T v' alone would
    accept it) but the true value is 0: the strict-gain check must refuse it."""
    imdp = idle_or_gamble()
    v0 = imdp.initial_values()
    guess = jnp.array([0.5, 1.0, 0.0])
    idle = jnp.array([0], jnp.int32)
    assert _warm_start(imdp, imdp.restrict(idle), v0, guess, 1e-6)[0] is None
    lower, _, _ = _pessimistic(imdp, v0, idle, 1e-9, 1000, guess)
    assert float(lower[0]) == 0.0


def test_a_guess_above_the_value_is_refused_and_one_below_is_taken():
    imdp = idle_or_gamble()
    v0 = imdp.initial_values()
    gamble = jnp.array([1], jnp.int32)
    assert _warm_start(imdp, imdp.restrict(gamble), v0, jnp.array([0.5 + 1e-3, 1.0, 0.0]), 1e-6)[0] is None
    # just above: the margins beyond tol take it below the value, and only there
    start, _ = _warm_start(imdp, imdp.restrict(gamble), v0, jnp.array([0.5 + 1e-6, 1.0, 0.0]), 1e-6)
    assert start is not None and float(start[0]) == pytest.approx(0.5 + 1e-6 - 1e-5, abs=1e-15)
    start, _ = _warm_start(imdp, imdp.restrict(gamble), v0, jnp.array([0.4, 1.0, 0.0]), 1e-6)
    assert start is not None and 0.4 - 1e-7 < float(start[0]) < 0.4
    lower, _, _ = _pessimistic(imdp, v0, gamble, 1e-12, 1000, jnp.array([0.4, 1.0, 0.0]))
    assert 0.5 - 1e-12 <= float(lower[0]) <= 0.5


def leaky_cell(stay):
    """Cell 0 stays put with probability ``stay`` and reaches the goal (cell 1) otherwise."""
    return sj.IMDP(successors=jnp.array([[[0, 1]]], jnp.int16), lower=jnp.array([[[stay, 1.0 - stay]]]),
                   upper=jnp.array([[[stay, 1.0 - stay]]]), upper_rest=jnp.asarray(0.0),
                   rows=jnp.array([0], jnp.int32), labels=jnp.array([NONTERMINAL, REACH, AVOID], jnp.int8))


@pytest.mark.parametrize("needed, tries", [(1.0, 4), (10.0, 5), (100.0, 6), (1000.0, None)])
def test_margins_go_up_to_the_tolerance_then_beyond_it_before_a_cold_start(needed, tries):
    """From 1 - m a backup of ``leaky_cell`` gains m (1 - stay): with 1 - stay = 2 slack /
    (needed tol) the margins below ``needed * tol`` gain at most the rounding bound slack, so the
    first margin that passes is ``needed * tol`` (tol lies strictly between two rungs of the
    ladder). Beyond 100 tol none is tried: the cold start."""
    probe = idle_or_gamble()
    slack = 2.0 * float(probe.rounding_per_backup())
    tol = 5e4 * slack  # between slack * 1e4 and slack * 1e5
    imdp = leaky_cell(1.0 - 2.0 * slack / (needed * tol))
    assert float(imdp.rounding_per_backup()) == float(probe.rounding_per_backup())
    margins = np.asarray(warm_margins(slack, tol))
    tried = margins[np.concatenate([[True], margins[1:] > np.maximum.accumulate(margins)[:-1]])]
    np.testing.assert_allclose(tried, [slack * 1e2, slack * 1e3, slack * 1e4, tol, 10 * tol, 100 * tol], rtol=1e-12)
    stays = jnp.array([0], jnp.int32)
    start, spent = _warm_start(imdp, imdp.restrict(stays), imdp.initial_values(), jnp.array([1.0, 1.0, 0.0]), tol)
    if tries is None:
        assert start is None and spent == len(tried)
    else:
        assert start is not None and spent == tries
        assert float(start[0]) == pytest.approx(1.0 - needed * tol, rel=0, abs=1e-15)


def relay_then_leak(stay):
    """Cell 0 moves to cell 1 with probability 1; cell 1 stays put with probability ``stay`` and
    reaches the goal (cell 2) otherwise. Both values are 1."""
    return sj.IMDP(successors=jnp.array([[[1, 4]], [[1, 2]]], jnp.int16),
                   lower=jnp.array([[[1.0, 0.0]], [[stay, 1.0 - stay]]]),
                   upper=jnp.array([[[1.0, 0.0]], [[stay, 1.0 - stay]]]), upper_rest=jnp.asarray(0.0),
                   rows=jnp.array([0, 1], jnp.int32),
                   labels=jnp.array([NONTERMINAL, NONTERMINAL, REACH, AVOID], jnp.int8))


def test_a_row_that_gains_only_after_two_backups_is_certified_by_them():
    """From 1 - m on both cells, one backup leaves cell 0 at exactly its start (it only copies cell
    1), so no number of one-step checks can certify it; the second backup carries cell 1's gain
    m (1 - stay) over, which exceeds twice the rounding bound: certified with the first margin,
    after two backups."""
    imdp = relay_then_leak(0.5)
    slack = 2.0 * float(imdp.rounding_per_backup())
    relay = jnp.array([0, 0], jnp.int32)
    start, spent = _warm_start(imdp, imdp.restrict(relay), imdp.initial_values(), jnp.array([1.0, 1.0, 1.0, 0.0]),
                               1e-6)
    assert start is not None and spent == 2
    np.testing.assert_allclose(np.asarray(start)[:2], 1.0 - slack * WARM_MARGINS[0], rtol=0, atol=1e-15)
    lower, _, _ = _pessimistic(imdp, imdp.initial_values(), relay, 1e-12, 1000, jnp.array([1.0, 1.0, 1.0, 0.0]))
    assert np.all(np.asarray(lower)[:2] <= 1.0) and np.all(np.asarray(lower)[:2] >= 1.0 - 1e-9)


def test_certificate_rejects_every_start_above_the_least_fixed_point():
    """Random guesses on a real SMDP: whenever one is certified, it lies below the strategy's
    pessimistic value computed cold to a tight tolerance."""
    def drift(x, u, w):
        return x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)

    system = sj.System(drift, actions=(np.arange(8) * np.pi / 4)[:, None], noise=sj.Gaussian([0, 0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 12, reach=[([0.75, 0.75], [1, 1])], avoid=[([0.4, 0.3], [0.6, 0.7])])
    smdp = sj.abstract(system, grid, sj.NoiseGrid.ball([0, 0], 2.1, 6), "smdp")
    cold = sj.synthesize(smdp, tol=1e-6)
    policy = jnp.asarray(np.asarray(cold.policy)[np.asarray(smdp.rows)])
    tight = sj.verify(smdp, np.asarray(cold.policy), tol=1e-13)
    truth = np.asarray(tight.lower) + tight.rounding_allowance  # undo the widening: the computed iterate
    v0 = smdp.initial_values()
    rng = np.random.default_rng(0)
    certified = 0
    for scale in (0.0, 1e-9, 1e-6, 1e-3, 1e-1):
        for _ in range(3):
            guess = jnp.asarray(np.clip(truth + scale * rng.standard_normal(truth.shape), 0, 1))
            start, _ = _warm_start(smdp, smdp.restrict(policy), v0, guess, 1e-3)
            if start is not None:
                certified += 1
                assert np.all(np.asarray(start) <= truth + 1e-9)
    assert certified >= 1  # the check is not simply refusing everything


@pytest.mark.parametrize("kind", ["imdp", "2imdp", "smdp"])
def test_synthesis_uses_the_warm_start_and_stays_below_the_cold_value(kind):
    def drift(x, u, w):
        return x + 0.1 * (jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)

    system = sj.System(drift, actions=(np.arange(8) * np.pi / 4)[:, None], noise=sj.Gaussian([0, 0], [0.3, 0.3]))
    grid = sj.StateGrid([0, 0], [1, 1], 20, reach=[([0.8, 0.8], [1, 1])], avoid=[([0.4, 0.3], [0.6, 0.7])])
    abstraction = sj.abstract(system, grid, sj.NoiseGrid.ball([0, 0], 2.1, 12), kind)
    warm = sj.synthesize(abstraction, tol=1e-6)
    cold = sj.verify(abstraction, np.asarray(warm.policy), tol=1e-6)  # from p^0, no guess
    lo_w, lo_c = np.asarray(warm.lower), np.asarray(cold.lower)
    tight = sj.verify(abstraction, np.asarray(warm.policy), tol=1e-13)
    assert np.all(lo_w <= np.asarray(tight.lower) + 2 * tight.rounding_allowance + 1e-15)
    assert np.max(np.abs(lo_w - lo_c)) < 1e-4
    # The IMDP's minimizing adversary keeps nearly all mass among states whose values no longer
    # move: one backup shows no margin there, so a one-step check fell back to the cold start
    # (344 backups); several backups from the start reach the rows near the goal and certify it.
    assert warm.evaluation_iterations < cold.evaluation_iterations / 2
    assert np.all(np.asarray(warm.lower_optimal) >= lo_w)
