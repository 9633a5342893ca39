"""The re-pricing benchmark: both variants of an MI-MDP row solve to the same bounds, and it reports both."""

import json

import pytest

from benchmarks import mimdp_reprice


def test_repriced_and_solved_lps_reported_side_by_side(tmp_path, capsys):
    pytest.importorskip("highspy")
    out = tmp_path / "reprice.json"
    mimdp_reprice.main(["--rows", "31", "--repeats", "1", "--out", str(out)])  # 2-D temperature, 145 states
    (row,) = json.loads(out.read_text())["rows"]
    assert row["row"] == 31 and row["repriced"] > 0 and row["solves_repriced"] < row["solves_highs"]
    assert row["max_bound_difference"] <= 1e-9 and row["same_policy"]
    assert "  31 " in capsys.readouterr().out


def test_rows_of_other_classes_are_refused():
    with pytest.raises(ValueError, match="not an MI-MDP row"):
        mimdp_reprice.measure(30, 1)
