"""The 2I-MDP pairs benchmark: both inner problems give the same values, and it reports both."""

import json

import pytest

from benchmarks import two_layer_pairs


def test_met_pairs_and_every_slot_reported_side_by_side(tmp_path, capsys):
    out = tmp_path / "pairs.json"
    two_layer_pairs.main(["--rows", "30", "--repeats", "1", "--out", str(out)])  # 2-D temperature, 145 states
    (row,) = json.loads(out.read_text())["rows"]
    assert row["row"] == 30 and row["max_value_difference"] <= 1e-14
    assert 0 < row["block_pairs"][0] and row["mean_blocks_met"] <= row["block_slots"]
    assert all(len(runs) == 1 for runs in row["runs"].values()) and len(row["runs"]) == 4
    assert "  30 " in capsys.readouterr().out


def test_rows_of_other_classes_are_refused():
    with pytest.raises(ValueError, match="not a 2I-MDP row"):
        two_layer_pairs.measure(29, 1)
