"""The count-table benchmark: both builds give the same table, both backups the same values."""

import json

import pytest

from benchmarks import count_table


def test_builds_and_backups_reported_side_by_side(tmp_path, capsys):
    out = tmp_path / "count_table.json"
    count_table.main(["--rows", "30", "--repeats", "1", "--out", str(out)])  # 2-D temperature, 145 states
    (row,) = json.loads(out.read_text())["rows"]
    assert row["row"] == 30 and row["same_table"] and row["max_value_difference"] <= 1e-14
    assert row["table_entries"] == (row["states"] + 1) * (row["blocks"] + 1)
    assert set(row["picks_table"]) == {"every action", "strategy"}
    assert len(row["runs"]) == 6 and all(len(runs) == 1 for runs in row["runs"].values())
    assert "  30 " in capsys.readouterr().out


def test_rows_of_other_classes_are_refused():
    with pytest.raises(ValueError, match="not a 2I-MDP row"):
        count_table.measure(29, 1)
