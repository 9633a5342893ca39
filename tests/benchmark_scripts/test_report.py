"""The speed report: ratios against the paper and the target lines, from row files."""

import json

from benchmarks import report
from benchmarks.paper_table1 import PAPER


def write_row(directory, row, total_s, memory_mb):
    record = dict(row=row, status="ok", quick=False, t_abs_s=total_s / 4, t_syn_s=3 * total_s / 4,
                  memory_bytes=memory_mb * 1e6, environment={"backend": "cpu"}, time_limit_min=8.0)
    (directory / f"row_{row:02d}.json").write_text(json.dumps(record))


def test_report_names_the_rows_that_meet_and_miss_the_cpu_target(tmp_path):
    paper = lambda row: (PAPER[row].t_abs_min + PAPER[row].t_syn_min) * 60
    write_row(tmp_path, 4, paper(4) / 60, 1.0)  # 60x faster than the paper: meets 50x
    write_row(tmp_path, 16, paper(16) / 10, 1e6)  # 10x: misses; memory above the paper's
    text = report.render([tmp_path])
    assert "target 50x met on 1 of 2 rows (met: 4; not met: 16)" in text
    assert "Memory below the paper's on 1 of 2 rows; not on rows [16]." in text
    line = next(line for line in text.splitlines() if line.startswith("| 4 |"))
    assert "| 60x |" in line
