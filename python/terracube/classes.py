"""The terrain classes of map cells and their picture colours.

A module of its own so that the pictures (:mod:`terracube.viz`, :mod:`terracube.viewer`) and the
maps (:mod:`terracube.elevation`) both use them without importing each other.
"""

from __future__ import annotations

import enum

__all__ = ["TERRAIN_COLORS", "TerrainClass"]


class TerrainClass(enum.IntEnum):
    """Per-cell terrain class (uint8), mirroring ``terracube::TerrainClass``."""

    UNKNOWN = 0
    GROUND = 1
    OBSTACLE = 2
    OVERHANGING_OBJECT = 3
    VERTICAL_OBJECT = 4
    HORIZONTAL_EDGE = 5


#: RGB colours used for class pictures.
TERRAIN_COLORS = {
    TerrainClass.UNKNOWN: (1.0, 1.0, 1.0),
    TerrainClass.GROUND: (0.62, 0.80, 0.45),
    TerrainClass.OBSTACLE: (0.90, 0.35, 0.20),
    TerrainClass.OVERHANGING_OBJECT: (0.15, 0.55, 0.25),
    TerrainClass.VERTICAL_OBJECT: (0.30, 0.30, 0.75),
    TerrainClass.HORIZONTAL_EDGE: (0.95, 0.80, 0.20),
}
