"""
terracube C++ core (private: use the terracube package)
"""
from __future__ import annotations
import collections.abc
import numpy
import numpy.typing
import typing
from . import simulation
__all__: list[str] = ['AbsoluteTrajectoryError', 'CollapseMethod', 'CollapseParams', 'CollapseResult', 'CorrelativeSearchParams', 'CorrelativeSearchResult', 'CropBox', 'CubeGrid', 'CubeReason', 'CubeStorage', 'ElevationMap', 'ElevationParams', 'ErrorStatistics', 'FuzzyElevationMap', 'FuzzyParams', 'GroundReference', 'LocalMap', 'LocalMapParams', 'LocalMapUpdate', 'LoopClosure', 'MapGeometry', 'Mapper', 'MapperParams', 'MapperTimings', 'MembershipFamily', 'OverhangFreeMap', 'Pairing', 'PclIcpParams', 'PclIcpResult', 'PointBasedParams', 'PoseGraphEdge', 'PoseGraphParams', 'PoseGraphResult', 'PoseSegmentError', 'RegionLayoutComparison', 'RegionPairError', 'RegionRelations', 'RegionTripleError', 'RegistrationParams', 'RegistrationResult', 'RelativePoseError', 'RelativePoseErrorParams', 'RobustLoss', 'ScanReport', 'SegmentLengthError', 'ShadowAwareParams', 'StepRule', 'StopReason', 'TerrainParams', 'TrajectoryAlignment', 'TraversabilityParams', 'absolute_trajectory_error', 'add_traversability_layers', 'attitude_from_gravity', 'build_elevation_map', 'build_elevation_map_into', 'build_overhang_free_map', 'classify_terrain', 'collapse_overhangs', 'compare_region_layouts', 'correlative_search', 'cube_reason_name', 'error_statistics', 'fit_fuzzy_elevation_map', 'has_pcl', 'leveling_transform', 'octomap_column_overhangs', 'optimize_pose_graph', 'pcl_gicp', 'pcl_icp', 'point_based_overhangs', 'point_reasons', 'points_of_map', 'register_maps', 'register_points', 'relative_pose_error', 'rigid_alignment', 'sigma_from_robot_height', 'simulation', 'step_layer']
class CubeGrid:
    """
    CBC grid geometry ([CBC] eqs. (1)-(9)); cube (0,0,0) is centred on min_corner.
    """
    def __getstate__(self) -> dict:
        ...
    def __init__(self) -> None:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    def centers(self, index: typing.Annotated[numpy.typing.ArrayLike, numpy.int64]) -> numpy.typing.NDArray[numpy.float64]:
        """
        (K,) int64 cube indices I -> (K, 3) float64 cube centres [m]
        """
    def coordinates(self, index: typing.Annotated[numpy.typing.ArrayLike, numpy.int64]) -> numpy.typing.NDArray[numpy.int64]:
        """
        (K,) int64 cube indices I -> (K, 3) int64 (ix, iy, iz), [CBC] eqs. (7)-(9)
        """
    @property
    def edge(self) -> float:
        """
        cube edge E [m]
        """
    @property
    def ixmax(self) -> int:
        """
        cubes along x
        """
    @property
    def iymax(self) -> int:
        """
        cubes along y
        """
    @property
    def izmax(self) -> int:
        """
        cubes along z
        """
    @property
    def min_corner(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[3, 1]"]:
        """
        (3,) float64: (xmin, ymin, zmin) [m]
        """
    @property
    def num_columns(self) -> int:
        ...
    @property
    def num_cubes(self) -> int:
        ...
class CubeStorage:
    """
    Members:
    
      auto
    
      dense
    
      sparse
    """
    __members__: typing.ClassVar[dict[str, CubeStorage]]
    auto: typing.ClassVar[CubeStorage]
    dense: typing.ClassVar[CubeStorage]
    sparse: typing.ClassVar[CubeStorage]
    @typing.overload
    def __eq__(self, other: CubeStorage) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: CubeStorage) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class CropBox:
    def __init__(self, min: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[3, 1]"], max: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[3, 1]"]) -> None:
        ...
    @property
    def max(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[3, 1]"]:
        ...
    @max.setter
    def max(self, arg0: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[3, 1]"]) -> None:
        ...
    @property
    def min(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[3, 1]"]:
        ...
    @min.setter
    def min(self, arg0: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[3, 1]"]) -> None:
        ...
class CollapseMethod:
    """
    Members:
    
      paper
    
      shadow_aware
    """
    __members__: typing.ClassVar[dict[str, CollapseMethod]]
    paper: typing.ClassVar[CollapseMethod]
    shadow_aware: typing.ClassVar[CollapseMethod]
    @typing.overload
    def __eq__(self, other: CollapseMethod) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: CollapseMethod) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class CubeReason:
    """
    Why the shadow-aware rule kept or removed a cube (terracube::CubeReason, uint8)
    
    Members:
    
      supported
    
      below_ground
    
      no_ground_estimate
    
      shadowed
    
      removed_above_kept
    
      removed_free_below
    
      thin
    
      removed_rim
    
      not_used
    """
    __members__: typing.ClassVar[dict[str, CubeReason]]
    below_ground: typing.ClassVar[CubeReason]
    no_ground_estimate: typing.ClassVar[CubeReason]
    not_used: typing.ClassVar[CubeReason]
    removed_above_kept: typing.ClassVar[CubeReason]
    removed_free_below: typing.ClassVar[CubeReason]
    removed_rim: typing.ClassVar[CubeReason]
    shadowed: typing.ClassVar[CubeReason]
    supported: typing.ClassVar[CubeReason]
    thin: typing.ClassVar[CubeReason]
    @typing.overload
    def __eq__(self, other: CubeReason) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: CubeReason) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class ShadowAwareParams:
    remove_rims: bool
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    @property
    def azimuth_bins(self) -> int:
        ...
    @azimuth_bins.setter
    def azimuth_bins(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def bottom_window(self) -> int:
        ...
    @bottom_window.setter
    def bottom_window(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def free_margin_m(self) -> float:
        ...
    @free_margin_m.setter
    def free_margin_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def ground_radius_m(self) -> float:
        ...
    @ground_radius_m.setter
    def ground_radius_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def ground_support(self) -> int:
        ...
    @ground_support.setter
    def ground_support(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def hidden_ground_margin_m(self) -> float:
        ...
    @hidden_ground_margin_m.setter
    def hidden_ground_margin_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def min_bottom_neighbours(self) -> int:
        ...
    @min_bottom_neighbours.setter
    def min_bottom_neighbours(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def no_return_range_m(self) -> float:
        ...
    @no_return_range_m.setter
    def no_return_range_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def sensor_origin(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[3, 1]"] | None:
        ...
    @sensor_origin.setter
    def sensor_origin(self, arg0: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[3, 1]"] | None) -> None:
        ...
class CollapseParams:
    crop: CropBox | None
    drop_non_finite: bool
    method: CollapseMethod
    shadow_aware: ShadowAwareParams
    storage: CubeStorage
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    @property
    def dense_budget_bytes(self) -> int:
        ...
    @dense_budget_bytes.setter
    def dense_budget_bytes(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def edge_m(self) -> float:
        ...
    @edge_m.setter
    def edge_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def num_threads(self) -> int:
        ...
    @num_threads.setter
    def num_threads(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def sigma(self) -> int:
        ...
    @sigma.setter
    def sigma(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def transform(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        ...
    @transform.setter
    def transform(self, arg0: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[4, 4]"]) -> None:
        ...
class CollapseResult:
    """
    Result of collapse_overhangs; arrays are views into it. Pickles whole (its arrays copied).
    """
    def __getstate__(self) -> tuple:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: tuple) -> None:
        ...
    @property
    def cube_reasons(self) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
        """
        (K,) uint8: CubeReason per cube of occupied_cubes (method shadow_aware; empty for paper)
        """
    @property
    def grid(self) -> CubeGrid:
        ...
    @property
    def num_cropped(self) -> int:
        ...
    @property
    def num_dropped_non_finite(self) -> int:
        ...
    @property
    def num_overhang(self) -> int:
        ...
    @property
    def num_points(self) -> int:
        ...
    @property
    def num_used(self) -> int:
        ...
    @property
    def occupied_cubes(self) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
        """
        (K,) int64: L, indices I of occupied cubes, sorted
        """
    @property
    def overhang(self) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
        """
        (N,) bool: the point lies in a collapsed cube (input order)
        """
    @property
    def removed_cubes(self) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
        """
        (R,) int64: R, indices I of collapsed cubes, sorted
        """
    @property
    def storage_used(self) -> str:
        ...
class PointBasedParams:
    crop: CropBox | None
    drop_non_finite: bool
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    @property
    def edge_m(self) -> float:
        ...
    @edge_m.setter
    def edge_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def sigma(self) -> int:
        ...
    @sigma.setter
    def sigma(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def transform(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        ...
    @transform.setter
    def transform(self, arg0: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[4, 4]"]) -> None:
        ...
    @property
    def variance_threshold_m2(self) -> float:
        ...
    @variance_threshold_m2.setter
    def variance_threshold_m2(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
class MapGeometry:
    """
    Cell (i, j) is centred on origin + (i + 0.5, j + 0.5) * resolution; i along x, j along y.
    """
    __hash__: typing.ClassVar[None] = None
    def __eq__(self, arg0: MapGeometry) -> bool:
        ...
    def __getstate__(self) -> dict:
        ...
    def __init__(self, resolution: typing.SupportsFloat | typing.SupportsIndex, origin: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[2, 1]"], size: typing.Annotated[numpy.typing.ArrayLike, numpy.int32, "[2, 1]"]) -> None:
        ...
    def __ne__(self, arg0: MapGeometry) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    def index_of(self, x: typing.SupportsFloat | typing.SupportsIndex, y: typing.SupportsFloat | typing.SupportsIndex) -> tuple[int, int] | None:
        """
        cell (i, j) holding (x, y), or None outside the map
        """
    def position_of(self, i: typing.SupportsInt | typing.SupportsIndex, j: typing.SupportsInt | typing.SupportsIndex) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[2, 1]"]:
        """
        centre of cell (i, j) [m]
        """
    @property
    def length(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[2, 1]"]:
        """
        (2,) map length along x and y [m]
        """
    @property
    def num_cells(self) -> int:
        ...
    @property
    def origin(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[2, 1]"]:
        """
        (2,) lower-left corner of cell (0, 0) [m]
        """
    @property
    def resolution(self) -> float:
        """
        cell edge [m]
        """
    @property
    def size(self) -> typing.Annotated[numpy.typing.NDArray[numpy.int32], "[2, 1]"]:
        """
        (2,) cells along x and y
        """
class ElevationMap:
    def __getstate__(self) -> tuple:
        ...
    def __init__(self, geometry: MapGeometry) -> None:
        ...
    def __setstate__(self, arg0: tuple) -> None:
        ...
    def add(self, name: str, data: typing.Annotated[numpy.typing.ArrayLike, numpy.float32]) -> None:
        ...
    def add_constant(self, name: str, value: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    def exists(self, name: str) -> bool:
        ...
    def get(self, name: str) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
        """
        (nx, ny) float32 view of a layer; KeyError when missing
        """
    @property
    def geometry(self) -> MapGeometry:
        ...
    @property
    def layers(self) -> list[str]:
        ...
class ElevationParams:
    crop: CropBox | None
    drop_non_finite: bool
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    def clear_extent(self) -> None:
        ...
    def set_extent(self, origin_x: typing.SupportsFloat | typing.SupportsIndex, origin_y: typing.SupportsFloat | typing.SupportsIndex, size_x: typing.SupportsInt | typing.SupportsIndex, size_y: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def discontinuity_m(self) -> float:
        ...
    @discontinuity_m.setter
    def discontinuity_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def has_extent(self) -> bool:
        ...
    @property
    def max_cells(self) -> int:
        ...
    @max_cells.setter
    def max_cells(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def num_threads(self) -> int:
        ...
    @num_threads.setter
    def num_threads(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def resolution_m(self) -> float:
        ...
    @resolution_m.setter
    def resolution_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def transform(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        ...
    @transform.setter
    def transform(self, arg0: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[4, 4]"]) -> None:
        ...
class OverhangFreeMap:
    def __getstate__(self) -> tuple[ElevationMap, CollapseResult]:
        ...
    def __setstate__(self, arg0: tuple) -> None:
        ...
    @property
    def collapse(self) -> CollapseResult:
        ...
    @property
    def map(self) -> ElevationMap:
        ...
class GroundReference:
    """
    Members:
    
      sensor_height
    
      local_ground
    """
    __members__: typing.ClassVar[dict[str, GroundReference]]
    local_ground: typing.ClassVar[GroundReference]
    sensor_height: typing.ClassVar[GroundReference]
    @typing.overload
    def __eq__(self, other: GroundReference) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: GroundReference) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class TerrainParams:
    reference: GroundReference
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    @property
    def ground_height_m(self) -> float:
        ...
    @ground_height_m.setter
    def ground_height_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def local_ground_radius_cells(self) -> int:
        ...
    @local_ground_radius_cells.setter
    def local_ground_radius_cells(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def num_threads(self) -> int:
        ...
    @num_threads.setter
    def num_threads(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def robot_height_m(self) -> float:
        ...
    @robot_height_m.setter
    def robot_height_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def sensor_height_m(self) -> float:
        ...
    @sensor_height_m.setter
    def sensor_height_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def std_dev_m(self) -> float:
        ...
    @std_dev_m.setter
    def std_dev_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
class MembershipFamily:
    """
    Members:
    
      triangular
    
      gaussian
    """
    __members__: typing.ClassVar[dict[str, MembershipFamily]]
    gaussian: typing.ClassVar[MembershipFamily]
    triangular: typing.ClassVar[MembershipFamily]
    @typing.overload
    def __eq__(self, other: MembershipFamily) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: MembershipFamily) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class StepRule:
    """
    Members:
    
      guarded
    
      jang
    """
    __members__: typing.ClassVar[dict[str, StepRule]]
    guarded: typing.ClassVar[StepRule]
    jang: typing.ClassVar[StepRule]
    @typing.overload
    def __eq__(self, other: StepRule) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: StepRule) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class FuzzyParams:
    membership: MembershipFamily
    step_rule: StepRule
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    def clear_extent(self) -> None:
        ...
    def set_extent(self, x_min: typing.SupportsFloat | typing.SupportsIndex, y_min: typing.SupportsFloat | typing.SupportsIndex, x_max: typing.SupportsFloat | typing.SupportsIndex, y_max: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def epochs(self) -> int:
        ...
    @epochs.setter
    def epochs(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def gaussian_width(self) -> float:
        ...
    @gaussian_width.setter
    def gaussian_width(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def has_extent(self) -> bool:
        ...
    @property
    def learning_rate(self) -> float:
        ...
    @learning_rate.setter
    def learning_rate(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def min_confidence(self) -> float:
        ...
    @min_confidence.setter
    def min_confidence(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def min_points_per_rule(self) -> float:
        ...
    @min_points_per_rule.setter
    def min_points_per_rule(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def ridge(self) -> float:
        ...
    @ridge.setter
    def ridge(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def rules_x(self) -> int:
        ...
    @rules_x.setter
    def rules_x(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def rules_y(self) -> int:
        ...
    @rules_y.setter
    def rules_y(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def smoothness(self) -> float:
        ...
    @smoothness.setter
    def smoothness(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
class FuzzyElevationMap:
    def __init__(self, params: FuzzyParams, centers_x: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[m, 1]"], centers_y: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[m, 1]"], consequents: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[m, n]"], rule_support: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[m, n]"], rmse_history: collections.abc.Sequence[typing.SupportsFloat | typing.SupportsIndex] = [], num_training_points: typing.SupportsInt | typing.SupportsIndex = 0) -> None:
        ...
    def confidence(self, xy: typing.Annotated[numpy.typing.NDArray[numpy.float64], "[m, 2]", "flags.c_contiguous"]) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[m, 1]"]:
        ...
    def evaluate(self, xy: typing.Annotated[numpy.typing.NDArray[numpy.float64], "[m, 2]", "flags.c_contiguous"]) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[m, 1]"]:
        ...
    def to_layer(self, map: ElevationMap, min_confidence: typing.SupportsFloat | typing.SupportsIndex, name: str) -> None:
        ...
    @property
    def centers_x(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[m, 1]"]:
        ...
    @property
    def centers_y(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[m, 1]"]:
        ...
    @property
    def consequents(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[m, n]"]:
        ...
    @property
    def extent(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[2, 2]"]:
        """
        ((x_min, y_min), (x_max, y_max)) [m]
        """
    @property
    def gaussian_sigma(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[2, 1]"]:
        ...
    @property
    def num_parameters(self) -> int:
        ...
    @property
    def num_rules(self) -> int:
        ...
    @property
    def num_training_points(self) -> int:
        ...
    @property
    def params(self) -> FuzzyParams:
        ...
    @property
    def rmse_history(self) -> list[float]:
        ...
    @property
    def rule_support(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[m, n]"]:
        ...
class Pairing:
    """
    Members:
    
      source_to_target
    
      target_to_source
    """
    __members__: typing.ClassVar[dict[str, Pairing]]
    source_to_target: typing.ClassVar[Pairing]
    target_to_source: typing.ClassVar[Pairing]
    @typing.overload
    def __eq__(self, other: Pairing) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: Pairing) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class StopReason:
    """
    Members:
    
      converged
    
      error_below_threshold
    
      max_iterations
    
      too_few_correspondences
    
      no_common_class
    
      degenerate
    """
    __members__: typing.ClassVar[dict[str, StopReason]]
    converged: typing.ClassVar[StopReason]
    degenerate: typing.ClassVar[StopReason]
    error_below_threshold: typing.ClassVar[StopReason]
    max_iterations: typing.ClassVar[StopReason]
    no_common_class: typing.ClassVar[StopReason]
    too_few_correspondences: typing.ClassVar[StopReason]
    @typing.overload
    def __eq__(self, other: StopReason) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: StopReason) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class CorrelativeSearchParams:
    refine: bool
    def __init__(self) -> None:
        ...
    @property
    def cell_m(self) -> float:
        ...
    @cell_m.setter
    def cell_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def step_cells(self) -> int:
        ...
    @step_cells.setter
    def step_cells(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def tie_tolerance(self) -> float:
        ...
    @tie_tolerance.setter
    def tie_tolerance(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def window_m(self) -> float:
        ...
    @window_m.setter
    def window_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def yaw_hypotheses(self) -> int:
        ...
    @yaw_hypotheses.setter
    def yaw_hypotheses(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def yaw_window_rad(self) -> float:
        ...
    @yaw_window_rad.setter
    def yaw_window_rad(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
class RegistrationParams:
    correlative_search: bool
    extrapolate: bool
    pairing: Pairing
    search: CorrelativeSearchParams
    use_classes: bool
    @staticmethod
    def paper_icp() -> RegistrationParams:
        """
        the paper's plain weighted ICP: no correlative search, extrapolation or coarse-to-fine
        """
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    @property
    def class_weights(self) -> typing.Annotated[list[float], "FixedSize(6)"]:
        ...
    @class_weights.setter
    def class_weights(self, arg0: typing.Annotated[collections.abc.Sequence[typing.SupportsFloat | typing.SupportsIndex], "FixedSize(6)"]) -> None:
        ...
    @property
    def coarse_subsample(self) -> int:
        ...
    @coarse_subsample.setter
    def coarse_subsample(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def coarse_until_motion_m(self) -> float:
        ...
    @coarse_until_motion_m.setter
    def coarse_until_motion_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def correspondence_distance_decay(self) -> float:
        ...
    @correspondence_distance_decay.setter
    def correspondence_distance_decay(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def degeneracy_threshold(self) -> float:
        ...
    @degeneracy_threshold.setter
    def degeneracy_threshold(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def error_threshold_m(self) -> float:
        ...
    @error_threshold_m.setter
    def error_threshold_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def ground_cell_m(self) -> float:
        ...
    @ground_cell_m.setter
    def ground_cell_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def ground_weight(self) -> float:
        ...
    @ground_weight.setter
    def ground_weight(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_correspondence_distance_m(self) -> float:
        ...
    @max_correspondence_distance_m.setter
    def max_correspondence_distance_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_iterations(self) -> int:
        ...
    @max_iterations.setter
    def max_iterations(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def min_correspondence_distance_m(self) -> float:
        ...
    @min_correspondence_distance_m.setter
    def min_correspondence_distance_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def min_correspondences(self) -> int:
        ...
    @min_correspondences.setter
    def min_correspondences(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def rotation_tolerance_rad(self) -> float:
        ...
    @rotation_tolerance_rad.setter
    def rotation_tolerance_rad(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def structure_radius_m(self) -> float:
        ...
    @structure_radius_m.setter
    def structure_radius_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def translation_tolerance_m(self) -> float:
        ...
    @translation_tolerance_m.setter
    def translation_tolerance_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def trust_max_rmse_m(self) -> float:
        ...
    @trust_max_rmse_m.setter
    def trust_max_rmse_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def trust_min_contrast(self) -> float:
        ...
    @trust_min_contrast.setter
    def trust_min_contrast(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def trust_min_held(self) -> float:
        ...
    @trust_min_held.setter
    def trust_min_held(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def trust_min_overlap(self) -> float:
        ...
    @trust_min_overlap.setter
    def trust_min_overlap(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
class RegistrationResult:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def chance_overlap(self) -> float:
        """
        the overlap at the result moved by 1 m along +-x or +-y, the least: coincidence alone
        """
    @property
    def constraint_eigenvalues(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[6, 1]"]:
        """
        (6,) eigenvalues of constraint_matrix, ascending
        """
    @property
    def constraint_eigenvectors(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[6, 6]"]:
        """
        (6, 6) unit eigenvectors of constraint_matrix, as columns
        """
    @property
    def constraint_matrix(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[6, 6]"]:
        """
        (6, 6) what the geometry constrains (structure_radius > 0)
        """
    @property
    def converged(self) -> bool:
        ...
    @property
    def correspondence_distance(self) -> float:
        ...
    @property
    def correspondences_per_class(self) -> typing.Annotated[list[int], "FixedSize(6)"]:
        ...
    @property
    def eigenvalues(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[6, 1]"]:
        """
        (6,) eigenvalues of H, ascending
        """
    @property
    def extrapolations(self) -> int:
        """
        extrapolated jumps kept by the guard
        """
    @property
    def held(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[6, 1]"]:
        """
        (6,) how firmly each motion is held, per unit of the class pairs' weight, ascending (0 none, 1 every pair)
        """
    @property
    def held_directions(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[6, 6]"]:
        """
        (6, 6) unit eigenvectors of held as columns (rotation x rms radius, translation)
        """
    @property
    def icp_start(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        """
        (4, 4) where the ICP started: initial, or the correlative search's best hypothesis
        """
    @property
    def inlier_share_per_class(self) -> typing.Annotated[list[float], "FixedSize(6)"]:
        """
        (6,) per source class: share of its points with a partner
        """
    @property
    def iterations(self) -> int:
        ...
    @property
    def normal_matrix(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[6, 6]"]:
        """
        (6, 6) H of eq. (A6)
        """
    @property
    def num_correspondences(self) -> int:
        ...
    @property
    def overlap(self) -> float:
        """
        share of the source's object cells with a partner within the last distance limit
        """
    @property
    def passes(self) -> int:
        """
        correspondence passes: one per iteration, one more per extrapolation tried
        """
    @property
    def reason(self) -> StopReason:
        ...
    @property
    def rmse(self) -> float:
        """
        weighted RMSE of the final correspondences [m]
        """
    @property
    def transform(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        """
        (4, 4) source -> target
        """
    @property
    def trusted(self) -> bool:
        """
        every trust threshold of RegistrationParams met
        """
    @property
    def verdict(self) -> str:
        """
        why the result is (not) trusted, in plain words
        """
class CorrelativeSearchResult:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def points(self) -> int:
        """
        source points that took part (non-ground)
        """
    @property
    def score(self) -> int:
        """
        source points on occupied target cells
        """
    @property
    def transform(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        """
        (4, 4) the best hypothesis, source -> target
        """
class PclIcpParams:
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    @property
    def euclidean_fitness_epsilon(self) -> float:
        ...
    @euclidean_fitness_epsilon.setter
    def euclidean_fitness_epsilon(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_correspondence_distance_m(self) -> float:
        ...
    @max_correspondence_distance_m.setter
    def max_correspondence_distance_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_iterations(self) -> int:
        ...
    @max_iterations.setter
    def max_iterations(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def relative_mse_epsilon(self) -> float:
        ...
    @relative_mse_epsilon.setter
    def relative_mse_epsilon(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def rotation_epsilon(self) -> float:
        ...
    @rotation_epsilon.setter
    def rotation_epsilon(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def transformation_epsilon(self) -> float:
        ...
    @transformation_epsilon.setter
    def transformation_epsilon(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
class PclIcpResult:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def converged(self) -> bool:
        ...
    @property
    def fitness(self) -> float:
        """
        mean squared pair distance [m^2]
        """
    @property
    def iterations(self) -> int:
        ...
    @property
    def transform(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        ...
class TrajectoryAlignment:
    """
    Members:
    
      none
    
      first_pose
    
      rigid
    """
    __members__: typing.ClassVar[dict[str, TrajectoryAlignment]]
    first_pose: typing.ClassVar[TrajectoryAlignment]
    none: typing.ClassVar[TrajectoryAlignment]
    rigid: typing.ClassVar[TrajectoryAlignment]
    @typing.overload
    def __eq__(self, other: TrajectoryAlignment) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: TrajectoryAlignment) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class RegionRelations:
    """
    Members:
    
      consecutive
    
      all_pairs
    """
    __members__: typing.ClassVar[dict[str, RegionRelations]]
    all_pairs: typing.ClassVar[RegionRelations]
    consecutive: typing.ClassVar[RegionRelations]
    @typing.overload
    def __eq__(self, other: RegionRelations) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: RegionRelations) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class ErrorStatistics:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def count(self) -> int:
        ...
    @property
    def max(self) -> float:
        ...
    @property
    def mean(self) -> float:
        ...
    @property
    def median(self) -> float:
        ...
    @property
    def rmse(self) -> float:
        ...
class AbsoluteTrajectoryError:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def alignment(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        """
        (4, 4) applied to the estimate
        """
    @property
    def rotation(self) -> ErrorStatistics:
        """
        statistics [deg]
        """
    @property
    def rotation_errors(self) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
        """
        (K,) [deg]
        """
    @property
    def translation(self) -> ErrorStatistics:
        """
        statistics [m]
        """
    @property
    def translation_errors(self) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
        """
        (K,) [m]
        """
class RelativePoseErrorParams:
    def __init__(self) -> None:
        ...
    @property
    def lengths_m(self) -> list[float]:
        ...
    @lengths_m.setter
    def lengths_m(self, arg0: collections.abc.Sequence[typing.SupportsFloat | typing.SupportsIndex]) -> None:
        ...
    @property
    def step_frames(self) -> int:
        ...
    @step_frames.setter
    def step_frames(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
class PoseSegmentError:
    def __getstate__(self) -> dict:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def first_frame(self) -> int:
        ...
    @property
    def last_frame(self) -> int:
        ...
    @property
    def length(self) -> float:
        ...
    @property
    def rotation_deg_per_100m(self) -> float:
        ...
    @property
    def translation_percent(self) -> float:
        ...
class SegmentLengthError:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def length(self) -> float:
        ...
    @property
    def num_segments(self) -> int:
        ...
    @property
    def rotation_deg_per_100m(self) -> float:
        ...
    @property
    def translation_percent(self) -> float:
        ...
class RelativePoseError:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def num_segments(self) -> int:
        ...
    @property
    def per_length(self) -> list[SegmentLengthError]:
        ...
    @property
    def rotation_deg_per_100m(self) -> float:
        ...
    @property
    def segments(self) -> list[PoseSegmentError]:
        ...
    @property
    def translation_percent(self) -> float:
        ...
class RegionPairError:
    def __getstate__(self) -> dict:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def dsm_distance(self) -> float:
        ...
    @property
    def error(self) -> float:
        ...
    @property
    def i(self) -> int:
        ...
    @property
    def j(self) -> int:
        ...
    @property
    def map_distance(self) -> float:
        ...
class RegionTripleError:
    def __getstate__(self) -> dict:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def dsm_angle(self) -> float:
        ...
    @property
    def error(self) -> float:
        ...
    @property
    def i(self) -> int:
        ...
    @property
    def j(self) -> int:
        ...
    @property
    def k(self) -> int:
        ...
    @property
    def map_angle(self) -> float:
        ...
class RegionLayoutComparison:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def max_angle_error(self) -> float:
        ...
    @property
    def max_distance_error(self) -> float:
        ...
    @property
    def mean_angle_error(self) -> float:
        ...
    @property
    def mean_distance_error(self) -> float:
        ...
    @property
    def pairs(self) -> list[RegionPairError]:
        ...
    @property
    def triples(self) -> list[RegionTripleError]:
        ...
class RobustLoss:
    """
    Members:
    
      huber
    
      cauchy
    """
    __members__: typing.ClassVar[dict[str, RobustLoss]]
    cauchy: typing.ClassVar[RobustLoss]
    huber: typing.ClassVar[RobustLoss]
    @typing.overload
    def __eq__(self, other: RobustLoss) -> bool:
        ...
    @typing.overload
    def __eq__(self, other: typing.Any) -> bool:
        ...
    def __getstate__(self) -> int:
        ...
    def __hash__(self) -> int:
        ...
    def __index__(self) -> int:
        ...
    def __init__(self, value: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __int__(self) -> int:
        ...
    @typing.overload
    def __ne__(self, other: RobustLoss) -> bool:
        ...
    @typing.overload
    def __ne__(self, other: typing.Any) -> bool:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, state: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    def __str__(self) -> str:
        ...
    @property
    def name(self) -> str:
        ...
    @property
    def value(self) -> int:
        ...
class PoseGraphEdge:
    robust: bool
    def __init__(self) -> None:
        ...
    @property
    def from_(self) -> int:
        ...
    @from_.setter
    def from_(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def information(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[6, 6]"]:
        ...
    @information.setter
    def information(self, arg0: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[6, 6]"]) -> None:
        ...
    @property
    def measurement(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        ...
    @measurement.setter
    def measurement(self, arg0: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[4, 4]"]) -> None:
        ...
    @property
    def to(self) -> int:
        ...
    @to.setter
    def to(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
class PoseGraphParams:
    robust_loss: RobustLoss
    def __init__(self) -> None:
        ...
    @property
    def fixed(self) -> list[int]:
        ...
    @fixed.setter
    def fixed(self, arg0: collections.abc.Sequence[typing.SupportsInt | typing.SupportsIndex]) -> None:
        ...
    @property
    def fixed_rotations(self) -> list[int]:
        ...
    @fixed_rotations.setter
    def fixed_rotations(self, arg0: collections.abc.Sequence[typing.SupportsInt | typing.SupportsIndex]) -> None:
        ...
    @property
    def function_tolerance(self) -> float:
        ...
    @function_tolerance.setter
    def function_tolerance(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def gradient_tolerance(self) -> float:
        ...
    @gradient_tolerance.setter
    def gradient_tolerance(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_iterations(self) -> int:
        ...
    @max_iterations.setter
    def max_iterations(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def num_threads(self) -> int:
        ...
    @num_threads.setter
    def num_threads(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def parameter_tolerance(self) -> float:
        ...
    @parameter_tolerance.setter
    def parameter_tolerance(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def robust_loss_scale(self) -> float:
        ...
    @robust_loss_scale.setter
    def robust_loss_scale(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
class PoseGraphResult:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def converged(self) -> bool:
        ...
    @property
    def final_cost(self) -> float:
        ...
    @property
    def initial_cost(self) -> float:
        ...
    @property
    def iterations(self) -> int:
        ...
    @property
    def message(self) -> str:
        ...
    @property
    def poses(self) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
        """
        (K, 4, 4) optimised poses
        """
class MapperParams:
    ground_step_height: bool
    keep_local_maps: bool
    lidar_only: bool
    loop_closing: bool
    registration: RegistrationParams
    terrain: TerrainParams
    use_registration: bool
    yaw_only_registration: bool
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    @property
    def discontinuity_m(self) -> float:
        ...
    @discontinuity_m.setter
    def discontinuity_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def keyframe_distance_m(self) -> float:
        ...
    @keyframe_distance_m.setter
    def keyframe_distance_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def keyframe_rotation_rad(self) -> float:
        ...
    @keyframe_rotation_rad.setter
    def keyframe_rotation_rad(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def local_map_size_m(self) -> float:
        ...
    @local_map_size_m.setter
    def local_map_size_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def loop_max_candidates(self) -> int:
        ...
    @loop_max_candidates.setter
    def loop_max_candidates(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def loop_max_rmse_m(self) -> float:
        ...
    @loop_max_rmse_m.setter
    def loop_max_rmse_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def loop_min_inlier_ratio(self) -> float:
        ...
    @loop_min_inlier_ratio.setter
    def loop_min_inlier_ratio(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def loop_min_overlap(self) -> float:
        ...
    @loop_min_overlap.setter
    def loop_min_overlap(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def loop_min_travel_m(self) -> float:
        ...
    @loop_min_travel_m.setter
    def loop_min_travel_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def loop_search_radius_m(self) -> float:
        ...
    @loop_search_radius_m.setter
    def loop_search_radius_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def loop_search_window_m(self) -> float:
        ...
    @loop_search_window_m.setter
    def loop_search_window_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def loop_yaw_hypotheses(self) -> int:
        ...
    @loop_yaw_hypotheses.setter
    def loop_yaw_hypotheses(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def loop_yaw_search_rad(self) -> float:
        ...
    @loop_yaw_search_rad.setter
    def loop_yaw_search_rad(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_correction_m(self) -> float:
        ...
    @max_correction_m.setter
    def max_correction_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_correction_rad(self) -> float:
        ...
    @max_correction_rad.setter
    def max_correction_rad(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_odometry_step_m(self) -> float:
        ...
    @max_odometry_step_m.setter
    def max_odometry_step_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_range_m(self) -> float:
        ...
    @max_range_m.setter
    def max_range_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_scans_per_local_map(self) -> int:
        ...
    @max_scans_per_local_map.setter
    def max_scans_per_local_map(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def min_range_m(self) -> float:
        ...
    @min_range_m.setter
    def min_range_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def num_threads(self) -> int:
        ...
    @num_threads.setter
    def num_threads(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def odometry_sigma_m_per_m(self) -> float:
        ...
    @odometry_sigma_m_per_m.setter
    def odometry_sigma_m_per_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def odometry_sigma_rad_per_m(self) -> float:
        ...
    @odometry_sigma_rad_per_m.setter
    def odometry_sigma_rad_per_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def optimize_interval_keyframes(self) -> int:
        ...
    @optimize_interval_keyframes.setter
    def optimize_interval_keyframes(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def overlap_block_m(self) -> float:
        ...
    @overlap_block_m.setter
    def overlap_block_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def pose_graph_iterations(self) -> int:
        ...
    @pose_graph_iterations.setter
    def pose_graph_iterations(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def registration_sigma_m(self) -> float:
        ...
    @registration_sigma_m.setter
    def registration_sigma_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def registration_sigma_rad(self) -> float:
        ...
    @registration_sigma_rad.setter
    def registration_sigma_rad(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def resolution_m(self) -> float:
        ...
    @resolution_m.setter
    def resolution_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
class ScanReport:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def index(self) -> int:
        ...
    @property
    def keyframe(self) -> bool:
        ...
    @property
    def loops_closed(self) -> int:
        ...
    @property
    def num_out_of_range(self) -> int:
        """
        points of the scan left out by min_range and max_range
        """
    @property
    def pose(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        """
        (4, 4) the scan's estimated world <- sensor when it was added (loop closing may correct the keyframes later)
        """
    @property
    def registered(self) -> bool:
        ...
    @property
    def registration(self) -> RegistrationResult:
        ...
class LoopClosure:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def overlap(self) -> float:
        ...
    @property
    def relative(self) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
        """
        (4, 4) L_target <- L_source
        """
    @property
    def rmse(self) -> float:
        ...
    @property
    def source(self) -> int:
        """
        the later keyframe
        """
    @property
    def target(self) -> int:
        """
        the earlier keyframe
        """
class MapperTimings:
    def __getstate__(self) -> dict:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def classification_ms(self) -> float:
        ...
    @property
    def fusion_ms(self) -> float:
        ...
    @property
    def keyframes(self) -> int:
        ...
    @property
    def loop_closing_ms(self) -> float:
        ...
    @property
    def map_building_ms(self) -> float:
        ...
    @property
    def registered_steps(self) -> int:
        """
        steps whose registration was accepted
        """
    @property
    def registration_ms(self) -> float:
        ...
    @property
    def scans(self) -> int:
        ...
    @property
    def untrusted_steps(self) -> int:
        """
        steps whose registration was not trusted (odometry or the prediction was used)
        """
class Mapper:
    def __init__(self, params: MapperParams) -> None:
        ...
    def add_scan(self, points: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], pose: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]) -> ScanReport:
        ...
    def global_map(self, classify: bool = True) -> ElevationMap:
        ...
    def keyframe_odometry(self) -> numpy.typing.NDArray[numpy.float64]:
        ...
    def keyframe_poses(self) -> numpy.typing.NDArray[numpy.float64]:
        ...
    def keyframe_scan_indices(self) -> list[int]:
        ...
    def local_map(self, k: typing.SupportsInt | typing.SupportsIndex) -> ElevationMap:
        ...
    def optimize(self) -> None:
        ...
    @property
    def global_memory_bytes(self) -> int:
        ...
    @property
    def global_tiles(self) -> int:
        ...
    @property
    def loop_closures(self) -> list[LoopClosure]:
        ...
    @property
    def num_keyframes(self) -> int:
        ...
    @property
    def pending_loops(self) -> int:
        ...
    @property
    def points_out_of_range(self) -> int:
        ...
    @property
    def timings(self) -> MapperTimings:
        ...
class TraversabilityParams:
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    @property
    def footprint_radius_m(self) -> float:
        ...
    @footprint_radius_m.setter
    def footprint_radius_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_roughness_m(self) -> float:
        ...
    @max_roughness_m.setter
    def max_roughness_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_slope_rad(self) -> float:
        ...
    @max_slope_rad.setter
    def max_slope_rad(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_step_m(self) -> float:
        ...
    @max_step_m.setter
    def max_step_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def min_clearance_m(self) -> float:
        ...
    @min_clearance_m.setter
    def min_clearance_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def min_window_cells(self) -> int:
        ...
    @min_window_cells.setter
    def min_window_cells(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def roughness_weight(self) -> float:
        ...
    @roughness_weight.setter
    def roughness_weight(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def slope_weight(self) -> float:
        ...
    @slope_weight.setter
    def slope_weight(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def step_weight(self) -> float:
        ...
    @step_weight.setter
    def step_weight(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
class LocalMapParams:
    clear_seen_through: bool
    collapse: CollapseParams
    compute_planner_layers: bool
    traversability: TraversabilityParams
    def __init__(self) -> None:
        ...
    def check(self) -> None:
        """
        Raises ValueError naming the first field out of range (as every call taking them).
        """
    @property
    def angle_sigma_rad(self) -> float:
        ...
    @angle_sigma_rad.setter
    def angle_sigma_rad(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def cell_sigma_m(self) -> float:
        ...
    @cell_sigma_m.setter
    def cell_sigma_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def clearing_beyond_m(self) -> float:
        ...
    @clearing_beyond_m.setter
    def clearing_beyond_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def clearing_depth_m(self) -> float:
        ...
    @clearing_depth_m.setter
    def clearing_depth_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def clearing_margin_m(self) -> float:
        ...
    @clearing_margin_m.setter
    def clearing_margin_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def discontinuity_m(self) -> float:
        ...
    @discontinuity_m.setter
    def discontinuity_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def drift_m_per_sqrt_m(self) -> float:
        ...
    @drift_m_per_sqrt_m.setter
    def drift_m_per_sqrt_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def gate_sigmas(self) -> float:
        ...
    @gate_sigmas.setter
    def gate_sigmas(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def length_m(self) -> float:
        ...
    @length_m.setter
    def length_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def max_cells(self) -> int:
        ...
    @max_cells.setter
    def max_cells(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def max_range_m(self) -> float:
        ...
    @max_range_m.setter
    def max_range_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def min_range_m(self) -> float:
        ...
    @min_range_m.setter
    def min_range_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def num_threads(self) -> int:
        ...
    @num_threads.setter
    def num_threads(self, arg0: typing.SupportsInt | typing.SupportsIndex) -> None:
        ...
    @property
    def range_sigma_m(self) -> float:
        ...
    @range_sigma_m.setter
    def range_sigma_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def resolution_m(self) -> float:
        ...
    @resolution_m.setter
    def resolution_m(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
    @property
    def visibility_bin_rad(self) -> float:
        ...
    @visibility_bin_rad.setter
    def visibility_bin_rad(self, arg0: typing.SupportsFloat | typing.SupportsIndex) -> None:
        ...
class LocalMapUpdate:
    def __getstate__(self) -> dict:
        ...
    def __repr__(self) -> str:
        ...
    def __setstate__(self, arg0: dict) -> None:
        ...
    @property
    def map_reset(self) -> bool:
        ...
    @property
    def num_cleared_cells(self) -> int:
        ...
    @property
    def num_cropped(self) -> int:
        ...
    @property
    def num_dropped_non_finite(self) -> int:
        ...
    @property
    def num_fused_cells(self) -> int:
        ...
    @property
    def num_in_map(self) -> int:
        ...
    @property
    def num_out_of_range(self) -> int:
        ...
    @property
    def num_overhang(self) -> int:
        ...
    @property
    def num_points(self) -> int:
        ...
    @property
    def num_replaced_cells(self) -> int:
        ...
class LocalMap:
    def __init__(self, params: LocalMapParams) -> None:
        ...
    def clear(self) -> None:
        ...
    def get(self, name: str) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
        """
        (n, n) read-only float32 view of a layer, storage order
        """
    def index_of(self, x: typing.SupportsFloat | typing.SupportsIndex, y: typing.SupportsFloat | typing.SupportsIndex) -> tuple[int, int] | None:
        ...
    def move_to(self, x: typing.SupportsFloat | typing.SupportsIndex, y: typing.SupportsFloat | typing.SupportsIndex) -> bool:
        ...
    def position_of(self, i: typing.SupportsInt | typing.SupportsIndex, j: typing.SupportsInt | typing.SupportsIndex) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[2, 1]"]:
        ...
    def to_elevation_map(self) -> ElevationMap:
        ...
    def update(self, points: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], pose: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], stamp: typing.SupportsFloat | typing.SupportsIndex = ..., no_returns: typing.Any = None) -> LocalMapUpdate:
        ...
    def update_planner_layers(self) -> None:
        ...
    @property
    def geometry(self) -> MapGeometry:
        ...
    @property
    def layers(self) -> list[str]:
        ...
    @property
    def num_updates(self) -> int:
        ...
    @property
    def params(self) -> LocalMapParams:
        ...
    @property
    def start_index(self) -> tuple[int, int]:
        ...
    @property
    def time_origin(self) -> float:
        """
        the first update's stamp [s]
        """
def absolute_trajectory_error(estimate: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], ground_truth: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], alignment: TrajectoryAlignment) -> AbsoluteTrajectoryError:
    ...
def add_traversability_layers(map: ElevationMap, params: TraversabilityParams, height_layer: str, start: typing.Annotated[numpy.typing.ArrayLike, numpy.int32, "[2, 1]"], num_threads: typing.SupportsInt | typing.SupportsIndex) -> None:
    ...
def attitude_from_gravity(up: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[3, 1]"]) -> tuple[float, float]:
    ...
def build_elevation_map(points: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], params: ElevationParams, use: typing.Annotated[numpy.typing.ArrayLike, numpy.bool] | None = None) -> ElevationMap:
    ...
def build_elevation_map_into(map: ElevationMap, points: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], params: ElevationParams, use: typing.Annotated[numpy.typing.ArrayLike, numpy.bool] | None = None) -> None:
    ...
def build_overhang_free_map(points: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], collapse: CollapseParams, elevation: ElevationParams, no_returns: typing.Any = None) -> OverhangFreeMap:
    ...
def classify_terrain(map: ElevationMap, params: TerrainParams) -> numpy.typing.NDArray[numpy.uint8]:
    """
    (nx, ny) uint8 classes; adds class, relative_height, ground layers
    """
def collapse_overhangs(points: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], params: CollapseParams, no_returns: typing.Any = None) -> CollapseResult:
    ...
def compare_region_layouts(map_centres: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], dsm_centres: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], relations: RegionRelations = ...) -> RegionLayoutComparison:
    ...
def correlative_search(source: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], source_classes: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], target: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], target_classes: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], guess: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[4, 4]"], params: CorrelativeSearchParams) -> CorrelativeSearchResult:
    ...
def cube_reason_name(reason: typing.SupportsInt | typing.SupportsIndex) -> str:
    ...
def error_statistics(errors: collections.abc.Sequence[typing.SupportsFloat | typing.SupportsIndex]) -> ErrorStatistics:
    ...
def fit_fuzzy_elevation_map(points: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], params: FuzzyParams, use: typing.Annotated[numpy.typing.ArrayLike, numpy.bool] | None = None) -> FuzzyElevationMap:
    ...
def leveling_transform(roll: typing.SupportsFloat | typing.SupportsIndex, pitch: typing.SupportsFloat | typing.SupportsIndex) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
    ...
def octomap_column_overhangs(points: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], params: CollapseParams) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
    ...
def optimize_pose_graph(poses: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], edges: collections.abc.Sequence[PoseGraphEdge], params: PoseGraphParams) -> PoseGraphResult:
    ...
def pcl_gicp(source: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], target: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], initial: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[4, 4]"], params: PclIcpParams) -> PclIcpResult:
    ...
def pcl_icp(source: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], target: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], initial: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[4, 4]"], params: PclIcpParams) -> PclIcpResult:
    ...
def point_based_overhangs(points: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], params: PointBasedParams) -> numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]:
    ...
def point_reasons(points: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], params: CollapseParams, result: CollapseResult) -> numpy.typing.NDArray[numpy.uint8]:
    """
    (N,) uint8: the CubeReason of each point's cube (not_used: it took no part)
    """
def points_of_map(map: ElevationMap) -> tuple[numpy.typing.NDArray[numpy.float64], numpy.typing.NDArray[numpy.uint8]]:
    """
    ((N, 3) float64 cell centres at max, (N,) uint8 classes)
    """
def register_maps(source: ElevationMap, target: ElevationMap, initial: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[4, 4]"], params: RegistrationParams) -> RegistrationResult:
    ...
def register_points(source: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], source_classes: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]] | None, target: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], target_classes: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]] | None, initial: typing.Annotated[numpy.typing.ArrayLike, numpy.float64, "[4, 4]"], params: RegistrationParams) -> RegistrationResult:
    ...
def relative_pose_error(estimate: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], ground_truth: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], params: RelativePoseErrorParams) -> RelativePoseError:
    ...
def rigid_alignment(source: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]], target: numpy.ndarray[typing.Any, numpy.dtype[typing.Any]]) -> typing.Annotated[numpy.typing.NDArray[numpy.float64], "[4, 4]"]:
    ...
def sigma_from_robot_height(robot_height: typing.SupportsFloat | typing.SupportsIndex, edge: typing.SupportsFloat | typing.SupportsIndex) -> int:
    ...
def step_layer(arg0: typing.Annotated[numpy.typing.ArrayLike, numpy.float32]) -> typing.Annotated[numpy.typing.NDArray[numpy.float32], "[m, n]"]:
    ...
has_pcl: bool = True
