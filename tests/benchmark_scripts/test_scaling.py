"""The scaling benchmark at tiny sizes: one subprocess per size, the table, the JSON with its
slopes, the figure, the memory skip, and an encoding that does not apply to a system."""

import json

import numpy as np
import pytest

from benchmarks import scaling

pytest.importorskip("matplotlib")

FIELDS = ("cells", "rows", "actions", "noise_cells", "boxes", "t_abs_s", "t_syn_s", "iterations", "backups",
          "t_syn_per_iteration_s", "t_backup_s", "ns_per_box", "rss_peak_bytes", "bytes", "p_low_mean")


def run(tmp_path, *extra):
    out = tmp_path / "scaling.json"
    records = scaling.main(["--repeats", "0", "--backup-repeats", "1", "--out", str(out), *extra])
    return records, json.loads(out.read_text())


def test_two_sizes_give_a_slope_a_table_and_a_figure(tmp_path, capsys):
    records, saved = run(tmp_path, "--systems", "2d", "--sizes", "100,400")
    assert [r["cells"] for r in records] == [100, 400] and all(r["status"] == "ok" for r in records)
    for r in records:
        assert all(key in r for key in FIELDS), set(FIELDS) - set(r)
        assert r["boxes"] == r["rows"] * r["actions"] * (r["noise_cells"] - 1)  # 12x12 bounded + remainder
        assert r["actions"] == 8 and r["noise_cells"] == 145 and r["backups"] >= r["iterations"] > 0
        assert r["rss_peak_bytes"] >= r["rss_synthesis_bytes"] >= r["rss_abstraction_bytes"] > 0
        assert r["ns_per_box"] == pytest.approx(1e9 * r["t_backup_s"] / r["boxes"])
    assert saved["benchmark"] == "scaling" and saved["args"]["systems"] == "2d" and "environment" in saved
    slopes = saved["slopes"]["2d"]
    assert all(slopes[key] is not None and np.isfinite(slopes[key]) for key in ("t_backup_s", "ns_per_box",
                                                                                "rss_peak_bytes"))
    printed = capsys.readouterr().out
    assert "ns/box" in printed and "log-log slopes" in printed
    figure = tmp_path / "scaling.png"
    assert figure.exists() and figure.stat().st_size > 10_000 and f"wrote {figure}" in printed


def test_three_and_four_dimensions(tmp_path):
    records, _ = run(tmp_path, "--systems", "3d,4d", "--sizes", "300", "--no-plot")
    assert [(r["system"], r["cells"], r["status"]) for r in records] == [("3d", 343, "ok"), ("4d", 256, "ok")]
    four = records[1]
    assert four["actions"] == 25 and four["noise_cells"] == 5 and four["case_study"] == "double_integrator_4d"
    assert records[0]["encoding_used"] == "boxes" and four["encoding_used"] in ("boxes", "structured")
    assert not (tmp_path / "scaling.png").exists()


def test_a_size_over_the_memory_limit_is_skipped_and_ends_the_ladder(tmp_path, capsys):
    records, _ = run(tmp_path, "--systems", "4d", "--sizes", "1e4,1e5", "--max-memory-gb", "0.01", "--no-plot")
    assert len(records) == 1 and records[0]["status"] == "skipped" and "--max-memory-gb" in records[0]["error"]
    assert "skipped" in capsys.readouterr().out


def test_an_encoding_that_does_not_apply_is_reported_not_raised(tmp_path):
    """Structured clusters need System.additive: the 2-D unicycle is not declared so (unavailable,
    and the run goes on), the double integrator is."""
    records, _ = run(tmp_path, "--systems", "2d,4d", "--sizes", "256", "--encoding", "structured", "--no-plot")
    assert [r["system"] for r in records] == ["2d", "4d"]
    assert records[0]["status"] == "unavailable" and "additive" in records[0]["error"], records[0]
    assert records[1]["status"] in ("ok", "unavailable"), records[1]  # ok since the library offers it
    if records[1]["status"] == "ok":
        assert records[1]["encoding_used"] == "structured"


def test_estimate_and_arguments():
    assert scaling.cells_per_dimension("4d", 1e6) == 32 and scaling.cells_per_dimension("2d", 1e4) == 100
    per_box = scaling.estimate_bytes(4, 1e6, 32) - scaling.estimate_bytes(4, 0, 32)
    assert per_box == pytest.approx(1e6 * (2 * 9 + 18 * 4 + 12))  # int8 boxes twice, synthesis temporaries
    assert scaling.estimate_bytes(2, 1e6, 1000) - scaling.estimate_bytes(2, 0, 1000) == pytest.approx(1e6 * 66)  # int16
    assert scaling.parse_noise_cells("4d:3") == {"2d": 12, "3d": 6, "4d": 3}
    with pytest.raises(ValueError):
        scaling.parse_noise_cells("5d:3")
    for bad in (["--systems", "5d"], ["--sizes", "0"], ["--max-memory-gb", "-1"]):
        with pytest.raises(SystemExit):
            scaling.main(bad)
