"""Seeded fuzzing of terracube's Python API with hostile clouds, poses and parameters.

Every call must answer with a result or a ``ValueError`` / ``TypeError`` / ``KeyError`` /
``IndexError`` naming the problem, in bounded time and memory: never another exception
(``MemoryError`` from an allocation the input asked for, ``OverflowError``, ``RuntimeError``), a
crash or a hang. A case is drawn from its seed alone: a cloud (empty, one point, all equal, 1e300
or 1e-300 wide, NaN/Inf rows, float32 extremes, Fortran order), a pose (shifted, turned,
non-rigid, NaN) and either extreme arguments of one function, the defaults of a parameter struct
with a few fields set to 0, -1, NaN, +-inf, 1e300, 2^31 ..., maps, local maps, fuzzy maps and files
used with such values, a command line (collapse, dem, classify, fem) with such options, which
must exit 0 or 2 (``CommandFailed``), or a small ROS 2 bag of hostile PointCloud2 layouts, IMU
messages, odometry and mounts, read by ``read_bag`` or a command.
Cases run in the reader fuzzer's worker (a subprocess under a memory limit and an alarm,
restarted after a crash), which calls ``answer_case``; a failure replays with ``run_case(seed)``.

Used by ``tests/fuzz/run.py --target api`` (a bounded run for CI) and
``tests/python/test_fuzz_quick.py``.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

MEMORY_LIMIT_BYTES = 6 << 30  # the largest maps the guards allow (64 M cells) take about 2 GB
CASE_SECONDS = 30.0
FLOATS = [0.0, -1.0, math.nan, math.inf, -math.inf, 1e300, 1e-300, 1e-9, 1e9, 0.5, 3.0]
INTEGERS = [0, -1, 1, 2, 7, 10**9, 2**31, 2**63 - 1]


def cloud(rng: np.random.Generator) -> np.ndarray:
    """An (N, 3) cloud of one of fourteen hostile kinds; sometimes with wider rows, transposed or in
    Fortran order."""
    n = int(rng.choice([0, 1, 2, 3, 5, 50, 1000, 20000]))
    kind = int(rng.integers(0, 14))
    normal = rng.normal(0.0, 10.0, (n, 3))
    if kind == 1:
        points = np.tile(rng.normal(0.0, 1.0, (1, 3)), (n, 1))  # one point, n times
    elif kind == 2:
        points = normal * 10.0 ** rng.integers(3, 300)  # up to 1e300 wide
    elif kind == 3:
        points = normal / 10.0 + 10.0 ** rng.integers(5, 300)  # far from the origin
    elif kind == 4:
        points = normal * 1e-300  # denormal spread
    elif kind in (5, 6) and n > 0:
        points = normal
        rows = rng.integers(0, n, max(1, n // 10))
        points[rows, rng.integers(0, 3)] = math.nan if kind == 5 else math.inf
    elif kind == 7:
        points = np.c_[rng.uniform(-1e4, 1e4, (n, 2)), rng.normal(0.0, 1.0, n)]  # 20 km flat
    elif kind == 8:
        points = np.c_[rng.uniform(-1.0, 1.0, (n, 2)), rng.uniform(-1e6, 1e6, n)]  # 2000 km tall
    elif kind == 9:
        points = np.c_[np.linspace(0.0, 1e6, n), np.zeros((n, 2))]  # a line
    elif kind == 10:
        points = np.full((n, 3), -0.0)
    elif kind == 11:
        points = normal.astype(np.float32)
    elif kind == 12:
        points = rng.uniform(-3e38, 3e38, (n, 3)).astype(np.float32)  # float32's extremes
    elif kind == 13:
        points = normal
        points[:, 2] = rng.choice([0.0, 5.0, 1e9], n)  # layers far apart
    else:
        points = normal
    layout = rng.random()
    if layout < 0.1:  # wider rows, x, y, z first (intensity, ring, time ...), read in place
        extra = rng.normal(0.0, 1.0, (n, int(rng.integers(1, 15)))).astype(points.dtype)
        return np.concatenate([points, extra], axis=1)
    if layout < 0.13:
        return np.ascontiguousarray(points.T)  # a cloud stored by columns: refused unless tiny
    return np.asfortranarray(points) if layout < 0.33 else points


def pose(rng: np.random.Generator) -> np.ndarray:
    """A 4x4 pose: identity, shifted (up to 1e300), turned, non-rigid or NaN."""
    matrix = np.eye(4)
    kind = int(rng.integers(0, 6))
    if kind == 1:
        matrix[:3, 3] = rng.normal(0.0, 10.0, 3)
    elif kind == 2:
        matrix[:3, 3] = 10.0 ** rng.integers(5, 300) * rng.normal(0.0, 1.0, 3)
    elif kind == 3:
        yaw = rng.uniform(-3.2, 3.2)
        matrix[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    elif kind == 4:
        matrix[0, 0] = 2.0
    elif kind == 5:
        matrix[:3, 3] = math.nan
    return matrix


def beams(rng: np.random.Generator):
    """Directions of beams without a return: None, none, a few, many, tiny or huge, some zero or NaN."""
    m = int(rng.choice([-1, 0, 1, 5, 1000, 100000]))
    if m < 0:
        return None
    directions = rng.normal(0.0, 1.0, (m, 3)) * 10.0 ** float(rng.choice([0, -300, 300, -30]))
    kind = int(rng.integers(0, 4))
    if kind == 1 and m > 0:
        directions[rng.integers(0, m)] = 0.0
    elif kind == 2 and m > 0:
        directions[rng.integers(0, m), rng.integers(0, 3)] = float(rng.choice([math.nan, math.inf]))
    return directions


def organised(rng: np.random.Generator, points: np.ndarray):
    """An organised image (H, W, 3) of a cloud, or its rows with a ring field: empty pixels as
    (0, 0, 0) or NaN, beams whose pixel counts may differ."""
    n = len(points)
    height = int(rng.choice([1, 2, 4, 64]))
    width = max(1, n // height)
    image = np.resize(points, (height, width, 3)).astype(float) if n else np.zeros((height, width, 3))
    empty = rng.random((height, width)) < float(rng.choice([0.0, 0.3, 1.0]))
    image[empty] = float(rng.choice([0.0, math.nan]))
    if rng.random() < 0.5:
        return {"organised": image}
    ring = np.repeat(np.arange(height), width)
    if rng.random() < 0.3 and ring.size:
        ring[0] = height + 5  # a beam of one pixel
    return {
        "organised": image.reshape(-1, 3),
        "ring": ring.astype(rng.choice([np.int64, np.uint16, np.float64])),
    }


#: Memory guards: raising them is the caller's choice to allow that much memory (a MemoryError
#: is then the honest answer), so they keep their defaults.
MEMORY_GUARDS = ("max_cells", "dense_budget_bytes")


def perturb(params, rng: np.random.Generator, share: float = 0.08):
    """A copy of a parameter dataclass with about `share` of its numbers (not its memory guards)
    set to extremes."""
    changes = {}
    for field in dataclasses.fields(params):
        value = getattr(params, field.name)
        if field.name in MEMORY_GUARDS:
            continue
        if dataclasses.is_dataclass(value):
            changes[field.name] = perturb(value, rng, share)
        elif rng.random() < share:
            if isinstance(value, bool):
                changes[field.name] = not value
            elif isinstance(value, int):
                changes[field.name] = int(rng.choice(INTEGERS))
            elif isinstance(value, float):
                changes[field.name] = float(rng.choice(FLOATS))
    try:
        return dataclasses.replace(params, **changes)
    except (ValueError, TypeError):  # refused at once: as good as a refusal later
        return params


def _round_trip(result):
    """`result` pickled and read back, checked against it (a failure, not a refusal, if it differs).
    Maps over 4 M cells are left out: the round trip holds the map about four times (the map, the
    pickle's bytes, the arrays read back and the new map), over the worker's memory limit for the
    largest maps the guards allow."""
    import pickle

    if hasattr(result, "geometry") and result.geometry.num_cells > 1 << 22:
        return
    back = pickle.loads(pickle.dumps(result))
    if repr(back) != repr(result):
        raise AssertionError(f"pickling changed {result!r} into {back!r}")
    if hasattr(result, "layers"):  # a map: every layer, NaN where NaN
        same = all(np.array_equal(back[name], result[name], equal_nan=True) for name in result.layers)
    elif hasattr(result, "overhang"):
        same = np.array_equal(back.overhang, result.overhang) and np.array_equal(
            back.cube_reasons, result.cube_reasons
        )
    else:
        same = (
            np.array_equal(back.transform, result.transform, equal_nan=True)
            and back.verdict == result.verdict
        )
    if not same:
        raise AssertionError(f"pickling changed the contents of {result!r}")


def _function_case(tc, rng: np.random.Generator, points: np.ndarray) -> None:
    """One function with extreme arguments."""
    which = int(rng.integers(0, 12))
    edge = float(rng.choice([0.5, 0.1, 1e-3, 1e-9, 100.0, 1e300, 0.0, -1.0, math.nan]))
    sigma = int(rng.choice([1, 2, 4, 100, 10**9, 0]))
    resolution = float(rng.choice([0.1, 1.0, 1e-4, 1e-12, 1e6, 1e300, 0.0, math.inf]))
    drop = bool(rng.random() < 0.5)
    if which == 0:
        method = str(rng.choice(["paper", "shadow_aware"]))
        transform = pose(rng)
        result = tc.collapse_overhangs(
            points,
            edge,
            sigma,
            drop_non_finite=drop,
            method=method,
            transform=transform,
            no_returns=beams(rng),
        )
        _round_trip(result)
        # the reasons of its own points, or of another cloud (a refusal, never a wrong lookup)
        tc.point_reasons(points if rng.random() < 0.5 else cloud(rng), result, transform=transform)
    elif which == 1:
        elevation_map = tc.build_elevation_map(points, resolution, drop_non_finite=drop)
        tc.classify_terrain(elevation_map)
        _round_trip(elevation_map)
    elif which == 2:
        method = str(rng.choice(["paper", "shadow_aware"]))
        collapse = tc.CollapseParams(edge, sigma, drop_non_finite=drop, method=method)
        tc.dem_without_overhangs(points, resolution=resolution, collapse=collapse, no_returns=beams(rng))
    elif which == 3:
        local = tc.LocalMap(float(rng.choice([20.0, 1.0, 0.05, 1e4])), float(rng.choice([0.1, 1.0, 1e-3])))
        for _ in range(3):
            local.update(points, pose(rng), no_returns=beams(rng))
        local.update_planner_layers()
    elif which == 4:
        tc.register_points(points, cloud(rng), initial=pose(rng))
    elif which == 5:
        source = tc.build_elevation_map(points, resolution, drop_non_finite=drop)
        target = tc.build_elevation_map(cloud(rng), resolution, drop_non_finite=drop)
        if rng.random() < 0.5:  # classified maps register; unclassified ones are refused
            tc.classify_terrain(source)
            tc.classify_terrain(target)
        _round_trip(tc.register_maps(source, target, initial=pose(rng)))
    elif which == 6:
        tc.fit_fuzzy_elevation_map(points)
    elif which == 7:
        tc.point_based_overhangs(points, edge, sigma)
    elif which == 8:
        tc.octomap_column_overhangs(points, edge, sigma)
    elif which == 9:
        tc.add_traversability_layers(tc.build_elevation_map(points, resolution, drop_non_finite=drop))
    elif which == 10:
        tc.run_mapper([points, cloud(rng)], [pose(rng), pose(rng)])
    else:
        origin = [None, (0.0, 0.0, 1.7), (math.nan, 0.0, 0.0)][int(rng.integers(0, 3))]
        layout = organised(rng, points)
        tc.no_return_directions(**layout, origin=origin)
        if "ring" in layout:  # what the CLI reads from a file's ring field
            from terracube.pipeline import empty_beams

            empty_beams(layout["organised"], layout["ring"], origin)


def _parameter_case(tc, rng: np.random.Generator, points: np.ndarray) -> None:
    """A stage with a parameter struct whose fields are partly extreme."""
    which = int(rng.integers(0, 9))
    if which == 0:
        method = str(rng.choice(["paper", "shadow_aware"]))
        tc.collapse_overhangs(points, params=perturb(tc.CollapseParams(method=method), rng))
    elif which == 1:
        elevation_map = tc.build_elevation_map(
            points, params=perturb(tc.ElevationParams(drop_non_finite=True), rng)
        )
        tc.classify_terrain(elevation_map, perturb(tc.TerrainParams(), rng))
    elif which == 2:
        local = tc.LocalMap(params=perturb(tc.LocalMapParams(length=float(rng.choice([2.0, 20.0]))), rng))
        for _ in range(3):
            local.update(points, pose(rng), stamp=float(rng.choice([math.nan, 0.0, 1e9, -5.0, 1e300])))
    elif which == 3:
        tc.register_points(points, cloud(rng), params=perturb(tc.RegistrationParams(), rng))
    elif which == 4:
        source = tc.build_elevation_map(points, 0.2, drop_non_finite=True)
        target = tc.build_elevation_map(cloud(rng), 0.2, drop_non_finite=True)
        tc.register_maps(source, target, params=perturb(tc.RegistrationParams(), rng))
    elif which == 5:
        tc.fit_fuzzy_elevation_map(points, perturb(tc.FuzzyParams(), rng))
    elif which == 6:
        params = perturb(tc.MapperParams(lidar_only=bool(rng.random() < 0.5)), rng)
        if rng.random() < 0.3:  # None by default, which perturb leaves alone
            params = dataclasses.replace(params, max_range=float(rng.choice(FLOATS)))
        mapper = tc.Mapper(params)
        for _ in range(3):
            report = mapper.add_scan(points if rng.random() < 0.7 else cloud(rng), pose(rng))
            if not np.isfinite(report.pose).all():
                raise AssertionError(f"a scan's pose is not finite: {report.pose}")
        mapper.global_map()
    elif which == 7:
        collapse, elevation = perturb(tc.CollapseParams(), rng), perturb(tc.ElevationParams(), rng)
        tc.dem_without_overhangs(points, collapse=collapse, elevation=elevation)
    else:
        elevation_map = tc.build_elevation_map(points, 0.2, drop_non_finite=True)
        tc.add_traversability_layers(elevation_map, perturb(tc.TraversabilityParams(), rng))


def _object_case(tc, rng: np.random.Generator, points: np.ndarray) -> None:
    """Maps, local maps, fuzzy maps and files used with hostile values."""
    import tempfile
    from pathlib import Path

    value = float(rng.choice(FLOATS))
    which = int(rng.integers(0, 6))
    if which == 0:
        size = [int(rng.choice([0, 1, 3, 2**31, -1])), int(rng.choice([0, 2, 5]))]
        empty = tc.ElevationMap.empty(float(rng.choice([0.1, value])), (value, 0.0), size)
        empty["mean"] = np.full(tuple(empty.geometry.size), value, dtype=rng.choice([np.float32, np.float64]))
        empty["other"] = rng.normal(0.0, 1.0, (int(rng.integers(0, 4)), 3))  # often the wrong shape
        tc.points_of_map(empty)
        tc.classify_terrain(empty)
    elif which == 1:
        local = tc.LocalMap(length=2.0)
        local.update(points, pose(rng))
        local.index_of((value, float(rng.choice(FLOATS))))
        local.position_of((int(rng.choice(INTEGERS)), int(rng.choice(INTEGERS))))
        local.move_to((value, 0.0))
        tc.classify_terrain(local.to_elevation_map(), reference="local_ground")
    elif which == 2:
        fem = tc.fit_fuzzy_elevation_map(points)
        fem.evaluate(cloud(rng)[:, :2] if rng.random() < 0.5 else np.full((3, 2), value))
    elif which == 3:
        elevation_map = tc.build_elevation_map(points, float(rng.choice([0.1, 1.0])), drop_non_finite=True)
        with tempfile.TemporaryDirectory() as folder:
            loaded = tc.ElevationMap.load(elevation_map.save(Path(folder) / "map.npz"))
            assert loaded.layers == elevation_map.layers
    elif which == 4:
        with tempfile.TemporaryDirectory() as folder:
            path = tc.io.write_pcd(
                Path(folder) / "cloud.pcd", {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}
            )
            back = tc.io.read_points(path)
            assert back.shape == (len(points), 3)
    else:
        with tempfile.TemporaryDirectory() as folder:
            path = tc.io.write_kitti_bin(Path(folder) / "scan.bin", points)
            assert tc.io.read_points(path).shape == (len(points), 3)


#: Options of the single-scan commands that take numbers (and a few words), and the values tried.
_OVERHANG_OPTIONS = ("--edge", "--sigma", "--robot-height", "--method", "--crop", "--num-threads")
_RANGE_OPTIONS = ("--min-range", "--max-range", "--roll", "--pitch")
_MAP_OPTIONS = ("--resolution", "--origin", "--size")
COMMAND_OPTIONS = {
    "collapse": [*_OVERHANG_OPTIONS, *_RANGE_OPTIONS],
    "dem": [*_MAP_OPTIONS, *_OVERHANG_OPTIONS, *_RANGE_OPTIONS],
    "classify": [
        *_MAP_OPTIONS,
        *_OVERHANG_OPTIONS,
        "--sensor-height",
        "--reference",
        "--ground-radius",
        "--ground-height",
        "--high-height",
        "--std-dev",
    ],
    "fem": [*_MAP_OPTIONS, "--edge", "--sigma", "--crop", "--rules", "--membership"],
    # Sequences without odometry (--lidar-only), over a folder holding the scan twice.
    "map": ["--min-range", "--max-range", "--keyframe-distance", "--resolution", "--limit"],
    "stream": ["--min-range", "--max-range", "--edge", "--sigma", "--length", "--resolution", "--every"],
}
COMMAND_VALUES = [
    "nan",
    "inf",
    "-inf",
    "0",
    "-1",
    "1e300",
    "1e-300",
    "2147483648",
    "-0",
    "0.5",
    "3",
    "abc",
    "",
]
_scan_file: list = []


class CommandFailed(Exception):
    """A command ended with neither success (0) nor a named refusal (2)."""


def _command_case(rng: np.random.Generator) -> None:
    """A command line (collapse, dem, classify, fem; map and stream without odometry) with one or two
    options set to hostile text: it must exit 0 or 2 (an ``error:`` line), never 1 with a traceback."""
    import tempfile
    from pathlib import Path

    from terracube.cli import app
    from terracube.io import write_kitti_bin
    from typer.testing import CliRunner

    if not _scan_file:  # a small flat scan, written once per process
        folder = Path(tempfile.mkdtemp(prefix="terracube-fuzz-cli-"))
        ground = np.random.default_rng(0)
        points = np.c_[ground.uniform(-20.0, 20.0, (3000, 2)), ground.normal(0.0, 0.2, 3000)]
        _scan_file.append(write_kitti_bin(folder / "scan.bin", points.astype(np.float32)))
        sequence = Path(tempfile.mkdtemp(prefix="terracube-fuzz-sequence-"))
        for k in range(2):
            write_kitti_bin(sequence / f"{k:06d}.bin", points.astype(np.float32))
        _scan_file.append(sequence)
    command = str(rng.choice(list(COMMAND_OPTIONS)))
    args = [command, str(_scan_file[0]), "-o", str(_scan_file[0].parent / "out"), "--no-png"]
    if command in ("map", "stream"):
        args = [
            command,
            str(_scan_file[1]),
            "--lidar-only",
            "-o",
            str(_scan_file[0].parent / "out"),
            "--no-png",
        ]
    args += ["--epochs", "1"] if command == "fem" else []
    numbers = COMMAND_VALUES[:11]
    for option in rng.choice(COMMAND_OPTIONS[command], int(rng.integers(1, 3)), replace=False):
        if option == "--size":
            args += [option, str(rng.choice(numbers)), str(rng.choice(numbers))]
        elif option in ("--origin", "--crop"):
            args += [
                option,
                ",".join(str(rng.choice(numbers)) for _ in range(2 if option == "--origin" else 6)),
            ]
        else:
            args += [option, str(rng.choice(COMMAND_VALUES))]
    result = CliRunner().invoke(app, args)
    if result.exit_code not in (0, 2) or not isinstance(result.exception, (SystemExit, type(None))):
        raise CommandFailed(f"{' '.join(args[:1] + args[4:])}: exit {result.exit_code}, {result.exception!r}")


def _hostile_cloud_message(types, rng: np.random.Generator, stamp_ns: int):
    """A PointCloud2 whose layout or values may be hostile: fields of any type at any offset (or
    missing), point and row steps that do not fit them, data shorter or longer than the points,
    either byte order, coordinates NaN, huge or at 0."""
    count = int(rng.choice([0, 1, 5, 200]))
    height = int(rng.choice([1, 1, 2, max(count, 1)]))
    width = count // height if rng.random() < 0.8 else int(rng.choice([0, 3, 2**31 - 1]))
    datatype = [int(rng.choice([7, 7, 8, 1, 2, 4, 5, 6, 0, 9])) for _ in range(3)]
    offsets = (
        [0, 4, 8] if rng.random() < 0.6 else [int(rng.choice([0, 2, 4, 8, 12, 40, 2**20])) for _ in range(3)]
    )
    names = ["x", "y", "z"] if rng.random() < 0.9 else list(rng.choice(["x", "y", "z", "w"], 3))
    point_step = int(rng.choice([12, 16, 32, 0, 1, 2**20])) if rng.random() < 0.5 else 16
    row_step = width * point_step if rng.random() < 0.8 else int(rng.choice([0, 1, 2**31]))
    row_step = min(row_step, 2**32 - 1)  # a uint32 in the message
    size = height * width * point_step if rng.random() < 0.7 else int(rng.choice([0, 7, 4096]))
    size = min(size, 1 << 16)
    values = rng.choice([0.0, math.nan, math.inf, 1e30, 1.5, -3.0], size // 4 + 1).astype("<f4")
    data = values.view(np.uint8)[:size] if rng.random() < 0.7 else rng.integers(0, 256, size, dtype=np.uint8)
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
        frame_id=str(rng.choice(["lidar", "", "/lidar", "imu"])),
    )
    fields = [
        types["sensor_msgs/msg/PointField"](
            name=n, offset=o, datatype=d, count=int(rng.choice([1, 1, 1, 0, 3]))
        )
        for n, o, d in zip(names, offsets, datatype, strict=True)
    ]
    return types["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=height,
        width=width,
        fields=fields,
        is_bigendian=bool(rng.random() < 0.2),
        point_step=point_step,
        row_step=row_step,
        data=np.ascontiguousarray(data, dtype=np.uint8),
        is_dense=False,
    )


def _hostile_imu_message(types, rng: np.random.Generator, stamp_ns: int):
    """A sensor_msgs/Imu with hostile orientation, accelerations and covariances, or a plain one."""
    pick = lambda: float(rng.choice([0.0, 9.81, -9.81, 0.3, math.nan, math.inf, 1e300]))  # noqa: E731
    vector = types["geometry_msgs/msg/Vector3"]
    covariance = np.zeros(9)
    covariance[0] = float(rng.choice([0.0, -1.0, math.nan]))
    return types["sensor_msgs/msg/Imu"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
            frame_id=str(rng.choice(["imu", "lidar", "", "nowhere"])),
        ),
        orientation=types["geometry_msgs/msg/Quaternion"](x=pick(), y=pick(), z=pick(), w=pick()),
        orientation_covariance=covariance,
        angular_velocity=vector(x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=covariance,
        linear_acceleration=vector(x=pick(), y=pick(), z=pick()),
        linear_acceleration_covariance=covariance,
    )


def _bag_case(rng: np.random.Generator) -> None:
    """A small ROS 2 bag of hostile clouds, IMU messages, odometry and mounts: read_bag (with the
    IMU, the odometry) gives clouds or a refusal, and dem, map or stream on it exits 0 or 2."""
    import shutil
    import tempfile
    from pathlib import Path

    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in store.types:
        store.register(
            get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
        )
    types = store.types
    t0 = int(rng.choice([1_600_000_000 * 10**9, 0, 5 * 10**9]))
    folder = Path(tempfile.mkdtemp(prefix="terracube-fuzz-bag-"))
    try:
        path = folder / "bag"
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            clouds = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=store)
            imu = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
            odom = writer.add_connection("/odom", "geometry_msgs/msg/PoseStamped", typestore=store)
            static = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=store)
            mount = (
                rng.choice([0.0, 1.0, math.nan], 4) if rng.random() < 0.3 else np.array([0.0, 0.0, 0.0, 1.0])
            )
            transform = types["geometry_msgs/msg/TransformStamped"](
                header=types["std_msgs/msg/Header"](
                    stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="lidar"
                ),
                child_frame_id=str(rng.choice(["imu", "lidar", "base"])),
                transform=types["geometry_msgs/msg/Transform"](
                    translation=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.1),
                    rotation=types["geometry_msgs/msg/Quaternion"](*map(float, mount)),
                ),
            )
            message = types["tf2_msgs/msg/TFMessage"](transforms=[transform])
            writer.write(static, max(t0 - 1, 0), store.serialize_cdr(message, "tf2_msgs/msg/TFMessage"))
            for k in range(int(rng.integers(0, 12))):
                stamp = t0 + int(rng.choice([k * 50_000_000, 0, 10**15]))
                msg = _hostile_imu_message(types, rng, stamp)
                writer.write(imu, stamp, store.serialize_cdr(msg, "sensor_msgs/msg/Imu"))
            for k in range(int(rng.integers(0, 4))):
                stamp = t0 + k * 100_000_000
                q = (
                    rng.choice([0.0, 1.0, math.nan], 4)
                    if rng.random() < 0.3
                    else np.array([0.0, 0.0, 0.0, 1.0])
                )
                msg = types["geometry_msgs/msg/PoseStamped"](
                    header=types["std_msgs/msg/Header"](
                        stamp=types["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9),
                        frame_id="world",
                    ),
                    pose=types["geometry_msgs/msg/Pose"](
                        position=types["geometry_msgs/msg/Point"](
                            x=float(k), y=float(rng.choice([0.0, math.nan])), z=0.0
                        ),
                        orientation=types["geometry_msgs/msg/Quaternion"](*map(float, q)),
                    ),
                )
                writer.write(odom, stamp, store.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))
            for k in range(int(rng.integers(1, 4))):
                stamp = t0 + k * 100_000_000
                msg = _hostile_cloud_message(types, rng, stamp)
                writer.write(clouds, stamp, store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
        if rng.random() < 0.5:
            from terracube.bag import read_bag

            poses = str(rng.choice(["/odom", "none"]))
            read = read_bag(
                path,
                "/points",
                None if poses == "none" else poses,
                imu=None if rng.random() < 0.3 else "/imu",
                imu_window=float(rng.choice([0.1, 1e-9, 1e9])),
                keep_invalid=bool(rng.random() < 0.5),
            )
            for cloud in read.clouds():
                assert cloud.points.ndim == 2 and cloud.points.shape[1] == 3
                assert cloud.attitude is None or all(math.isfinite(a) for a in cloud.attitude)
            return
        from terracube.cli import app
        from typer.testing import CliRunner

        command = str(rng.choice(["dem", "map", "stream", "collapse"]))
        args = [command, str(path), "--points", "/points", "-o", str(folder / "out"), "--no-png"]
        if rng.random() < 0.7:
            args += ["--imu", "/imu"]
        if command in ("map", "stream"):
            args += ["--odom", "/odom"] if rng.random() < 0.4 else ["--lidar-only"]
        result = CliRunner().invoke(app, args)
        if result.exit_code not in (0, 2) or not isinstance(result.exception, (SystemExit, type(None))):
            raise CommandFailed(
                f"{' '.join(args[:1] + args[3:])}: exit {result.exit_code}, {result.exception!r}"
            )
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def run_case(seed: int) -> None:
    """The case of `seed`: raises whatever terracube raises."""
    import terracube as tc

    rng = np.random.default_rng(seed)
    points = cloud(rng)
    family = rng.random()
    if family < 0.35:
        _function_case(tc, rng, points)
    elif family < 0.7:
        _parameter_case(tc, rng, points)
    elif family < 0.82:
        _object_case(tc, rng, points)
    elif family < 0.92:
        _command_case(rng)
    else:
        _bag_case(rng)


REFUSALS = (ValueError, TypeError, KeyError, IndexError)  # what a call may answer bad arguments with


def answer_case(line: str) -> None:
    """The worker's answer to one line (a case seed); numpy's own overflow warnings on extreme
    clouds are not findings."""
    with np.errstate(all="ignore"):
        run_case(int(line))


def fuzz(work, *, seed: int, cases: int | None, seconds: float | None) -> tuple[int, list[tuple[int, str]]]:
    """Runs cases seed, seed + 1, ... until ``cases`` are done or ``seconds`` have passed.
    Returns (cases run, [(case seed, error)])."""
    from pathlib import Path

    import fuzz_readers

    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)

    def worker():
        return fuzz_readers.Worker(
            work / "api-worker-stderr.txt", "fuzz_api", MEMORY_LIMIT_BYTES, CASE_SECONDS
        )

    current = worker()
    findings: list[tuple[int, str]] = []
    start, done = time.monotonic(), 0
    try:
        while (cases is None or done < cases) and (seconds is None or time.monotonic() - start < seconds):
            answer = current.run(str(seed + done))
            if answer["outcome"] == "failure":
                findings.append((seed + done, answer["error"]))
                if answer.get("worker_lost"):
                    current = worker()
            done += 1
    finally:
        current.close()
    return done, findings
