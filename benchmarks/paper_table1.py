"""The paper's Table 1 ("Beyond Interval MDPs"), transcribed, and which case study each row is.

Paper times are minutes and memory GB (MATLAB, one thread of an i7 at 3.6 GHz, GUROBI, a
360-minute timeout on T_syn); ``None`` is the paper's "-" and ``TO`` its timeout.
"""

from __future__ import annotations

import dataclasses

TO = "TO"
KIND_ORDER = ("imdp", "2imdp", "mimdp", "smdp")
KIND_NAMES = {"imdp": "IMDP", "2imdp": "2I-MDP", "mimdp": "MI-MDP", "smdp": "SMDP"}


@dataclasses.dataclass(frozen=True)
class PaperRow:
    e_avg: float | None
    t_abs_min: float
    t_syn_min: float | str
    memory_gb: float
    p_low_avg: float | None
    p_up_avg: float | None
    p_mc_avg: float | None


# (e_avg, T_abs min, T_syn min, memory GB, p_low_avg, p_up_avg, P_avg)
_VALUES = {
    1: (0.156, 0.235, 0.620, 0.017, 0.645, 1.000, 0.996),
    2: (0.129, 0.359, 2.619, 0.018, 0.715, 1.000, 0.995),
    3: (0.099, 1.872, 3.709, 0.045, 0.907, 1.000, 0.998),
    4: (0.083, 0.087, 0.695, 0.014, 0.923, 1.000, 0.999),
    5: (0.064, 0.597, 2.160, 0.076, 0.956, 1.000, 0.999),
    6: (0.055, 0.853, 8.680, 0.082, 0.951, 1.000, 0.999),
    7: (0.039, 4.086, 11.060, 0.148, 0.965, 1.000, 0.999),
    8: (0.033, 0.203, 1.580, 0.043, 0.971, 1.000, 0.999),
    9: (0.064, 1.280, 7.854, 0.236, 0.942, 1.000, 0.999),
    10: (0.044, 1.707, 24.511, 0.255, 0.955, 1.000, 1.000),
    11: (0.029, 7.258, 22.850, 0.387, 0.975, 1.000, 1.000),
    12: (0.027, 0.372, 2.659, 0.101, 0.978, 1.000, 1.000),
    13: (0.048, 2.395, 16.948, 0.577, 0.957, 1.000, 0.999),
    14: (0.035, 2.960, 58.710, 0.626, 0.969, 1.000, 0.999),
    15: (0.023, 11.504, 56.672, 0.856, 0.981, 1.000, 1.000),
    16: (0.020, 0.603, 4.455, 0.205, 0.984, 1.000, 0.999),
    17: (0.885, 2.800, 4.671, 0.625, 0.048, 0.976, 0.866),
    18: (0.884, 4.710, 15.005, 0.633, 0.050, 0.976, 0.868),
    19: (0.740, 11.645, 347.826, 1.234, 0.218, 0.977, 0.910),
    20: (0.558, 1.325, 10.563, 0.486, 0.411, 0.969, 0.913),
    21: (0.710, 4.650, 4.769, 0.586, 0.243, 0.975, 0.874),
    22: (0.704, 7.625, 18.060, 0.594, 0.247, 0.975, 0.877),
    23: (None, 26.646, TO, 1.517, None, None, None),
    24: (0.367, 2.322, 14.228, 0.707, 0.605, 0.968, 0.910),
    25: (0.497, 6.571, 6.765, 0.554, 0.479, 0.972, 0.880),
    26: (0.490, 12.303, 22.283, 0.562, 0.485, 0.972, 0.876),
    27: (None, 55.822, TO, 1.869, None, None, None),
    28: (0.260, 3.450, 24.414, 0.962, 0.707, 0.963, 0.909),
    29: (0.031, 0.0003, 0.0009, 6e-5, 0.974, 1.000, 1.000),
    30: (0.030, 0.001, 0.002, 8e-5, 0.975, 1.000, 1.000),
    31: (0.016, 0.002, 0.091, 1e-4, 0.986, 1.000, 1.000),
    32: (0.013, 0.0003, 0.0021, 3e-5, 0.989, 1.000, 1.000),
    33: (0.066, 0.010, 0.027, 0.004, 0.928, 1.000, 1.000),
    34: (0.065, 0.018, 0.053, 0.004, 0.940, 1.000, 1.000),
    35: (0.039, 0.170, 1.958, 0.010, 0.966, 1.000, 1.000),
    36: (0.015, 0.010, 0.099, 0.004, 0.983, 1.000, 1.000),
    37: (0.150, 0.740, 1.117, 0.200, 0.857, 1.000, 1.000),
    38: (0.150, 1.245, 2.043, 0.205, 0.851, 1.000, 1.000),
    39: (0.102, 39.257, 110.211, 0.828, 0.894, 1.000, 1.000),
    40: (0.021, 0.584, 6.822, 0.544, 0.975, 1.000, 1.000),
}
PAPER = {row: PaperRow(*values) for row, values in _VALUES.items()}
ROWS = tuple(sorted(PAPER))


@dataclasses.dataclass(frozen=True)
class RowSpec:
    """Which case study, at which size, with which abstraction class, a row is."""

    row: int
    system: str  # "unicycle_2d" | "unicycle_3d" | "temperature"
    kind: str
    parameter: str  # the size varied within the system's block of rows
    value: int

    @property
    def group(self) -> tuple:
        """Rows sharing partitions (the four classes of one configuration)."""
        return (self.system, self.value)


def row_spec(row: int) -> RowSpec:
    if row not in PAPER:
        raise ValueError(f"Table 1 has rows 1-40, got {row}")
    kind = KIND_ORDER[(row - 1) % 4]
    if row <= 16:
        return RowSpec(row, "unicycle_2d", kind, "cells", (30, 45, 60, 75)[(row - 1) // 4])
    if row <= 28:
        return RowSpec(row, "unicycle_3d", kind, "noise_cells", (6, 8, 10)[(row - 17) // 4])
    return RowSpec(row, "temperature", kind, "rooms", (2, 3, 4)[(row - 29) // 4])


def parse_rows(text: str) -> list[int]:
    """``"1-4,17,29-32"`` -> ``[1, 2, 3, 4, 17, 29, 30, 31, 32]`` (each checked against Table 1)."""
    rows = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            first, last = (int(p) for p in part.split("-"))
            if first > last:
                raise ValueError(f"empty row range {part!r}")
            rows.extend(range(first, last + 1))
        else:
            rows.append(int(part))
    for row in rows:
        row_spec(row)
    return sorted(set(rows))
