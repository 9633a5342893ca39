"""Case study 3: n-room temperature regulation, verification of a look-up table (rows 29-40)."""

from __future__ import annotations

import itertools

import jax.numpy as jnp
import numpy as np

from ..noise import Gaussian
from ..partition import NoiseGrid, StateGrid
from ..system import System
from .case_study import CaseStudy

# Abate et al. (2008) coefficients per 10 minutes, doubled for 20-minute steps.
LOSS = 0.0334  # b: to the ambient temperature
COUPLING = 0.044  # a: between neighbouring rooms
AMBIENT = 6.0  # x_a
HEATER = 0.8 * 1.6  # 0.8 c
SETPOINT = 19.75  # heater on below the middle of the band
BAND = (17.5, 22.0)
NOISE_STD = 0.0075
HORIZON = 15


def dynamics(x, u, w):
    """x_i' = (x_i + b (x_a - x_i) + sum_{j ~ i} a (x_j - x_i) + 0.8 c u_i) (1 + w_i), rooms in a
    row (room i's neighbours are i - 1 and i + 1). ``x, u, w: (n,)``.

    Written with every state variable once per output, ``((1 - b - a d_i) x_i + a x_{i-1} +
    a x_{i+1} + b x_a + 0.8 c u_i) (1 + w_i)`` with ``d_i`` room i's number of neighbours: the
    same map (``textbook_dynamics`` is the form above; they agree to rounding), but natural
    interval arithmetic is then exact up to outward rounding (an affine map of independent
    intervals, times an independent interval), so the cheap ``"natural"`` enclosure is tighter
    than the centred form was on the textbook form.
    """
    n = x.shape[-1]
    index = np.arange(n)
    neighbours = np.minimum(index, 1) + np.minimum(index[::-1], 1)
    own = 1.0 - LOSS - COUPLING * neighbours
    left = jnp.pad(x[:-1], (1, 0))  # x_{i-1}, 0 for the first room
    right = jnp.pad(x[1:], (0, 1))  # x_{i+1}, 0 for the last room
    return (own * x + COUPLING * (left + right) + (LOSS * AMBIENT + HEATER * u)) * (1 + w)


def textbook_dynamics(x, u, w):
    """The model as the paper writes it (``dynamics`` is the same map, arranged for intervals)."""
    step = x[1:] - x[:-1]  # x_{i+1} - x_i
    exchange = jnp.pad(step, (0, 1)) - jnp.pad(step, (1, 0))  # from the right and the left neighbour
    return (x + LOSS * (AMBIENT - x) + COUPLING * exchange + HEATER * u) * (1 + w)


def lookup_table(grid: StateGrid) -> np.ndarray:
    """``(N,)`` action index per cell: heater i on iff the centre of the cell's i-th interval is
    below the set point. Action ``k`` switches heater ``i`` on iff bit ``n - 1 - i`` of ``k`` is set
    (the order of ``itertools.product``)."""
    on = (np.asarray(grid.cell_centers()) < SETPOINT).astype(np.int64)  # (N, n)
    weights = 1 << np.arange(grid.n - 1, -1, -1)
    return (on @ weights).astype(np.int32)


def temperature(rooms: int = 2, cells: int = 12, noise_cells: int = 4) -> CaseStudy:
    """``rooms`` rooms (paper: 2, 3, 4) on [17.5, 22]^n with ``cells`` per dimension, 2^n heater
    actions, multiplicative noise w ~ N(0, 0.0075^2 I), noise ball radius 0.0295 with
    ``noise_cells`` per axis + remainder; verify the look-up table for 15-step safety."""
    if int(rooms) < 1:
        raise ValueError(f"rooms must be a positive integer, got {rooms}")
    actions = np.array(list(itertools.product((0.0, 1.0), repeat=rooms)))
    system = System(dynamics, actions=actions, noise=Gaussian(np.zeros(rooms), np.full(rooms, NOISE_STD)))
    grid = StateGrid(np.full(rooms, BAND[0]), np.full(rooms, BAND[1]), cells)
    noise = NoiseGrid.ball(np.zeros(rooms), 0.0295, noise_cells)
    return CaseStudy("temperature", system, grid, noise, objective="safety", horizon=HORIZON,
                     controller=lookup_table(grid), max_steps=HORIZON, reach_method="natural")
