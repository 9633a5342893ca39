"""The paper's evaluation metrics (Section 7): e_avg, p_low/p_up averages, memory, wall times."""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from .partition import NONTERMINAL, StateGrid


def average_error(solution, grid: StateGrid) -> float:
    """e_avg: mean of p_up - p_low over the non-terminal safe cells S_nt."""
    nt = grid.labels == NONTERMINAL
    gap = np.asarray(solution.upper)[:-1] - np.asarray(solution.lower)[:-1]
    return float(gap[nt].mean())


def average_bounds(solution, cells) -> tuple[float, float]:
    """(p_low_avg, p_up_avg) over the initial cells S_0 (flat indices)."""
    cells = np.asarray(cells)
    return float(np.asarray(solution.lower)[cells].mean()), float(np.asarray(solution.upper)[cells].mean())


def memory_bytes(abstraction) -> int:
    """Bytes of the arrays that store the abstraction (its PyTree leaves). The MI-MDP's host-side
    LP data (``abstraction.lps.data_nbytes``) and solver state are a solver's workspace and not
    included."""
    return abstraction.nbytes


def initial_cells(grid: StateGrid, count: int, seed: int = 0) -> np.ndarray:
    """``count`` cells drawn uniformly without replacement from S_nt (the paper's S_0)."""
    nt = grid.nonterminal
    if count > nt.size:
        raise ValueError(f"asked for {count} initial cells but S_nt has only {nt.size}")
    return np.sort(np.random.default_rng(seed).choice(nt, size=count, replace=False))


@dataclasses.dataclass
class Stopwatch:
    """Wall time of a block, waiting for JAX's asynchronous work: ``with Stopwatch() as sw: ...``.

    Assign the block's result to ``sw.result`` (or call ``sw.block(x)``) so the clock stops only
    once the arrays are ready.
    """

    seconds: float = float("nan")
    result: object = None

    def block(self, value):
        self.result = value
        return value

    def __enter__(self):
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        if self.result is not None:
            jax.block_until_ready(self.result)
        self.seconds = time.perf_counter() - self._start
        return False
