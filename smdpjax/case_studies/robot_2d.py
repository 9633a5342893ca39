"""The 2-D robot of IMPaCT (Wooding & Lavaei, 2024), a reach-avoid benchmark with additive noise.

    x' = x + 10 u_0 (cos u_1, sin u_1) + w,    w ~ N(0, 0.75 I)

* state x in [-10, 10]^2, a 40 x 40 grid of cells of width 0.5 (``cells``);
* inputs u_0, u_1 in [-1, 1], each on the grid of step 0.1 (21 values, ``inputs``): 441 actions
  (u_0 = 0 gives 21 identical "stay" actions, as in IMPaCT; u_0 < 0 drives backwards);
* noise: covariance 0.75 I (IMPaCT's inverse covariance 1.3333 I, determinant 0.5625), so each
  component has standard deviation sqrt(0.75) = 0.866;
* reach [5, 7]^2, avoid [-2, 2]^2 (both aligned with the grid), unbounded horizon;
* noise partition for the Lemma 1 classes: the ball of radius 4 sigma around 0 with
  ``noise_cells`` x ``noise_cells`` cells, plus the remainder.

Declared with ``System.additive`` (g = x + 10 u_0 (cos u_1, sin u_1), B = I), so the direct IMDP
(``abstract(..., kind="imdp", bounds="direct")``) applies; its natural enclosure of g over a cell
is the cell shifted by a point (exact up to outward rounding), hence ``reach_method="natural"``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..noise import Gaussian
from ..partition import NoiseGrid, StateGrid
from ..system import System
from .case_study import CaseStudy

GAIN = 10.0
VARIANCE = 0.75
STD = float(np.sqrt(VARIANCE))
LOW, HIGH = -10.0, 10.0
REACH = ([5.0, 5.0], [7.0, 7.0])
AVOID = ([-2.0, -2.0], [2.0, 2.0])


def drift(x, u):
    """g(x, u) = x + 10 u_0 (cos u_1, sin u_1): ``x (2,)``, ``u (2,)``."""
    return x + GAIN * u[0] * jnp.array([jnp.cos(u[1]), jnp.sin(u[1])])


def actions(inputs: int = 21) -> np.ndarray:
    """``(inputs^2, 2)``: (u_0, u_1) on ``inputs`` equally spaced values of [-1, 1] each (21:
    step 0.1, the decimals k / 10 correctly rounded)."""
    if int(inputs) < 2:
        raise ValueError(f"inputs must be at least 2 (the endpoints -1 and 1), got {inputs}")
    steps = int(inputs) - 1
    values = (2 * np.arange(inputs) - steps) / steps
    u0, u1 = np.meshgrid(values, values, indexing="ij")
    return np.stack([u0.ravel(), u1.ravel()], axis=1)


def robot_2d(cells: int = 40, noise_cells: int = 10, inputs: int = 21) -> CaseStudy:
    """IMPaCT's robot: ``cells`` x ``cells`` grid on [-10, 10]^2 (40: width 0.5), ``inputs``^2
    actions (21: 441), w ~ N(0, 0.75 I); noise ball radius 4 sqrt(0.75) with ``noise_cells`` per
    axis + remainder (used by the Lemma 1 classes only). ``cells`` must keep [5, 7] and [-2, 2]
    on cell faces for the labels to match the sets exactly (multiples of 20 do)."""
    system = System.additive(drift, None, actions=actions(inputs), noise=Gaussian([0.0, 0.0], [STD, STD]))
    grid = StateGrid([LOW, LOW], [HIGH, HIGH], cells, reach=[REACH], avoid=[AVOID])
    noise = NoiseGrid.ball([0.0, 0.0], 4 * STD, noise_cells)
    return CaseStudy("robot_2d", system, grid, noise, objective="reach_avoid", max_steps=1000,
                     reach_method="natural")
