"""2I-MDP backups with the capacities laid out for the met blocks only, against every block slot.

For each Table 1 2I-MDP row the abstraction is built once; one backup with every action and one
with a fixed strategy (``q_values``, the two kinds of backup the synthesis runs) are timed for two
variants of the inner problem, alternately in one process (medians of ``--repeats`` warm runs):

* ``met pairs``: the default, one row of capacities per met (list, block) pair
  (``block_pairs``), the count table where ``wants_count_table`` builds it, two-level prefix sums;
* ``every slot``: the solver before issue 21's eighth session, a row per block slot ``T`` of every
  list (padding blocks included), a binary search per block and bisection step, one product with
  a triangular matrix for the prefix sums.

Reports both times, their ratio and the largest difference of the values (the same sums in
another order).

    python -m benchmarks.two_layer_pairs --rows 34,38 [--repeats 3]
"""

from __future__ import annotations

import contextlib
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .common import alternating, argument_parser, median, row_clusters, write_result


@contextlib.contextmanager
def _every_slot():
    from smdpjax.abstraction import twolayer

    saved = twolayer.COUNT_TABLE_MAX, twolayer._ONE_LEVEL_MAX
    twolayer.COUNT_TABLE_MAX, twolayer._ONE_LEVEL_MAX = 0, twolayer._MATMUL_PREFIX_MAX
    try:
        yield
    finally:
        twolayer.COUNT_TABLE_MAX, twolayer._ONE_LEVEL_MAX = saved


def measure(row: int, repeats: int) -> dict:
    from smdpjax.abstraction import build

    study, clusters = row_clusters(row, "2imdp")
    pairs = build("2imdp", study.state_grid, clusters)
    variants = {"met pairs": (pairs, contextlib.nullcontext), "every slot": (
        dataclasses.replace(pairs, block_pairs=(0, 0)), _every_slot)}
    rng = np.random.default_rng(row)
    v = jnp.asarray(rng.uniform(0, 1, pairs.num_states)).at[-1].set(0.0)
    strategy = jnp.asarray(rng.integers(0, pairs.num_actions, pairs.num_rows), jnp.int32)
    calls, values = {}, {}
    for name, (abstraction, setting) in variants.items():
        every = jax.jit(lambda a, v: a.q_values(v, "min"))
        fixed = jax.jit(lambda a, v, s: a.q_values(v, "max", s))
        with setting():  # traced under the variant's settings, then reused
            values[name] = (np.asarray(every(abstraction, v)), np.asarray(fixed(abstraction, v, strategy)))
        calls[name] = {"every action": lambda a=abstraction, f=every: f(a, v),
                       "strategy": lambda a=abstraction, f=fixed: f(a, v, strategy)}
    times = alternating({(name, kind): calls[name][kind] for name in variants for kind in ("every action", "strategy")},
                        repeats)
    diff = max(float(np.max(np.abs(a - b))) for a, b in zip(values["met pairs"], values["every slot"]))
    met = np.asarray(jnp.sum(pairs.blocks < pairs.cells_of.shape[0], -1))
    return dict(row=row, states=pairs.num_states, actions=pairs.num_actions, block_slots=pairs.num_block_slots,
                cells_per_block=int(pairs.cells_of.shape[1]), mean_blocks_met=float(met.mean()),
                block_pairs=list(pairs.block_pairs), block_rows=pairs.block_rows,
                **{f"{kind.replace(' ', '_')}_{name.replace(' ', '_')}_s": median(times[name, kind])
                   for name, kind in times},
                runs={f"{name}/{kind}": t for (name, kind), t in times.items()}, max_value_difference=diff)


def main(argv=None):
    parser = argument_parser(__doc__, "two_layer_pairs", repeats=3)
    parser.add_argument("--rows", default="34,38", help="Table 1 2I-MDP rows")
    args = parser.parse_args(argv)
    results = []
    print(f"{'row':>4} {'T x S':>8} {'met':>5} {'every action: pairs':>20} {'every slot':>11} {'ratio':>6} "
          f"{'strategy: pairs':>16} {'every slot':>11} {'ratio':>6} {'max diff':>9}")
    for row in (int(r) for r in args.rows.split(",")):
        r = measure(row, args.repeats)
        results.append(r)
        a, b = r["every_action_met_pairs_s"], r["every_action_every_slot_s"]
        c, d = r["strategy_met_pairs_s"], r["strategy_every_slot_s"]
        print(f"{row:>4} {r['block_slots']:>3} x {r['cells_per_block']:<3} {r['mean_blocks_met']:>5.1f} {a:>20.3f} "
              f"{b:>11.3f} {b / a:>5.2f}x {c:>16.3f} {d:>11.3f} {d / c:>5.2f}x {r['max_value_difference']:>9.1e}",
              flush=True)
    print("wrote", write_result("two_layer_pairs", args, rows=results))


if __name__ == "__main__":
    main()
