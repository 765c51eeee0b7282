"""terracube: navigable 2.5D elevation maps from ground-robot 3D LiDAR scans."""

from .collapse import (
    CollapseParams,
    CollapseResult,
    CubeGrid,
    PointGapParams,
    collapse_overhangs,
    leveling_transform,
    octomap_column_overhangs,
    point_gap_overhangs,
    sigma_from_robot_height,
)

__version__ = "0.1.0"

__all__ = [
    "CollapseParams",
    "CollapseResult",
    "CubeGrid",
    "PointGapParams",
    "collapse_overhangs",
    "leveling_transform",
    "octomap_column_overhangs",
    "point_gap_overhangs",
    "sigma_from_robot_height",
]
