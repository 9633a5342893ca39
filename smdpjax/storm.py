r"""Storm's explicit DRN format for an IMDP abstraction, and Storm's robust value iteration on it.

``to_drn`` writes an ``IMDP`` as an interval MDP (``@type: MDP``, ``@value_type: double-interval``)
that Storm reads with ``stormpy.build_model_from_drn[stormpy.Interval](path)``; ``from_drn`` reads
such a file back into an ``IMDP``. The file of a 3-state example (cell 0 with two actions, the
reach cell 1, the sink 2)::

    // smdpjax upper_rest 0.0
    // written by smdpjax.storm.to_drn
    @type: MDP
    @value_type: double-interval
    @parameters

    @reward_models

    @nr_states
    3
    @nr_choices
    4
    @model
    state 0
    \taction 0
    \t\t0 : [0.25, 0.5]
    \t\t1 : [0.5, 0.75]
    \taction 1
    \t\t1 : [0.1, 1.0]
    \t\t2 : [0.0, 0.9]
    state 1 reach
    \taction 0
    \t\t1 : [1, 1]
    state 2 avoid
    \taction 0
    \t\t2 : [1, 1]

(``\t`` is a tab; Storm's parser wants exactly one space on each side of the colon.)

States keep their indices (grid cells ``0 .. N-1``, the sink ``N``). A non-terminal state has one
``action a`` block per action of the abstraction; reach states, avoid states and the sink are
absorbing (a ``[1, 1]`` self-loop) and carry the labels ``reach`` / ``avoid``, so that Storm's
``Pmax=? [ !"avoid" U<=K "reach" ]`` is the abstraction's K-step reach-avoid problem. Bounds are
written with ``repr`` (shortest decimal that reads back to the same float64), so the intervals
round-trip exactly. The bound ``upper_rest`` of the unlisted states (the remainder noise cell of
unbounded noise) is written out as an explicit ``[0, upper_rest]`` entry for every state not in
a row's list (rows become dense: fine for small models), and recorded in the leading comment
so that ``from_drn`` can fold those entries back into ``upper_rest``. Entries with upper bound 0
(no probability) are omitted.

The Storm helpers (``storm_model``, ``storm_values``) import ``stormpy`` (the ``storm`` extra)
only when called.
"""

from __future__ import annotations

import io
import os
import re

import jax.numpy as jnp
import numpy as np

from .abstraction.clusters import index_dtype
from .abstraction.imdp import IMDP
from .abstraction.imdp_compact import CompactIMDP
from .partition import AVOID, NONTERMINAL, REACH

__all__ = ["to_drn", "from_drn", "drn_string", "reach_avoid_formula", "storm_model", "storm_values"]

_REST_COMMENT = "// smdpjax upper_rest "


def _open(path_or_file, mode):
    if isinstance(path_or_file, (str, os.PathLike)):
        return open(path_or_file, mode, encoding="ascii"), True
    return path_or_file, False


def to_drn(imdp: IMDP, path_or_file, *, reach_label: str = "reach", avoid_label: str = "avoid") -> None:
    """Write ``imdp`` in Storm's explicit DRN format with interval probabilities.

    Args:
        imdp: an ``IMDP`` or ``CompactIMDP`` (what ``abstract(..., "imdp")`` returns; any number of
            actions, e.g. ``imdp.restrict(actions)`` for one).
        path_or_file: a path, or a text file object open for writing.
        reach_label, avoid_label: the state labels of reach states and of avoid states and the sink.
    """
    if isinstance(imdp, CompactIMDP):
        imdp = imdp.padded()
    if not isinstance(imdp, IMDP):
        raise TypeError(f"to_drn writes an IMDP, got {type(imdp).__name__}")
    for label in (reach_label, avoid_label):
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", label):
            raise ValueError(f"labels must be identifiers, got {label!r}")
    labels = np.asarray(imdp.labels)
    n = labels.shape[0]
    succ = np.asarray(imdp.successors).astype(np.int64)
    lower = np.asarray(imdp.lower, np.float64)
    upper = np.asarray(imdp.upper, np.float64)
    rest = float(imdp.upper_rest)
    rows = np.asarray(imdp.rows)
    if np.any(labels[rows] != NONTERMINAL):
        raise ValueError("rows of the IMDP must be non-terminal states")
    row_of = np.full(n, -1, np.int64)
    row_of[rows] = np.arange(rows.shape[0])
    num_actions = succ.shape[1]
    terminal = labels != NONTERMINAL
    unrowed = np.flatnonzero((~terminal) & (row_of < 0))
    if unrowed.size:
        raise ValueError(f"non-terminal states without a row: {unrowed[:5].tolist()}")

    prefix = [f"\t\t{j} : " for j in range(n)]
    dense_row = [f"{prefix[j]}[0, {rest!r}]\n" for j in range(n)] if rest > 0 else [""] * n
    label_names = {REACH: f" {reach_label}", AVOID: f" {avoid_label}", NONTERMINAL: ""}
    out, close = _open(path_or_file, "w")
    try:
        out.write(f"{_REST_COMMENT}{rest!r}\n// written by smdpjax.storm.to_drn\n@type: MDP\n"
                  f"@value_type: double-interval\n@parameters\n\n@reward_models\n\n@nr_states\n{n}\n"
                  f"@nr_choices\n{int(terminal.sum()) + rows.shape[0] * num_actions}\n@model\n")
        for s in range(n):
            out.write(f"state {s}{label_names[int(labels[s])]}\n")
            if terminal[s]:
                out.write(f"\taction 0\n{prefix[s]}[1, 1]\n")
                continue
            r = row_of[s]
            for a in range(num_actions):
                ids, lo, up = succ[r, a], lower[r, a], upper[r, a]
                keep = (ids < n) & (up > 0)
                order = np.argsort(ids[keep], kind="stable")
                ids, lo, up = ids[keep][order].tolist(), lo[keep][order].tolist(), up[keep][order].tolist()
                out.write(f"\taction {a}\n")
                entries = list(dense_row)  # rest > 0: every state is a possible successor
                for j, l, u in zip(ids, lo, up):
                    entries[j] = f"{prefix[j]}[{l!r}, {u!r}]\n"
                out.write("".join(entries))
    finally:
        if close:
            out.close()


_INTERVAL = re.compile(r"^\s*\[\s*([^,\]]+?)\s*,\s*([^\]]+?)\s*\]\s*$")


def _parse_value(text: str) -> tuple[float, float]:
    m = _INTERVAL.match(text)
    if m:
        return float(m.group(1)), float(m.group(2))
    value = float(text)
    return value, value


def from_drn(path_or_file, *, reach_label: str = "reach", avoid_label: str = "avoid") -> IMDP:
    """Read an interval MDP in DRN format (as written by ``to_drn``) into an ``IMDP``.

    States labelled ``reach_label`` are reach states, states labelled ``avoid_label`` avoid states
    (the last state is the sink, as in every smdpjax abstraction); their transitions are ignored
    (terminal states are absorbing). Every other state is a row. When the file records
    ``upper_rest > 0`` (the leading comment of ``to_drn``), every row must list every state, and
    the entries ``[0, upper_rest]`` become unlisted states again. Rows with fewer actions than the
    most are padded by repeating their last action (which changes no value).
    """
    inp, close = _open(path_or_file, "r")
    try:
        text = inp.read()
    finally:
        if close:
            inp.close()
    rest = 0.0
    n = None
    lines = text.splitlines()
    pos = 0
    value_type = None
    while pos < len(lines):
        line = lines[pos].strip()
        pos += 1
        if line.startswith(_REST_COMMENT.strip()):
            rest = float(line[len(_REST_COMMENT.strip()):])
        elif line.startswith("@type:"):
            if line.split(":", 1)[1].strip() != "MDP":
                raise ValueError(f"expected an MDP, got {line!r}")
        elif line.startswith("@value_type:"):
            value_type = line.split(":", 1)[1].strip()
        elif line == "@nr_states":
            n = int(lines[pos])
            pos += 1
        elif line == "@model":
            break
    if n is None:
        raise ValueError("no @nr_states before @model")
    if value_type not in (None, "double", "double-interval"):
        raise ValueError(f"unsupported value type {value_type!r}")

    labels = np.full(n, NONTERMINAL, np.int8)
    choices: list[list[dict]] = [[] for _ in range(n)]
    state = -1
    current = None
    for raw in lines[pos:]:
        line = raw.strip()
        if not line or line.startswith("//"):
            continue
        if line.startswith("state "):
            words = line.split()
            if int(words[1]) != state + 1:
                raise ValueError(f"states must be numbered 0, 1, ... in order; got {raw!r}")
            state += 1
            names = {w.strip('"') for w in words[2:]}
            if reach_label in names and avoid_label in names:
                raise ValueError(f"state {state} is labelled both {reach_label!r} and {avoid_label!r}")
            if reach_label in names:
                labels[state] = REACH
            elif avoid_label in names:
                labels[state] = AVOID
            current = None
        elif line.startswith("action"):
            if state < 0:
                raise ValueError(f"action before any state: {raw!r}")
            current = {}
            choices[state].append(current)
        else:
            target, _, value = line.partition(":")
            if current is None or not value:
                raise ValueError(f"unexpected line {raw!r}")
            j = int(target)
            if not 0 <= j < n:
                raise ValueError(f"successor {j} out of range in {raw!r}")
            current[j] = _parse_value(value)
    if state != n - 1:
        raise ValueError(f"@nr_states is {n} but the model has {state + 1} states")
    if labels[n - 1] != AVOID:
        raise ValueError(f"the last state (the sink) must be labelled {avoid_label!r}")

    rows = np.flatnonzero(labels == NONTERMINAL)
    lists = []
    for s in rows:
        if not choices[s]:
            raise ValueError(f"non-terminal state {s} has no action")
        acts = []
        for entries in choices[s]:
            if rest > 0:
                if len(entries) != n:
                    raise ValueError(f"upper_rest = {rest} > 0 but state {s} does not list every state")
                entries = {j: b for j, b in entries.items() if b != (0.0, rest)}
            acts.append(sorted(entries.items()))
        lists.append(acts)
    num_actions = max(len(a) for a in lists) if lists else 1
    width = max([len(e) for acts in lists for e in acts] + [1])
    r_count = rows.shape[0]
    succ = np.full((r_count, num_actions, width), n, np.int64)
    lower = np.zeros((r_count, num_actions, width))
    upper = np.zeros((r_count, num_actions, width))
    for r, acts in enumerate(lists):
        acts = acts + [acts[-1]] * (num_actions - len(acts))
        for a, entries in enumerate(acts):
            for k, (j, (lo, up)) in enumerate(entries):
                succ[r, a, k], lower[r, a, k], upper[r, a, k] = j, lo, up
    return IMDP(successors=jnp.asarray(succ, index_dtype(n)), lower=jnp.asarray(lower),
                upper=jnp.asarray(upper), upper_rest=jnp.asarray(rest, jnp.float64),
                rows=jnp.asarray(rows, jnp.int32), labels=jnp.asarray(labels))


def reach_avoid_formula(horizon: int | None, *, reach_label: str = "reach", avoid_label: str = "avoid") -> str:
    """PCTL for the reach-avoid probability: bounded until ``U<=K`` (or unbounded for ``None``)."""
    bound = "" if horizon is None else f"<={int(horizon)}"
    return f'Pmax=? [ !"{avoid_label}" U{bound} "{reach_label}" ]'


def storm_model(path):
    """Storm's sparse interval MDP built from a DRN file (needs ``stormpy``)."""
    import stormpy

    return stormpy.build_model_from_drn[stormpy.Interval](str(path))


def storm_values(model, horizon: int | None, *, cooperative: bool = False, reach_label: str = "reach",
                 avoid_label: str = "avoid") -> np.ndarray:
    """Storm's robust (``cooperative=False``: the adversary minimizes) or cooperative value of
    ``Pmax=? [ !"avoid" U<=K "reach" ]`` at every state, ``(num_states,)`` (needs ``stormpy``).

    ``model``: a Storm interval model (``storm_model``) or a DRN path. Storm refuses the unbounded
    until on intervals of the form ``[0, u]``; the bounded one (``horizon=K``) accepts them.
    """
    import stormpy

    if isinstance(model, (str, os.PathLike)):
        model = storm_model(model)
    prop = stormpy.parse_properties(reach_avoid_formula(horizon, reach_label=reach_label, avoid_label=avoid_label))[0]
    mode = stormpy.UncertaintyResolutionMode.COOPERATIVE if cooperative else stormpy.UncertaintyResolutionMode.ROBUST
    result = stormpy.model_checking(model, prop, only_initial_states=False, uncertainty_resolution_mode=mode)
    return np.asarray(result.get_value_vector(), np.float64)


def drn_string(imdp: IMDP, **labels) -> str:
    """``to_drn`` into a string (small models, tests)."""
    buffer = io.StringIO()
    to_drn(imdp, buffer, **labels)
    return buffer.getvalue()
