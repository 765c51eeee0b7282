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
from .elevation import (
    TERRAIN_COLORS,
    ElevationMap,
    ElevationParams,
    MapGeometry,
    TerrainClass,
    TerrainParams,
    build_elevation_map,
    classify_terrain,
    dem_without_overhangs,
)
from .fuzzy import FuzzyElevationMap, FuzzyParams, fit_fuzzy_elevation_map

__version__ = "0.1.0"

__all__ = [
    "CollapseParams",
    "CollapseResult",
    "CubeGrid",
    "ElevationMap",
    "ElevationParams",
    "FuzzyElevationMap",
    "FuzzyParams",
    "MapGeometry",
    "TERRAIN_COLORS",
    "TerrainClass",
    "TerrainParams",
    "build_elevation_map",
    "classify_terrain",
    "dem_without_overhangs",
    "fit_fuzzy_elevation_map",
    "PointGapParams",
    "collapse_overhangs",
    "leveling_transform",
    "octomap_column_overhangs",
    "point_gap_overhangs",
    "sigma_from_robot_height",
]
