"""Temporal logic on the 2-D unicycle: visit A, then B, avoiding the obstacles.

The system and noise are case study 1's (``unicycle_2d``); the grid carries no reach/avoid boxes
(every cell is a row of the abstraction) and the regions belong to the specifications:

* ``A`` (top left) and ``B`` (bottom right), closed boxes to visit;
* ``O``, the two obstacles of case study 1 (open boxes);
* ``C``, the passage above the first obstacle (closed box).

Two specifications over them (acceptance ``"reach"``: the mission ends when the DFA accepts):

* ``"sequence"``: ``F(a & F b) & G !o`` -- A then B, never an obstacle (4 DFA states);
* ``"never_after"``: ``F(a & F b) & G !o & G(a -> G !c)`` -- and, once A was visited, never the
  passage C: the robot has to go round the first obstacle's bottom (4 DFA states).

Both DFAs are written out by hand (``dfa``), so no LTLf translator is needed; with one installed,
``Specification.ltlf(FORMULAS[name], REGIONS)`` gives the same automata (tests check it).
"""

from __future__ import annotations

import numpy as np

from ..noise import Gaussian
from ..partition import NoiseGrid, StateGrid
from ..specification import DFA, Region, Specification
from ..system import System
from .unicycle_2d import dynamics

OBSTACLES = [([0.40, 0.30], [0.60, 0.70]), ([0.75, 0.50], [0.90, 0.65])]
REGIONS = {"a": Region([([0.1, 0.7], [0.3, 0.9])]), "b": Region([([0.7, 0.1], [0.9, 0.3])]),
           "c": Region([([0.4, 0.7], [0.6, 1.0])]), "o": Region(OBSTACLES, closed=False)}
FORMULAS = {"sequence": "F(a & F(b)) & G(!o)", "never_after": "F(a & F(b)) & G(!o) & G(a -> G(!c))"}


def dfa(name: str) -> DFA:
    """The DFA of ``FORMULAS[name]`` (co-safe reading: the run stops at acceptance)."""
    if name == "sequence":
        return DFA(["start", "seen_a", "done", "fail"], ["a", "b", "o"],
                   {"start": {"o": "fail", "a & b & !o": "done", "a & !b & !o": "seen_a", "!a & !o": "start"},
                    "seen_a": {"o": "fail", "b & !o": "done", "!b & !o": "seen_a"},
                    "done": {"true": "done"}, "fail": {"true": "fail"}}, "start", ["done"])
    if name == "never_after":
        return DFA(["start", "seen_a", "done", "fail"], ["a", "b", "c", "o"],
                   {"start": {"o | (a & c)": "fail", "a & b & !c & !o": "done", "a & !b & !c & !o": "seen_a",
                              "!a & !o": "start"},
                    "seen_a": {"o | c": "fail", "b & !c & !o": "done", "!b & !c & !o": "seen_a"},
                    "done": {"true": "done"}, "fail": {"true": "fail"}}, "start", ["done"])
    raise ValueError(f"unknown specification {name!r}; expected one of {sorted(FORMULAS)}")


def unicycle_2d_dfa(cells: int = 30, noise_cells: int = 12, spec: str = "sequence"):
    """``(system, grid, noise_grid, specification)``: case study 1 on a ``cells`` x ``cells``
    grid without reach/avoid boxes, and the specification ``spec`` (module docstring)."""
    system = System(dynamics, actions=(np.arange(8) * np.pi / 4)[:, None], noise=Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = StateGrid([0, 0], [1, 1], cells)
    noise = NoiseGrid.ball([0.0, 0.0], 2.1, noise_cells)
    automaton = dfa(spec)
    regions = {p: REGIONS[p] for p in automaton.propositions}
    return system, grid, noise, Specification(automaton, regions, name=FORMULAS[spec])
