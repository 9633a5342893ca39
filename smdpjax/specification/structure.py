"""Gradients and sweeps for DFA specifications: a frozen cluster structure with product tables.

``ProductStructure(structure, tables)`` behaves as a ``gradients.ClusterStructure`` whose
``abstraction(prob, prob_rest, kind)`` is the product abstraction (``synthesis.product``) of the
structure's SMDP or IMDP with the specification. So ``gradients.guarantee``,
``gradients.robust_lower`` (the frozen-structure adjoint, here over the product values) and
``sweep.batched_synthesis`` take it unchanged; ``sweep.sweep(..., specification=spec)`` builds it
per structure.
"""

from __future__ import annotations

import hashlib

import numpy as np

from .._pytree import pytree_dataclass, static_field
from ..gradients import ClusterStructure
from .specification import GridSpecification
from .tables import ProductTables


@pytree_dataclass
class ProductStructure:
    """A ``ClusterStructure`` and the product tables of a specification for its rows.

    Attributes:
        structure: the frozen clusters (computed on a grid without reach/avoid boxes).
        tables: ``ProductTables`` for ``structure.rows``.
        batching: ``"vmap"``, ``"map"`` or ``None`` (``ProductAbstraction``).
    """

    structure: ClusterStructure
    tables: ProductTables
    batching: str | None = static_field(default=None)

    @classmethod
    def of(cls, structure: ClusterStructure, specification: GridSpecification,
           batching: str | None = None) -> "ProductStructure":
        """The product structure of ``structure`` (concrete) with ``specification``."""
        if not isinstance(specification, GridSpecification):
            raise TypeError("specification must be a GridSpecification (spec.on(grid))")
        if int(structure.labels.shape[0]) != specification.grid.num_states:
            raise ValueError(f"the structure has {int(structure.labels.shape[0])} states, the specification's grid "
                             f"{specification.grid.num_states}")
        return cls(structure=structure, tables=specification.tables(np.asarray(structure.rows)), batching=batching)

    def abstraction(self, prob, prob_rest, kind: str = "smdp"):
        """The product of the structure's ``kind`` abstraction under ``prob``, ``prob_rest``
        with the specification (differentiable and vmappable in the probabilities)."""
        from ..synthesis.product import ProductAbstraction

        return ProductAbstraction.of(self.structure.abstraction(prob, prob_rest, kind), self.tables, self.batching)

    @property
    def members(self):
        return self.structure.members

    @property
    def labels(self):
        """The product states' labels ``(P,)``."""
        return self.tables.labels

    @property
    def num_bounded(self) -> int:
        return self.structure.num_bounded

    def fingerprint(self) -> str:
        h = hashlib.sha1(self.structure.fingerprint().encode())
        h.update(self.tables.fingerprint())
        return h.hexdigest()

    def __repr__(self):
        return f"ProductStructure({self.structure!r}, |Q|={self.tables.num_dfa_states}, live={len(self.tables.live)})"
