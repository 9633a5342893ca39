"""The HiGHS replay benchmark: the captured solves replayed under two option sets reach the same optima."""

import json

import pytest

from benchmarks import highs_replay


def test_presolve_on_and_off_replay_the_same_solves_to_the_same_optima(tmp_path, capsys):
    pytest.importorskip("highspy")
    out = tmp_path / "replay.json"
    highs_replay.main(["--rows", "31", "--repeats", "1", "--options", '[{}, {"presolve": "on"}]',
                       "--out", str(out)])  # 2-D temperature, 145 states
    without, presolved = json.loads(out.read_text())["rows"]
    assert without["options"] == {} and presolved["options"] == {"presolve": "on"}
    assert without["solves"] == presolved["solves"] > 0 and without["iterations"] > 0
    assert without["max_value_diff"] == 0.0 and presolved["max_value_diff"] <= 1e-8
    assert "  31 " in capsys.readouterr().out


def test_option_sets_must_be_a_list_of_objects():
    with pytest.raises(SystemExit):
        highs_replay.main(["--options", '{"presolve": "on"}'])
