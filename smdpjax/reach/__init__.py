"""Reachable sets: sound box enclosures of the one-step image of a box under the dynamics."""

from .centered import centered_enclosure, enclose
from .interval import natural_enclosure
from .reachable import reachable_boxes

__all__ = ["natural_enclosure", "centered_enclosure", "enclose", "reachable_boxes"]
