"""terracube: navigable 2.5D elevation maps from ground-robot 3D LiDAR scans."""

from . import _core

if getattr(_core, "__file__", None) is None:  # only the stubs' folder, python/terracube/_core/
    raise ImportError("terracube._core, the compiled extension, is missing: pip install . (scripts/setup.sh)")

from . import bag, config, evaluation, io, pipeline, pose_graph, poses, simulation
from .collapse import (
    CollapseParams,
    CollapseResult,
    CubeGrid,
    CubeReason,
    PointBasedParams,
    attitude_from_gravity,
    collapse_overhangs,
    leveling_transform,
    no_return_directions,
    octomap_column_overhangs,
    point_based_overhangs,
    point_reasons,
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
from .evaluation import absolute_trajectory_error, compare_region_layouts, relative_pose_error
from .fuzzy import FuzzyElevationMap, FuzzyParams, fit_fuzzy_elevation_map
from .local_map import LocalMap, LocalMapParams
from .mapping import LoopClosure, Mapper, MapperParams, ScanReport, run_mapper
from .pose_graph import PoseGraphEdge, PoseGraphParams, optimize_pose_graph
from .registration import (
    DEFAULT_CLASS_WEIGHTS,
    PclIcpParams,
    RegistrationParams,
    RegistrationResult,
    StopReason,
    constrained_directions,
    has_pcl,
    pcl_gicp,
    pcl_icp,
    points_of_map,
    register_maps,
    register_maps_all_cells,
    register_points,
)
from .traversability import TraversabilityParams, add_traversability_layers

__version__ = "0.1.0"

__all__ = [
    "bag",
    "config",
    "evaluation",
    "io",
    "pipeline",
    "pose_graph",
    "poses",
    "simulation",
    "absolute_trajectory_error",
    "compare_region_layouts",
    "relative_pose_error",
    "LocalMap",
    "LocalMapParams",
    "TraversabilityParams",
    "LoopClosure",
    "Mapper",
    "MapperParams",
    "ScanReport",
    "run_mapper",
    "PoseGraphEdge",
    "PoseGraphParams",
    "optimize_pose_graph",
    "CollapseParams",
    "DEFAULT_CLASS_WEIGHTS",
    "PclIcpParams",
    "RegistrationParams",
    "RegistrationResult",
    "StopReason",
    "has_pcl",
    "pcl_gicp",
    "pcl_icp",
    "points_of_map",
    "register_maps",
    "register_maps_all_cells",
    "register_points",
    "constrained_directions",
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
    "add_traversability_layers",
    "dem_without_overhangs",
    "fit_fuzzy_elevation_map",
    "PointBasedParams",
    "collapse_overhangs",
    "no_return_directions",
    "attitude_from_gravity",
    "leveling_transform",
    "octomap_column_overhangs",
    "point_based_overhangs",
    "point_reasons",
    "CubeReason",
    "sigma_from_robot_height",
]
