"""Temporal-logic specifications over labelled regions: DFAs, LTLf formulas (optional
translator), and the ready-made reach-avoid, safety and sequence specifications.

* ``Region``: a union of closed (or open) boxes, the set where an atomic proposition holds.
* ``DFA``: a complete deterministic automaton over the letters ``2^propositions``.
* ``Specification(dfa, regions, acceptance)``; ``Specification.ltlf(formula, regions)``.
* ``spec.on(grid)``: the possible letters of every cell (``GridSpecification``), checked before
  any abstraction work.

Synthesis on the product: ``smdpjax.synthesize_product``; closed loop:
``smdpjax.specification.ProductController`` and ``simulate_product``.
"""

from .dfa import DFA
from .ltlf import available_backends, ltlf_to_dfa
from .regions import Labelling, Region, labelling
from .simulation import ProductController, ProductSimulationResult, simulate_product
from .specification import (ACCEPTANCE, GridSpecification, Specification, reach_avoid, reach_avoid_dfa,
                            reach_avoid_of, safety, sequence)
from .tables import ProductTables, build_tables

__all__ = ["DFA", "Region", "Labelling", "labelling", "Specification", "GridSpecification", "ACCEPTANCE",
           "reach_avoid", "reach_avoid_of", "reach_avoid_dfa", "safety", "sequence", "ltlf_to_dfa",
           "available_backends", "ProductTables", "build_tables", "ProductController", "ProductSimulationResult",
           "simulate_product"]
