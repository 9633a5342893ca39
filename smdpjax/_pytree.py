"""Immutable dataclasses that are JAX PyTrees.

Array fields are PyTree leaves (they move through ``jit``/``vmap``); fields declared with
``static_field()`` are treated as hashable metadata (shapes, flags, names).
"""

from __future__ import annotations

import dataclasses

import jax


def static_field(**kwargs):
    """A dataclass field that is PyTree metadata instead of a leaf."""
    metadata = dict(kwargs.pop("metadata", {}))
    metadata["static"] = True
    return dataclasses.field(metadata=metadata, **kwargs)


def pytree_dataclass(cls):
    """Freeze ``cls`` as a dataclass and register it as a PyTree."""
    cls = dataclasses.dataclass(frozen=True)(cls)  # keeps a __repr__ the class defines itself
    fields = dataclasses.fields(cls)
    data = [f.name for f in fields if not f.metadata.get("static", False)]
    meta = [f.name for f in fields if f.metadata.get("static", False)]
    jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)
    return cls
