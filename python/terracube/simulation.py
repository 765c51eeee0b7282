"""Synthetic LiDAR sequences: ray-cast scans of an analytic scene along a loop with drifting odometry.

A scene of analytic primitives with semantic labels (a terrain heightfield with ramps and hills,
boxes rotated about z, vertical cylinders, ellipsoids), a rotating multi-beam LiDAR or a tilting
2D scanner, and a robot driving a closed loop (or a straight road) past trees, walls, buildings,
through a tunnel, under a bridge and over a ramp. Scans are in the SENSOR frame (x forward, y left,
z up); poses are world <- sensor (4, 4) with attitude Rz(yaw) Ry(pitch) Rx(roll), so
``leveling_transform(roll, pitch)`` levels a scan. See ``terracube/simulation.hpp`` for the design.

Example
-------
>>> from terracube.simulation import generate_sequence, RotatingLidar
>>> sequence = generate_sequence(sensor=RotatingLidar(channels=32, steps_per_revolution=512))
>>> points, labels, rays = sequence.scan(0)          # (N, 3) float32, (N,) uint8, (N,) uint32
>>> sequence.poses.shape, sequence.odometry.shape    # (K, 4, 4) each
"""

from __future__ import annotations

import enum
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import NamedTuple, get_type_hints

import numpy as np

from . import _core

_sim = _core.simulation

__all__ = [
    "Label",
    "OVERHANG_LABELS",
    "Primitive",
    "RotatingLidar",
    "Tilting2DScanner",
    "LoopSceneParams",
    "TrajectoryParams",
    "Scan",
    "Trajectory",
    "SyntheticWorld",
    "SyntheticSequence",
    "make_loop_scene",
    "make_scene",
    "cast_scan",
    "organised_image",
    "sensor_rays",
    "generate_trajectory",
    "generate_sequence",
]


class Label(enum.IntEnum):
    """Semantic label per point (uint8), mirroring ``terracube::simulation::Label``."""

    GROUND = 0
    WALL = 1
    BUILDING = 2
    TRUNK = 3
    CANOPY = 4
    TUNNEL_WALL = 5
    TUNNEL_CEILING = 6
    BRIDGE_DECK = 7
    PILLAR = 8


#: Surfaces a ground robot drives under.
OVERHANG_LABELS = frozenset({Label.CANOPY, Label.TUNNEL_CEILING, Label.BRIDGE_DECK})


class Primitive(NamedTuple):
    """One solid of a scene (see :meth:`SyntheticWorld.primitives`).

    ``kind`` is "box" (``half_extents`` along its own axes, rotated by ``yaw`` [rad] about z),
    "cylinder" (vertical; ``center`` at mid height, ``half_extents`` = (r, r, half height)) or
    "ellipsoid" (axis-aligned, ``half_extents`` = radii). Lengths in metres.
    """

    kind: str
    label: Label
    center: np.ndarray
    half_extents: np.ndarray
    yaw: float

    def to_core(self):
        if self.kind == "box":
            return _sim.Primitive.box(self.center, self.half_extents, float(self.yaw), int(self.label))
        if self.kind == "cylinder":
            c, h = np.asarray(self.center, float), np.asarray(self.half_extents, float)
            return _sim.Primitive.cylinder(c[0], c[1], h[0], c[2] - h[2], c[2] + h[2], int(self.label))
        if self.kind == "ellipsoid":
            return _sim.Primitive.ellipsoid(self.center, self.half_extents, int(self.label))
        raise ValueError(f"kind must be 'box', 'cylinder' or 'ellipsoid', got {self.kind!r}")

    @staticmethod
    def box(center, half_extents, yaw: float, label: Label) -> Primitive:
        return Primitive(
            "box", Label(label), np.asarray(center, float), np.asarray(half_extents, float), float(yaw)
        )

    @staticmethod
    def cylinder(x: float, y: float, radius: float, z_min: float, z_max: float, label: Label) -> Primitive:
        centre = np.array([x, y, 0.5 * (z_min + z_max)], float)
        return Primitive(
            "cylinder", Label(label), centre, np.array([radius, radius, 0.5 * (z_max - z_min)]), 0.0
        )

    @staticmethod
    def ellipsoid(center, radii, label: Label) -> Primitive:
        return Primitive("ellipsoid", Label(label), np.asarray(center, float), np.asarray(radii, float), 0.0)


def _primitive_of(core) -> Primitive:
    return Primitive(
        core.kind, Label(core.label), np.array(core.center), np.array(core.half_extents), core.yaw
    )


@dataclass
class RotatingLidar:
    """A spinning multi-beam LiDAR, mirroring ``terracube::simulation::RotatingLidar``.

    ``channels`` beams evenly in elevation over [vertical_fov_min, vertical_fov_max] [deg], fired at
    ``steps_per_revolution`` azimuths 2 pi j / steps (azimuth-major order: ray = step * channels +
    channel). First surfaces nearer than ``min_range`` or beyond ``max_range`` [m] give no point;
    Gaussian noise of ``range_noise_sigma`` [m] is added to the range. Defaults: an Ouster
    OS1-64-like 64 x 1024 over +-22.5 degrees.
    """

    channels: int = 64
    vertical_fov_min: float = -22.5
    vertical_fov_max: float = 22.5
    steps_per_revolution: int = 1024
    min_range: float = 0.5
    max_range: float = 100.0
    range_noise_sigma: float = 0.02

    def to_core(self):
        core = _sim.RotatingLidar()
        core.channels = _whole(self.channels, "channels")
        core.vertical_fov_min_deg = float(self.vertical_fov_min)
        core.vertical_fov_max_deg = float(self.vertical_fov_max)
        core.steps_per_revolution = _whole(self.steps_per_revolution, "steps_per_revolution")
        core.min_range_m = float(self.min_range)
        core.max_range_m = float(self.max_range)
        core.range_noise_sigma_m = float(self.range_noise_sigma)
        return core


@dataclass
class Tilting2DScanner:
    """A nodding 2D scanner, mirroring ``terracube::simulation::Tilting2DScanner``.

    Each of ``lines`` lines is a fan of ``beams_per_line`` beams over +-horizontal_fov / 2 [deg]
    about +x in a plane tilted up by the line's tilt, which runs evenly from ``tilt_from`` to
    ``tilt_to`` [deg]; beam (a, tilt) = (cos tilt cos a, sin a, sin tilt cos a). Line-major order.
    """

    beams_per_line: int = 541
    horizontal_fov: float = 270.0
    tilt_from: float = -40.0
    tilt_to: float = 40.0
    lines: int = 80
    min_range: float = 0.3
    max_range: float = 60.0
    range_noise_sigma: float = 0.01

    def to_core(self):
        core = _sim.Tilting2DScanner()
        core.beams_per_line = _whole(self.beams_per_line, "beams_per_line")
        core.horizontal_fov_deg = float(self.horizontal_fov)
        core.tilt_from_deg = float(self.tilt_from)
        core.tilt_to_deg = float(self.tilt_to)
        core.lines = _whole(self.lines, "lines")
        core.min_range_m = float(self.min_range)
        core.max_range_m = float(self.max_range)
        core.range_noise_sigma_m = float(self.range_noise_sigma)
        return core


@dataclass
class LoopSceneParams:
    """Parameters of :func:`make_loop_scene`, mirroring ``terracube::simulation::LoopSceneParams``.

    ``path="loop"``: a rounded rectangle (``loop_length`` x ``loop_width`` [m] centreline, corner
    radius ``corner_radius``) centred at the origin, driven counter-clockwise from the start of its
    bottom side; ramp mid bottom, tunnel mid right, bridge mid top, buildings outside the left and
    top sides and in the middle, garden walls outside the bottom and right sides, trees along both
    roadsides. ``path="straight"``: a road of ``straight_length`` from (0, 0) along +x with the
    ramp, tunnel and bridge at 1/4, 1/2 and 3/4. Heights in metres above the local ground.
    """

    path: str = "loop"
    loop_length: float = 80.0
    loop_width: float = 50.0
    corner_radius: float = 10.0
    straight_length: float = 200.0
    road_width: float = 6.0
    with_tunnel: bool = True
    with_bridge: bool = True
    with_ramp: bool = True
    with_trees: bool = True
    with_buildings: bool = True
    tunnel_length: float = 16.0
    tunnel_clearance: float = 4.0
    bridge_clearance: float = 5.0
    bridge_deck_width: float = 6.0
    ramp_height: float = 2.0
    ramp_length: float = 12.0
    ramp_plateau: float = 8.0
    tree_spacing: float = 9.0
    canopy_bottom: float = 3.2
    seed: int = 7
    grid_cell: float = 2.0

    def to_core(self):
        paths = {"loop": _sim.PathShape.loop, "straight": _sim.PathShape.straight}
        if self.path not in paths:
            raise ValueError(f"path must be 'loop' or 'straight', got {self.path!r}")
        core = _sim.LoopSceneParams()
        core.path = paths[self.path]
        for name in (
            "loop_length",
            "loop_width",
            "corner_radius",
            "straight_length",
            "road_width",
            "tunnel_length",
            "tunnel_clearance",
            "bridge_clearance",
            "bridge_deck_width",
            "ramp_height",
            "ramp_length",
            "ramp_plateau",
            "tree_spacing",
            "canopy_bottom",
            "grid_cell",
        ):
            setattr(core, name + "_m", float(getattr(self, name)))
        for name in ("with_tunnel", "with_bridge", "with_ramp", "with_trees", "with_buildings"):
            setattr(core, name, bool(getattr(self, name)))
        core.seed = _seed(self.seed)
        return core


@dataclass
class TrajectoryParams:
    """Parameters of :func:`generate_trajectory`, mirroring ``terracube::simulation::TrajectoryParams``.

    Keyframes every ``scan_spacing`` [m] of road for ``laps`` laps (a straight road once), the
    sensor ``mount_height`` [m] vertically above the terrain, ``lateral_offset`` [m] left of the
    centreline, yaw along the road, roll/pitch putting its z axis on the terrain normal. Odometry
    starts at the first true pose and integrates the true relative motions with drift per metre
    travelled d: yaw += ``yaw_bias`` d + ``yaw_random_walk`` sqrt(d) N(0,1); the step is scaled by
    (1 + ``translation_scale_error``) and gets ``translation_random_walk`` sqrt(d) N(0,1) per axis;
    roll and pitch are the truth plus ``roll_pitch_noise`` N(0,1) (IMU-like, no accumulation).
    """

    scan_spacing: float = 0.5
    laps: int = 1
    mount_height: float = 0.8
    lateral_offset: float = 0.0
    start_arc_length: float = 0.0
    yaw_bias: float = 2e-4
    yaw_random_walk: float = 1e-3
    translation_scale_error: float = 0.01
    translation_random_walk: float = 0.0
    roll_pitch_noise: float = 1e-3
    seed: int = 1

    def to_core(self):
        core = _sim.TrajectoryParams()
        core.scan_spacing_m = float(self.scan_spacing)
        core.laps = _whole(self.laps, "laps")
        core.mount_height_m = float(self.mount_height)
        core.lateral_offset_m = float(self.lateral_offset)
        core.start_arc_length_m = float(self.start_arc_length)
        core.yaw_bias_rad_per_m = float(self.yaw_bias)
        core.yaw_random_walk_rad_per_sqrt_m = float(self.yaw_random_walk)
        core.translation_scale_error = float(self.translation_scale_error)
        core.translation_random_walk_m_per_sqrt_m = float(self.translation_random_walk)
        core.roll_pitch_noise_rad = float(self.roll_pitch_noise)
        core.seed = _seed(self.seed)
        return core

    @classmethod
    def exact(cls, **kwargs) -> TrajectoryParams:
        """No drift at all: the odometry is the ground truth."""
        zero = dict(yaw_bias=0.0, yaw_random_walk=0.0, translation_scale_error=0.0, roll_pitch_noise=0.0)
        return cls(**{**zero, **kwargs})


def _whole(value, name: str) -> int:
    if isinstance(value, bool) or int(value) != value:
        raise ValueError(f"{name} must be a whole number, got {value!r}")
    if not -(2**31) <= int(value) < 2**31:
        raise ValueError(f"{name} out of range: {value!r}")
    return int(value)


def _seed(value) -> int:
    if isinstance(value, bool) or int(value) != value or not 0 <= int(value) < 2**64:
        raise ValueError(f"seed must be a whole number in [0, 2**64), got {value!r}")
    return int(value)


class Scan(NamedTuple):
    """One simulated scan in the sensor frame."""

    points: np.ndarray  #: (N, 3) float32 [m]
    labels: np.ndarray  #: (N,) uint8, :class:`Label` values
    ray_indices: np.ndarray  #: (N,) uint32 index into :func:`sensor_rays`, ascending


class Trajectory(NamedTuple):
    poses: np.ndarray  #: (K, 4, 4) ground truth, world <- sensor
    odometry: np.ndarray  #: (K, 4, 4) drifting odometry, odometry[0] == poses[0]
    arc_length: np.ndarray  #: (K,) along the road [m], unwrapped


# A NamedTuple's generated __new__ keeps this module's postponed annotations as names it cannot
# resolve (it lives in another namespace): give it the resolved types, for help() and the API pages.
for _named in (Primitive, Scan, Trajectory):
    _named.__new__.__annotations__ = get_type_hints(_named)


class SyntheticWorld:
    """A scene and, for generated worlds, the road a robot drives (owns the C++ object)."""

    def __init__(self, core, scene=None):
        self._core = core  # _sim.SyntheticWorld or None
        self._scene = scene if scene is not None else core.scene

    @property
    def scene(self):
        return self._scene

    def primitives(self) -> list[Primitive]:
        """Every primitive of the scene, in index order (for tests and plots)."""
        return [_primitive_of(p) for p in self._scene.primitives]

    def terrain_height(self, x, y) -> np.ndarray:
        """h(x, y) [m], element-wise over arrays of the same shape."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if x.shape != y.shape:
            raise ValueError(f"x and y must have the same shape, got {x.shape} and {y.shape}")
        return np.asarray(self._scene.terrain.height(x.ravel(), y.ravel())).reshape(x.shape)

    def terrain_gradient(self, x: float, y: float) -> tuple[float, float]:
        return self._scene.terrain.gradient(float(x), float(y))

    def intersect(self, origin, direction, max_range: float = 100.0, *, brute_force: bool = False):
        """First surface along one ray: (range [m] or inf, :class:`Label`, primitive index or -1)."""
        r, label, index = self._scene.intersect(
            np.asarray(origin, float), np.asarray(direction, float), float(max_range), brute_force
        )
        return r, Label(label), index

    @property
    def road(self):
        """The centreline: ``.length``, ``.closed``, ``.position(s)``, ``.heading(s)``."""
        if self._core is None:
            raise AttributeError("a scene built by make_scene has no road")
        return self._core.road

    def __repr__(self) -> str:
        road = f", road {self._core.road.length:.1f} m" if self._core is not None else ""
        return f"SyntheticWorld({len(self._scene.primitives)} primitives{road})"


def make_loop_scene(params: LoopSceneParams | None = None, **kwargs) -> SyntheticWorld:
    """The loop (or straight-road) scene of :class:`LoopSceneParams` (built from ``kwargs`` if not given)."""
    params = params or LoopSceneParams(**kwargs)
    return SyntheticWorld(_sim.make_loop_scene(params.to_core()))


def make_scene(
    primitives: Sequence[Primitive],
    base_height: float = 0.0,
    *,
    ramps: Sequence[dict] = (),
    hills: Sequence[dict] = (),
    grid_cell: float = 2.0,
) -> SyntheticWorld:
    """A custom scene: primitives over a terrain of ``base_height`` plus ramps and hills.

    Ramps are dicts with center (x, y), heading [rad], height, ramp_length, plateau_length,
    half_width and side_falloff [m]; hills with center, height and radius [m].
    """
    terrain = _sim.Terrain()
    terrain.base_height_m = float(base_height)
    core_ramps = []
    for spec in ramps:
        ramp = _sim.Ramp()
        for key, value in spec.items():
            name = {"center": "center", "heading": "heading_rad"}.get(key, key + "_m")
            setattr(ramp, name, np.asarray(value, float) if key == "center" else float(value))
        core_ramps.append(ramp)
    terrain.ramps = core_ramps
    core_hills = []
    for spec in hills:
        hill = _sim.Hill()
        for key, value in spec.items():
            setattr(
                hill,
                "center" if key == "center" else key + "_m",
                np.asarray(value, float) if key == "center" else float(value),
            )
        core_hills.append(hill)
    terrain.hills = core_hills
    scene = _sim.Scene(terrain, [p.to_core() for p in primitives], float(grid_cell))
    return SyntheticWorld(None, scene)


def _sensor(model):
    if model is None:
        model = RotatingLidar()
    if not isinstance(model, (RotatingLidar, Tilting2DScanner)):
        raise TypeError(f"sensor must be a RotatingLidar or a Tilting2DScanner, got {type(model).__name__}")
    return model.to_core()


def _pose(world_T_sensor) -> np.ndarray:
    pose = np.asarray(world_T_sensor, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"world_T_sensor must be a (4, 4) rigid transform, got shape {pose.shape}")
    return pose


def sensor_rays(model: RotatingLidar | Tilting2DScanner) -> np.ndarray:
    """(R, 3) float64 unit ray directions in the sensor frame, in firing order."""
    return _sim.sensor_rays(_sensor(model))


def cast_scan(
    world: SyntheticWorld,
    world_T_sensor,
    model: RotatingLidar | Tilting2DScanner | None = None,
    seed: int = 0,
) -> Scan:
    """Ray-cast one scan from the pose ``world_T_sensor`` (4, 4, world <- sensor).

    Returns a :class:`Scan` in the SENSOR frame: points (N, 3) float32, labels (N,) uint8 and the
    ray index of each point; rays without a surface within [min_range, max_range] are dropped.
    The noise is deterministic in ``seed``. Raises ValueError for invalid sensor parameters or a
    NaN/Inf or non-rigid pose. The GIL is released while casting.
    """
    return Scan(*_sim.cast_scan(world.scene, _pose(world_T_sensor), _sensor(model), _seed(seed)))


def organised_image(scan: Scan, model: RotatingLidar) -> np.ndarray:
    """The scan laid out as the organised image a spinning lidar's driver publishes: (channels,
    steps_per_revolution, 3) float64, a row per beam, (0, 0, 0) where a ray returned nothing
    (:func:`terracube.no_return_directions` takes it). ValueError for another scanner or a scan of
    another sensor."""
    if not isinstance(model, RotatingLidar):
        raise ValueError(f"an organised image needs a RotatingLidar, got {type(model).__name__}")
    rays = model.channels * model.steps_per_revolution
    indices = np.asarray(scan.ray_indices, dtype=np.int64)
    if indices.size and (indices.min() < 0 or indices.max() >= rays):
        raise ValueError(f"the scan's ray indices exceed this sensor's {rays} rays")
    image = np.zeros((rays, 3))
    image[indices] = scan.points  # firing order: the channels of one step, step by step
    return image.reshape(model.steps_per_revolution, model.channels, 3).transpose(1, 0, 2)


def generate_trajectory(
    world: SyntheticWorld, params: TrajectoryParams | None = None, **kwargs
) -> Trajectory:
    """Ground-truth poses and drifting odometry along the world's road (see :class:`TrajectoryParams`)."""
    params = params or TrajectoryParams(**kwargs)
    if world._core is None:
        raise ValueError("generate_trajectory needs a world with a road (make_loop_scene)")
    return Trajectory(*_sim.generate_trajectory(world._core, params.to_core()))


class SyntheticSequence:
    """Poses, odometry, world and sensor; ``scan(k)`` is cast on demand, so long runs never hold
    all scans. ``len(sequence)`` keyframes; iterating yields :class:`Scan` objects in order."""

    def __init__(self, world: SyntheticWorld, sensor, trajectory: TrajectoryParams, seed: int = 0):
        if world._core is None:
            raise ValueError("a sequence needs a world with a road (make_loop_scene)")
        self.world = world
        self.sensor = sensor if sensor is not None else RotatingLidar()
        self._core = _sim.SyntheticSequence(
            world._core, _sensor(self.sensor), trajectory.to_core(), _seed(seed)
        )
        self.poses = self._core.poses  # (K, 4, 4)
        self.odometry = self._core.odometry  # (K, 4, 4)
        self.arc_length = self._core.arc_length  # (K,)

    def __len__(self) -> int:
        return len(self._core)

    def scan(self, k: int) -> Scan:
        """Scan k in the sensor frame, cast from ``poses[k]`` (IndexError beyond the end)."""
        k = int(k)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(f"scan index out of range for a sequence of {len(self)} scans")
        return Scan(*self._core.scan(k))

    def __getitem__(self, k: int) -> Scan:
        return self.scan(k)

    def __iter__(self) -> Iterator[Scan]:
        for k in range(len(self)):
            yield self.scan(k)

    def __repr__(self) -> str:
        return f"SyntheticSequence({len(self)} scans, {type(self.sensor).__name__}, {self.world!r})"


def generate_sequence(
    scene: LoopSceneParams | None = None,
    trajectory: TrajectoryParams | None = None,
    sensor: RotatingLidar | Tilting2DScanner | None = None,
    seed: int = 0,
) -> SyntheticSequence:
    """:func:`make_loop_scene` + :func:`generate_trajectory` + a :class:`SyntheticSequence`."""
    world = make_loop_scene(scene or LoopSceneParams())
    return SyntheticSequence(world, sensor, trajectory or TrajectoryParams(), seed)
