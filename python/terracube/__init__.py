"""terracube: navigable 2.5D elevation maps from ground-robot 3D LiDAR scans."""

from . import io
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
from .registration import (
    DEFAULT_CLASS_WEIGHTS,
    PclIcpParams,
    RegistrationParams,
    RegistrationResult,
    StopReason,
    has_pcl,
    pcl_icp,
    points_of_map,
    register_maps,
    register_maps_all_cells,
    register_points,
)

__version__ = "0.1.0"

__all__ = [
    "io",
    "CollapseParams",
    "DEFAULT_CLASS_WEIGHTS",
    "PclIcpParams",
    "RegistrationParams",
    "RegistrationResult",
    "StopReason",
    "has_pcl",
    "pcl_icp",
    "points_of_map",
    "register_maps",
    "register_maps_all_cells",
    "register_points",
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
