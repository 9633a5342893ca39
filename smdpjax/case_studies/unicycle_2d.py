"""Case study 1: the linear 2-D unicycle (Table 1 rows 1-16)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..noise import Gaussian
from ..partition import NoiseGrid, StateGrid
from ..system import System
from .case_study import CaseStudy

DT = 0.1
SPEED = 1.0


def dynamics(x, u, w):
    """x' = x + dt (v (cos th_a, sin th_a) + w): ``x (2,)`` position, ``u (1,)`` heading."""
    return x + DT * (SPEED * jnp.array([jnp.cos(u[0]), jnp.sin(u[0])]) + w)


def unicycle_2d(cells: int = 30, noise_cells: int = 12) -> CaseStudy:
    """``cells`` x ``cells`` grid on [0, 1]^2 (paper: 30, 45, 60, 75), 8 headings a pi/4,
    w ~ N(0, 0.3^2 I), noise ball centre 0, radius 2.1 with ``noise_cells`` per axis + remainder."""
    system = System(dynamics, actions=(np.arange(8) * np.pi / 4)[:, None], noise=Gaussian([0.0, 0.0], [0.3, 0.3]))
    grid = StateGrid([0, 0], [1, 1], cells, reach=[([0.8, 0.8], [1.0, 1.0])],
                     avoid=[([0.40, 0.30], [0.60, 0.70]), ([0.75, 0.50], [0.90, 0.65])])
    noise = NoiseGrid.ball([0.0, 0.0], 2.1, noise_cells)
    # Natural enclosures: each variable occurs once per output, so the centred form never tightens
    # an index box here (30x30: identical boxes, tests/test_case_studies.py).
    return CaseStudy("unicycle_2d", system, grid, noise, objective="reach_avoid", max_steps=1000,
                     reach_method="natural")
