"""A 4-D planar double integrator with additive Gaussian noise, reach-avoid around two obstacles.

State x = (p_x, p_y, v_x, v_y), input u = (a_x, a_y) an acceleration, w = (w_x, w_y) an
acceleration disturbance on both axes; the exact zero-order-hold discretization with time step
``DT = 1``:

    p' = p + dt v + dt^2/2 (a + w),    v' = v + dt (a + w)

that is ``x' = g(x, u) + B w`` with ``g(x, u) = A x + B u``, ``A = [[I, dt I], [0, I]]`` and
``B = [[dt^2/2, 0], [0, dt^2/2], [dt, 0], [0, dt]]`` (one nonzero per row).

* grid box: p in [0, 8]^2, v in [-2, 2]^2 (leaving it is failure: the velocity bounds belong to
  the safe set), ``cells`` per dimension (default 32: 32^4 = 1 048 576 cells);
* 25 actions: a in {-1, -0.5, 0, 0.5, 1}^2;
* noise: w ~ N(0, 0.035^2 I_2); noise partition: the inf-norm ball of radius 3.5 sigma = 0.1225
  around 0 with ``noise_cells`` x ``noise_cells`` cells (default 2), plus the remainder;
* reach: p in [6, 8]^2 with |v_x|, |v_y| <= 0.5; avoid (open boxes in position, any velocity):
  the block (3, 5) x (3, 5) and the ledge (6, 8) x (4, 5) below the goal.

Why these numbers (measured with the SMDP, see docs/case_studies_scaling.md): a reachable box is
at most ``w_p + dt w_v + dt^2/2 dw`` wide in position and ``w_v + dt dw`` in velocity (cell widths
``w_p, w_v``, noise cell width ``dw = 2 * 0.1225 / noise_cells``): at 32 cells (0.25 x 0.125) and
2 noise cells per axis, 0.436 < 2 w_p and 0.2475 < 2 w_v, so boxes span 1 to 3 cells per
dimension. An SMDP backup lets the adversary move the state by about one cell per dimension
per step, so the controller needs accelerations finer than the velocity range: with
{-1, 0, 1}^2 (9 actions) p_low from rest at (1, 1) is 0.006 at 16^4 cells, with the half
steps (25 actions) 0.62. Below about 16 cells per dimension the goal is too few cells wide for
the SMDP to certify anything (p_low is 0 from rest on 12^4 cells).

Declared with ``System.additive``; g is affine with each state variable once per output, so
natural interval arithmetic encloses it exactly (up to outward rounding): ``reach_method="natural"``.
"""

from __future__ import annotations

import itertools

import jax.numpy as jnp
import numpy as np

from ..noise import Gaussian
from ..partition import NoiseGrid, StateGrid
from ..system import System
from .case_study import CaseStudy

DT = 1.0
POSITION = (0.0, 8.0)  # p_x, p_y bounds
VELOCITY = (-2.0, 2.0)  # v_x, v_y bounds
ACCELERATIONS = (-1.0, -0.5, 0.0, 0.5, 1.0)  # per axis: 25 actions
NOISE_STD = 0.035
NOISE_RADIUS = 3.5 * NOISE_STD
REACH = ([6.0, 6.0, -0.5, -0.5], [8.0, 8.0, 0.5, 0.5])
AVOID = (([3.0, 3.0, VELOCITY[0], VELOCITY[0]], [5.0, 5.0, VELOCITY[1], VELOCITY[1]]),
         ([6.0, 4.0, VELOCITY[0], VELOCITY[0]], [8.0, 5.0, VELOCITY[1], VELOCITY[1]]))
B = np.array([[DT ** 2 / 2, 0.0], [0.0, DT ** 2 / 2], [DT, 0.0], [0.0, DT]])  # (4, 2)
B.setflags(write=False)


def drift(x, u):
    """g(x, u) = A x + B u: ``x (4,) = (p_x, p_y, v_x, v_y)``, ``u (2,)`` accelerations -> ``(4,)``.
    Each variable once per output (``p + dt v + dt^2/2 a``, ``v + dt a``): exact intervals."""
    return jnp.concatenate([x[:2] + DT * x[2:] + (DT ** 2 / 2) * u, x[2:] + DT * u])


def zoh_step(x, u, w):
    """The ZOH formulas written out (reference for tests): ``x (..., 4)``, ``u, w (..., 2)``."""
    p, v = x[..., :2], x[..., 2:]
    return jnp.concatenate([p + DT * v + DT ** 2 / 2 * (u + w), v + DT * (u + w)], axis=-1)


def actions() -> np.ndarray:
    """``(25, 2)``: (a_x, a_y) in {-1, -0.5, 0, 0.5, 1}^2, a_x major."""
    return np.array(list(itertools.product(ACCELERATIONS, repeat=2)))


def double_integrator_4d(cells=32, noise_cells: int = 2) -> CaseStudy:
    """``cells`` per dimension (an int or 4 ints; default 32: 1 048 576 cells) on
    [0, 8]^2 x [-2, 2]^2, 25 actions, w ~ N(0, 0.035^2 I_2), noise ball radius 0.1225 with
    ``noise_cells`` per axis + remainder (default 2: |C| = 5); reach-avoid, unbounded horizon."""
    if isinstance(noise_cells, bool) or not isinstance(noise_cells, (int, np.integer)) or noise_cells < 1:
        raise ValueError(f"noise_cells must be a positive integer, got {noise_cells!r}")
    system = System.additive(drift, B, actions=actions(), noise=Gaussian([0.0, 0.0], [NOISE_STD, NOISE_STD]))
    grid = StateGrid([POSITION[0], POSITION[0], VELOCITY[0], VELOCITY[0]],
                     [POSITION[1], POSITION[1], VELOCITY[1], VELOCITY[1]], cells, reach=[REACH], avoid=list(AVOID))
    noise = NoiseGrid.ball([0.0, 0.0], NOISE_RADIUS, int(noise_cells))
    return CaseStudy("double_integrator_4d", system, grid, noise, objective="reach_avoid", max_steps=200,
                     reach_method="natural")
