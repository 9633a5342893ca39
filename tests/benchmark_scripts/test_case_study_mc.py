"""The case-study Monte Carlo script on a small verification problem, and its --study parsing."""

import json

import numpy as np
import pytest

from benchmarks import case_study_mc


def test_temperature_verification_is_checked_by_simulation(tmp_path, capsys):
    out = tmp_path / "mc.json"
    result = case_study_mc.main(["--study", "temperature:rooms=2,cells=8", "--initial", "6",
                                 "--trajectories", "100", "--out", str(out)])
    assert result["kind"] == "smdp" and "|S|=65" in result["study"]
    assert result["mc_cells"] == 6 and result["mc_cells_in_bounds"] == 6
    assert 0 <= result["p_low_initial"] <= result["p_up_initial"] <= 1
    # 15-step safety of the look-up table: simulated frequencies lie between the bounds' means up to sampling
    assert result["p_low_initial"] - 0.1 <= result["p_mc_initial"] <= result["p_up_initial"] + 0.1
    assert result["p_low_min"] <= result["p_low_nonterminal"] <= result["p_low_max"]
    record = json.loads(out.read_text())
    assert record["benchmark"] == "case_study_mc" and record["args"]["study"] == "temperature:rooms=2,cells=8"
    assert np.isclose(record["t_abs_s"], result["t_abs_s"])
    assert "mc_cells_in_bounds: 6" in capsys.readouterr().out


def test_study_options_are_parsed_by_type():
    study = case_study_mc.parse_study("temperature:rooms=3,cells=5,noise_cells=2")
    assert study.state_grid.num_cells == 125 and study.noise_grid.num_cells == 2**3 + 1


@pytest.mark.parametrize("text, message", [("nowhere:cells=3", "unknown case study 'nowhere'"),
                                           ("CaseStudy", "unknown case study"),
                                           ("temperature:rooms", "key=value")])
def test_bad_study_is_refused(text, message):
    with pytest.raises(SystemExit, match=message):
        case_study_mc.parse_study(text)
