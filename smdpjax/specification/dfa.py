"""Deterministic finite automata over sets of atomic propositions.

A ``DFA`` reads one *letter* per time step: the set of propositions that hold at the current
state of the system. Letters are bitmasks over ``propositions`` (bit ``i`` set when
``propositions[i]`` holds), so the transition function is a table ``(Q, 2^P)``.

The run on a trajectory ``x_0, x_1, ...`` starts in ``initial`` and reads ``L(x_0)`` first:
``q_0 = delta(initial, L(x_0))``, ``q_{t+1} = delta(q_t, L(x_{t+1}))`` (the convention of
ltlf2dfa and flloat, whose DFAs accept a finite trace iff the run that read all of it ends in an
accepting state).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping, Sequence

import numpy as np

from . import guards as _guards

# 2^P letters per state are enumerated; beyond this many propositions the table is too large.
MAX_PROPOSITIONS = 16
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _check_propositions(propositions) -> tuple[str, ...]:
    if isinstance(propositions, str):
        propositions = (propositions,)
    props = tuple(str(p) for p in propositions)
    if not props:
        raise ValueError("the alphabet is empty: a DFA needs at least one atomic proposition")
    bad = [p for p in props if not _NAME.fullmatch(p) or p.lower() in ("true", "false")]
    if bad:
        raise ValueError(f"proposition names must be identifiers other than true/false, got {bad}")
    if len(set(props)) != len(props):
        raise ValueError(f"propositions must be distinct, got {list(props)}")
    if len(props) > MAX_PROPOSITIONS:
        raise ValueError(f"at most {MAX_PROPOSITIONS} propositions (2^P letters are enumerated), got {len(props)}")
    return props


@dataclasses.dataclass(frozen=True, eq=False)
class DFA:
    """A complete deterministic automaton over the letters ``2^propositions``.

    Args:
        states: the state names (distinct; any hashables, kept as given).
        propositions: the atomic propositions (identifiers), the alphabet ``2^P``; not empty.
        transitions: for every state, its outgoing transitions: a mapping ``{guard: next}`` or a
            sequence of ``(guard, next)`` pairs. A guard is a Boolean formula over the
            propositions (``"a & !b"``, ``"(a | b) & ~c"``, ``"true"``; see ``guards``), a
            ``set``/``frozenset`` of propositions (exactly that letter) or ``True``. Every
            letter must be covered by exactly one target per state (overlapping guards with
            the same target are fine).
        initial: the initial state (reads the letter of x_0 first).
        accepting: the accepting states.

    Raises ValueError before anything else when a state, a target or a proposition is unknown,
    a guard does not parse, some letter has no transition from some state (incomplete) or two
    (nondeterministic), or the alphabet is empty.

    Attributes:
        table: ``(Q, 2^P)`` int32 next-state index of every state and letter.
        initial_index: index of ``initial`` in ``states``.
        accepting_mask: ``(Q,)`` bool.
    """

    states: tuple
    propositions: tuple[str, ...]
    table: np.ndarray
    initial_index: int
    accepting_mask: np.ndarray

    def __init__(self, states: Sequence, propositions: Sequence[str], transitions, initial, accepting):
        states = tuple(states)
        if not states:
            raise ValueError("a DFA needs at least one state")
        if len(set(states)) != len(states):
            raise ValueError(f"states must be distinct, got {list(states)}")
        props = _check_propositions(propositions)
        index = {s: i for i, s in enumerate(states)}

        def state_index(s, what):
            if s not in index:
                raise ValueError(f"{what} {s!r} is not a state of the DFA (states: {list(states)})")
            return index[s]

        q0 = state_index(initial, "the initial state")
        acc = np.zeros(len(states), bool)
        for s in accepting:
            acc[state_index(s, "the accepting state")] = True
        if not isinstance(transitions, Mapping):
            raise TypeError("transitions must map every state to its {guard: next} mapping or (guard, next) pairs")
        n_letters = 1 << len(props)
        table = np.full((len(states), n_letters), -1, np.int64)
        for source, outgoing in transitions.items():
            q = state_index(source, "the transition source")
            pairs = outgoing.items() if isinstance(outgoing, Mapping) else outgoing
            for pair in pairs:
                try:
                    guard, target = pair
                except (TypeError, ValueError) as exc:
                    raise ValueError(f"transitions of {source!r} must be (guard, next) pairs, got {pair!r}") from exc
                t = state_index(target, f"the target of {source!r} --{guard!r}-->")
                holds = guard_letters(guard, props)
                clash = holds & (table[q] >= 0) & (table[q] != t)
                if np.any(clash):
                    letter = _guards.letter_name(int(np.flatnonzero(clash)[0]), props)
                    raise ValueError(f"the DFA is not deterministic: from {source!r} the letter {{{letter}}} leads "
                                     f"to {states[table[q][clash][0]]!r} and to {target!r}")
                table[q, holds] = t
        missing = np.argwhere(table < 0)
        if missing.size:
            q, letter = map(int, missing[0])
            raise ValueError(f"the DFA's transition table is incomplete: {missing.shape[0]} (state, letter) pairs "
                             f"have no transition, e.g. state {states[q]!r} on letter "
                             f"{{{_guards.letter_name(letter, props)}}}")
        object.__setattr__(self, "states", states)
        object.__setattr__(self, "propositions", props)
        object.__setattr__(self, "table", table.astype(np.int32))
        object.__setattr__(self, "initial_index", q0)
        object.__setattr__(self, "accepting_mask", acc)

    @classmethod
    def from_table(cls, states: Sequence, propositions: Sequence[str], table, initial, accepting) -> "DFA":
        """A DFA from its full table ``(Q, 2^P)`` of next-state indices (letter bit ``i`` is
        ``propositions[i]``)."""
        states = tuple(states)
        if not states or len(set(states)) != len(states):
            raise ValueError(f"states must be distinct and not empty, got {list(states)}")
        props = _check_propositions(propositions)
        table = np.asarray(table)
        if table.shape != (len(states), 1 << len(props)) or not np.issubdtype(table.dtype, np.integer):
            raise ValueError(f"table must be integer of shape (Q, 2^P) = ({len(states)}, {1 << len(props)}), "
                             f"got {table.dtype} {table.shape}")
        if np.any((table < 0) | (table >= len(states))):
            raise ValueError(f"table entries must be state indices in [0, {len(states)})")
        index = {s: i for i, s in enumerate(states)}
        if initial not in index:
            raise ValueError(f"the initial state {initial!r} is not a state of the DFA (states: {list(states)})")
        acc = np.zeros(len(states), bool)
        for s in accepting:
            if s not in index:
                raise ValueError(f"the accepting state {s!r} is not a state of the DFA (states: {list(states)})")
            acc[index[s]] = True
        dfa = object.__new__(cls)
        for name, value in (("states", states), ("propositions", props), ("table", table.astype(np.int32)),
                            ("initial_index", index[initial]), ("accepting_mask", acc)):
            object.__setattr__(dfa, name, value)
        return dfa

    # -- structure ---------------------------------------------------------------------------
    @property
    def num_states(self) -> int:
        return len(self.states)

    @property
    def num_letters(self) -> int:
        return int(self.table.shape[1])

    @property
    def initial(self):
        return self.states[self.initial_index]

    @property
    def accepting(self) -> tuple:
        return tuple(s for s, a in zip(self.states, self.accepting_mask) if a)

    def letter(self, holds) -> int:
        """The letter (bitmask) of a set of propositions that hold; unknown names are an error."""
        holds = set(holds)
        unknown = holds - set(self.propositions)
        if unknown:
            raise ValueError(f"unknown propositions {sorted(unknown)}; the alphabet is {list(self.propositions)}")
        return sum(1 << i for i, p in enumerate(self.propositions) if p in holds)

    def run(self, word) -> list:
        """The states visited on ``word``, a sequence of letters (bitmasks or sets of
        propositions): ``[delta(initial, w_0), delta(., w_1), ...]``."""
        q, visited = self.initial_index, []
        for w in word:
            q = int(self.table[q, w if isinstance(w, (int, np.integer)) else self.letter(w)])
            visited.append(self.states[q])
        return visited

    def accepts(self, word) -> bool:
        """Whether the finite ``word`` (non-empty) is accepted: the run ends in an accepting state."""
        visited = self.run(word)
        if not visited:
            raise ValueError("accepts needs a non-empty word (a trace has at least x_0)")
        return bool(self.accepting_mask[self.states.index(visited[-1])])

    def reachable(self, letters=None, start=None) -> np.ndarray:
        """``(Q,)`` bool: states reachable from ``start`` (default: the initial state, which
        counts as reached) reading only ``letters`` (default: all)."""
        letters = np.arange(self.num_letters) if letters is None else np.unique(np.asarray(letters))
        seen = np.zeros(self.num_states, bool)
        seen[self.initial_index if start is None else start] = True
        while True:  # at most Q rounds of one vectorized step each
            nxt = seen.copy()
            nxt[np.unique(self.table[seen][:, letters])] = True
            if np.array_equal(nxt, seen):
                return seen
            seen = nxt

    def coreachable(self, letters=None) -> np.ndarray:
        """``(Q,)`` bool: states from which an accepting state can be reached reading only
        ``letters`` (default: all). The others are *traps*: a run in one never accepts."""
        letters = np.arange(self.num_letters) if letters is None else np.unique(np.asarray(letters))
        good = self.accepting_mask.copy()
        while True:
            nxt = good | np.any(good[self.table[:, letters]], axis=1)
            if np.array_equal(nxt, good):
                return good
            good = nxt

    def absorbing_accepting(self, letters=None) -> bool:
        """Whether no accepting state can be left (reading ``letters``): once accepted, every
        continuation is accepted (a co-safe, "good prefix" specification)."""
        letters = np.arange(self.num_letters) if letters is None else np.unique(np.asarray(letters))
        nxt = self.table[self.accepting_mask][:, letters]
        return bool(np.all(self.accepting_mask[nxt]))

    def with_propositions(self, propositions: Sequence[str]) -> "DFA":
        """The same automaton over a larger alphabet (extra propositions are ignored by it)."""
        props = _check_propositions(propositions)
        missing = set(self.propositions) - set(props)
        if missing:
            raise ValueError(f"with_propositions must keep every proposition; {sorted(missing)} are missing")
        letters = np.arange(1 << len(props))
        old = np.zeros(letters.shape, np.int64)
        for i, p in enumerate(self.propositions):
            old |= ((letters >> props.index(p)) & 1) << i
        return DFA.from_table(self.states, props, self.table[:, old], self.initial, self.accepting)

    def __repr__(self):
        return (f"DFA(|Q|={self.num_states}, propositions={list(self.propositions)}, initial={self.initial!r}, "
                f"accepting={list(self.accepting)})")


def guard_letters(guard, propositions: tuple[str, ...]) -> np.ndarray:
    """``(2^P,)`` bool: the letters on which ``guard`` holds (a formula string, a set of
    propositions meaning exactly that letter, or a bool)."""
    if isinstance(guard, (bool, np.bool_)):
        return np.full(1 << len(propositions), bool(guard))
    if isinstance(guard, (set, frozenset)):
        unknown = {str(p) for p in guard} - set(propositions)
        if unknown:
            raise ValueError(f"guard {set(guard)} mentions propositions {sorted(unknown)} that are not in the "
                             f"alphabet {list(propositions)}")
        letter = sum(1 << propositions.index(str(p)) for p in guard)
        out = np.zeros(1 << len(propositions), bool)
        out[letter] = True
        return out
    if not isinstance(guard, str):
        raise TypeError(f"a guard is a formula string, a set of propositions or a bool, got {type(guard).__name__}")
    tree = _guards.parse(guard)
    unknown = _guards.atoms(tree) - set(propositions)
    if unknown:
        raise ValueError(f"guard {guard!r} mentions propositions {sorted(unknown)} that are not in the alphabet "
                         f"{list(propositions)}")
    return _guards.evaluate(tree, propositions)
