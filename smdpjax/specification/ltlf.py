"""LTLf formulas to DFAs through an existing translator (the optional ``ltlf`` extra).

Two translators are supported:

* ``ltlf2dfa`` (PyPI) runs the MONA tool (Debian/Ubuntu package ``mona``): fast, minimal DFAs.
  It writes its MONA program into its own package directory, so calls are serialized here.
* ``flloat`` (PyPI) is pure Python: no outside tool, slower on large formulas (seconds for a
  few operators), same automata up to state names.

``backend="auto"`` takes ltlf2dfa when both it and ``mona`` are found, else flloat. Both parse
the usual LTLf syntax: ``F``, ``G``, ``X`` (strong next), ``WX`` (weak next), ``U``, ``R``,
``!``/``~``, ``&``, ``|``, ``->``, ``<->``, ``true``, ``false``; propositions are lower-case
identifiers.

Semantics: a formula holds on a finite trace ``x_0 .. x_T`` (LTLf); the DFA reads the letters of
the states in order. See ``Specification`` for how that becomes a probability.
"""

from __future__ import annotations

import re
import shutil
import threading
from collections.abc import Sequence

from .dfa import DFA

BACKENDS = ("auto", "ltlf2dfa", "flloat")
_MONA_LOCK = threading.Lock()
_INSTALL = ("LTLf formulas need a translator, the optional extra `pip install 'smdpjax[ltlf]'`: ltlf2dfa (which "
            "also needs the MONA tool, e.g. `apt-get install mona`) or flloat (pure Python)")


def available_backends() -> list[str]:
    """The translators that can run here, preferred first."""
    out = []
    try:
        import ltlf2dfa  # noqa: F401

        if shutil.which("mona"):
            out.append("ltlf2dfa")
    except ImportError:
        pass
    try:
        import flloat  # noqa: F401

        out.append("flloat")
    except ImportError:
        pass
    return out


def _choose(backend: str) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"unknown LTLf backend {backend!r}; expected one of {BACKENDS}")
    if backend == "auto":
        found = available_backends()
        if not found:
            raise ImportError(f"{_INSTALL}; neither is installed")
        return found[0]
    if backend == "ltlf2dfa":
        try:
            import ltlf2dfa  # noqa: F401
        except ImportError as exc:
            raise ImportError(f"backend 'ltlf2dfa' is not installed: `pip install ltlf2dfa` ({_INSTALL})") from exc
        if not shutil.which("mona"):
            raise ImportError("backend 'ltlf2dfa' needs the MONA tool on the PATH, which is missing: install it "
                              "(Debian/Ubuntu: `apt-get install mona`) or use backend='flloat'")
        return backend
    try:
        import flloat  # noqa: F401
    except ImportError as exc:
        raise ImportError(f"backend 'flloat' is not installed: `pip install flloat` ({_INSTALL})") from exc
    return backend


def ltlf_to_dfa(formula: str, propositions: Sequence[str] | None = None, *, backend: str = "auto") -> DFA:
    """The DFA of an LTLf formula.

    Args:
        formula: the LTLf formula, e.g. ``"F(a & F b) & G !o"``.
        propositions: the alphabet; default: the formula's own propositions (sorted). Extra
            names are allowed (the DFA ignores them); a proposition of the formula that is not
            listed is an error.
        backend: ``"auto"``, ``"ltlf2dfa"`` or ``"flloat"`` (module docstring).

    Raises:
        ImportError: no translator (names what to install).
        ValueError: the formula does not parse, or its propositions are not in ``propositions``,
            or it has no proposition and none are given (an empty alphabet).
    """
    if not isinstance(formula, str) or not formula.strip():
        raise ValueError(f"an LTLf formula must be a non-empty string, got {formula!r}")
    backend = _choose(backend)
    parsed = _parse(formula, backend)
    atoms = sorted(str(a) for a in parsed.find_labels())
    props = tuple(atoms if propositions is None else propositions)
    unknown = sorted(set(atoms) - set(props))
    if unknown:
        raise ValueError(f"the formula {formula!r} uses propositions {unknown} that have no region (are not in the "
                         f"alphabet {list(props)})")
    if not props:
        raise ValueError(f"the formula {formula!r} mentions no proposition: the alphabet is empty")
    if backend == "ltlf2dfa":
        with _MONA_LOCK:
            dot = parsed.to_dfa()
        return _from_dot(dot, props, formula)
    return _from_pythomata(parsed.to_automaton(), props)


def _parse(formula: str, backend: str):
    if backend == "ltlf2dfa":
        from ltlf2dfa.parser.ltlf import LTLfParser
    else:
        from flloat.parser.ltlf import LTLfParser
    try:
        return LTLfParser()(formula)
    except Exception as exc:  # lark raises several exception types
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"the LTLf formula {formula!r} does not parse ({backend}): {first}") from None


_EDGE = re.compile(r'^\s*(\w+)\s*->\s*(\w+)\s*\[label="([^"]*)"\];')
_ACCEPTING = re.compile(r"node \[shape = doublecircle\];([^\n]*)")
_INIT = re.compile(r"init\s*->\s*(\w+);")


def _from_dot(dot: str, props: tuple, formula: str) -> DFA:
    """A DFA from ltlf2dfa's DOT output (MONA's automaton; guards in sympy syntax)."""
    init = _INIT.search(dot)
    if init is None:
        raise ValueError(f"ltlf2dfa gave no initial state for {formula!r}: {dot[:200]}")
    accepting = _ACCEPTING.search(dot)
    accepting = [a.strip() for a in accepting.group(1).replace(";", " ").split()] if accepting else []
    transitions: dict[str, list] = {}
    for line in dot.splitlines():
        m = _EDGE.match(line)
        if m and m.group(1) != "init":
            transitions.setdefault(m.group(1), []).append((m.group(3), m.group(2)))
    states = sorted(set(transitions) | {t for pairs in transitions.values() for _, t in pairs} | set(accepting)
                    | {init.group(1)}, key=lambda s: (len(s), s))
    return DFA(states, props, transitions, init.group(1), [a for a in accepting if a])


def _from_pythomata(automaton, props: tuple) -> DFA:
    """A DFA from flloat's pythomata ``SymbolicDFA`` (guards are sympy expressions)."""
    states = sorted(automaton.states)
    transitions = {s: [(str(guard), t) for _, guard, t in automaton.get_transitions_from(s)] for s in states}
    return DFA(states, props, transitions, automaton.initial_state, sorted(automaton.accepting_states))
