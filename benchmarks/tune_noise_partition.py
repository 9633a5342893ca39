"""Tune the noise partition with optax: radius r_W and per-axis cell boundaries, fixed cell count.

The 2-D unicycle of ``core_2d`` (Gaussian std 0.3, 8 headings), SMDP abstraction. The noise
partition is the inf-norm ball of radius ``r = exp(log_r)`` split into ``k x k`` cells whose
per-axis widths are ``2 r softmax(logits[i])`` (``warped_ball_edges``); the start is the paper's
uniform choice, r_W = 2.1 and equal widths. Adam ascends the mean p_low over 100 initial cells.

Each step recomputes the cluster structure at the current partition (reachable sets; outside
the differentiated path) and takes ``jax.value_and_grad`` of the guarantee with that structure
frozen (``smdpjax.gradients``). The true objective is piecewise smooth: it jumps whenever a
reachable box crosses a grid line, which the gradient cannot see, so a step is accepted only if
the true value does not decrease (else the learning rate is halved). The start and the final
partitions are then re-abstracted from scratch with ``sj.abstract`` and ``sj.synthesize`` (sound
bounds, rounding allowance included) and compared on mean p_low and e_avg.

``SMDPJAX_SMALL=1`` shrinks the defaults (16x16 cells, 6x6 noise cells, 3 steps) for a smoke run.

    python -m benchmarks.tune_noise_partition [--cells 20] [--noise-cells 12] [--steps 40] [--lr 0.05]
"""

from __future__ import annotations

import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import smdpjax as sj
from smdpjax import gradients
from smdpjax.partition.noise_grid import warped_ball_edges

from .common import argument_parser, write_result
from .core_2d import problem


def edges_of(theta, center):
    return warped_ball_edges(center, jnp.exp(theta["log_radius"]), theta["logits"])


def bucket(x: int, step: int) -> int:
    return int(-(-x // step) * step)


def tune(system, grid, cells, *, noise_cells: int = 12, radius: float = 2.1, steps: int = 40, lr: float = 0.05,
         tol: float = 1e-10, log=print):
    """Adam on (log r_W, per-axis logits), safeguarded by the true value.

    The gradient is exact for the structure at the iterate but blind to structure changes, and
    those are not small here: a larger r_W always looks better to it (less remainder mass), yet
    coarser noise cells make every reachable box larger. So a step is accepted only if the true
    guarantee (structure recomputed at the candidate) does not decrease; otherwise the candidate
    is dropped and the learning rate halved (and the run stops once it is below ``1e-3 lr``).
    Returns (history, start theta, final theta); the final theta has the best true value seen.
    """
    center = jnp.asarray(system.noise.mean())
    theta = {"log_radius": jnp.log(jnp.asarray(radius)), "logits": jnp.zeros((grid.n, noise_cells))}
    start = theta

    def objective(theta, structure):
        edges = edges_of(theta, center)
        return gradients.guarantee(structure, system.noise, edges, cells, tol=tol)

    value_and_grad = jax.jit(jax.value_and_grad(objective))
    optimizer = optax.inject_hyperparams(optax.adam)(learning_rate=lr)
    shape = (0, 0)

    def measure(theta):
        nonlocal shape
        edges = edges_of(theta, center)
        structure = gradients.cluster_structure(system, grid, gradients.noise_grid_of(edges))
        # Pad to bucketed shapes so the jitted gradient compiles a handful of times, not per step.
        shape = (max(shape[0], bucket(structure.members.shape[-1], 4)), max(shape[1], bucket(structure.width, 16)))
        value, grad = value_and_grad(theta, structure.padded(*shape))
        return float(value), grad, [np.asarray(e).tolist() for e in edges]

    t0 = time.perf_counter()
    value, grad, edges = measure(theta)
    state = optimizer.init(theta)
    history = [dict(step=0, mean_p_low=value, accepted=True, radius=float(jnp.exp(theta["log_radius"])),
                    learning_rate=lr, edges=edges, seconds=time.perf_counter() - t0)]
    log(f"step   0  mean p_low {value:.5f}  r_W {history[-1]['radius']:.4f}  |grad| "
        f"{float(optax.global_norm(grad)):.3e}")
    for step in range(1, steps + 1):
        t0 = time.perf_counter()
        updates, new_state = optimizer.update(jax.tree.map(jnp.negative, grad), state, theta)  # ascend
        candidate = optax.apply_updates(theta, updates)
        c_value, c_grad, c_edges = measure(candidate)
        accepted = c_value >= value
        rate = float(state.hyperparams["learning_rate"])
        if rate < 1e-3 * lr:  # wedged against a structure change that lowers the value: done
            log(f"step {step:3d}  stopping: the learning rate fell below {1e-3 * lr:g}")
            break
        if accepted:
            theta, value, grad, state = candidate, c_value, c_grad, new_state
        else:  # the structure changed for the worse: stay, and try a shorter step
            state.hyperparams["learning_rate"] = jnp.asarray(rate / 2)
        history.append(dict(step=step, mean_p_low=c_value, accepted=bool(accepted),
                            radius=float(jnp.exp(candidate["log_radius"])), learning_rate=rate, edges=c_edges,
                            seconds=time.perf_counter() - t0))
        log(f"step {step:3d}  mean p_low {c_value:.5f}  r_W {history[-1]['radius']:.4f}  lr {rate:.4f}  "
            f"{'accepted' if accepted else 'rejected'}  best {value:.5f}  {history[-1]['seconds']:.2f} s")
    return history, start, theta


def evaluate(system, grid, theta, cells, tol: float = 1e-6):
    """Sound numbers for a partition, from scratch: mean p_low, mean p_up over ``cells``, e_avg."""
    noise_grid = gradients.noise_grid_of(edges_of(theta, jnp.asarray(system.noise.mean())))
    solution = sj.synthesize(sj.abstract(system, grid, noise_grid, "smdp"), tol=tol)
    p_low, p_up = sj.metrics.average_bounds(solution, cells)
    return dict(radius=float(jnp.exp(theta["log_radius"])), mean_p_low=p_low, mean_p_up=p_up,
                e_avg=sj.metrics.average_error(solution, grid),
                edges=[np.asarray(e).tolist() for e in noise_grid.edges])


def main(argv=None):
    small = os.environ.get("SMDPJAX_SMALL") == "1"
    parser = argument_parser(__doc__, "tune_noise_partition")
    parser.add_argument("--cells", type=int, default=16 if small else 20, help="state grid cells per dimension")
    parser.add_argument("--noise-cells", type=int, default=6 if small else 12, help="noise cells per axis")
    parser.add_argument("--initial", type=int, default=100, help="initial cells |S_0| (capped at S_nt)")
    parser.add_argument("--steps", type=int, default=3 if small else 40)
    parser.add_argument("--lr", type=float, default=0.05)
    args = parser.parse_args(argv)

    system, grid, _ = problem(args.cells)
    cells = sj.metrics.initial_cells(grid, min(args.initial, grid.nonterminal.size), seed=0)
    history, start, best = tune(system, grid, cells, noise_cells=args.noise_cells, steps=args.steps, lr=args.lr)
    rows = {"uniform r_W=2.1 (paper)": evaluate(system, grid, start, cells),
            "tuned": evaluate(system, grid, best, cells)}
    print(f"\n{'partition':26} {'r_W':>7} {'mean p_low':>10} {'mean p_up':>10} {'e_avg':>8}")
    for name, r in rows.items():
        print(f"{name:26} {r['radius']:7.4f} {r['mean_p_low']:10.5f} {r['mean_p_up']:10.5f} {r['e_avg']:8.5f}")
    print("tuned edges per axis:")
    for e in rows["tuned"]["edges"]:
        print("  " + " ".join(f"{x:+.3f}" for x in e))
    write_result("tune_noise_partition", args, history=history, results=rows)
    print(f"\nwrote {args.out}")
    return history, rows


if __name__ == "__main__":
    main()
