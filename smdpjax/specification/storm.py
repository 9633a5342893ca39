"""The product IMDP of an IMDP abstraction and a DFA specification, in Storm's DRN format.

The product of an interval MDP and a DFA is an interval MDP: state (q, s) under action a moves
to (delta(q, L(s')), s') with the interval of s' (distinct s' give distinct product states, so the
intervals carry over unchanged). ``product_drn`` writes it with the states numbered as the
product values (``q (N+1) + s``): accepted pairs are labelled ``reach``, traps, the sink column
and pairs no run can occupy ``avoid`` (all absorbing), so Storm's
``Pmax=? [ !"avoid" U<=K "reach" ]`` (``smdpjax.storm.storm_values``) is the K-step value of the
specification (acceptance ``"reach"``) at every product state, the cross-check of
``synthesize_product``'s finite-horizon bounds.

The IMDP is read through its own DRN text (``smdpjax.storm.drn_string``), so this module does not
depend on how an IMDP stores its bounds. Each product row lists every successor the base row
lists (rows are dense when the noise has a remainder cell): for small models.
"""

from __future__ import annotations

import io
import os

import numpy as np

from ..partition import AVOID, NONTERMINAL, REACH
from .specification import as_grid_specification

__all__ = ["product_drn", "product_drn_string", "read_drn_rows"]


def read_drn_rows(text: str) -> tuple[int, dict]:
    """``(number of states, {state: [[(target, "interval text"), ...] per action]})`` of the
    non-absorbing states of a DRN model written by ``smdpjax.storm.to_drn``."""
    lines = text.splitlines()
    n = int(lines[lines.index("@nr_states") + 1])
    body = lines[lines.index("@model") + 1:]
    rows, state, labels = {}, -1, {}
    for raw in body:
        line = raw.strip()
        if not line or line.startswith("//"):
            continue
        if line.startswith("state "):
            words = line.split()
            state = int(words[1])
            labels[state] = words[2:]
            rows[state] = []
        elif line.startswith("action"):
            rows[state].append([])
        else:
            target, _, value = line.partition(":")
            rows[state][-1].append((int(target), value.strip()))
    moving = {s: acts for s, acts in rows.items() if not labels[s]}
    return n, moving


def product_drn(imdp, specification, path_or_file) -> None:
    """Write the product IMDP of ``imdp`` (an IMDP abstraction, e.g. ``imdp.restrict(actions)``,
    on the specification's grid) and ``specification`` (a ``GridSpecification`` with acceptance
    ``"reach"`` and no cell with several possible letters) in DRN format."""
    from ..storm import drn_string

    spec = as_grid_specification(specification)
    if spec.acceptance != "reach":
        raise ValueError("the product DRN encodes acceptance 'reach' (Pmax [ !avoid U reach ])")
    if np.any(spec.labelling.count > 1):
        raise ValueError(f"{int(np.sum(spec.labelling.count > 1))} cells have several possible letters: the product "
                         f"is not an interval MDP there (the adversary picks the letter)")
    tables = spec.tables(np.asarray(imdp.rows))
    n_base, base_rows = read_drn_rows(drn_string(imdp))
    size = spec.grid.num_states
    if n_base != size:
        raise ValueError(f"the IMDP has {n_base} states, the specification's grid {size}")
    labels = np.asarray(tables.labels)
    rows = np.asarray(tables.rows)
    live = np.asarray(tables.live)
    delta_of = np.asarray(spec.dfa.table)[:, spec.labelling.letters[:, 0]]  # (Q, N) next DFA state per cell
    num_choices = int(np.sum(labels != NONTERMINAL)) + sum(len(base_rows[r % size]) for r in rows)
    names = {REACH: " reach", AVOID: " avoid", NONTERMINAL: ""}
    out, close = (open(path_or_file, "w", encoding="ascii"), True) if isinstance(path_or_file, (str, os.PathLike)) \
        else (path_or_file, False)
    try:
        out.write(f"// product of a DFA with {spec.num_dfa_states} states and an IMDP with {size} states\n"
                  f"// written by smdpjax.specification.storm.product_drn\n@type: MDP\n"
                  f"@value_type: double-interval\n@parameters\n\n@reward_models\n\n@nr_states\n{labels.size}\n"
                  f"@nr_choices\n{num_choices}\n@model\n")
        is_row = labels == NONTERMINAL
        for p in range(labels.size):  # a writer of a text file: one line per entry
            out.write(f"state {p}{names[int(labels[p])]}\n")
            if not is_row[p]:
                out.write(f"\taction 0\n\t\t{p} : [1, 1]\n")
                continue
            q, s = divmod(p, size)
            for a, entries in enumerate(base_rows[s]):
                out.write(f"\taction {a}\n")
                targets = [(int(delta_of[q, t]) * size + t if t < size - 1 else q * size + t, value)
                           for t, value in entries]
                for t, value in sorted(targets):
                    out.write(f"\t\t{t} : {value}\n")
    finally:
        if close:
            out.close()


def product_drn_string(imdp, specification) -> str:
    """``product_drn`` into a string."""
    buffer = io.StringIO()
    product_drn(imdp, specification, buffer)
    return buffer.getvalue()
