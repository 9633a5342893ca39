"""System.check_against: runs once per function, actions, noise mean and probe states."""

import numpy as np
import pytest

import smdpjax as sj
from smdpjax.system import System


def counting(monkeypatch):
    calls = []
    check = System._check

    def counted(self, *args):
        calls.append(args)
        return check(self, *args)

    monkeypatch.setattr(System, "_check", counted)
    return calls


def test_a_passed_check_is_not_run_again_for_the_same_inputs(monkeypatch):
    calls = counting(monkeypatch)

    def drift(x, u, w):
        return x + 0.1 * u + w

    system = sj.System(drift, actions=np.eye(2), noise=sj.Gaussian([0, 0], [0.1, 0.1]))
    probe = np.array([[0.1, 0.2], [0.3, 0.4]])
    system.check_against(2, probe)
    system.check_against(2, probe.copy())
    assert len(calls) == 1
    system.check_against(2, probe + 0.5)  # other states
    assert len(calls) == 2
    system.actions[0, 0] = 2.0  # the same System, its actions changed in place
    system.check_against(2, probe)
    assert len(calls) == 3
    with pytest.raises(ValueError, match=r"must return shape \(3,\)"):
        system.check_against(3, probe)  # another state dimension is checked, and fails


def test_a_failed_check_fails_every_time(monkeypatch):
    calls = counting(monkeypatch)

    def blows_up(x, u, w):
        return x / (x[0] - 0.1)  # inf at the probe's first state

    system = sj.System(blows_up, actions=np.eye(2), noise=sj.Gaussian([0, 0], [0.1, 0.1]))
    probe = np.array([[0.1, 0.2]])
    for _ in range(2):
        with pytest.raises(ValueError, match="NaN/inf"):
            system.check_against(2, probe)
    assert len(calls) == 2
