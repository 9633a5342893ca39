"""The main command at a small size: its table, JSON and figure (or none with --no-plot)."""

import json

import pytest

from benchmarks import core_2d
from benchmarks.common import argument_parser, write_result

pytest.importorskip("matplotlib")


def run(tmp_path, *extra):
    out = tmp_path / "core_2d.json"
    rows = core_2d.main(["--kinds", "imdp,smdp", "--cells", "10", "--repeats", "0", "--initial", "5",
                         "--trajectories", "50", "--out", str(out), *extra])
    return out, rows


def test_core_2d_writes_results_and_the_figure(tmp_path, capsys):
    out, rows = run(tmp_path)
    assert [r["kind"] for r in rows] == ["imdp", "smdp"]
    assert all(r["mc_in_bounds"] for r in rows)
    record = json.loads(out.read_text())
    assert record["benchmark"] == "core_2d" and record["args"]["cells"] == "10" and "environment" in record
    figure = tmp_path / "core_2d.png"
    assert figure.exists() and figure.stat().st_size > 10_000
    assert f"wrote {figure}" in capsys.readouterr().out


def test_no_plot(tmp_path):
    out, _ = run(tmp_path, "--no-plot")
    assert out.exists() and not (tmp_path / "core_2d.png").exists()


def test_common_parser_and_record(tmp_path):
    parser = argument_parser("doc", "name", repeats=4, tol=1e-7)
    args = parser.parse_args(["--out", str(tmp_path / "x.json")])
    assert args.repeats == 4 and args.tol == 1e-7
    assert parser.parse_args([]).out.as_posix() == "results/name.json"
    path = write_result("name", args, rows=[1, 2])
    record = json.loads(path.read_text())
    assert record["benchmark"] == "name" and record["rows"] == [1, 2] and record["args"]["repeats"] == "4"
