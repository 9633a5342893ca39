"""Refusing work that will not fit in memory, before allocating it.

Every stage that allocates in proportion to the problem size (the grid's per-cell arrays, the
clusters of every (cell, action, noise cell)) first estimates what it needs and compares it with
the memory the machine has available. An estimate above ``FRACTION`` of it raises
`InsufficientMemoryError` naming the estimate, the memory available and what to change,
instead of an allocation failure (or the kernel's OOM killer) minutes later.
"""

from __future__ import annotations

import os

# The share of the available memory one stage may plan to use (the rest: Python, XLA, its
# temporaries and whatever else runs).
FRACTION = 0.8


class InsufficientMemoryError(MemoryError):
    """An estimated allocation exceeds the memory available (raised before allocating)."""


def available_bytes() -> int | None:
    """Memory available to a new allocation: ``MemAvailable`` of /proc/meminfo (Linux), else the
    physical memory (``os.sysconf``), else None (unknown: nothing is refused)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def format_bytes(n: float) -> str:
    """``1.5 GiB``-style size."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"  # pragma: no cover


def require(nbytes: float, what: str, advice: str) -> None:
    """Raise `InsufficientMemoryError` if ``nbytes`` exceeds ``FRACTION`` of the available memory.

    Args:
        nbytes: the estimated peak of the stage.
        what: what would be allocated (``"the state grid's per-cell arrays (8.0e9 cells)"``).
        advice: what to change to make it fit.
    """
    available = available_bytes()
    if available is None or nbytes <= FRACTION * available:
        return
    raise InsufficientMemoryError(f"{what} would need about {format_bytes(nbytes)}, but only "
                                  f"{format_bytes(available)} of memory is available; {advice}")
