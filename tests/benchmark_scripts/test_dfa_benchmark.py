"""benchmarks/dfa.py at a small size: the per-class table (Monte Carlo inside the bounds)."""

import json

from benchmarks import dfa


def test_dfa_benchmark_small(tmp_path, capsys):
    out = tmp_path / "dfa.json"
    result = dfa.main(["--kinds", "imdp,smdp", "--cells", "10", "--noise-cells", "4", "--repeats", "0",
                       "--initial", "4", "--trajectories", "40", "--out", str(out)])
    rows = result["classes"]
    assert [r["kind"] for r in rows] == ["imdp", "smdp"]
    assert all(r["mc_per_cell_in_bounds"] and r["dfa_states"] == 4 for r in rows)
    assert rows[1]["p_low_avg"] >= rows[0]["p_low_avg"]  # Theorem 3 on the product, on average
    record = json.loads(out.read_text())
    assert record["benchmark"] == "dfa" and record["targets"] == []
    assert "e_avg" in capsys.readouterr().out
