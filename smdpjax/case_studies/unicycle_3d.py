"""Case study 2: the 3-D unicycle with Coulomb friction and a periodic heading (rows 17-28)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..noise import Gaussian
from ..partition import NoiseGrid, StateGrid
from ..system import System
from .case_study import CaseStudy

DT = 0.1


def dynamics(x, u, w):
    """Nonlinear in state and noise. ``x = (p_x, p_y, th)``, ``u = (v, om)``, ``w = (w1, w2)``:
    friction w1 slows the vehicle but cannot reverse it, w2 perturbs the yaw rate."""
    speed = jnp.maximum(u[0] - w[0], 0.0)
    return jnp.array([x[0] + DT * speed * jnp.cos(x[2]), x[1] + DT * speed * jnp.sin(x[2]),
                      x[2] + DT * (u[1] + w[1])])


def unicycle_3d(noise_cells: int = 6, cells: int = 30) -> CaseStudy:
    """``cells``^3 grid on [0,1]^2 x [0, 2 pi) (heading periodic), 10 actions
    {0.5, 1.5} x {-6, -3, 0, 3, 6}, w ~ N((0.4, 0), 0.5^2 I), noise ball centre (0.4, 0), radius 2,
    ``noise_cells`` per axis (paper: 6, 8, 10) + remainder."""
    actions = np.array([[v, om] for v in (0.5, 1.5) for om in (-6.0, -3.0, 0.0, 3.0, 6.0)])
    system = System(dynamics, actions=actions, noise=Gaussian([0.4, 0.0], [0.5, 0.5]))
    two_pi = 2 * np.pi
    grid = StateGrid([0, 0, 0], [1, 1, two_pi], cells, periodic=[False, False, True],
                     reach=[([0.7, 0.7, 0.0], [1.0, 1.0, two_pi])],
                     avoid=[([0.40, 0.30, 0.0], [0.60, 0.70, two_pi])])
    noise = NoiseGrid.ball([0.4, 0.0], 2.0, noise_cells)
    # Natural enclosures: on the 30^3 grid with 6x6 noise cells they give exactly the index boxes of
    # natural and centred forms intersected (8.3M boxes), in 1.1 s instead of 12.5 s on 2 cores.
    return CaseStudy("unicycle_3d", system, grid, noise, objective="reach_avoid", max_steps=1000,
                     reach_method="natural")
