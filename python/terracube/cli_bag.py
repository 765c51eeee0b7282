"""ROS bags on the command line: ``terracube bag-info BAG``, and a bag as the input of ``map``,
``stream``, ``collapse``, ``dem``, ``classify`` and ``fem``.

:func:`register` adds the ``bag-info`` command and gives each of those six commands the options
``--points TOPIC`` (the PointCloud2 topic; optional when the bag has one), ``--imu TOPIC`` (each
cloud leveled by the IMU's roll and pitch, [CBC] section IV-B), ``--out DIR`` (write the usual files
there, and the results as a bag beside them), ``--bag-storage`` and, for ``map`` and ``stream``,
``--odom TOPIC`` or ``--tf BASE_FRAME`` (where the poses come from). The commands' own
code is left as it is: a wrapper takes the bag options off each callback. Given a bag, ``map``
runs :func:`map_bag` and ``stream`` :func:`stream_bag`; a per-scan stage runs
:func:`terracube.pipeline.run_stage` with the command's options once per cloud, named
``BAGNAME_0000``, ... (so outputs are named as for loose files), in the cloud's own frame (the
per-scan stages use no pose).
"""

from __future__ import annotations

import functools
import inspect
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import typer

__all__ = ["BagOptions", "is_bag", "map_bag", "register", "run_stage_on_bag", "stream_bag"]

BAG_STORAGES = ("mcap", "sqlite3", "ros1")


@dataclass(frozen=True)
class BagOptions:
    """The bag options of one command call."""

    points: str | None = None
    odom: str | None = None
    tf: str | None = None
    out: Path | None = None
    storage: str = "mcap"
    imu: str | None = None


def is_bag(path: Path) -> bool:
    """A ROS 1 ``.bag``, an ``.mcap`` file or a ROS 2 bag folder (one holding metadata.yaml)."""
    path = Path(path)
    return path.suffix.lower() in (".bag", ".mcap") or (path.is_dir() and (path / "metadata.yaml").is_file())


def _points_topic(bag: Path, topic: str | None) -> str:
    """``topic``, or the bag's only PointCloud2 topic."""
    from .bag import cloud_topic

    return cloud_topic(bag, topic, hint="pass --points TOPIC")


def _output_bag(directory: Path, stem: str, storage: str):
    from .bag import MapBagWriter

    name = f"{stem}.bag" if storage == "ros1" else stem
    return MapBagWriter(Path(directory) / name, storage, overwrite=True)


def _bag_size(path: Path) -> str:
    """A written bag's size on disk (a ROS 1 file, or a ROS 2 folder's files together)."""
    size = (
        path.stat().st_size
        if path.is_file()
        else sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    )
    return f"{size / 2**20:.1f} MiB" if size >= 2**20 else f"{size / 2**10:.1f} KiB"


def _closed_bag_line(writer) -> str:
    """Close the output bag and say what it holds and how big it is."""
    path = writer.close()
    counts = ", ".join(f"{topic} x{count}" for topic, count in writer.counts.items())
    return f"bag: {path} ({counts}; {_bag_size(path)})"


def _imu_line(clouds) -> str | None:
    """What leveled the clouds of a bag read with an IMU topic, once they were read."""
    if clouds.imu is None or clouds.imu_clock is None:
        return None
    clock = (
        "by header stamps"
        if clouds.imu_clock == "header"
        else "by the bag's record times (its header stamps are on another clock)"
    )
    source = "orientations" if clouds.imu_source == "orientation" else "accelerations (gravity)"
    return (
        f"IMU {clouds.imu}: each cloud leveled by the roll and pitch from its {source} "
        f"within {clouds.imu_window:g} s, matched {clock}"
    )


def _leveled_pose(cloud) -> np.ndarray | None:
    """A cloud's pose with the IMU's roll and pitch (its heading and position kept), or without a
    pose the IMU's leveling alone; the pose as read without an IMU."""
    if cloud.attitude is None:
        return cloud.pose
    from .bag import with_attitude
    from .collapse import leveling_transform

    return (
        leveling_transform(*cloud.attitude)
        if cloud.pose is None
        else with_attitude(cloud.pose, *cloud.attitude)
    )


def _progress(iterable, total: int, what: str):
    from .cli import progress_bar

    return progress_bar(iterable, what, unit="cloud", total=total, disable=total < 2)


# ------------------------------------------------------------------------------------------ stages


def _write_stage_results(writer, outputs: list[Path], cloud) -> None:
    """Every map (.npz) a stage wrote as a GridMap (and an OccupancyGrid of its classes), every
    labelled cloud as a PointCloud2 with a label field, stamped and framed like the input cloud."""
    from .bag import occupancy_from_classes
    from .elevation import ElevationMap
    from .io import read_cloud

    for path in outputs:
        if path.suffix in (".png", ".tif"):
            continue
        try:
            elevation_map = ElevationMap.load(path) if path.suffix == ".npz" else None
        except ValueError:  # an .npz cloud, not a map
            elevation_map = None
        if elevation_map is not None:
            writer.write_grid_map(elevation_map, stamp=cloud.stamp, frame_id=cloud.frame_id)
            if "class" in elevation_map:
                occupancy = occupancy_from_classes(elevation_map["class"])
                writer.write_occupancy_grid(
                    elevation_map, occupancy, stamp=cloud.stamp, frame_id=cloud.frame_id
                )
        else:
            fields = read_cloud(path)
            writer.write_cloud(fields["xyz"], fields.get("label"), stamp=cloud.stamp, frame_id=cloud.frame_id)


def run_stage_on_bag(stage: str, values: dict, bag: Path, bag_options: BagOptions) -> None:
    """Run a per-scan stage (with the command's option ``values``) on every cloud of the bag's point
    topic as ``NAME_0000``, ``NAME_0001``, ..., in the cloud's own frame (the per-scan stages use no
    pose), and, with ``--out``, write what each run wrote (maps as GridMap + OccupancyGrid, labelled
    clouds as PointCloud2) into a bag ``NAME_STAGE``. With ``--method shadow_aware`` the empty pixels
    of clouds whose ``ring`` field lays them out are its beams without a return."""
    from .bag import read_bag
    from .cli import (
        STAGE_OPTIONS,
        _echo_report,
        _exit_on_bad_input,
        _fail,
        _writable_folder,
        command_config,
        stage_output_options,
    )
    from .pipeline import run_stage

    options = {name: values.get(name) for name in STAGE_OPTIONS[stage]}
    config = command_config(stage, options)
    outputs = stage_output_options(stage, options)
    output_dir = _writable_folder(Path(bag_options.out or values.get("output_dir") or "."))
    beams = config.collapse.method == "shadow_aware"
    if bag_options.imu is not None and (values.get("roll") is not None or values.get("pitch") is not None):
        raise _fail("give the attitude once: --imu TOPIC or --roll/--pitch, not both")
    if bag_options.imu is not None and (config.frame.roll_deg != 0.0 or config.frame.pitch_deg != 0.0):
        raise _fail(
            f"the configuration levels by roll_deg {config.frame.roll_deg:g}, pitch_deg "
            f"{config.frame.pitch_deg:g} ('frame' section) and --imu levels each cloud by its IMU: "
            "give the attitude once"
        )
    with _exit_on_bad_input():  # the bag's errors name it
        topic = _points_topic(bag, bag_options.points)
        clouds = read_bag(bag, topic, keep_invalid=beams, imu=bag_options.imu)
    writer = _output_bag(output_dir, f"{bag.stem}_{stage}", bag_options.storage) if bag_options.out else None
    try:
        with _exit_on_bad_input():  # the bag's errors name it
            for index, cloud in enumerate(_progress(clouds.clouds(), len(clouds), stage)):
                name = f"{bag.stem}_{index:04d}"
                points, no_returns = returns_and_empty_beams(cloud) if beams else (cloud.points, None)
                with _exit_on_bad_input(name):
                    report = run_stage(
                        stage,
                        points,
                        name,
                        output_dir,
                        _leveled_config(config, cloud),
                        no_returns=no_returns,
                        **outputs,
                    )
                _echo_report(report)
                dropped = cloud.no_returns + len(cloud.points) - len(points)
                if dropped and no_returns is None:
                    typer.echo(f"  {dropped:,} no-returns dropped")
                if writer is not None:
                    _write_stage_results(writer, report.outputs, cloud)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    if _imu_line(clouds):
        typer.echo(_imu_line(clouds))
    if writer is not None:
        typer.echo(_closed_bag_line(writer))


def _leveled_config(config, cloud):
    """``config`` with the frame's roll and pitch of the cloud's IMU attitude, if it has one."""
    if cloud.attitude is None:
        return config
    roll, pitch = (float(np.degrees(angle)) for angle in cloud.attitude)
    return config.replace("frame", roll_deg=roll, pitch_deg=pitch)


# ------------------------------------------------------------------------------------------ map


def _check_pose_source(bag_options: BagOptions, lidar_only: bool) -> None:
    """Exit 2 unless the bag options name one pose source (or, LiDAR-only, at most one)."""
    from .cli import _fail

    if bag_options.odom is not None and bag_options.tf is not None:
        raise _fail("give one pose source: --odom TOPIC or --tf BASE_FRAME, not both")
    if bag_options.odom is None and bag_options.tf is None and not lidar_only:
        raise _fail(
            "a bag needs one pose source: --odom TOPIC (Odometry or PoseStamped) or --tf BASE_FRAME, "
            "or none with --lidar-only"
        )


def _pose_topic(bag_options: BagOptions) -> str | None:
    """read_bag's pose source: the --odom topic, /tf for --tf, or none (LiDAR-only)."""
    if bag_options.odom is not None:
        return bag_options.odom
    return "/tf" if bag_options.tf is not None else None


def map_bag(bag: Path, values: dict, bag_options: BagOptions) -> None:
    """``terracube map BAG``: the mapper over every cloud of the topic, posed by --odom or --tf, or
    with --lidar-only by its own registrations."""
    from .bag import occupancy_from_classes, read_bag
    from .cli import _echo_report, _exit_on_bad_input, _fail
    from .config import ConfigError, load_config
    from .pipeline import map_scans, write_global_map

    for option, flag in (
        ("poses", "--poses"),
        ("calib", "--calib"),
        ("ground_truth", "--ground-truth"),
        ("times", "--times"),
    ):
        if values.get(option) is not None:
            raise _fail(f"{flag} is for a folder of scans; a bag takes its poses from --odom or --tf")
    try:
        cfg = load_config(values.get("config"), preset=values.get("preset"))
    except ConfigError as error:
        raise _fail(str(error)) from error
    with _exit_on_bad_input("command line"):
        cfg = cfg.replace("frame", min_range=values.get("min_range"), max_range=values.get("max_range"))
        cfg = cfg.replace(
            "mapper",
            keyframe_distance=values.get("keyframe_distance"),
            resolution=values.get("resolution"),
            loop_closing=values.get("loop_closing"),
            use_registration=values.get("registration"),
            lidar_only=values.get("lidar_only"),
        )
    _check_pose_source(bag_options, cfg.mapper.lidar_only)
    output_dir = bag_options.out or values["output_dir"]
    with _exit_on_bad_input():  # the bag's errors name it
        topic = _points_topic(bag, bag_options.points)
        clouds = read_bag(
            bag, topic, _pose_topic(bag_options), base_frame=bag_options.tf, imu=bag_options.imu
        )
    limit = values.get("limit")
    total = len(clouds) if limit is None else min(len(clouds), max(limit, 0))

    def posed_clouds():
        """Each cloud's name, points, pose (LiDAR-only: the identity, or its IMU's leveling), stamp."""
        for index, cloud in enumerate(_progress(clouds.clouds(), total, "mapping")):
            if index >= total:
                break
            pose = _leveled_pose(cloud)
            yield f"{bag.stem} cloud {index}", cloud.points, np.eye(4) if pose is None else pose, cloud.stamp

    with _exit_on_bad_input():  # the bag's errors name it
        if total == 0:
            raise ValueError(f"no cloud on {topic}")
        run = map_scans(posed_clouds(), cfg)
        report = write_global_map(
            run, output_dir, cfg, png=values.get("png", True), what=f"clouds of {topic}"
        )
    if bag_options.out is not None:
        dem, stamp, frame = run.global_map, float(run.stamps[-1]), clouds.pose_frame or "map"
        with _output_bag(Path(output_dir), "global_map", bag_options.storage) as writer:
            writer.write_grid_map(dem, stamp=stamp, frame_id=frame)
            writer.write_occupancy_grid(
                dem, occupancy_from_classes(dem["class"]), stamp=stamp, frame_id=frame
            )
        report.outputs.append(writer.path)
    report.lines += [_imu_line(clouds)] if _imu_line(clouds) else []
    dropped = sum(clouds.no_returns)
    report.lines += [f"{dropped:,} no-returns dropped"] if dropped else []
    report.lines += [
        f"written: {path}"
        + (f" ({_bag_size(path)})" if bag_options.out is not None and path == writer.path else "")
        for path in report.outputs
    ]
    _echo_report(report)


def stream_bag(bag: Path, values: dict, bag_options: BagOptions) -> None:
    """``terracube stream BAG``: the local map over every cloud of the topic, posed by --odom or
    --tf (or with --lidar-only by a LiDAR-only mapper); with --out, the local map as a GridMap and
    its traversability as an OccupancyGrid every --every clouds (every cloud when 0) and after the
    last cloud (the map of local_map.npz), in the poses' frame, stamped like the cloud."""
    from .bag import occupancy_from_traversability, read_bag
    from .cli import (
        _echo_report,
        _exit_on_bad_input,
        _fail,
        _writable_folder,
        stream_lidar_only_poses,
        stream_params,
    )
    from .stream import check_animation_target, run_stream

    for option, flag in (("poses", "--poses"), ("calib", "--calib"), ("times", "--times")):
        if values.get(option) is not None:
            raise _fail(f"{flag} is for a folder of scans; a bag takes its poses from --odom or --tf")
    _check_pose_source(bag_options, values.get("lidar_only", False))
    if values.get("animation") is not None:  # before the output folder is made
        with _exit_on_bad_input("stream"):
            check_animation_target(values["animation"])
    output_dir = _writable_folder(bag_options.out or values["output_dir"])
    params = stream_params(values)
    beams = params.collapse.method == "shadow_aware"  # the empty pixels of organised clouds help it
    with _exit_on_bad_input():  # the bag's errors name it
        topic = _points_topic(bag, bag_options.points)
        clouds = read_bag(
            bag,
            topic,
            _pose_topic(bag_options),
            base_frame=bag_options.tf,
            keep_invalid=beams,
            imu=bag_options.imu,
        )
    limit = values.get("limit")
    total = len(clouds) if limit is None else min(len(clouds), max(limit, 0))
    writer = _output_bag(output_dir, f"{bag.stem}_stream", bag_options.storage) if bag_options.out else None

    def publish(local_map, name: str, stamp: float) -> None:
        frame = clouds.pose_frame or "odom"  # known once the first cloud is read
        ordered = local_map.to_elevation_map()
        writer.write_grid_map(ordered, stamp=stamp, frame_id=frame)
        occupancy = occupancy_from_traversability(ordered["traversability"])
        writer.write_occupancy_grid(ordered, occupancy, stamp=stamp, frame_id=frame)

    used_beams = []

    def scans():
        for index, cloud in enumerate(clouds.clouds()):
            if index >= total:
                return
            points, no_returns = returns_and_empty_beams(cloud) if beams else (cloud.points, None)
            used_beams.append(0 if no_returns is None else len(no_returns))
            yield f"{bag.stem}_{index:04d}", points, _leveled_pose(cloud), cloud.stamp, no_returns

    lidar_only = values.get("lidar_only", False)
    posed = stream_lidar_only_poses(scans(), values) if lidar_only else scans()
    try:
        with _exit_on_bad_input("stream"):
            report = run_stream(
                _progress(posed, total, "streaming"),
                output_dir,
                params,
                every=values.get("every", 0),
                animation=values.get("animation"),
                png=values.get("png", True),
                on_update=publish if writer is not None else None,
            )
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    _echo_report(report)
    if lidar_only:
        typer.echo(posed.summary())
    if _imu_line(clouds):
        typer.echo(_imu_line(clouds))
    dropped = sum(clouds.no_returns)
    if sum(used_beams):
        typer.echo(f"{sum(used_beams):,} beams without a return (from the ring field) showed free space")
    elif dropped:
        typer.echo(f"{dropped:,} no-returns dropped")
    if writer is not None:
        typer.echo(_closed_bag_line(writer))


def returns_and_empty_beams(cloud) -> tuple[np.ndarray, np.ndarray | None]:
    """The returns of a cloud read with ``keep_invalid`` and the directions of its empty pixels
    (:func:`terracube.pipeline.returns_and_beams` of its points and ``ring`` field)."""
    from .pipeline import returns_and_beams

    return returns_and_beams(cloud.points, cloud.fields.get("ring"))


# ------------------------------------------------------------------------------------------ bag-info


def bag_info_command(
    bag: Path = typer.Argument(..., help="ROS 1 .bag, ROS 2 bag folder or .mcap file.", show_default=False),
) -> None:
    """List the topics of a ROS bag with their message types and counts."""
    from .bag import bag_info
    from .cli import _fail

    try:
        topics = bag_info(bag)
    except (ValueError, FileNotFoundError, ImportError) as error:
        raise _fail(str(error)) from error
    width = max((len(t.name) for t in topics), default=5)
    typer.echo(f"{'topic':<{width}}  {'count':>7}  type")
    for topic in topics:
        typer.echo(f"{topic.name:<{width}}  {topic.count:>7}  {topic.msgtype}")


# ------------------------------------------------------------------------------------------ register

_POINTS = typer.Option(
    None,
    "--points",
    help="Bag input: the PointCloud2 topic (default: the bag's only one).",
    show_default=False,
)
_ODOM = typer.Option(
    None,
    "--odom",
    help="Bag input (map, stream): poses from this Odometry/PoseStamped topic, the cloud's mount "
    "from /tf_static.",
    show_default=False,
)
_TF = typer.Option(
    None,
    "--tf",
    help="Bag input (map, stream): poses of BASE_FRAME from /tf (in the tree's root), the mount "
    "from /tf_static.",
    metavar="BASE_FRAME",
    show_default=False,
)
_IMU = typer.Option(
    None,
    "--imu",
    help="Bag input: level each cloud by the roll and pitch of this sensor_msgs/Imu topic (its "
    "orientation, or else its gravity, within 0.1 s; the mount from /tf_static). With --odom or "
    "--tf it replaces their roll and pitch; without, it levels the LiDAR-only mapper's scans.",
    show_default=False,
)
_OUT = typer.Option(
    None,
    "--out",
    help="Bag input: write the usual files to DIR and the results as a bag there too (GridMap, "
    "OccupancyGrid of classes or, for stream, of traversability, labelled PointCloud2).",
    show_default=False,
)
_STORAGE = typer.Option("mcap", "--bag-storage", help="Bag written by --out: mcap, sqlite3 (ROS 2) or ros1.")

_BAG_PARAMETERS = {
    "points": (_POINTS, str | None),
    "odom": (_ODOM, str | None),
    "tf": (_TF, str | None),
    "imu": (_IMU, str | None),
    "out": (_OUT, Path | None),
    "bag_storage": (_STORAGE, str),
}


def _with_bag_input(callback, posed=None):
    """``callback`` with the bag options added to its signature (typer reads ``__signature__``).
    ``posed`` (map_bag, stream_bag) runs a command whose scans need poses; without it every cloud
    runs the command on its own (run_stage_on_bag)."""
    from .cli import _fail

    needs_poses = posed is not None

    signature = inspect.signature(callback)
    names = list(signature.parameters)
    input_name = names[0]  # every wrapped command takes its scan(s) as the first argument
    parameters = list(signature.parameters.values())
    taken = {"odom", "tf"} if needs_poses else set()
    for name, (option, annotation) in _BAG_PARAMETERS.items():
        if name in ("odom", "tf") and not needs_poses:
            continue
        parameters.append(
            inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=option, annotation=annotation)
        )
        taken.add(name)

    @functools.wraps(callback)
    def command(**values):
        bag_values = {name: values.pop(name, None) for name in _BAG_PARAMETERS}
        storage = bag_values["bag_storage"] or "mcap"
        if storage not in BAG_STORAGES:
            raise _fail(f"--bag-storage must be one of {', '.join(BAG_STORAGES)}, got {storage!r}")
        bag_options = BagOptions(
            bag_values["points"],
            bag_values["odom"],
            bag_values["tf"],
            bag_values["out"],
            storage,
            bag_values["imu"],
        )
        source = Path(values[input_name])
        if not is_bag(source):
            given = [
                f"--{n.replace('_', '-')}"
                for n in ("points", "odom", "tf", "imu", "out")
                if bag_values[n] is not None
            ]
            if given:
                raise _fail(f"{' '.join(given)}: only for a bag input (.bag, .mcap or a ROS 2 bag folder)")
            return callback(**values)
        if needs_poses:
            return posed(source, values, bag_options)
        return run_stage_on_bag(callback.__name__, values, source, bag_options)

    input_help = (
        "\n\nA ROS bag (.bag, .mcap or a ROS 2 bag folder) as input: --points TOPIC picks the "
        "PointCloud2 topic, --imu TOPIC levels each cloud"
        + (
            ", --odom TOPIC or --tf BASE_FRAME the poses (neither with --lidar-only)"
            if needs_poses
            else ", every cloud is processed"
        )
        + "; --out DIR writes the files and the results as a bag there."
    )
    command.__doc__ = inspect.cleandoc(callback.__doc__ or "") + input_help
    annotations = dict(getattr(callback, "__annotations__", {}))
    annotations.update({name: _BAG_PARAMETERS[name][1] for name in taken})
    command.__annotations__ = annotations
    command.__signature__ = signature.replace(parameters=parameters)
    return command


def register(app: typer.Typer) -> None:
    """Add ``bag-info`` and the bag input of map, stream, collapse, dem, classify and fem to ``app``
    (once)."""
    if any(info.name == "bag-info" for info in app.registered_commands):
        return
    for info in app.registered_commands:
        name = info.name or (info.callback.__name__ if info.callback else None)
        if name in ("map", "stream", "collapse", "dem", "classify", "fem"):
            info.callback = _with_bag_input(info.callback, {"map": map_bag, "stream": stream_bag}.get(name))
    app.command("bag-info")(bag_info_command)
