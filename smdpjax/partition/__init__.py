"""Partitions of the state space (S) and of the disturbance space (C)."""

from .noise_grid import NoiseGrid, cell_boxes, cell_probabilities
from .state_grid import AVOID, NONTERMINAL, REACH, StateGrid

__all__ = ["StateGrid", "NoiseGrid", "cell_boxes", "cell_probabilities", "NONTERMINAL", "REACH", "AVOID"]
