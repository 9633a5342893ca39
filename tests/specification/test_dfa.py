"""DFAs, guards, LTLf translation and every bad input, checked before any abstraction work."""

import numpy as np
import pytest

import smdpjax as sj
from smdpjax import specification as sp
from smdpjax.specification import guards, ltlf


def test_guards_evaluate_on_every_letter():
    props = ("a", "b", "c")
    truth = lambda text: np.flatnonzero(guards.evaluate(guards.parse(text), props)).tolist()
    assert truth("a") == [1, 3, 5, 7]
    assert truth("a & !b") == [1, 5]
    assert truth("(a | b) & ~c") == [1, 2, 3]
    assert truth("a && b || c") == [3, 4, 5, 6, 7]
    assert truth("true") == list(range(8)) and truth("false") == []
    for bad in ("a &", "(a", "a b", "& a", ""):
        with pytest.raises(ValueError):
            guards.parse(bad)


def sequence_dfa():
    return sp.DFA(["s0", "s1", "acc", "bad"], ["a", "b", "o"],
                  {"s0": {"o": "bad", "a & !o": "s1", "!a & !o": "s0"},
                   "s1": [("o", "bad"), ("b & !o", "acc"), ("!b & !o", "s1")],
                   "acc": {True: "acc"}, "bad": {"true": "bad"}},
                  initial="s0", accepting=["acc"])


def test_dfa_runs_and_accepts():
    dfa = sequence_dfa()
    assert dfa.table.shape == (4, 8)
    assert dfa.run([{"a"}, set(), {"b"}]) == ["s1", "s1", "acc"]
    assert dfa.accepts([{"a"}, {"b"}]) and not dfa.accepts([{"b"}, {"a"}]) and not dfa.accepts([{"a"}, {"o"}, {"b"}])
    assert dfa.accepts([{"a", "b"}, {"b"}])  # a, then b at the next step
    np.testing.assert_array_equal(dfa.coreachable(), [True, True, True, False])
    assert dfa.absorbing_accepting()
    again = sp.DFA.from_table(dfa.states, dfa.propositions, dfa.table, "s0", ["acc"])
    np.testing.assert_array_equal(again.table, dfa.table)
    wider = dfa.with_propositions(["c", "a", "b", "o"])
    assert wider.accepts([{"a", "c"}, {"b"}]) and wider.num_letters == 16


def test_bad_dfas():
    ok = {"q": {"a": "r", "!a": "q"}, "r": {"true": "r"}}
    with pytest.raises(ValueError, match="alphabet is empty"):
        sp.DFA(["q", "r"], [], ok, "q", ["r"])
    with pytest.raises(ValueError, match="incomplete"):
        sp.DFA(["q", "r"], ["a"], {"q": {"a": "r"}, "r": {"true": "r"}}, "q", ["r"])
    with pytest.raises(ValueError, match="incomplete"):
        sp.DFA(["q", "r"], ["a"], {"q": {"true": "q"}}, "q", ["r"])  # r has no transitions
    with pytest.raises(ValueError, match="not a state"):
        sp.DFA(["q", "r"], ["a"], {"q": {"a": "x", "!a": "q"}, "r": {"true": "r"}}, "q", ["r"])
    with pytest.raises(ValueError, match="not a state"):
        sp.DFA(["q", "r"], ["a"], ok, "z", ["r"])
    with pytest.raises(ValueError, match="not a state"):
        sp.DFA(["q", "r"], ["a"], ok, "q", ["z"])
    with pytest.raises(ValueError, match="not in the alphabet"):
        sp.DFA(["q", "r"], ["a"], {"q": {"b": "r", "!b": "q"}, "r": {"true": "r"}}, "q", ["r"])
    with pytest.raises(ValueError, match="not deterministic"):
        sp.DFA(["q", "r"], ["a"], {"q": {"a": "r", "true": "q"}, "r": {"true": "r"}}, "q", ["r"])
    with pytest.raises(ValueError, match="malformed guard|cannot read"):
        sp.DFA(["q", "r"], ["a"], {"q": {"a &": "r", "!a": "q"}, "r": {"true": "r"}}, "q", ["r"])
    with pytest.raises(ValueError, match="identifiers"):
        sp.DFA(["q"], ["a b"], {"q": {"true": "q"}}, "q", [])
    with pytest.raises(ValueError, match="table must be"):
        sp.DFA.from_table(["q"], ["a"], np.zeros((1, 3), int), "q", [])


def test_specification_checks_before_any_abstraction_work():
    dfa = sequence_dfa()
    regions = {"a": [([0, 0], [1, 1])], "b": [([2, 2], [3, 3])], "o": sp.Region([([1, 1], [2, 2])], closed=False)}
    with pytest.raises(ValueError, match=r"\['o'\] have no region"):
        sp.Specification(dfa, {k: v for k, v in regions.items() if k != "o"})
    with pytest.raises(ValueError, match="acceptance"):
        sp.Specification(dfa, regions, acceptance="sometimes")
    grid = sj.StateGrid([0, 0], [3, 3], 3)
    spec = sp.Specification(dfa, regions)
    assert sp.Specification(dfa, regions, faces="interior").on(grid).labelling.letters.shape == (9, 1)
    # cell 4 = [1, 2)^2 holds the corner (1, 1) of the closed box a, and its faces x = 1, y = 1 are
    # outside the open box o: a and o are both possible there, on faces only (not "mixed")
    exact = spec.on(grid).labelling
    assert exact.count[4] == 4 and not exact.mixed.any()
    assert sorted(exact.letters[4].tolist()) == [0, 1, 4, 5]
    with pytest.raises(ValueError, match="not inside the grid box"):
        spec.on(sj.StateGrid([0, 0], [2.5, 3], 3))
    with pytest.raises(ValueError, match="dimension"):
        spec.on(sj.StateGrid([0], [3], 3))
    with pytest.raises(ValueError, match="pair"):
        sp.Region([([0, 0], [1, 1], [2, 2])])
    with pytest.raises(ValueError, match="low < high"):
        sp.Region([([1, 0], [0, 1])])


# ------------------------------------------------------------------ LTLf (optional translators)

FORMULAS = ["F(a & F(b)) & G(!o)", "!o U (a & (!o U b))", "F(a) & G(a -> X(G(!b)))", "G(!o) & F(b)"]


def words(props, count, length, seed=0):
    rng = np.random.default_rng(seed)
    return [[set(p for p in props if rng.random() < 0.3) for _ in range(length)] for _ in range(count)]


def semantics(formula, word):
    """The LTLf semantics of the four formulas, by hand, on a finite word."""
    has = lambda i, p: p in word[i]
    n = len(word)
    if formula == FORMULAS[0]:
        return all(not has(i, "o") for i in range(n)) and any(
            has(i, "a") and any(has(j, "b") for j in range(i, n)) for i in range(n))
    if formula == FORMULAS[1]:
        for i in range(n):
            if has(i, "a") and all(not has(k, "o") for k in range(i)):
                for j in range(i, n):
                    if has(j, "b"):
                        return all(not has(k, "o") for k in range(i, j))
                    if has(j, "o"):
                        break
        return False
    if formula == FORMULAS[2]:  # after a, never b at a later step (X is strong: a needs a successor)
        ok = any(has(i, "a") for i in range(n))
        for i in range(n):
            if has(i, "a") and (i + 1 >= n or any(has(j, "b") for j in range(i + 1, n))):
                ok = False
        return ok
    return all(not has(i, "o") for i in range(n)) and any(has(i, "b") for i in range(n))


@pytest.mark.parametrize("backend", ["ltlf2dfa", "flloat"])
def test_ltlf_translations_agree_with_the_semantics(backend):
    if backend not in ltlf.available_backends():
        pytest.skip(f"{backend} is not installed (the ltlf extra; ltlf2dfa also needs mona)")
    for formula in FORMULAS:
        dfa = ltlf.ltlf_to_dfa(formula, ["a", "b", "o"], backend=backend)
        for word in words(("a", "b", "o"), 150, 5, seed=len(formula)):
            assert dfa.accepts(word) == semantics(formula, word), (formula, word)


def test_ltlf_backends_agree_and_errors():
    found = ltlf.available_backends()
    if not found:
        pytest.skip("no LTLf translator installed")
    if len(found) == 2:
        a = ltlf.ltlf_to_dfa(FORMULAS[0], backend="ltlf2dfa")
        b = ltlf.ltlf_to_dfa(FORMULAS[0], backend="flloat")
        for word in words(a.propositions, 200, 6):
            assert a.accepts(word) == b.accepts(word)
    with pytest.raises(ValueError, match="does not parse"):
        ltlf.ltlf_to_dfa("F(a &")
    with pytest.raises(ValueError, match="not in"):
        ltlf.ltlf_to_dfa("F a & F c", ["a", "b"])
    with pytest.raises(ValueError, match="no region"):
        sp.Specification.ltlf("F a & F c", {"a": [([0], [1])]})
    with pytest.raises(ValueError, match="unknown LTLf backend"):
        ltlf.ltlf_to_dfa("F a", backend="spot")
    spec = sp.Specification.ltlf("F(a) & G(!o)", {"a": [([0], [1])], "o": sp.Region([([2], [3])], closed=False)})
    assert spec.dfa.propositions == ("a", "o")


def test_missing_translator_is_named(monkeypatch):
    monkeypatch.setattr(ltlf, "available_backends", lambda: [])
    with pytest.raises(ImportError, match="ltlf2dfa.*mona.*flloat"):
        ltlf.ltlf_to_dfa("F a")
    monkeypatch.setattr(ltlf.shutil, "which", lambda name: None)
    try:
        import ltlf2dfa  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="ltlf2dfa"):
            ltlf.ltlf_to_dfa("F a", backend="ltlf2dfa")
    else:
        with pytest.raises(ImportError, match="MONA"):
            ltlf.ltlf_to_dfa("F a", backend="ltlf2dfa")


@pytest.mark.parametrize("name", ["sequence", "never_after"])
def test_case_study_dfas_equal_their_formulas(name):
    import importlib

    cs = importlib.import_module("smdpjax.case_studies.unicycle_2d_dfa")  # the module, not the function

    if not ltlf.available_backends():
        pytest.skip("no LTLf translator installed")
    hand = cs.dfa(name)
    translated = ltlf.ltlf_to_dfa(cs.FORMULAS[name], hand.propositions)
    for word in words(hand.propositions, 400, 6, seed=3):
        # the co-safe reading: accepted once some prefix is accepted (the hand DFA stops there)
        prefix = any(translated.accepts(word[:k]) for k in range(1, len(word) + 1))
        assert hand.accepts(word) == prefix, word
