"""Boolean guards over atomic propositions: ``"a & !b"``, ``"(a | b) & ~c"``, ``"true"``.

A guard is parsed once into a small expression tree and evaluated on *every* letter at once: a
letter is a set of propositions, encoded as a bitmask (bit ``i`` set when ``propositions[i]``
holds), and the ``2^P`` letters are evaluated as NumPy boolean arrays.

Grammar (the operators of ltlf2dfa's and flloat's DFA labels, and the usual spellings)::

    guard := or ;  or := and (("|" | "||") and)* ;  and := not (("&" | "&&") not)*
    not   := ("!" | "~") not | "(" or ")" | "true" | "false" | NAME
"""

from __future__ import annotations

import re

import numpy as np

_TOKEN = re.compile(r"\s*(?:(\|\||&&|[|&!~()])|([A-Za-z_][A-Za-z0-9_]*))")
_TRUE, _FALSE = {"true", "True", "TRUE"}, {"false", "False", "FALSE"}


def tokenize(text: str) -> list[str]:
    """The tokens of ``text``; ValueError at the first character that is none."""
    tokens, pos, text = [], 0, str(text)
    while pos < len(text):
        if text[pos:].strip() == "":
            break
        m = _TOKEN.match(text, pos)
        if m is None:
            raise ValueError(f"cannot read guard {text!r} at position {pos}: {text[pos:]!r}")
        tokens.append(m.group(1) or m.group(2))
        pos = m.end()
    return tokens


def parse(text: str):
    """An expression tree: ``("const", bool)``, ``("atom", name)``, ``("not", e)``,
    ``("and", e1, e2)``, ``("or", e1, e2)``. ValueError on a malformed guard."""
    tokens = tokenize(text)
    if not tokens:
        raise ValueError(f"empty guard {text!r}")
    pos = 0

    def peek():
        return tokens[pos] if pos < len(tokens) else None

    def take(expected=None):
        nonlocal pos
        tok = peek()
        if tok is None or (expected is not None and tok != expected):
            raise ValueError(f"malformed guard {text!r}: expected {expected or 'more'} at token {pos}")
        pos += 1
        return tok

    def disjunction():
        left = conjunction()
        while peek() in ("|", "||"):
            take()
            left = ("or", left, conjunction())
        return left

    def conjunction():
        left = negation()
        while peek() in ("&", "&&"):
            take()
            left = ("and", left, negation())
        return left

    def negation():
        tok = take()
        if tok in ("!", "~"):
            return ("not", negation())
        if tok == "(":
            inner = disjunction()
            take(")")
            return inner
        if tok in _TRUE:
            return ("const", True)
        if tok in _FALSE:
            return ("const", False)
        if tok in ("|", "||", "&", "&&", ")"):
            raise ValueError(f"malformed guard {text!r}: unexpected {tok!r}")
        return ("atom", tok)

    tree = disjunction()
    if pos != len(tokens):
        raise ValueError(f"malformed guard {text!r}: unexpected {tokens[pos]!r}")
    return tree


def atoms(tree) -> set[str]:
    """The proposition names a parsed guard mentions."""
    if tree[0] == "atom":
        return {tree[1]}
    if tree[0] == "const":
        return set()
    return set().union(*(atoms(t) for t in tree[1:]))


def evaluate(tree, propositions: tuple[str, ...]) -> np.ndarray:
    """``(2^P,)`` bool: the guard's value on every letter (bit i of the letter index is
    ``propositions[i]``)."""
    letters = np.arange(1 << len(propositions))

    def ev(t):
        if t[0] == "const":
            return np.full(letters.shape, t[1])
        if t[0] == "atom":
            return (letters >> propositions.index(t[1])) & 1 == 1
        if t[0] == "not":
            return ~ev(t[1])
        left, right = ev(t[1]), ev(t[2])
        return (left & right) if t[0] == "and" else (left | right)

    return ev(tree)


def letter_name(letter: int, propositions: tuple[str, ...]) -> str:
    """``"a & !b"``: the letter as a conjunction over every proposition."""
    return " & ".join(p if (letter >> i) & 1 else f"!{p}" for i, p in enumerate(propositions))
