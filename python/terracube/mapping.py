"""Global elevation maps from scan sequences: the SLAM half of the terrain-classification paper.

Every ``keyframe_distance`` metres of travel (about 3 m in the paper) the :class:`Mapper` builds a
local classified elevation map from the scan (leveled by odometry's roll and pitch), registers it
to the previous local map with the class-weighted ICP (:func:`terracube.register_maps`'s core,
odometry as the initial guess) and fuses it into a global elevation map that grows with the area
covered: highest elevation per cell as in the paper, plus the mean DEM, std-dev, discontinuity and
the classes. Revisits are detected by pose proximity and then map overlap, registered, and the
pose graph is optimised with Ceres; the global map is then rebuilt from the corrected poses.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import _core
from .collapse import _as_points, _checked, _num_threads
from .elevation import ElevationMap, TerrainParams
from .registration import RegistrationParams

__all__ = ["Mapper", "MapperParams", "MapperTimings", "ScanReport", "LoopClosure", "run_mapper"]

ScanReport = _core.ScanReport
LoopClosure = _core.LoopClosure
MapperTimings = _core.MapperTimings


@dataclass
class MapperParams:
    """Parameters of :class:`Mapper`, mirroring ``terracube::MapperParams``.

    Attributes
    ----------
    keyframe_distance : float
        A new local map every this much odometry travel [m] (the paper: about 3 m).
    keyframe_rotation : float
        ... or when odometry turned this much since the last one [rad].
    max_odometry_step : float
        :meth:`Mapper.add_scan` refuses odometry that moved farther than this since the previous
        scan [m] (a glitch such as a GPS jump would stretch the global map over kilometres).
    resolution : float
        Cell size of the local and global maps [m].
    local_map_size : float
        Side of the square local map centred on the sensor [m].
    max_scans_per_local_map : int
        A local map holds the keyframe's scan and the scans since the previous keyframe (at most this
        many, the newest), moved into the keyframe's leveled frame by odometry; 1: one scan alone.
    num_threads : int
        Threads of each local map (as :class:`terracube.ElevationParams`': 1 the calling thread, 0
        one per processor; the same map whatever the number). Its classes take
        ``terrain.num_threads``.
    keep_local_maps : bool
        Keep every keyframe's local map for :meth:`Mapper.local_map`; off, only the newest is kept
        (memory per keyframe: its cells and the cells its class weights can pair).
    min_range : float
        Points nearer the sensor take no part (the robot itself) [m].
    max_range : float or None
        Points farther from the sensor take no part [m] (None or inf: no limit);
        :attr:`Mapper.points_out_of_range` counts the points either limit left out.
    discontinuity : float
        Gap between sorted elevations that flags a cell discontinuous [m] (the paper: 1 m).
    terrain : TerrainParams
        [TC] Table 1 thresholds; heights are measured from the local ground by default (slopes), the
        lowest elevation within 5 cells (0.5 m at 0.1 m: on a slope the window minimum lies
        slope x radius below the cell, so a wider window calls ramps obstacles).
    use_registration : bool
        False chains local maps by odometry alone (a baseline).
    lidar_only : bool
        LiDAR-only mode (no odometry): the translation and yaw of the poses given to ``add_scan``
        are ignored (their roll and pitch still level the local maps: pass identity for a level
        sensor, or an IMU's attitude). Every scan is registered to the newest keyframe from a
        constant-velocity prediction (the previous scan's motion repeated, from the Mapper's own
        estimates; until a first registration succeeds, searched within ``keyframe_distance`` +
        the registration's search window) and becomes a keyframe once the estimates travelled
        ``keyframe_distance`` (or turned ``keyframe_rotation``): feed every scan of a sequence. A
        trusted registration is accepted whatever its correction of the prediction
        (``max_correction`` bounds odometry's only); an untrusted one keeps the prediction. Each
        scan costs a local map and a registration; local maps are single scans. The height comes
        from the ground (``ground_step_height``). Without an attitude the motion is level: a
        ramp's height is not followed. Needs ``use_registration``.
    registration : RegistrationParams
        The class-weighted ICP ([TC] Table 2 weights by default). With odometry a step is first
        registered from odometry's guess without the correlative search, and again with it only
        when that answer is not trusted.
    yaw_only_registration : bool
        Keep only the translation and yaw of each registration: local maps are leveled by odometry's
        roll and pitch, so their relative rotation is a yaw (the ground-free ICP leaves roll and pitch
        weakly constrained). False: the full 6-DOF result, as the paper.
    ground_step_height : bool
        A registered step's or loop edge's height from the ground the two local maps share (the
        median offset of their common ground cells; not in [TC]): the ICP leaves the ground out, so
        only the objects hold the height, loosely. False: the ICP's height, as the paper.
    max_correction, max_correction_rot : float
        A step registration that moves odometry's guess further [m], [rad], or whose result is not
        ``trusted`` (counted in ``timings.untrusted_steps``), is rejected (odometry is used for
        that step).
    registration_sigma, registration_sigma_rot : float
        Standard deviations of registered steps and loop edges in the pose graph [m], [rad].
    odometry_sigma_per_m, odometry_sigma_rot_per_m : float
        ... of odometry-only steps, per metre travelled.
    loop_closing : bool
        Detect revisits and optimise the pose graph with Ceres.
    loop_search_radius : float
        Candidates lie within this distance of the new keyframe's estimated position [m].
    loop_min_travel : float
        ... and at least this much path before it [m].
    loop_min_overlap : float
        Share of the new local map's cells that must land on blocks with data of the candidate's map.
    overlap_block : float
        Block size for the overlap [m] (sparse scans sample different cells of one surface).
    loop_max_candidates : int
        Candidates registered per keyframe, nearest first.
    loop_search_window, loop_yaw_search, loop_yaw_hypotheses : float, float, int
        Loop registrations start from drifted estimates: a correlative search over
        ``loop_yaw_hypotheses`` yaw offsets within +-``loop_yaw_search`` [rad] and translations within
        +-``loop_search_window`` [m] picks the start with the most non-ground cells landing on
        non-ground cells of the candidate map; the ICP refines it.
    loop_max_rmse : float
        A loop registration is accepted below this weighted RMSE [m] ...
    loop_min_inlier_ratio : float
        ... when this share of the new map's weighted cells found a correspondence.
    pose_graph_iterations : int
        Ceres iterations at most, 1 to 10,000.
    optimize_interval_keyframes : int
        While a revisit keeps closing loops, the pose graph is optimised (and the global map rebuilt)
        at most once per this many keyframes; :meth:`Mapper.optimize` applies loops still pending
        (:func:`run_mapper` and ``terracube map`` call it after the last scan).
    """

    keyframe_distance: float = 3.0
    keyframe_rotation: float = 0.5
    max_odometry_step: float = 50.0
    resolution: float = 0.1
    local_map_size: float = 40.0
    max_scans_per_local_map: int = 1
    num_threads: int = 1
    keep_local_maps: bool = False
    min_range: float = 0.5
    max_range: float | None = None
    discontinuity: float = 1.0
    terrain: TerrainParams = field(
        default_factory=lambda: TerrainParams(reference="local_ground", local_ground_radius=5)
    )
    use_registration: bool = True
    lidar_only: bool = False
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    yaw_only_registration: bool = True
    ground_step_height: bool = True
    max_correction: float = 1.5
    max_correction_rot: float = 0.15
    registration_sigma: float = 0.05
    registration_sigma_rot: float = 0.005
    odometry_sigma_per_m: float = 0.05
    odometry_sigma_rot_per_m: float = 0.01
    loop_closing: bool = True
    loop_search_radius: float = 10.0
    loop_min_travel: float = 30.0
    loop_min_overlap: float = 0.3
    overlap_block: float = 1.0
    loop_max_candidates: int = 2
    loop_search_window: float = 6.0
    loop_yaw_search: float = 0.15
    loop_yaw_hypotheses: int = 13
    loop_max_rmse: float = 0.2
    loop_min_inlier_ratio: float = 0.3
    pose_graph_iterations: int = 50
    optimize_interval_keyframes: int = 5

    def to_core(self) -> _core.MapperParams:
        params = _checked(_core.MapperParams)()
        params.keyframe_distance_m = float(self.keyframe_distance)
        params.keyframe_rotation_rad = float(self.keyframe_rotation)
        params.max_odometry_step_m = float(self.max_odometry_step)
        params.resolution_m = float(self.resolution)
        params.local_map_size_m = float(self.local_map_size)
        params.max_scans_per_local_map = int(self.max_scans_per_local_map)
        params.num_threads = _num_threads(self.num_threads)
        params.keep_local_maps = bool(self.keep_local_maps)
        params.min_range_m = float(self.min_range)
        params.max_range_m = math.inf if self.max_range is None else float(self.max_range)
        params.discontinuity_m = float(self.discontinuity)
        params.terrain = self.terrain.to_core()
        params.use_registration = bool(self.use_registration)
        params.lidar_only = bool(self.lidar_only)
        params.registration = self.registration.to_core()
        params.yaw_only_registration = bool(self.yaw_only_registration)
        params.ground_step_height = bool(self.ground_step_height)
        params.max_correction_m = float(self.max_correction)
        params.max_correction_rad = float(self.max_correction_rot)
        params.registration_sigma_m = float(self.registration_sigma)
        params.registration_sigma_rad = float(self.registration_sigma_rot)
        params.odometry_sigma_m_per_m = float(self.odometry_sigma_per_m)
        params.odometry_sigma_rad_per_m = float(self.odometry_sigma_rot_per_m)
        params.loop_closing = bool(self.loop_closing)
        params.loop_search_radius_m = float(self.loop_search_radius)
        params.loop_min_travel_m = float(self.loop_min_travel)
        params.loop_min_overlap = float(self.loop_min_overlap)
        params.overlap_block_m = float(self.overlap_block)
        params.loop_max_candidates = int(self.loop_max_candidates)
        params.loop_search_window_m = float(self.loop_search_window)
        params.loop_yaw_search_rad = float(self.loop_yaw_search)
        params.loop_yaw_hypotheses = int(self.loop_yaw_hypotheses)
        params.loop_max_rmse_m = float(self.loop_max_rmse)
        params.loop_min_inlier_ratio = float(self.loop_min_inlier_ratio)
        params.pose_graph_iterations = int(self.pose_graph_iterations)
        params.optimize_interval_keyframes = int(self.optimize_interval_keyframes)
        params.check()  # the core's own ranges, before any scan (and in a config file)
        return params


class Mapper:
    """Chains scans into a global elevation map (see the module docstring).

    >>> mapper = Mapper(MapperParams(keyframe_distance=3.0))
    >>> for points, pose in zip(scans, odometry):   # (N, 3) sensor-frame points, (4, 4) world <- sensor
    ...     mapper.add_scan(points, pose)
    >>> dem = mapper.global_map()                    # ElevationMap: max, mean, std_dev, class, ...
    >>> poses = mapper.keyframe_poses()              # (K, 4, 4)
    """

    def __init__(self, params: MapperParams | None = None, **kwargs):
        self.params = params or MapperParams(**kwargs)
        self._core = _core.Mapper(self.params.to_core())

    def add_scan(self, points, pose) -> ScanReport:
        """Feeds one scan: ``points`` (N, 3) or wider float32/float64 (x, y, z first) in the sensor
        frame, ``pose`` its (4, 4) odometry world <- sensor. Returns what happened (keyframe,
        registration, loops closed) and ``.pose``, the scan's estimated (4, 4) world <- sensor at
        that time (its keyframe's estimate moved by odometry since; LiDAR-only: its own
        registration) and ``.num_out_of_range``, the points left out by ``min_range`` and
        ``max_range`` (summed in :attr:`points_out_of_range`)."""
        points = _as_points(points, self.params.resolution, "resolution")
        return self._core.add_scan(points, np.asarray(pose, dtype=np.float64))

    @property
    def points_out_of_range(self) -> int:
        """Points of the scans so far left out by ``min_range`` and ``max_range``."""
        return int(self._core.points_out_of_range)

    def __reduce__(self):
        raise TypeError(
            "a Mapper holds a live session (keyframes, pose graph) and does not pickle; pickle what it "
            "made instead: mapper.global_map(), mapper.keyframe_poses()"
        )

    def __len__(self) -> int:
        return int(self._core.num_keyframes)

    @property
    def num_keyframes(self) -> int:
        return int(self._core.num_keyframes)

    def keyframe_poses(self) -> np.ndarray:
        """Estimated world <- sensor pose of every keyframe, (K, 4, 4)."""
        return self._core.keyframe_poses()

    def keyframe_odometry(self) -> np.ndarray:
        """Odometry world <- sensor pose of every keyframe as given, (K, 4, 4)."""
        return self._core.keyframe_odometry()

    def keyframe_scan_indices(self) -> np.ndarray:
        """Index of the scan (in add_scan order) each keyframe was built from."""
        return np.asarray(self._core.keyframe_scan_indices(), dtype=np.int64)

    @property
    def loop_closures(self) -> list[LoopClosure]:
        return list(self._core.loop_closures)

    @property
    def timings(self) -> MapperTimings:
        """Milliseconds per stage summed over all scans: map building, classification,
        registration, fusion, loop closing."""
        return self._core.timings

    @property
    def global_memory_bytes(self) -> int:
        """Bytes held by the global map's tiles (grows with the area covered)."""
        return int(self._core.global_memory_bytes)

    def local_map(self, k: int) -> ElevationMap:
        """Keyframe ``k``'s local classified map in its leveled frame (IndexError unless it is the
        newest keyframe or ``keep_local_maps`` is set)."""
        try:
            return ElevationMap(self._core.local_map(int(k)))
        except IndexError as error:
            raise IndexError(str(error)) from None

    def global_map(self, classify: bool = True) -> ElevationMap:
        """The global elevation map over the area covered so far: layers count, min, max (highest
        elevation), mean (DEM), std_dev, discontinuity and, with ``classify``, class,
        relative_height and ground."""
        return ElevationMap(self._core.global_map(bool(classify)))

    @property
    def pending_loops(self) -> int:
        """Loop edges added since the last pose-graph optimisation."""
        return int(self._core.pending_loops)

    def optimize(self) -> None:
        """Optimises the pose graph now and rebuilds the global map. add_scan does this when it
        closes loops, at most every ``optimize_interval_keyframes``; call it after the last scan."""
        self._core.optimize()


def run_mapper(
    scans: Iterable[np.ndarray],
    poses: Iterable[np.ndarray],
    params: MapperParams | None = None,
    progress: bool = False,
    total: int | None = None,
) -> Mapper:
    """Feeds ``scans`` with their odometry ``poses`` to a new :class:`Mapper`, applies loops still
    pending (:meth:`Mapper.optimize`) and returns it.

    ``progress`` shows a tqdm bar (``total`` scans if known).
    """
    mapper = Mapper(params)
    pairs = zip(scans, poses, strict=False)
    if progress:
        from tqdm import tqdm

        pairs = tqdm(pairs, total=total, unit="scan", desc="mapping")
    for points, pose in pairs:
        mapper.add_scan(points, pose)
    if mapper.pending_loops:
        mapper.optimize()
    return mapper


# ------------------------------------------------------------------------------------------ sequences


def read_kitti_calibration(path) -> np.ndarray:
    """The 4x4 ``Tr`` (Velodyne -> left camera) of a KITTI ``calib.txt`` (a rotation rounded to fewer
    than six digits replaced by the nearest rotation, see :mod:`terracube.poses`)."""
    path = Path(path)
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        key, _, values = line.partition(":")
        if key.strip() == "Tr":
            try:
                numbers = np.array(values.split(), dtype=np.float64)
            except ValueError:
                raise ValueError(f"{path}, line {number}: Tr must be 12 numbers") from None
            if numbers.shape != (12,) or not np.isfinite(numbers).all():
                raise ValueError(f"{path}, line {number}: Tr must be 12 finite numbers, got {numbers.size}")
            from .poses import rigid_from_file

            return rigid_from_file(
                np.vstack([numbers.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]]), f"{path}, line {number}"
            )
    raise ValueError(f"{path}: no 'Tr:' line (the Velodyne-to-camera calibration)")


def detect_pose_format(path) -> str:
    """``kitti`` or ``tum`` by the count of numbers on the first pose line (12 or 8)."""
    path = Path(path)
    with path.open("r", encoding="utf-8") as file:
        first = next((ln for ln in file if ln.strip() and not ln.lstrip().startswith("#")), "")
    pose_format = {12: "kitti", 8: "tum"}.get(len(first.split()))
    if pose_format is None:
        raise ValueError(
            f"{path}: cannot tell the pose format from its first line ({len(first.split())} numbers; "
            "KITTI has 12, TUM 8): pass --pose-format"
        )
    return pose_format


def read_pose_file(path, pose_format: str = "auto", calibration=None) -> tuple[np.ndarray, np.ndarray]:
    """Reads odometry poses: ((K,) timestamps or indices, (K, 4, 4) world <- sensor).

    ``pose_format`` is ``kitti`` (12 numbers per line), ``tum`` (timestamp tx ty tz qx qy qz qw) or
    ``auto`` (by the count of numbers on the first pose line). KITTI poses are the left camera's: with
    ``calibration`` (the 4x4 ``Tr`` of :func:`read_kitti_calibration`) they become the Velodyne's,
    ``inv(Tr) @ P @ Tr``.
    """
    from .poses import read_kitti_poses, read_tum_poses

    path = Path(path)
    if pose_format == "auto":
        pose_format = detect_pose_format(path)
    if pose_format == "kitti":
        poses = read_kitti_poses(path)
        stamps = np.arange(len(poses), dtype=np.float64)
    elif pose_format == "tum":
        stamps, poses = read_tum_poses(path)
    else:
        raise ValueError(f"pose format must be kitti, tum or auto, got {pose_format!r}")
    if calibration is not None:
        if pose_format != "kitti":
            raise ValueError(f"{path}: a KITTI calibration applies to KITTI (camera) poses only")
        tr = np.asarray(calibration, dtype=np.float64)
        poses = np.linalg.inv(tr) @ poses @ tr
    return stamps, poses


@dataclass
class Odometry:
    """The odometry of each scan of a sequence, as :func:`read_odometry` matched it."""

    stamps: np.ndarray  #: (S,) each scan's time [s] (TUM's, times.txt's or its name's), else its index
    poses: np.ndarray  #: (S, 4, 4) each scan's world <- sensor (the identity without a pose file)
    pose_format: str | None  #: "kitti" or "tum"; None without a pose file or a reference
    calibration: np.ndarray | None  #: KITTI's Tr (Velodyne -> camera) the poses were turned by
    calib: Path | None  #: the calib.txt read, given or found beside KITTI poses
    times: Path | None  #: the times.txt read, given or found beside KITTI poses
    source: Path | None = None  #: the pose file, or the reference standing in for it
    indices: np.ndarray | None = None  #: each scan's row of a pose file; None when matched by time
    by_time: bool = False  #: poses interpolated at the times the scans' names give
    in_order_of: int | None = None  #: matched in order: how many scans (and so poses) there are

    def read_like(self, path) -> np.ndarray:
        """(S, 4, 4) poses of each scan from another file in the same format and frame (a ground
        truth), matched as the odometry was: by row, or interpolated at the scans' times."""
        stamps, poses = read_pose_file(path, self.pose_format or "auto", self.calibration)
        if self.in_order_of is not None and len(poses) != self.in_order_of:
            raise ValueError(f"{self.in_order_of} scans and {len(poses)} poses in {path}: {_IN_ORDER}")
        if self.by_time:
            from .poses import interpolate_poses

            return interpolate_poses(stamps, poses, self.stamps, what=str(path))
        return poses[_rows(self.indices, len(poses), path)]

    def notes(self) -> list[tuple[str, bool]]:
        """What a user should know, as (text, is_warning): the calibration and the timestamps used,
        or that KITTI poses are used without a calibration (camera poses: a skewed map)."""
        notes = []
        if self.calib is not None:
            notes.append((f"calibration: {self.calib} (camera poses -> Velodyne)", False))
        elif self.pose_format == "kitti":
            notes.append(
                (
                    f"warning: no calib.txt beside {self.source} and no --calib: the KITTI poses are used "
                    "as they are (KITTI's are the left camera's, not the LiDAR's: the map is skewed and "
                    "an ATE against camera poses measures nothing); give --calib calib.txt",
                    True,
                )
            )
        if self.pose_format == "kitti":
            notes.append(
                (f"timestamps: {self.times}" if self.times else "timestamps: none (the pose index)", False)
            )
        if self.by_time:
            notes.append(
                (f"poses: interpolated at the times the {len(self.poses)} scans are named by", False)
            )
        return notes


#: Why scans matched in order need one pose each.
_IN_ORDER = (
    "scans named neither by their row (000123.bin) nor by their time with TUM poses "
    "(1622812345.123456789.pcd) take one pose each, in order"
)


def _suffix_counts(scans: list, total: int) -> str:
    """`` (6 .bin, 2 .txt)`` when the ``total`` scans are all listed and of several suffixes (a
    glob that caught a folder's other files), else ``""``."""
    if len(scans) != total:
        return ""
    counts: dict[str, int] = {}
    for scan in scans:
        suffix = Path(scan).suffix.lower() or "no suffix"
        counts[suffix] = counts.get(suffix, 0) + 1
    if len(counts) < 2:
        return ""
    return (
        " (" + ", ".join(f"{n} {suffix}" for suffix, n in sorted(counts.items(), key=lambda c: -c[1])) + ")"
    )


def _rows(indices: np.ndarray, count: int, path, names=None) -> np.ndarray:
    """``indices`` when each is a row of a file of ``count`` poses; else ValueError naming a scan."""
    beyond = np.flatnonzero(indices >= count)
    if beyond.size:
        first = int(beyond[0])
        scan = (
            f"{names[first]}: no pose for it" if names else f"no pose for the scan numbered {indices[first]}"
        )
        raise ValueError(f"{scan} (row {indices[first]}; {path} has {count} poses)")
    return indices


def _beside(path: Path, name: str) -> Path | None:
    """The file ``name`` in ``path``'s folder, if there is one."""
    return path.parent / name if (path.parent / name).is_file() else None


def scan_time(name: str) -> float | None:
    """A scan's time [s] from its file name, as ROS's bag_to_pcd writes them (``1622812345.123456789.pcd``),
    or None: whole numbers (``000123.bin``) are indices, other names no time."""
    stem = Path(name).stem
    if stem.isdigit():
        return None
    try:
        time = float(stem)
    except ValueError:
        return None
    return time if math.isfinite(time) else None


def read_odometry(
    poses, scans: list, pose_format: str = "auto", calib=None, times=None, reference=None, total=None
) -> Odometry:
    """The odometry of each scan file of ``scans`` from a pose file (KITTI or TUM, see
    :func:`read_pose_file`), or the identity for each without one (LiDAR-only, level).

    A scan takes the pose of the row its name numbers (KITTI's ``000123.bin``); with TUM poses, the
    pose interpolated at the time its name gives (``1622812345.123456789.pcd``, odometry at any rate;
    linear in translation, SLERP in rotation); otherwise the scans in sorted order take one pose
    each, and there must be as many poses as scans (``total``: how many there are before a limit).
    KITTI poses take ``calib`` (default: ``calib.txt`` beside them) to become the Velodyne's and
    ``times`` (default: ``times.txt`` beside them) for their times. ``reference`` stands in for a
    missing pose file when telling the format and finding those files (a ground truth to be read
    by :meth:`Odometry.read_like`). ValueError naming the file and the scan that cannot be matched."""
    from .poses import interpolate_poses, read_times

    source = Path(poses) if poses is not None else (Path(reference) if reference is not None else None)
    if source is not None and pose_format == "auto":
        pose_format = detect_pose_format(source)
    calib = Path(calib) if calib is not None else None
    times = Path(times) if times is not None else None
    if source is not None and pose_format == "kitti":  # KITTI's files beside its poses
        calib = calib or _beside(source, "calib.txt")
        times = times or _beside(source, "times.txt")
    calibration = read_kitti_calibration(calib) if calib is not None else None
    stems = [Path(scan).stem for scan in scans]
    if poses is not None:
        stamps, matrices = read_pose_file(poses, pose_format, calibration)
    names_times = [scan_time(scan) for scan in scans]
    by_time = source is not None and pose_format == "tum" and all(t is not None for t in names_times)
    known = dict(pose_format=None if source is None else pose_format, calibration=calibration, calib=calib)
    if by_time:
        scan_times = np.asarray(names_times, dtype=np.float64)
        matrices = (
            np.tile(np.eye(4), (len(scans), 1, 1))
            if poses is None
            else interpolate_poses(stamps, matrices, scan_times, what=str(poses))
        )
        return Odometry(scan_times, matrices, **known, times=times, source=source, by_time=True)
    numbered = all(stem.isdigit() for stem in stems)
    in_order_of = None if numbered else (total or len(scans))
    indices = np.asarray([int(stem) for stem in stems], dtype=np.int64) if numbered else np.arange(len(scans))
    if poses is None:
        matrices = np.tile(np.eye(4), (len(scans), 1, 1))
    else:
        if in_order_of is not None and in_order_of != len(matrices):
            counted = f"{in_order_of} scans{_suffix_counts(scans, in_order_of)}"
            raise ValueError(f"{counted} and {len(matrices)} poses in {poses}: {_IN_ORDER}")
        matrices = matrices[_rows(indices, len(matrices), poses, [str(scan) for scan in scans])]
    if times is not None:
        per_scan = read_times(times, int(indices.max()) + 1 if len(indices) else 0)[indices]
    else:
        per_scan = stamps[indices] if poses is not None else indices.astype(np.float64)
    return Odometry(
        per_scan, matrices, **known, times=times, source=source, indices=indices, in_order_of=in_order_of
    )
