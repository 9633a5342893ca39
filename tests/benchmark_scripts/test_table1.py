"""Smoke test of the Table 1 runner: the smallest row of each system at the quick scale, the
rendered table with its checks, resuming, and the figures."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.paper_table1 import parse_rows, row_spec
from smdpjax import case_studies

ROOT = Path(__file__).resolve().parents[2]


def test_row_specs_match_the_paper_sizes():
    sizes = {1: 901, 5: 2026, 9: 3601, 13: 5626, 17: 27001, 29: 145, 33: 1729, 37: 20737}
    for row, states in sizes.items():
        spec = row_spec(row)
        study = {"unicycle_2d": lambda v: case_studies.unicycle_2d(v), "unicycle_3d": lambda v: case_studies.unicycle_3d(v),
                 "temperature": lambda v: case_studies.temperature(v)}[spec.system](spec.value)
        assert study.state_grid.num_states == states
    assert case_studies.unicycle_3d(10).noise_grid.num_cells == 101
    assert case_studies.temperature(4).noise_grid.num_cells == 257
    assert case_studies.temperature(3).num_actions == 1 and case_studies.temperature(3).system.num_actions == 8
    assert parse_rows("1-3,17,3") == [1, 2, 3, 17]
    with pytest.raises(ValueError):
        parse_rows("40-41")


def test_lookup_table_heats_the_cold_rooms():
    study = case_studies.temperature(3)
    centers = np.asarray(study.state_grid.cell_centers())
    heaters = study.system.actions[study.controller]  # (N, n) heater inputs the table picks
    np.testing.assert_array_equal(heaters, (centers < 19.75).astype(float))


def _run(args, tmp_path):
    return subprocess.run([sys.executable, "-m", "benchmarks.table1", *args, "--out", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=1500)


def test_quick_rows_run_render_and_resume(tmp_path):
    rows = "4,20,29,32"  # SMDP of the smallest 2-D and 3-D configurations, IMDP and SMDP of 2 rooms
    done = _run(["--rows", rows, "--quick", "--repeats", "0", "--initial", "6", "--trajectories", "200"], tmp_path)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    for row in parse_rows(rows):
        record = json.loads((tmp_path / f"row_{row:02d}.json").read_text())
        assert record["status"] == "ok", record
        assert record["quick"] and record["mc_in_bounds"], record
        assert 0.0 <= record["p_low_avg"] <= record["p_mc_avg"] + record["mc_tolerance"]
        assert record["p_mc_avg"] <= record["p_up_avg"] + record["mc_tolerance"]
        assert record["t_abs_s"] > 0 and record["t_syn_s"] > 0 and record["memory_bytes"] > 0
    table = (tmp_path / "table1.md").read_text()
    rows_md = [line for line in table.splitlines() if line.startswith("| ") and line.split("|")[1].strip().isdigit()]
    lines = {int(line.split("|")[1]): line for line in rows_md}
    assert sorted(lines) == [4, 20, 29, 32]
    assert all("yes (" in line for line in lines.values())  # Monte Carlo inside the bounds
    assert "ok (" in lines[29] and "ok (" in lines[32]  # Theorem 3 order checked between rows 29 and 32
    # the 2-room rows show that the SMDP's bounds are tighter than the IMDP's
    imdp, smdp = (json.loads((tmp_path / f"row_{r}.json").read_text()) for r in (29, 32))
    assert smdp["e_avg"] <= imdp["e_avg"] + 1e-12 and smdp["p_low_avg"] >= imdp["p_low_avg"] - 1e-12

    again = _run(["--rows", rows, "--quick"], tmp_path)  # resumes: nothing left to run
    assert again.returncode == 0 and "4 row(s) already in" in again.stdout

    figures = subprocess.run([sys.executable, "-m", "benchmarks.table1_figures", "--results", str(tmp_path),
                              "--out", str(tmp_path / "figures")], cwd=ROOT, capture_output=True, text=True,
                             timeout=600)
    assert figures.returncode == 0, figures.stderr[-3000:]
    names = sorted(p.name for p in (tmp_path / "figures").glob("*.png"))
    assert {"fig2_unicycle_2d.png", "fig5_unicycle_3d.png", "fig6_vs_rooms.png"} <= set(names)
