"""The block benchmark: both variants of a Table 1 row solve to the same bounds, and it reports both."""

import json

from benchmarks import imdp_blocks


def test_blocked_and_whole_rows_reported_side_by_side(tmp_path, capsys):
    out = tmp_path / "blocks.json"
    # row 30 (2I-MDP, 144 rows) with blocks of 4 096 slots: several blocks where the library keeps one
    imdp_blocks.main(["--rows", "30", "--repeats", "1", "--budget", "4096", "--out", str(out)])
    (row,) = json.loads(out.read_text())["rows"]
    assert row["kind"] == "2imdp" and 0 < row["block_rows"] < row["rows"]
    assert row["max_bound_difference"] <= 1e-15
    assert row["t_syn_blocked_s"] > 0 and row["q_values_all_s"] > 0
    assert "  30  2imdp" in capsys.readouterr().out
