"""ROS bags in and out, without ROS: point clouds and poses in, grid maps and classified clouds out.

Reading (:func:`read_bag`, :func:`bag_info`) covers ROS 1 ``.bag`` files, ROS 2 bag folders (sqlite3 and
mcap storage), plain ROS 2 ``.mcap`` files and ``.mcap`` files with the ros1 profile, through the
pure-Python ``rosbags`` library (and ``mcap`` for the ros1 profile, which rosbags' reader refuses).
Writing (:class:`MapBagWriter`) makes a ROS 2 bag (mcap or sqlite3) or a ROS 1 bag holding
``grid_map_msgs/msg/GridMap``, ``nav_msgs/msg/OccupancyGrid`` and ``sensor_msgs/msg/PointCloud2``
messages. Both need the ``ros`` extra: ``pip install 'terracube[ros]'``.

Every reader raises ``FileNotFoundError`` for a missing bag and ``ValueError`` naming the bag and the
problem (an unknown topic, a cloud without x/y/z, a truncated file, a frame missing from the TF tree,
a stamp outside the poses' span). Writers build the bag under a temporary name in the target's folder
and rename it on success, so a failed write leaves nothing behind.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "BagCloud",
    "BagClouds",
    "BagTopic",
    "CLASS_OCCUPANCY",
    "GRID_MAP_MSGS_ROS1",
    "GRID_MAP_MSGS_ROS2",
    "MapBagWriter",
    "bag_info",
    "cloud_topic",
    "decode_pointcloud2",
    "grid_map_layer_data",
    "layer_from_grid_map_data",
    "occupancy_from_classes",
    "occupancy_from_traversability",
    "read_bag",
    "with_attitude",
]

PathLike = str | os.PathLike

_EXTRA_HINT = "pip install 'terracube[ros]'"

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
IMU = "sensor_msgs/msg/Imu"
POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, TRANSFORM_STAMPED)
TF_TOPIC, TF_STATIC_TOPIC = "/tf", "/tf_static"
#: Default half-width [s] of the window of IMU messages averaged for each cloud's attitude.
IMU_WINDOW_S = 0.1

# sensor_msgs/PointField datatypes -> numpy type codes (byte order added per cloud).
_POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def _require_rosbags():
    try:
        import rosbags  # noqa: F401
    except ImportError as error:
        raise ImportError(f"reading and writing ROS bags needs rosbags and mcap: {_EXTRA_HINT}") from error


# ------------------------------------------------------------------------------------------ opening


@dataclass(frozen=True)
class BagTopic:
    """One topic of a bag: its name, message type (``pkg/msg/Type``) and message count."""

    name: str
    msgtype: str
    count: int


class _Bag:
    """One opened bag of any supported kind: topics, and messages decoded on one interface."""

    def __init__(self, path: Path):
        _require_rosbags()
        self.path = path
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such bag file or folder")
        self._mcap_file = None
        self._reader = None
        self.ros1_mcap = path.is_file() and path.suffix.lower() == ".mcap" and _mcap_profile(path) == "ros1"
        try:
            if self.ros1_mcap:
                self._open_ros1_mcap()
            else:
                from rosbags.highlevel import AnyReader

                self._reader = AnyReader([path])
                self._reader.open()
        except (FileNotFoundError, ImportError):
            self.close()
            raise
        except Exception as error:
            self.close()
            raise ValueError(f"{path}: cannot read as a ROS bag: {_describe(error)}") from error

    def _open_ros1_mcap(self) -> None:
        from mcap.reader import make_reader
        from rosbags.typesys import Stores, get_typestore

        self._mcap_file = open(self.path, "rb")  # noqa: SIM115 - closed in close()
        reader = make_reader(self._mcap_file)
        summary = reader.get_summary()
        if summary is None:
            raise ValueError("the MCAP file has no summary section (truncated?)")
        self._mcap_reader = reader
        self._typestore = get_typestore(Stores.EMPTY)
        self._registered: set[str] = set()
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        self._channels = {}
        for channel_id, channel in summary.channels.items():
            schema = summary.schemas.get(channel.schema_id)
            if schema is None or schema.encoding != "ros1msg":
                continue
            self._channels[channel.topic] = (schema, counts.get(channel_id, 0))

    def close(self) -> None:
        if self._reader is not None and self._reader.stack is not None:
            self._reader.close()
        if self._mcap_file is not None:
            self._mcap_file.close()
            self._mcap_file = None

    def __enter__(self) -> _Bag:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def topics(self) -> list[BagTopic]:
        if self.ros1_mcap:
            from rosbags.typesys.msg import normalize_msgtype

            return sorted(
                (
                    BagTopic(name, normalize_msgtype(schema.name), int(count))
                    for name, (schema, count) in self._channels.items()
                ),
                key=lambda topic: topic.name,
            )
        return sorted(
            (
                BagTopic(name, info.msgtype or "?", int(info.msgcount))
                for name, info in self._reader.topics.items()
            ),
            key=lambda topic: topic.name,
        )

    def topic(self, name: str, types: Sequence[str] | None = None, what: str = "topic") -> BagTopic:
        """The topic called ``name``; ValueError listing the bag's topics when there is none or it
        has another type."""
        topics = {t.name: t for t in self.topics()}
        if name not in topics:
            listing = ", ".join(f"{t.name} ({t.msgtype}, {t.count})" for t in topics.values()) or "none"
            raise ValueError(f"{self.path}: no {what} {name!r} in the bag; its topics: {listing}")
        topic = topics[name]
        if types is not None and topic.msgtype not in types:
            raise ValueError(
                f"{self.path}: {what} {name!r} holds {topic.msgtype}, expected {' or '.join(types)}"
            )
        return topic

    def messages(self, topics: Sequence[str]) -> Iterator[tuple[str, str, int, object]]:
        """(topic, msgtype, log time [ns], message) of the given topics, in log-time order."""
        try:
            if self.ros1_mcap:
                yield from self._ros1_mcap_messages(topics)
                return
            connections = [c for c in self._reader.connections if c.topic in set(topics)]
            if not connections:
                return
            for connection, timestamp, raw in self._reader.messages(connections=connections):
                message = self._reader.deserialize(raw, connection.msgtype)
                yield connection.topic, connection.msgtype, int(timestamp), message
        except Exception as error:
            if isinstance(error, ValueError) and str(error).startswith(str(self.path)):
                raise
            raise ValueError(f"{self.path}: cannot read its messages: {_describe(error)}") from error

    def _ros1_mcap_messages(self, topics):
        from rosbags.typesys import get_types_from_msg
        from rosbags.typesys.msg import normalize_msgtype

        for schema, channel, message in self._mcap_reader.iter_messages(topics=list(topics)):
            msgtype = normalize_msgtype(schema.name)
            if msgtype not in self._registered:
                self._typestore.register(get_types_from_msg(schema.data.decode(), msgtype))
                self._registered.add(msgtype)
            decoded = self._typestore.deserialize_ros1(message.data, msgtype)
            yield channel.topic, msgtype, int(message.log_time), decoded


def _mcap_profile(path: Path) -> str | None:
    try:
        from mcap.reader import make_reader
    except ImportError as error:
        raise ImportError(f"reading MCAP files needs the mcap package: {_EXTRA_HINT}") from error
    try:
        with open(path, "rb") as file:
            return make_reader(file).get_header().profile
    except Exception as error:
        raise ValueError(f"{path}: cannot read as an MCAP file: {_describe(error)}") from error


def _describe(error: BaseException) -> str:
    text = str(error) or "(no message)"
    return f"{type(error).__name__}: {text}"


def bag_info(path: PathLike) -> list[BagTopic]:
    """Every topic of a bag with its message type and count, sorted by name."""
    with _Bag(Path(path)) as bag:
        return bag.topics()


# ------------------------------------------------------------------------------------------ clouds


def _seconds(stamp_ns) -> str:
    """A stamp [ns] as exact decimal seconds."""
    stamp_ns = int(stamp_ns)
    return f"{stamp_ns // 1_000_000_000}.{stamp_ns % 1_000_000_000:09d}"


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _cloud_dtype(msg) -> np.dtype:
    """A structured dtype of one point: every named field at its offset, itemsize = point_step."""
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for point_field in msg.fields:
        if point_field.name in names or point_field.count == 0:
            continue
        if point_field.name in ("x", "y", "z") and point_field.count != 1:
            raise ValueError(
                f"field {point_field.name!r} holds {point_field.count} values a point; a coordinate holds one"
            )
        code = _POINT_FIELD_TYPES.get(int(point_field.datatype))
        if code is None:
            raise ValueError(
                f"field {point_field.name!r} has unknown PointField datatype {point_field.datatype}"
            )
        base = np.dtype(order + code)
        fmt = base if point_field.count == 1 else np.dtype((base, (int(point_field.count),)))
        if point_field.offset + fmt.itemsize > msg.point_step:
            raise ValueError(
                f"field {point_field.name!r} (offset {point_field.offset}, {fmt.itemsize} bytes) does not "
                f"fit in point_step {msg.point_step}"
            )
        names.append(point_field.name)
        formats.append(fmt)
        offsets.append(int(point_field.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": int(msg.point_step)})


def decode_pointcloud2(msg, *, keep_invalid: bool = False) -> tuple[np.ndarray, dict[str, np.ndarray], int]:
    """Decode a ``sensor_msgs/PointCloud2`` (as rosbags deserialises it) without a loop per point.

    Any field layout works: x, y, z as float32 or float64 (or integers) at any offset, padding in
    ``point_step`` and ``row_step``, either byte order, extra fields of any PointField type, organised
    (height > 1, flattened row by row) or not. Points with a non-finite coordinate or at exactly
    (0, 0, 0), the two ways drivers store a missing return, are dropped unless ``keep_invalid``.

    Returns
    -------
    xyz : (N, 3) float32 or float64 array
        float64 when any of x, y, z is stored as float64 or as an integer, else float32.
    fields : dict of (N,) or (N, count) arrays
        The other fields, by name, in native byte order.
    no_returns : int
        How many points were invalid (dropped unless ``keep_invalid``).
    """
    dtype = _cloud_dtype(msg)
    missing = [name for name in "xyz" if name not in dtype.names]
    if missing:
        have = ", ".join(dtype.names) or "none"
        raise ValueError(f"the PointCloud2 has no {', '.join(missing)} field (its fields: {have})")
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if height * width and row_step < width * point_step:
        raise ValueError(f"row_step {row_step} is shorter than width {width} x point_step {point_step}")
    need = (height - 1) * row_step + width * point_step if height * width else 0
    if data.size < need:
        raise ValueError(
            f"the PointCloud2 data holds {data.size} bytes, its {height} x {width} points need {need}"
        )
    points = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step)).reshape(-1)
    x, y, z = points["x"], points["y"], points["z"]
    wide = any(array.dtype.kind != "f" or array.dtype.itemsize > 4 for array in (x, y, z))
    xyz = np.empty((points.size, 3), dtype=np.float64 if wide else np.float32)
    xyz[:, 0], xyz[:, 1], xyz[:, 2] = x, y, z
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]  # columns: row-wise reductions of (N, 3) are slow
    valid = np.isfinite(x) & np.isfinite(y) & np.isfinite(z) & ((x != 0) | (y != 0) | (z != 0))
    no_returns = int(points.size - np.count_nonzero(valid))
    fields = {}
    for name in dtype.names:
        if name not in ("x", "y", "z"):
            values = points[name]
            fields[name] = values.astype(values.dtype.newbyteorder("="), copy=True)
    if no_returns and not keep_invalid:
        xyz = xyz[valid]
        fields = {name: values[valid] for name, values in fields.items()}
    return xyz, fields, no_returns


# ------------------------------------------------------------------------------------------ poses


def _matrix(translation, quaternion) -> np.ndarray:
    from .poses import matrix_from_quaternion

    pose = np.eye(4)
    pose[:3, :3] = matrix_from_quaternion(quaternion)
    pose[:3, 3] = translation
    return pose


class _PoseSeries:
    """Timed rigid transforms of one frame, interpolated linearly (translation) and by SLERP."""

    def __init__(self, name: str, stamps_ns, translations, quaternions):
        order = np.argsort(np.asarray(stamps_ns, dtype=np.int64), kind="stable")
        stamps = np.asarray(stamps_ns, dtype=np.int64)[order]
        stamps, first = np.unique(stamps, return_index=True)
        self.name = name
        self.stamps = stamps
        self.translations = np.asarray(translations, dtype=np.float64)[order][first]
        quaternions = np.asarray(quaternions, dtype=np.float64)[order][first]
        norms = np.linalg.norm(quaternions, axis=1, keepdims=True)
        if not np.all(norms > 0):
            raise ValueError(f"{name}: a pose has a zero or non-finite quaternion")
        self.quaternions = quaternions / norms

    def at(self, stamp_ns: int) -> np.ndarray:
        stamps = self.stamps
        if stamp_ns < stamps[0] or stamp_ns > stamps[-1]:
            raise ValueError(
                f"stamp {_seconds(stamp_ns)} s is outside the span of {self.name}: "
                f"[{_seconds(stamps[0])}, {_seconds(stamps[-1])}] s ({len(stamps)} poses)"
            )
        i = int(np.searchsorted(stamps, stamp_ns, side="right")) - 1
        if stamps[i] == stamp_ns:
            return _matrix(self.translations[i], self.quaternions[i])
        from .poses import slerp

        alpha = (stamp_ns - stamps[i]) / (stamps[i + 1] - stamps[i])
        translation = (1.0 - alpha) * self.translations[i] + alpha * self.translations[i + 1]
        return _matrix(translation, slerp(self.quaternions[i], self.quaternions[i + 1], alpha))


def _transform_parts(transform):
    t, q = transform.translation, transform.rotation
    return (t.x, t.y, t.z), (q.x, q.y, q.z, q.w)


def _pose_parts(pose):
    p, q = pose.position, pose.orientation
    return (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)


class _TfTree:
    """The frames of /tf and /tf_static: each child has one parent; static edges are fixed."""

    def __init__(self, source: str):
        self.source = source
        self._static: dict[str, tuple[str, np.ndarray]] = {}
        self._samples: dict[str, tuple[str, list]] = {}
        self._dynamic: dict[str, tuple[str, _PoseSeries]] = {}

    def add(self, message, static: bool) -> None:
        for transform in message.transforms:
            parent = transform.header.frame_id.lstrip("/")
            child = transform.child_frame_id.lstrip("/")
            translation, quaternion = _transform_parts(transform.transform)
            if static:
                try:
                    self._static[child] = (parent, _matrix(translation, quaternion))
                except ValueError as error:
                    raise ValueError(
                        f"{self.source}: the /tf_static transform {parent} -> {child}: {error}"
                    ) from None
            else:
                samples = self._samples.setdefault(child, (parent, []))[1]
                samples.append((_stamp_ns(transform.header), translation, quaternion))

    def finish(self) -> None:
        for child, (parent, samples) in self._samples.items():
            stamps, translations, quaternions = zip(*samples, strict=True)
            name = f"the /tf transform {parent} -> {child}"
            self._dynamic[child] = (parent, _PoseSeries(name, stamps, translations, quaternions))

    @property
    def frames(self) -> set[str]:
        frames = set()
        for child, (parent, _) in [*self._static.items(), *self._dynamic.items()]:
            frames.update((child, parent))
        return frames

    def _check(self, frame: str) -> None:
        if frame not in self.frames:
            known = ", ".join(sorted(self.frames)) or "none (the bag has no /tf or /tf_static)"
            raise ValueError(f"{self.source}: frame {frame!r} is not in the TF tree; known frames: {known}")

    def _up(self, frame: str, stamp_ns: int) -> list[tuple[str, object]]:
        """[(frame, T_frame_start)] from the start frame up to the root, composing lazily."""
        chain = [(frame, None)]
        seen = {frame}
        while True:
            if frame in self._dynamic:
                parent, edge = self._dynamic[frame]
            elif frame in self._static:
                parent, edge = self._static[frame]
            else:
                return chain
            if parent in seen:
                raise ValueError(f"{self.source}: the TF tree has a cycle through {parent!r}")
            seen.add(parent)
            chain.append((parent, (edge, stamp_ns)))
            frame = parent

    def root(self, frame: str) -> str:
        self._check(frame)
        return self._up(frame, 0)[-1][0]

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        """T_target_source at ``stamp_ns``: maps points in ``source`` coordinates to ``target``."""
        if target == source:
            return np.eye(4)
        self._check(target)
        self._check(source)
        up_source = self._up(source, stamp_ns)
        up_target = self._up(target, stamp_ns)
        target_frames = [frame for frame, _ in up_target]
        common = next((frame for frame, _ in up_source if frame in target_frames), None)
        if common is None:
            raise ValueError(
                f"{self.source}: frames {target!r} and {source!r} are not connected in the TF tree "
                f"(roots {up_target[-1][0]!r} and {up_source[-1][0]!r})"
            )

        def to_common(chain):
            pose = np.eye(4)
            for frame, step in chain[1:]:
                edge, stamp = step
                pose = (edge.at(stamp) if isinstance(edge, _PoseSeries) else edge) @ pose
                if frame == common:
                    break
            return pose

        common_source = to_common(up_source) if source != common else np.eye(4)
        common_target = to_common(up_target) if target != common else np.eye(4)
        return np.linalg.solve(common_target, common_source)


def with_attitude(pose, roll: float, pitch: float) -> np.ndarray:
    """``pose`` (4x4) with its roll and pitch replaced: rotation Rz(yaw) Ry(pitch) Rx(roll), where
    yaw is the pose's heading (Z-Y-X angles), translation kept. For a wheeled robot's planar
    odometry and an IMU's attitude."""
    from .collapse import leveling_transform

    pose = np.asarray(pose, dtype=np.float64)
    yaw = math.atan2(pose[1, 0], pose[0, 0])
    turn = np.eye(4)
    turn[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    out = turn @ leveling_transform(roll, pitch)
    out[:3, 3] = pose[:3, 3]
    return out


class _ImuUp:
    """The up direction over time in the frame of a ``sensor_msgs/Imu`` topic, a unit vector per
    message: from the orientation when the messages carry one (REP 145: the IMU frame's rotation in
    a frame whose z points up; ``orientation_covariance[0] == -1`` when there is none), else from the
    linear acceleration (at rest an accelerometer reads +g along up; a robot accelerating by
    1 m/s^2 tilts it by about 6 degrees). Matched to clouds by header stamps, or by the bag's
    record times when the headers are on another clock (drivers often stamp their IMU with the
    sensor's uptime)."""

    def __init__(self, source: str, topic: str, messages, window_ns: int):
        self.name = f"{source}: the IMU topic {topic}"
        self.window_ns = window_ns
        stamps, records, ups = [], [], []
        self.frame, self.kind = None, None
        for record_ns, msg in messages:
            if self.kind is None:
                self.kind = "orientation" if self._orientation(msg) is not None else "acceleration"
                self.frame = msg.header.frame_id.lstrip("/")
            up = self._up(msg)
            if up is not None:
                stamps.append(_stamp_ns(msg.header))
                records.append(record_ns)
                ups.append(up)
        if not ups:
            raise ValueError(
                f"{self.name} holds no usable message (an orientation, or a linear acceleration that is "
                "finite and not zero)"
            )
        self.stamps = np.asarray(stamps, dtype=np.int64)
        self.records = np.asarray(records, dtype=np.int64)
        self.up = np.asarray(ups, dtype=np.float64)
        self.clock: str | None = None  # "header" or "record", chosen at the first cloud

    @staticmethod
    def _orientation(msg):
        """The message's unit quaternion (x, y, z, w), or None when it carries no orientation."""
        q = msg.orientation
        quaternion = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
        norm = np.linalg.norm(quaternion)
        if msg.orientation_covariance[0] == -1.0 or not abs(norm - 1.0) < 0.01:
            return None
        return quaternion / norm

    def _up(self, msg):
        if self.kind == "orientation":
            quaternion = self._orientation(msg)
            if quaternion is None:
                return None
            from .poses import matrix_from_quaternion

            return matrix_from_quaternion(quaternion)[2]  # R^T e_z: the world's up in the IMU frame
        a = msg.linear_acceleration
        if msg.linear_acceleration_covariance[0] == -1.0:
            return None
        vector = np.array([a.x, a.y, a.z], dtype=np.float64)
        norm = float(np.linalg.norm(vector))
        return vector / norm if math.isfinite(norm) and norm > 0.0 else None

    def _span(self, times) -> str:
        return f"[{_seconds(int(times.min()))}, {_seconds(int(times.max()))}] s"

    def at(self, stamp_ns: int, record_ns: int) -> np.ndarray:
        """The mean up direction of the messages within the window of the cloud's time."""
        if self.clock is None:
            covers = {
                name: times.min() - self.window_ns <= t <= times.max() + self.window_ns
                for name, times, t in (("header", self.stamps, stamp_ns), ("record", self.records, record_ns))
            }
            self.clock = "header" if covers["header"] else "record" if covers["record"] else None
            if self.clock is None:
                raise ValueError(
                    f"{self.name} does not cover the cloud at {_seconds(stamp_ns)} s (recorded at "
                    f"{_seconds(record_ns)} s): its stamps span {self._span(self.stamps)}, its record "
                    f"times {self._span(self.records)}"
                )
        times, t = (self.stamps, stamp_ns) if self.clock == "header" else (self.records, record_ns)
        near = np.abs(times - t) <= self.window_ns
        if not near.any():
            raise ValueError(
                f"{self.name} has no message within {self.window_ns * 1e-9:g} s of the cloud at "
                f"{_seconds(t)} s ({'stamps' if self.clock == 'header' else 'record times'} span "
                f"{self._span(times)}; read_bag's imu_window widens the window)"
            )
        mean = self.up[near].mean(axis=0)
        norm = float(np.linalg.norm(mean))
        if not norm > 0.5:  # unit vectors more than ~120 degrees apart on average
            raise ValueError(
                f"{self.name}: the up directions of its {int(near.sum())} messages within "
                f"{self.window_ns * 1e-9:g} s of the cloud disagree (mean length {norm:.2f} of 1)"
            )
        return mean / norm


# ------------------------------------------------------------------------------------------ read_bag


@dataclass
class BagCloud:
    """One decoded cloud: stamp [s], frame, points (N, 3), pose (4x4 or None), other fields, the
    count of invalid points dropped, the stamp [ns] and, read with an IMU topic, the attitude
    (roll, pitch) [rad] of the cloud's frame ([CBC] section IV-B: ``leveling_transform(roll,
    pitch)`` levels the points)."""

    stamp: float
    frame_id: str
    points: np.ndarray
    pose: np.ndarray | None
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    no_returns: int = 0
    stamp_ns: int = 0  #: the stamp in whole nanoseconds (a float of seconds keeps ~0.2 us)
    attitude: tuple[float, float] | None = None  #: (roll, pitch) [rad] from the IMU, or None

    def __repr__(self) -> str:
        attitude = ""
        if self.attitude is not None:
            roll, pitch = (math.degrees(angle) for angle in self.attitude)
            attitude = f", attitude=({roll:.2f}, {pitch:.2f}) deg"
        return (
            f"BagCloud(stamp={_seconds(self.stamp_ns)} s, frame_id={self.frame_id!r}, "
            f"{len(self.points)} points, pose={'yes' if self.pose is not None else 'None'}, "
            f"fields={sorted(self.fields)}, no_returns={self.no_returns}{attitude})"
        )


class BagClouds:
    """The clouds of one topic of a bag with their poses; iterate for ``(stamp, points, pose)``.

    Made by :func:`read_bag`. Each iteration opens the bag anew. ``no_returns`` lists, per cloud
    read so far, how many invalid points were dropped; :meth:`clouds` yields :class:`BagCloud`
    records with the extra fields as well.
    """

    def __init__(
        self,
        path: PathLike,
        points: str,
        poses: str | None = None,
        *,
        base_frame: str | None = None,
        fixed_frame: str | None = None,
        keep_invalid: bool = False,
        imu: str | None = None,
        imu_window: float = IMU_WINDOW_S,
    ):
        self.path = Path(path)
        self.points_topic = points
        self.poses = poses
        self.base_frame = base_frame.lstrip("/") if base_frame else None
        self.fixed_frame = fixed_frame.lstrip("/") if fixed_frame else None
        self.keep_invalid = keep_invalid
        self.imu = imu
        if not (math.isfinite(imu_window) and imu_window > 0.0):
            raise ValueError(f"imu_window must be a positive number of seconds, got {imu_window!r}")
        self.imu_window = imu_window
        #: How the IMU's messages were matched to the clouds: "header" stamps, or "record" times when
        #: the headers are on another clock; None before the first cloud or without an IMU.
        self.imu_clock: str | None = None
        #: "orientation" or "acceleration": what the IMU's attitude came from (None before reading).
        self.imu_source: str | None = None
        self.no_returns: list[int] = []
        #: The frame the poses map points into (the odometry's frame, the TF fixed frame or
        #: ``base_frame``), known once a cloud with a pose was read; None before or without poses.
        self.pose_frame: str | None = None
        if self.fixed_frame is not None and poses not in ("tf", TF_TOPIC):
            raise ValueError("fixed_frame applies to poses='/tf' only (a pose topic names its own frame)")
        with _Bag(self.path) as bag:  # fail early: a missing bag, topic or pose source
            self.count = bag.topic(points, (POINTCLOUD2,), "point-cloud topic").count
            if poses is not None and poses not in ("tf", TF_TOPIC):
                bag.topic(poses, POSE_TYPES, "pose topic")
            if imu is not None:
                bag.topic(imu, (IMU,), "IMU topic")

    def __len__(self) -> int:
        return self.count

    def __iter__(self) -> Iterator[tuple[float, np.ndarray, np.ndarray | None]]:
        for cloud in self.clouds():
            yield cloud.stamp, cloud.points, cloud.pose

    def __repr__(self) -> str:
        return (
            f"BagClouds({str(self.path)!r}, points={self.points_topic!r}, poses={self.poses!r}, "
            f"{self.count} clouds)"
        )

    def clouds(self) -> Iterator[BagCloud]:
        """Every cloud of the topic in bag order, decoded, with its pose and extra fields."""
        self.no_returns = []
        with _Bag(self.path) as bag:
            tree, series = self._pose_sources(bag)
            imu = None
            if self.imu is not None:
                imu = _ImuUp(
                    str(self.path),
                    self.imu,
                    ((record, msg) for _, _, record, msg in bag.messages([self.imu])),
                    round(self.imu_window * 1e9),
                )
                self.imu_source = imu.kind
            for _, _, log_time, msg in bag.messages([self.points_topic]):
                stamp_ns = _stamp_ns(msg.header) or log_time
                frame = msg.header.frame_id.lstrip("/")
                try:
                    xyz, fields, no_returns = decode_pointcloud2(msg, keep_invalid=self.keep_invalid)
                except ValueError as error:
                    raise ValueError(
                        f"{self.path}: {self.points_topic} at {_seconds(stamp_ns)} s: {error}"
                    ) from None
                pose = self._pose(tree, series, frame, stamp_ns)
                attitude = None if imu is None else self._attitude(tree, imu, frame, stamp_ns, log_time)
                self.no_returns.append(no_returns)
                yield BagCloud(stamp_ns * 1e-9, frame, xyz, pose, fields, no_returns, stamp_ns, attitude)

    def _attitude(self, tree, imu: _ImuUp, frame: str, stamp_ns: int, record_ns: int) -> tuple[float, float]:
        """The cloud frame's (roll, pitch): the IMU's up direction turned into the cloud's frame by
        the TF tree (the mount, usually on /tf_static)."""
        where = f"{self.path}: cloud at {_seconds(stamp_ns)} s in frame {frame!r}"
        try:
            up = imu.at(stamp_ns, record_ns)
            self.imu_clock = imu.clock
            if imu.frame and imu.frame != frame:
                try:
                    up = tree.lookup(frame, imu.frame, stamp_ns)[:3, :3] @ up
                except ValueError as error:
                    message = str(error).removeprefix(f"{self.path}: ")
                    raise ValueError(f"no transform from the IMU frame {imu.frame!r}: {message}") from None
        except ValueError as error:
            raise ValueError(f"{where}: {error}") from None
        from .collapse import attitude_from_gravity

        return attitude_from_gravity(up)

    def _pose_sources(self, bag: _Bag) -> tuple[_TfTree | None, tuple | None]:
        tree = None
        names = {t.name for t in bag.topics()}
        if self.poses is not None or self.base_frame is not None or self.imu is not None:
            tree = _TfTree(str(self.path))
            topics = [t for t in (TF_TOPIC, TF_STATIC_TOPIC) if t in names]
            for topic in topics:
                bag.topic(topic, (TF_MESSAGE,), "TF topic")
            for topic, _, _, message in bag.messages(topics):
                tree.add(message, static=topic == TF_STATIC_TOPIC)
            tree.finish()
            if self.poses in ("tf", TF_TOPIC) and TF_TOPIC not in names:
                warnings.warn(
                    f"{self.path}: poses from /tf, but the bag has no /tf topic"
                    + (" (only /tf_static)" if TF_STATIC_TOPIC in names else "")
                    + ": every cloud gets the same, static pose",
                    UserWarning,
                    stacklevel=4,
                )
        series = None
        if self.poses is not None and self.poses not in ("tf", TF_TOPIC):
            stamps, translations, quaternions = [], [], []
            child = None
            for _, msgtype, _, message in bag.messages([self.poses]):
                if msgtype == ODOMETRY:
                    translation, quaternion = _pose_parts(message.pose.pose)
                    child = message.child_frame_id.lstrip("/") or child
                elif msgtype == POSE_WITH_COVARIANCE_STAMPED:
                    translation, quaternion = _pose_parts(message.pose.pose)
                elif msgtype == POSE_STAMPED:
                    translation, quaternion = _pose_parts(message.pose)
                else:  # TransformStamped
                    translation, quaternion = _transform_parts(message.transform)
                    child = message.child_frame_id.lstrip("/") or child
                stamps.append(_stamp_ns(message.header))
                translations.append(translation)
                quaternions.append(quaternion)
                self.pose_frame = self.pose_frame or message.header.frame_id.lstrip("/")
            if not stamps:
                raise ValueError(f"{self.path}: the pose topic {self.poses!r} holds no message")
            try:
                series = (_PoseSeries(f"the poses of {self.poses}", stamps, translations, quaternions), child)
            except ValueError as error:
                raise ValueError(f"{self.path}: {error}") from None
        return tree, series

    def _pose(self, tree, series, frame: str, stamp_ns: int) -> np.ndarray | None:
        where = f"{self.path}: cloud at {_seconds(stamp_ns)} s in frame {frame!r}"
        try:
            if self.poses is None:
                if self.base_frame is None:
                    return None
                self.pose_frame = self.base_frame
                return tree.lookup(self.base_frame, frame, stamp_ns)
            if self.poses in ("tf", TF_TOPIC):
                base = self.base_frame or frame
                fixed = self.fixed_frame or tree.root(base)
                self.pose_frame = fixed
                return tree.lookup(fixed, base, stamp_ns) @ tree.lookup(base, frame, stamp_ns)
            poses, child = series
            base = self.base_frame or child or frame
            return poses.at(stamp_ns) @ tree.lookup(base, frame, stamp_ns)
        except ValueError as error:
            message = str(error)
            if message.startswith(str(self.path)):
                message = message[len(str(self.path)) + 2 :]
            raise ValueError(f"{where}: {message}") from None


def cloud_topic(path: PathLike, topic: str | None = None, hint: str = "pass points=TOPIC") -> str:
    """``topic``, or the bag's only ``sensor_msgs/PointCloud2`` topic; ValueError listing the bag's
    PointCloud2 topics (after ``hint``) when it has none or several."""
    if topic is not None:
        return topic
    clouds = [t.name for t in bag_info(path) if t.msgtype == POINTCLOUD2]
    if len(clouds) != 1:
        raise ValueError(f"{path}: {hint}; the bag's PointCloud2 topics: {', '.join(clouds) or 'none'}")
    return clouds[0]


def read_bag(
    path: PathLike,
    points: str | None = None,
    poses: str | None = None,
    *,
    base_frame: str | None = None,
    fixed_frame: str | None = None,
    keep_invalid: bool = False,
    imu: str | None = None,
    imu_window: float = IMU_WINDOW_S,
) -> BagClouds:
    """The ``sensor_msgs/PointCloud2`` clouds of one topic of a bag, as ``(stamp, points, pose)``.

    Parameters
    ----------
    path : str or Path
        A ROS 1 ``.bag``, a ROS 2 bag folder (sqlite3 or mcap storage), or an ``.mcap`` file (ROS 2 or
        ros1 profile).
    points : str, optional
        The PointCloud2 topic (default: the bag's only one, see :func:`cloud_topic`). Points are
        decoded as :func:`decode_pointcloud2` does; invalid points are dropped and counted in the
        result's ``no_returns``.
    poses : str, optional
        Where each cloud's pose comes from:

        - None: no pose (``pose`` is None), or with ``base_frame`` the static transform cloud frame ->
          ``base_frame`` from /tf_static.
        - a ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped`` or
          ``TransformStamped`` topic: the pose of ``base_frame`` (default: the odometry's child
          frame, else the cloud's frame) in the messages' frame, interpolated to the cloud's stamp,
          times the transform cloud frame -> base frame from the TF tree (/tf_static).
        - ``"/tf"``: the chain of /tf and /tf_static transforms from the cloud's frame (through
          ``base_frame`` when given) up to ``fixed_frame`` (default: the root of the tree).

        Timed transforms are interpolated to the cloud's header stamp: translation linearly,
        rotation by SLERP. A stamp outside a pose source's span and a frame missing from the tree
        raise ValueError (naming the span, or the frame and the known frames).
    keep_invalid : bool
        Keep points at (0, 0, 0) or with NaN (organised clouds keep their height x width order).
    imu : str, optional
        A ``sensor_msgs/Imu`` topic: each cloud's ``attitude`` (roll, pitch) [rad] of its frame, the
        leveling of [CBC] section IV-B, from the mean up direction of the IMU messages within
        ``imu_window`` seconds of the cloud (their orientations, or else their accelerations: right
        when the robot does not accelerate hard), turned into the cloud's frame through the TF tree.
        Matched by header stamps, or by the bag's record times when the IMU's headers are on
        another clock (``imu_clock`` says which).

    Returns
    -------
    BagClouds
        Iterable of ``(stamp [s], (N, 3) float32/float64 points in the cloud's frame, 4x4 float64
        pose or None)``, in bag order; the stamp is the cloud header's (the bag's record time when
        that is zero); ``len()`` is the number of clouds. The pose maps the cloud's points into the
        fixed (world) frame, or into ``base_frame`` without a pose source.
    """
    return BagClouds(
        path,
        cloud_topic(path, points),
        poses,
        base_frame=base_frame,
        fixed_frame=fixed_frame,
        keep_invalid=keep_invalid,
        imu=imu,
        imu_window=imu_window,
    )


# ------------------------------------------------------------------------------------------ writing

#: grid_map_msgs definitions for ROS 2 (the GridMap carries the header). The field lists follow
#: ANYbotics' grid_map_msgs (ROS 2 branch); comments are ours.
GRID_MAP_MSGS_ROS2 = {
    "grid_map_msgs/msg/GridMapInfo": """\
# Cell edge [m].
float64 resolution
# Extent along x and y [m].
float64 length_x
float64 length_y
# Pose of the map's centre in the header's frame.
geometry_msgs/Pose pose
""",
    "grid_map_msgs/msg/GridMap": """\
std_msgs/Header header
grid_map_msgs/GridMapInfo info
# Layer names, one per data array.
string[] layers
# Layers that must be valid for a cell to be valid.
string[] basic_layers
# One column-major matrix per layer, cell (0, 0) at the map's maximum x and y.
std_msgs/Float32MultiArray[] data
# Circular-buffer start indices (row, column).
uint16 outer_start_index
uint16 inner_start_index
""",
}

#: grid_map_msgs definitions for ROS 1 (the header lives in GridMapInfo). Same fields as upstream,
#: so the MD5 sums match: GridMapInfo 43ee5430e1c253682111cb6bedac0ef9.
GRID_MAP_MSGS_ROS1 = {
    "grid_map_msgs/msg/GridMapInfo": """\
std_msgs/Header header
float64 resolution
float64 length_x
float64 length_y
geometry_msgs/Pose pose
""",
    "grid_map_msgs/msg/GridMap": """\
grid_map_msgs/GridMapInfo info
string[] layers
string[] basic_layers
std_msgs/Float32MultiArray[] data
uint16 outer_start_index
uint16 inner_start_index
""",
}

GRID_MAP = "grid_map_msgs/msg/GridMap"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"

#: OccupancyGrid value (0 free .. 100 occupied, -1 unknown) of each terrain class
#: (:class:`terracube.TerrainClass`): unknown -1, ground 0, obstacle 100, overhanging object 100,
#: vertical object 100, horizontal edge 50 (ground at a border: passable with care).
CLASS_OCCUPANCY = {0: -1, 1: 0, 2: 100, 3: 100, 4: 100, 5: 50}


def _typestore(ros1: bool):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    definitions = GRID_MAP_MSGS_ROS1 if ros1 else GRID_MAP_MSGS_ROS2
    types = {}
    for name, text in definitions.items():
        types.update(get_types_from_msg(text, name))
    typestore.register(types)
    return typestore


def grid_map_layer_data(layer) -> np.ndarray:
    """A terracube layer ((nx, ny), cell (0, 0) at the minimum x and y) as grid_map's data vector.

    grid_map stores a layer as an Eigen matrix whose row index runs along -x and column index along
    -y (index (0, 0) is the cell at the maximum corner), serialised column by column. So the layer
    is flipped along both axes and flattened in Fortran order.
    """
    return np.asarray(layer, dtype=np.float32)[::-1, ::-1].ravel(order="F")


def layer_from_grid_map_data(data, size_x: int, size_y: int) -> np.ndarray:
    """The inverse of :func:`grid_map_layer_data`: an (nx, ny) terracube layer."""
    return np.asarray(data, dtype=np.float32).reshape((size_x, size_y), order="F")[::-1, ::-1].copy()


def occupancy_from_classes(classes) -> np.ndarray:
    """(nx, ny) terrain classes -> (nx, ny) int8 occupancy values by :data:`CLASS_OCCUPANCY`."""
    classes = np.nan_to_num(np.asarray(classes, dtype=np.float64), nan=0.0).astype(np.int64)
    table = np.full(256, -1, dtype=np.int8)
    for terrain_class, value in CLASS_OCCUPANCY.items():
        table[terrain_class] = value
    return table[np.clip(classes, 0, 255)]


def occupancy_from_traversability(traversability) -> np.ndarray:
    """(nx, ny) traversability in [0, 1] (1 = free) -> int8 occupancy 0..100, NaN -> -1 (unknown)."""
    values = np.asarray(traversability, dtype=np.float64)
    occupancy = np.rint(100.0 * (1.0 - np.clip(values, 0.0, 1.0)))
    return np.where(np.isfinite(values), occupancy, -1).astype(np.int8)


def _time(typestore, stamp: float):
    total = int(round(float(stamp) * 1e9))
    return typestore.types["builtin_interfaces/msg/Time"](
        sec=total // 1_000_000_000, nanosec=total % 1_000_000_000
    )


def _ros1_lz4_frame(data: bytes) -> bytes:
    """An lz4 frame as ROS 1's roslz4 writes and reads it: independent 256 KiB blocks, a content
    checksum, no content size. roslz4 refuses rosbags' default frame (linked 64 KiB blocks, a
    content size) as "malformed data", and bz2, which it reads, takes minutes on large NaN grids."""
    import lz4.frame

    return lz4.frame.compress(
        data,
        block_size=lz4.frame.BLOCKSIZE_MAX256KB,
        block_linked=False,
        content_checksum=True,
        store_size=False,
    )


class MapBagWriter:
    """Writes terracube results into a new ROS bag; use as a context manager.

    ``storage`` is ``"mcap"`` (a ROS 2 bag folder with mcap storage, the default for any path but
    ``*.bag``), ``"sqlite3"`` (a ROS 2 bag folder) or ``"ros1"`` (a ROS 1 bag file, the default for
    ``*.bag``). Every bag is compressed the storage's standard way, so the NaN of a sparse grid costs
    little: zstd chunks for mcap, zstd per message for sqlite3 (rosbag2's message mode), lz4 chunks
    for ROS 1. The bag is built under a temporary name in the same folder and renamed to ``path``
    when the ``with`` block ends without an exception (or on :meth:`close`); otherwise it is
    removed. An existing ``path`` raises FileExistsError unless ``overwrite``.
    """

    def __init__(self, path: PathLike, storage: str | None = None, *, overwrite: bool = False):
        _require_rosbags()
        self.path = Path(path)
        if storage is None:
            storage = "ros1" if self.path.suffix == ".bag" else "mcap"
        if storage not in ("mcap", "sqlite3", "ros1"):
            raise ValueError(f"storage must be mcap, sqlite3 or ros1, got {storage!r}")
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path} exists already (pass overwrite=True to replace it)")
        self.storage = storage
        self.ros1 = storage == "ros1"
        self.overwrite = overwrite
        self.typestore = _typestore(self.ros1)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._temporary = Path(
            tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        )
        staged = self._temporary / self.path.name
        try:
            if self.ros1:
                from rosbags.rosbag1 import Writer

                self._writer = Writer(staged)
                self._writer.set_compression(Writer.CompressionFormat.LZ4)
                self._writer.compressor = _ros1_lz4_frame
            else:
                from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

                plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
                self._writer = Writer(staged, version=9, storage_plugin=plugin)
                # mcap compresses its chunks itself; sqlite3 has no storage-side compression, so
                # rosbag2 compresses each message (compression_mode: message in metadata.yaml).
                mode = CompressionMode.STORAGE if storage == "mcap" else CompressionMode.MESSAGE
                self._writer.set_compression(mode, CompressionFormat.ZSTD)
            self._writer.open()
        except BaseException:
            shutil.rmtree(self._temporary, ignore_errors=True)
            raise
        self._staged = staged
        self._connections: dict[str, object] = {}
        self._open = True
        self.counts: dict[str, int] = {}

    def __enter__(self) -> MapBagWriter:
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def __repr__(self) -> str:
        return f"MapBagWriter({str(self.path)!r}, storage={self.storage!r}, messages={self.counts})"

    # -------------------------------------------------------------------------------- messages

    def _types(self):
        return self.typestore.types

    def _header(self, stamp: float, frame_id: str):
        types = self._types()
        if self.ros1:
            return types["std_msgs/msg/Header"](seq=0, stamp=_time(self.typestore, stamp), frame_id=frame_id)
        return types["std_msgs/msg/Header"](stamp=_time(self.typestore, stamp), frame_id=frame_id)

    def _pose(self, x: float, y: float, z: float = 0.0):
        types = self._types()
        return types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z)),
            orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        )

    def _write(self, topic: str, msgtype: str, message, stamp: float) -> None:
        if not self._open:
            raise ValueError(f"{self.path}: the writer is closed")
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
            self._connections[topic] = connection
        elif connection.msgtype != msgtype:
            raise ValueError(f"topic {topic!r} already holds {connection.msgtype}, not {msgtype}")
        serialize = self.typestore.serialize_ros1 if self.ros1 else self.typestore.serialize_cdr
        self._writer.write(connection, max(int(round(float(stamp) * 1e9)), 0), serialize(message, msgtype))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def write_grid_map(
        self,
        elevation_map,
        *,
        stamp: float = 0.0,
        frame_id: str = "map",
        layers: Sequence[str] | None = None,
        basic_layers: Sequence[str] = (),
        topic: str = "/terracube/grid_map",
    ) -> None:
        """One ``grid_map_msgs/msg/GridMap`` of an :class:`terracube.ElevationMap` (all layers, or
        ``layers``), converted to grid_map's layout (:func:`grid_map_layer_data`); NaN stays NaN
        (grid_map's empty cell)."""
        types = self._types()
        geometry = elevation_map.geometry
        nx, ny = (int(n) for n in geometry.size)
        resolution = float(geometry.resolution)
        names = list(elevation_map.layers if layers is None else layers)
        for name in [*names, *basic_layers]:
            if name not in elevation_map:
                raise KeyError(f"no layer {name!r}; layers: {', '.join(elevation_map.layers)}")
        dimension, layout = types["std_msgs/msg/MultiArrayDimension"], types["std_msgs/msg/MultiArrayLayout"]
        arrays = [
            types["std_msgs/msg/Float32MultiArray"](
                layout=layout(
                    dim=[
                        dimension(label="column_index", size=ny, stride=nx * ny),
                        dimension(label="row_index", size=nx, stride=nx),
                    ],
                    data_offset=0,
                ),
                data=grid_map_layer_data(elevation_map[name]),
            )
            for name in names
        ]
        centre = (
            float(geometry.origin[0]) + 0.5 * nx * resolution,
            float(geometry.origin[1]) + 0.5 * ny * resolution,
        )
        info_fields = dict(
            resolution=resolution,
            length_x=nx * resolution,
            length_y=ny * resolution,
            pose=self._pose(*centre),
        )
        common = dict(
            layers=names,
            basic_layers=list(basic_layers),
            data=arrays,
            outer_start_index=0,
            inner_start_index=0,
        )
        info_type = types["grid_map_msgs/msg/GridMapInfo"]
        if self.ros1:
            info = info_type(header=self._header(stamp, frame_id), **info_fields)
            message = types[GRID_MAP](info=info, **common)
        else:
            message = types[GRID_MAP](
                header=self._header(stamp, frame_id), info=info_type(**info_fields), **common
            )
        self._write(topic, GRID_MAP, message, stamp)

    def write_occupancy_grid(
        self,
        elevation_map,
        occupancy,
        *,
        stamp: float = 0.0,
        frame_id: str = "map",
        topic: str = "/terracube/occupancy",
    ) -> None:
        """One ``nav_msgs/msg/OccupancyGrid`` on the map's geometry from (nx, ny) int8 values
        (:func:`occupancy_from_classes`, :func:`occupancy_from_traversability`). The grid's origin
        is the lower-left corner of cell (0, 0); its width runs along x."""
        types = self._types()
        geometry = elevation_map.geometry
        nx, ny = (int(n) for n in geometry.size)
        values = np.asarray(occupancy)
        if values.shape != (nx, ny):
            raise ValueError(f"occupancy has shape {values.shape}, the map is {(nx, ny)}")
        if values.dtype != np.int8:
            if values.size and (values.min() < -1 or values.max() > 100):
                raise ValueError("occupancy values must lie in -1..100")
            values = values.astype(np.int8)
        info = types["nav_msgs/msg/MapMetaData"](
            map_load_time=_time(self.typestore, stamp),
            resolution=float(geometry.resolution),
            width=nx,
            height=ny,
            origin=self._pose(float(geometry.origin[0]), float(geometry.origin[1])),
        )
        message = types[OCCUPANCY_GRID](
            header=self._header(stamp, frame_id), info=info, data=values.ravel(order="F").copy()
        )
        self._write(topic, OCCUPANCY_GRID, message, stamp)

    def write_cloud(
        self,
        points,
        labels=None,
        *,
        stamp: float = 0.0,
        frame_id: str = "map",
        topic: str = "/terracube/classified_cloud",
    ) -> None:
        """One unorganised ``sensor_msgs/msg/PointCloud2``: float32 x, y, z at offsets 0, 4, 8 and,
        with ``labels``, a uint32 ``label`` field at 12 (PCL's PointXYZL layout), 16 bytes a point."""
        types = self._types()
        xyz = np.asarray(points, dtype=np.float32)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"points must be an (N, 3) array, got shape {xyz.shape}")
        record = np.zeros(
            len(xyz),
            dtype=np.dtype(
                {
                    "names": ["x", "y", "z", "label"],
                    "formats": ["<f4"] * 3 + ["<u4"],
                    "offsets": [0, 4, 8, 12],
                    "itemsize": 16,
                }
            ),
        )
        record["x"], record["y"], record["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        point_field = types["sensor_msgs/msg/PointField"]
        fields = [point_field(name=name, offset=4 * i, datatype=7, count=1) for i, name in enumerate("xyz")]
        if labels is not None:
            labels = np.asarray(labels)
            if labels.shape != (len(xyz),):
                raise ValueError(f"need one label per point: {labels.shape} labels for {len(xyz)} points")
            record["label"] = labels
            fields.append(point_field(name="label", offset=12, datatype=6, count=1))
        message = types[POINTCLOUD2](
            header=self._header(stamp, frame_id),
            height=1,
            width=len(xyz),
            fields=fields,
            is_bigendian=False,
            point_step=16,
            row_step=16 * len(xyz),
            data=record.view(np.uint8).reshape(-1).copy(),
            is_dense=bool(np.isfinite(xyz).all()),
        )
        self._write(topic, POINTCLOUD2, message, stamp)

    # -------------------------------------------------------------------------------- finishing

    def close(self) -> Path:
        """Finish the bag and move it to ``path``; returns ``path``."""
        if not self._open:
            return self.path
        self._open = False
        try:
            self._writer.close()
            if self.path.exists():  # overwrite (checked in __init__): move the old one aside first
                old = self._temporary / (".old-" + self.path.name)
                os.replace(self.path, old)
            os.replace(self._staged, self.path)
        except BaseException:
            shutil.rmtree(self._temporary, ignore_errors=True)
            raise
        shutil.rmtree(self._temporary, ignore_errors=True)
        return self.path

    def abort(self) -> None:
        """Drop the bag: nothing is left at ``path`` or under the temporary name."""
        if self._open:
            self._open = False
            try:
                self._writer.close()
            except Exception:  # noqa: S110 - the half-written bag is removed below anyway
                pass
        shutil.rmtree(self._temporary, ignore_errors=True)
