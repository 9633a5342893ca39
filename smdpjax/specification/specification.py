"""Specifications: a DFA over labelled regions, and how it becomes a probability.

``Specification(dfa, regions, acceptance)`` binds each atomic proposition of the DFA to a region
of the state space. ``spec.on(grid)`` checks it against a grid and computes every cell's
possible letters (``GridSpecification``); do it before abstracting: every bad input (a
proposition without a region, a region outside the grid, ...) is reported there, before any
reachable set is computed.

**What is guaranteed.** Along a closed-loop trajectory ``x_0, x_1, ...`` the DFA reads the letters
``L(x_0), L(x_1), ...`` of the true states (``DFA``'s convention). With ``acceptance="reach"``
(default) the trajectory **satisfies** the specification when the DFA reaches an accepting state
(within ``horizon`` steps, or eventually for ``horizon=None``) while the trajectory has stayed in
the grid box: the finite trace up to then is accepted (a "good prefix"; the mission is then
complete). For a co-safe formula (every accepting state absorbing: ``F``, ``U``, sequences) this
is exactly the formula on the trajectory. With ``acceptance="final"`` (finite horizon T only)
it satisfies the specification when the whole trace ``x_0 .. x_T`` is accepted (LTLf's own
semantics on a trace of T + 1 states) and never left the grid box: the semantics of safety
(``G safe``). In both, leaving the grid box is a failure (the sink), as in the built-in
reach-avoid problem.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping, Sequence

import numpy as np

from ..partition import StateGrid
from .dfa import DFA
from .regions import FACES, Labelling, Region, as_regions, labelling, point_letters
from .tables import ProductTables, build_tables

ACCEPTANCE = ("reach", "final")


@dataclasses.dataclass(frozen=True, eq=False)
class Specification:
    """A DFA and the region of each of its propositions.

    Args:
        dfa: the ``DFA``.
        regions: ``{proposition: Region | [(low, high), ...]}`` (plain boxes are closed); every
            proposition of the DFA needs one (extra entries are ignored).
        acceptance: ``"reach"`` (satisfied once the DFA accepts) or ``"final"`` (the trace of
            exactly ``horizon`` steps must be accepted); see the module docstring.
        name: a label for printing.
        faces: how a cell that shares only a face with a region is labelled.
            ``"exact"`` (default): with every letter its points carry (the face's too), the worst
            for p_low and the best for p_up: sound for both bounds at every point, whatever the
            next state's distribution. ``"interior"``: with the letter of its interior, as the
            built-in reach-avoid problem labels cells (``StateGrid``): exact for p_low where the
            regions that help are closed and those that hurt are open (as in ``reach_avoid``),
            and for p_up up to next states that land on a face with positive probability (never,
            when the next state has a density). Cells that lie partly inside a region (in a set
            of positive volume) are labelled conservatively in both modes, with a warning.
    """

    dfa: DFA
    regions: dict
    acceptance: str = "reach"
    name: str = ""
    faces: str = "exact"

    def __post_init__(self):
        if not isinstance(self.dfa, DFA):
            raise TypeError(f"dfa must be a smdpjax.specification.DFA, got {type(self.dfa).__name__}")
        regions = as_regions(self.regions)
        missing = [p for p in self.dfa.propositions if p not in regions]
        if missing:
            raise ValueError(f"propositions {missing} have no region (regions are given for {sorted(regions)})")
        used = {p: regions[p] for p in self.dfa.propositions}
        dims = {r.n for r in used.values()}
        if len(dims) > 1:
            raise ValueError(f"the regions have boxes of different dimensions {sorted(dims)}")
        if self.acceptance not in ACCEPTANCE:
            raise ValueError(f"acceptance must be one of {ACCEPTANCE}, got {self.acceptance!r}")
        if self.faces not in FACES:
            raise ValueError(f"faces must be one of {FACES}, got {self.faces!r}")
        object.__setattr__(self, "regions", used)

    @classmethod
    def ltlf(cls, formula: str, regions: Mapping, *, acceptance: str = "reach", backend: str = "auto",
             name: str | None = None, faces: str = "exact") -> "Specification":
        """The specification of an LTLf formula over the propositions of ``regions`` (translated
        by ``ltlf.ltlf_to_dfa``; needs the ``ltlf`` extra). Propositions of the formula without a
        region are an error, as is a formula that does not parse."""
        from .ltlf import ltlf_to_dfa

        regions = as_regions(regions)
        dfa = ltlf_to_dfa(formula, sorted(regions), backend=backend)
        return cls(dfa, regions, acceptance, name=formula if name is None else name, faces=faces)

    @property
    def propositions(self) -> tuple[str, ...]:
        return self.dfa.propositions

    def on(self, grid: StateGrid, *, warn: bool = True) -> "GridSpecification":
        """Check against ``grid`` and label its cells (cheap; before any abstraction work).

        ``warn``: warn with the number of cells that lie partly inside a region (labelled
        conservatively, ``regions``)."""
        if not isinstance(grid, StateGrid):
            raise TypeError(f"grid must be a smdpjax.StateGrid, got {type(grid).__name__}")
        labels = labelling(grid, self.regions, self.dfa.propositions, faces=self.faces, warn=warn)
        return GridSpecification(self, grid, labels)

    def __repr__(self):
        name = f"{self.name!r}, " if self.name else ""
        return f"Specification({name}{self.dfa!r}, acceptance={self.acceptance!r})"


@dataclasses.dataclass(frozen=True, eq=False)
class GridSpecification:
    """A ``Specification`` on a grid: every cell's possible letters (``labelling``).

    Build it with ``Specification.on(grid)``. ``tables(rows)`` gives the product tables of an
    abstraction with those rows (``synthesis.product``).
    """

    specification: Specification
    grid: StateGrid
    labelling: Labelling

    @property
    def dfa(self) -> DFA:
        return self.specification.dfa

    @property
    def acceptance(self) -> str:
        return self.specification.acceptance

    @property
    def num_dfa_states(self) -> int:
        return self.dfa.num_states

    @property
    def mixed_cells(self) -> np.ndarray:
        """Flat indices of the cells that lie partly inside a region (labelled conservatively)."""
        return np.flatnonzero(self.labelling.mixed)

    @functools.lru_cache(maxsize=8)  # noqa: B019  (keyed by the rows' bytes; the object is immutable)
    def _tables(self, rows_bytes: bytes) -> ProductTables:
        rows = np.frombuffer(rows_bytes, np.int64)
        return build_tables(self.dfa, self.labelling.letters, rows, self.acceptance)

    def tables(self, rows) -> ProductTables:
        """``ProductTables`` for an abstraction whose rows are ``rows`` (``(R,)`` cell indices)."""
        rows = np.asarray(rows, np.int64).reshape(-1)
        if rows.size and (rows.min() < 0 or rows.max() >= self.grid.num_cells):
            raise ValueError(f"rows must be cells of the grid (0 .. {self.grid.num_cells - 1})")
        return self._tables(rows.tobytes())

    def start_states(self, cells) -> np.ndarray:
        """Product indices ``(k,)`` of trajectories starting in the given cells (one letter each).

        For differentiable and swept guarantees (``gradients.mean_lower`` over these indices).
        A cell that lies partly inside a region has several possible start states: ValueError.
        """
        cells = np.asarray(cells, np.int64).reshape(-1)
        if np.any(self.labelling.count[cells] > 1):
            bad = cells[self.labelling.count[cells] > 1]
            raise ValueError(f"cells {bad[:5].tolist()} lie partly inside a region: their start state is not "
                             f"unique; pick cells inside or outside every region")
        first = self.labelling.letters[cells, 0]
        return self.dfa.table[self.dfa.initial_index, first] * self.grid.num_states + cells

    def point_letters(self, x):
        """``(...)`` int32 letters of points ``x: (..., n)`` (their true regions); jittable."""
        regions = [self.specification.regions[p] for p in self.dfa.propositions]
        return point_letters(regions, self.grid.wrap(x))

    def __repr__(self):
        mixed = int(self.labelling.mixed.sum())
        return (f"GridSpecification({self.specification!r} on {self.grid.num_cells} cells, "
                f"{mixed} mixed cell(s))")


# -- ready-made specifications -------------------------------------------------------------------

def reach_avoid_dfa() -> DFA:
    """The 3-state DFA of reach-avoid over propositions ``reach`` and ``avoid``: ``run`` until
    ``reach`` (accepting ``goal``) or ``avoid`` (trap ``fail``); avoiding wins a tie."""
    return DFA(["run", "goal", "fail"], ["reach", "avoid"],
               {"run": {"avoid": "fail", "reach & !avoid": "goal", "!reach & !avoid": "run"},
                "goal": {"true": "goal"}, "fail": {"true": "fail"}},
               initial="run", accepting=["goal"])


def reach_avoid(reach: Sequence, avoid: Sequence = (), *, faces: str = "interior") -> Specification:
    """Reach-avoid as a DFA specification: reach the closed ``reach`` boxes before the open
    ``avoid`` boxes, labelled as ``StateGrid`` labels them (``faces="interior"``): it gives the
    built-in reach-avoid problem's values and strategy (to rounding; the tests check 1e-12)."""
    boxes = list(avoid)
    regions = {"reach": Region(reach, closed=True)}
    if boxes:
        regions["avoid"] = Region(boxes, closed=False)
    else:  # an empty obstacle: a degenerate box that no cell meets is not allowed; drop the proposition
        return Specification(DFA(["run", "goal"], ["reach"], {"run": {"reach": "goal", "!reach": "run"},
                                                               "goal": {"true": "goal"}}, "run", ["goal"]),
                             regions, "reach", name="reach", faces=faces)
    return Specification(reach_avoid_dfa(), regions, "reach", name="reach-avoid", faces=faces)


def reach_avoid_of(grid: StateGrid, *, faces: str = "interior") -> Specification:
    """``reach_avoid`` with the reach and avoid boxes of ``grid`` (built-in reach-avoid as a DFA)."""
    r_lo, r_hi = grid.reach_boxes
    a_lo, a_hi = grid.avoid_boxes
    if r_lo.shape[0] == 0:
        raise ValueError("the grid has no reach box")
    return reach_avoid(list(zip(r_lo, r_hi)), list(zip(a_lo, a_hi)), faces=faces)


def safety(avoid: Sequence, *, faces: str = "interior") -> Specification:
    """Safety as a DFA specification: stay out of the open ``avoid`` boxes (and in the grid box)
    for the whole horizon (``acceptance="final"``, so it needs a finite horizon); the built-in
    ``objective="safety"`` on a grid without reach boxes."""
    dfa = DFA(["safe", "fail"], ["avoid"], {"safe": {"avoid": "fail", "!avoid": "safe"}, "fail": {"true": "fail"}},
              initial="safe", accepting=["safe"])
    return Specification(dfa, {"avoid": Region(avoid, closed=False)}, "final", name="safety", faces=faces)


def sequence(regions: Mapping, avoid: Sequence = (), *, faces: str = "interior") -> Specification:
    """Visit the regions in the given order, never entering the open ``avoid`` boxes before the
    last one is reached: ``!avoid U (a & (!avoid U b))`` for ``{"a": ..., "b": ...}``, the
    co-safe reading of ``F(a & F b) & G !avoid``. A DFA of ``len(regions) + 2`` states (one per
    stage, the goal, the failure), no translator needed.

    Args:
        regions: ``{name: Region | boxes}`` in the order of the visits (names are propositions).
        avoid: open obstacle boxes (the proposition ``avoid``); none by default.
        faces: as in ``Specification``; ``"interior"`` is exact for p_low here when the regions
            to visit are closed (plain boxes are) and the obstacles open.
    """
    regions = as_regions(regions)
    names = list(regions)
    if not names:
        raise ValueError("sequence needs at least one region")
    if "avoid" in regions:
        raise ValueError("'avoid' is the obstacles' proposition; name the regions to visit otherwise")
    boxes = list(avoid)
    props = names + (["avoid"] if boxes else [])
    bad = "avoid" if boxes else "false"
    stages = [f"visit_{r}" for r in names]
    states = stages + ["done", "fail"]
    transitions = {"done": {"true": "done"}, "fail": {"true": "fail"}}
    for k, (stage, target) in enumerate(zip(stages, names)):
        transitions[stage] = [(bad, "fail"), (f"{target} & !{bad}", states[k + 1]), (f"!{target} & !{bad}", stage)]
    dfa = DFA(states, props, transitions, stages[0], ["done"])
    all_regions = dict(regions)
    if boxes:
        all_regions["avoid"] = Region(boxes, closed=False)
    return Specification(dfa, all_regions, "reach", name=" then ".join(names), faces=faces)


def as_grid_specification(spec, grid: StateGrid | None = None) -> GridSpecification:
    """``spec`` if it already is a ``GridSpecification``, else ``spec.on(grid)``."""
    if isinstance(spec, GridSpecification):
        return spec
    if isinstance(spec, Specification):
        if grid is None:
            raise ValueError("a Specification must be put on a grid first: spec.on(grid)")
        return spec.on(grid)
    raise TypeError(f"expected a Specification or GridSpecification, got {type(spec).__name__}")


__all__ = ["Specification", "GridSpecification", "reach_avoid", "reach_avoid_of", "reach_avoid_dfa", "safety",
           "sequence", "ACCEPTANCE"]

