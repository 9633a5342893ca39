"""The IMDP time breakdown: its timed loops compute the synthesis' own backups, and it reports every stage."""

import json

import numpy as np

import smdpjax as sj
from benchmarks import imdp_breakdown
from smdpjax.synthesis import value_iteration


def test_timed_loops_are_the_synthesis_backups():
    system, grid, noise = imdp_breakdown.case(6, "uniform")
    imdp = sj.abstract(system, grid, noise, "imdp")
    v0 = imdp.initial_values("reach_avoid")
    loops = imdp_breakdown.stage_loops(imdp, 4)
    expected = np.asarray(value_iteration.finite_horizon(imdp, v0, 4, with_upper=False)[0])
    np.testing.assert_array_equal(np.asarray(loops["backup"](v0)), expected)
    np.testing.assert_array_equal(np.asarray(loops["q_values"](v0)), expected)
    # the sort loop passes the values through unchanged
    np.testing.assert_array_equal(np.asarray(loops["sort"](v0)), np.asarray(v0))
    assert expected.max() > 0  # the horizon reaches the target: the loops compared real values


def test_every_stage_is_reported(tmp_path, capsys):
    out = tmp_path / "breakdown.json"
    rows = imdp_breakdown.main(["--cells", "6", "--noise", "uniform", "--horizon", "3", "--repeats", "1",
                                "--out", str(out)])
    (row,) = rows
    assert set(row["per_step_ms"]) == set(imdp_breakdown.STAGES)
    assert all(t > 0 for t in row["per_step_ms"].values())
    assert row["rows"] * row["actions"] > 0 and row["chunks"] >= row["rows"]
    record = json.loads(out.read_text())
    assert record["benchmark"] == "imdp_breakdown" and record["rows"][0]["case"] == "unicycle 6x6, uniform"
    assert "| unicycle 6x6, uniform |" in capsys.readouterr().out
