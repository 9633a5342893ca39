"""The product of a DFA and a gridded abstraction, as index tables (the product is never built).

Product states are pairs (q, s) of a DFA state and a grid state; a value vector over them has
length ``P = |Q| (N + 1)``, state ``(q, s)`` at ``q (N + 1) + s`` (``v.reshape(Q, N + 1)``).
The DFA state of a pair already includes the letter of its cell: a trajectory that is in cell s
with DFA state q moves to cell s' with DFA state ``delta(q, L(s'))``. So the backup of (q, s)
under action a is the abstraction's own inner problem applied to the vector

    u_q(s') = v[delta(q, L(s')), s']      (s' a cell),       u_q(N) = 0 (the sink fails),

with the worst (best, for the maximizing adversary) of the possible letters of a cell that lies
partly inside a region. ``ProductTables`` holds what that needs:

* ``succ (Q_live, N+1, L)``: the product index ``delta(q, letter) (N+1) + s'`` of every live DFA
  state, successor state and possible letter (the sink column points at a state of value 0);
* ``rows (R,)``: the product states that are backed up, in the order of their DFA state and
  then of the abstraction's rows (``row_q``, ``row_r``);
* ``labels (P,)``: ``REACH`` for accepted pairs (value 1, absorbing; acceptance ``"reach"``),
  ``NONTERMINAL`` for the rows, ``AVOID`` (value 0) for traps (DFA states from which no accepting
  state can be reached), the sink column and every pair that no run can occupy;
* ``v0 (P,)``: the initial values p^0, 1 on accepted pairs;
* ``start (N+1, L)``: the product index of a trajectory that starts in cell s,
  ``delta(initial, L(s)) (N+1) + s``.

*Live* DFA states are those that have rows: reachable from the initial state, able to reach an
accepting state, and (acceptance ``"reach"``) not accepting. Only the pairs (q, s) that a run can
occupy, ``q = delta(q', sigma)`` for a reachable q' and a possible letter sigma of s, are rows;
for the 3-state reach-avoid DFA those are exactly the non-terminal cells of the built-in
reach-avoid problem.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import pytree_dataclass, static_field
from ..partition import AVOID, NONTERMINAL, REACH


@pytree_dataclass
class ProductTables:
    """Index tables of the product of a DFA and a grid abstraction (module docstring).

    Attributes:
        succ: ``(Q_live, N+1, L)`` int32 product index of every (live DFA state, state, letter).
        rows: ``(R,)`` int32 product index of every row.
        row_q: ``(R,)`` int32 live-state position of every row (into ``live``).
        row_r: ``(R,)`` int32 the abstraction's row of every row's cell.
        labels: ``(P,)`` int8 product-state labels.
        v0: ``(P,)`` float64 initial values.
        start: ``(N+1, L)`` int32 product index of a start in each grid state.
        num_dfa_states: |Q| (static).
        live: the live DFA states' indices (static tuple).
        num_base_rows: rows of the abstraction the tables were made for (static).
    """

    succ: jax.Array
    rows: jax.Array
    row_q: jax.Array
    row_r: jax.Array
    labels: jax.Array
    v0: jax.Array
    start: jax.Array
    num_dfa_states: int = static_field()
    live: tuple = static_field()
    num_base_rows: int = static_field()

    @property
    def num_grid_states(self) -> int:
        """N + 1."""
        return int(self.start.shape[0])

    @property
    def num_states(self) -> int:
        """P = |Q| (N + 1)."""
        return int(self.labels.shape[0])

    def fingerprint(self) -> bytes:
        """Bytes that identify the tables (for grouping sweeps)."""
        parts = [np.asarray(a).tobytes() for a in (self.succ, self.rows, self.labels, self.v0, self.start)]
        return b"|".join(parts) + repr((self.num_dfa_states, self.live, self.num_base_rows)).encode()


def build_tables(dfa, letters: np.ndarray, base_rows: np.ndarray, acceptance: str) -> ProductTables:
    """The product tables of a DFA and a grid labelling (NumPy, at concrete inputs).

    Args:
        dfa: the ``DFA``.
        letters: ``(N, L)`` possible letters of every cell (``regions.Labelling.letters``).
        base_rows: ``(R_base,)`` the cells the abstraction has transitions for.
        acceptance: ``"reach"`` (accepted pairs are absorbing with value 1) or ``"final"`` (the
            run must end in an accepting state; accepting states are backed up like any other).

    Raises ValueError when a pair that must be backed up has a cell that is not a row of the
    abstraction (the abstraction was built on a grid with reach or avoid cells).
    """
    table, accepting, initial = dfa.table, dfa.accepting_mask, dfa.initial_index
    q_count = table.shape[0]
    n = letters.shape[0]
    size = n + 1
    occurring = np.unique(letters)
    reach_q = dfa.reachable(occurring)
    good = dfa.coreachable(occurring)
    live_mask = reach_q & good & (~accepting if acceptance == "reach" else True)
    # pairs a run can occupy: delta(q', sigma) for reachable q' and possible letters sigma of s
    relevant = np.zeros((q_count, n), bool)
    nxt = table[np.flatnonzero(reach_q)][:, letters]  # (|Q_reach|, N, L)
    relevant[nxt, np.broadcast_to(np.arange(n)[None, :, None], nxt.shape)] = True
    live = np.flatnonzero(live_mask)

    row_of_cell = np.full(n + 1, -1, np.int64)
    row_of_cell[base_rows] = np.arange(base_rows.shape[0])
    labels = np.full((q_count, size), AVOID, np.int8)
    if acceptance == "reach":
        labels[accepting, :n] = REACH
    rows, row_q, row_r = [], [], []
    for i, q in enumerate(live):  # a loop over the live DFA states; cells are vectorized
        need = relevant[q]
        lacking = need & (row_of_cell[:n] < 0)
        if lacking.any():
            cell = int(np.flatnonzero(lacking)[0])
            raise ValueError(f"the abstraction has no transitions for {int(lacking.sum())} cells the product needs "
                             f"(e.g. cell {cell}, with DFA state {int(q)}): it was built on a grid whose reach or "
                             f"avoid cells are absorbing. Build it on a grid without reach/avoid boxes (every cell a "
                             f"row), the regions belong to the specification")
        r = np.flatnonzero(need[base_rows])  # the abstraction's rows, in their order
        rows.append(q * size + base_rows[r])
        row_q.append(np.full(r.shape, i))
        row_r.append(r)
        labels[q, base_rows[r]] = NONTERMINAL
    cat = lambda parts: np.concatenate(parts) if parts else np.zeros(0, np.int64)
    rows, row_q, row_r = cat(rows), cat(row_q), cat(row_r)
    v0 = np.zeros((q_count, size))
    v0[accepting, :n] = 1.0
    v0[labels == AVOID] = 0.0

    # successor product indices: delta(q, letter) * size + s'; the sink column: (q, N), value 0
    cells = np.arange(n)[None, :, None]
    succ = table[live][:, letters] * size + cells  # (Q_live, N, L)
    sink = np.broadcast_to((live * size + n)[:, None, None], (live.size, 1, letters.shape[1]))
    succ = np.concatenate([succ, sink], axis=1)
    start = np.concatenate([table[initial][letters] * size + np.arange(n)[:, None],
                            np.full((1, letters.shape[1]), initial * size + n)])
    i32 = lambda a: jnp.asarray(a, jnp.int32)
    return ProductTables(succ=i32(succ), rows=i32(rows), row_q=i32(row_q), row_r=i32(row_r),
                         labels=jnp.asarray(labels.reshape(-1)), v0=jnp.asarray(v0.reshape(-1)), start=i32(start),
                         num_dfa_states=int(q_count), live=tuple(int(q) for q in live),
                         num_base_rows=int(base_rows.shape[0]))

