"""ROS bags in and out (terracube.bag): real recordings, bags written here with rosbags from KITTI
frames and ground-truth poses, and the bags terracube writes read back by independent readers
(rosbags for ROS 2, Debian's python3-rosbag, ROS 1's reference implementation, for ROS 1)."""

from __future__ import annotations

import json
import math
import re
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("mcap")

import terracube as tc  # noqa: E402
from terracube.bag import (  # noqa: E402
    MapBagWriter,
    bag_info,
    decode_pointcloud2,
    grid_map_layer_data,
    layer_from_grid_map_data,
    occupancy_from_classes,
    occupancy_from_traversability,
    read_bag,
)

LUMINAR_COUNTS = [35707, 36055, 36267, 36457, 36336]
LUMINAR_TOPIC = "/luminar_pointcloud"
OUSTER_TOPIC = "/os1_cloud_node/points"
SYSTEM_PYTHON = Path("/usr/bin/python3")


@pytest.fixture(scope="module")
def bags(shared_data) -> Path:
    folder = shared_data.root / "rosbags"
    if not (folder / "luminar_embag.bag").is_file():
        pytest.skip(f"real bags not found under {folder}")
    return folder


def typestore(ros1: bool = False):
    """rosbags' ROS 1 or ROS 2 types plus tf2_msgs/msg/TFMessage, which its stores lack."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in store.types:
        store.register(
            get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
        )
    return store


def header(store, stamp_ns: int, frame: str, ros1: bool = False):
    types = store.types
    time = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    extra = {"seq": 0} if ros1 else {}
    return types["std_msgs/msg/Header"](stamp=time, frame_id=frame, **extra)


def cloud_message(
    store,
    records: np.ndarray,
    fields,
    *,
    height=1,
    row_step=None,
    bigendian=False,
    stamp_ns=0,
    frame="lidar",
    ros1=False,
):
    """A PointCloud2 of a structured array; ``fields`` lists (name, offset, datatype)."""
    types = store.types
    width = records.size // height
    point_step = records.dtype.itemsize
    data = records.view(np.uint8).reshape(height, width * point_step)
    if row_step is not None and row_step > width * point_step:  # pad every row
        padded = np.full((height, row_step), 0xAB, dtype=np.uint8)
        padded[:, : width * point_step] = data
        data = padded
    row_step = data.shape[1]
    return types["sensor_msgs/msg/PointCloud2"](
        header=header(store, stamp_ns, frame, ros1),
        height=height,
        width=width,
        fields=[
            types["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1) for n, o, d in fields
        ],
        is_bigendian=bigendian,
        point_step=point_step,
        row_step=row_step,
        data=data.reshape(-1).copy(),
        is_dense=False,
    )


# ------------------------------------------------------------------------------ the real recordings


def test_bag_info_lists_topics_types_and_counts_of_every_storage(bags):
    expected = [
        ("/base_pose_ground_truth", "nav_msgs/msg/Odometry", 5),
        ("/base_scan", "sensor_msgs/msg/LaserScan", 5),
        (LUMINAR_TOPIC, "sensor_msgs/msg/PointCloud2", 5),
    ]
    for name in ("luminar_embag.bag", "luminar_embag_ros2_db3", "luminar_embag_ros2_mcap"):
        assert [(t.name, t.msgtype, t.count) for t in bag_info(bags / name)] == expected, name
    ouster = {t.name: (t.msgtype, t.count) for t in bag_info(bags / "ouster_os1_pointcloudset_ros1.mcap")}
    assert ouster[OUSTER_TOPIC] == ("sensor_msgs/msg/PointCloud2", 2)
    assert ouster["/tf_static"] == ("tf2_msgs/msg/TFMessage", 1)
    assert len(ouster) == 10


def test_read_bag_takes_the_only_cloud_topic_by_default_and_lists_them_otherwise(bags, tmp_path):
    default = list(read_bag(bags / "luminar_embag.bag").clouds())
    named = list(read_bag(bags / "luminar_embag.bag", LUMINAR_TOPIC).clouds())
    assert [c.stamp for c in default] == [c.stamp for c in named] and len(default) == 5
    for got, want in zip(default, named, strict=True):
        np.testing.assert_array_equal(got.points, want.points)
    path = tmp_path / "two_clouds.mcap"  # a bag of two PointCloud2 topics: the choice is the user's
    points = np.random.default_rng(0).uniform(-5, 5, (50, 3)).astype(np.float32)
    with MapBagWriter(path, "mcap") as writer:
        for topic in ("/a/points", "/b/points"):
            writer.write_cloud(points, stamp=1.0, frame_id="lidar", topic=topic)
    with pytest.raises(
        ValueError, match=r"pass points=TOPIC; the bag's PointCloud2 topics: /a/points, /b/points"
    ):
        read_bag(path)


def test_luminar_clouds_are_identical_in_ros1_sqlite3_and_mcap_bags(bags):
    runs = {}
    for name in ("luminar_embag.bag", "luminar_embag_ros2_db3", "luminar_embag_ros2_mcap"):
        clouds = read_bag(bags / name, LUMINAR_TOPIC)
        assert len(clouds) == 5
        runs[name] = list(clouds.clouds())
        assert clouds.no_returns == [0] * 5
    reference = runs["luminar_embag.bag"]
    assert [len(c.points) for c in reference] == LUMINAR_COUNTS
    assert reference[0].stamp == pytest.approx(1583971570.015299642, abs=1e-6)
    assert {c.frame_id for c in reference} == {"luminar_lidar"}
    for name, clouds in runs.items():
        for cloud, expected in zip(clouds, reference, strict=True):
            assert cloud.stamp == expected.stamp and cloud.pose is None
            assert cloud.points.dtype == np.float32 and cloud.points.shape[1] == 3
            np.testing.assert_array_equal(cloud.points, expected.points, err_msg=name)
            assert sorted(cloud.fields) == ["intensity", "laser_id", "time_nsec", "time_sec"]
            for field, values in cloud.fields.items():
                np.testing.assert_array_equal(values, expected.fields[field], err_msg=f"{name} {field}")


def test_luminar_fields_match_struct_unpacking_of_the_raw_bytes(bags):
    """The structured-dtype decoding against struct.unpack at the README's offsets (32-byte points)."""
    from rosbags.highlevel import AnyReader

    with AnyReader([bags / "luminar_embag_ros2_mcap"]) as reader:
        connection = next(c for c in reader.connections if c.topic == LUMINAR_TOPIC)
        raw = next(reader.messages(connections=[connection]))[2]
        msg = reader.deserialize(raw, connection.msgtype)
    data = bytes(msg.data)
    xyz, fields, no_returns = decode_pointcloud2(msg)
    assert no_returns == 0 and len(xyz) == LUMINAR_COUNTS[0]
    assert fields["intensity"].dtype == np.float32 and fields["laser_id"].dtype == np.uint16
    assert fields["time_sec"].dtype == np.uint32
    for i in np.random.default_rng(7).integers(0, len(xyz), 50):
        x, y, z = struct.unpack_from("<fff", data, 32 * i)
        intensity, seconds, nanoseconds, laser = struct.unpack_from("<fIIH", data, 32 * i + 16)
        assert tuple(xyz[i]) == (np.float32(x), np.float32(y), np.float32(z))
        assert fields["intensity"][i] == np.float32(intensity) and fields["laser_id"][i] == laser
        assert fields["time_sec"][i] == seconds and fields["time_nsec"][i] == nanoseconds
    # The sensor looks along +y and sees up to ~252 m of road.
    assert 240 < np.linalg.norm(xyz, axis=1).max() < 260


def test_ouster_organised_cloud_drops_and_counts_no_returns(bags):
    path = bags / "ouster_os1_pointcloudset_ros1.mcap"
    clouds = read_bag(path, OUSTER_TOPIC)
    first = next(clouds.clouds())
    assert first.frame_id == "os1_lidar" and first.stamp_ns == 1588075038_629915872
    assert first.no_returns == 85356 and len(first.points) == 64 * 2048 - 85356
    assert not (first.points == 0).all(axis=1).any() and np.isfinite(first.points).all()
    # The range field (uint32 at offset 32, millimetres) is the norm of x, y, z at offsets 0, 4, 8.
    np.testing.assert_allclose(np.linalg.norm(first.points, axis=1) * 1000, first.fields["range"], atol=0.01)
    assert sorted(first.fields) == ["intensity", "noise", "range", "reflectivity", "ring", "t"]
    assert [len(points) for _, points, _ in clouds] == [45716, 64 * 2048 - 85263]
    assert clouds.no_returns == [85356, 85263]

    kept = next(read_bag(path, OUSTER_TOPIC, keep_invalid=True).clouds())
    assert kept.points.shape == (64 * 2048, 3) and kept.no_returns == 85356
    returns = (kept.points != 0).any(axis=1)
    np.testing.assert_array_equal(kept.points[returns], first.points)
    assert (kept.fields["range"][~returns] == 0).all()


def test_ouster_static_transform_to_the_sensor_frame_comes_from_tf_static(bags):
    path = bags / "ouster_os1_pointcloudset_ros1.mcap"
    poses = [pose for _, _, pose in read_bag(path, OUSTER_TOPIC, base_frame="os1_sensor")]
    # /tf_static: os1_sensor -> os1_lidar is a half turn about z (quaternion z = 1) and 36.18 mm up.
    expected = np.diag([-1.0, -1.0, 1.0, 1.0])
    expected[2, 3] = 0.03618
    for pose in poses:
        np.testing.assert_allclose(pose, expected, atol=1e-12)
    with pytest.raises(
        ValueError,
        match=r"frame 'base_link' is not in the TF tree; known frames: os1_imu, os1_lidar, os1_sensor",
    ):
        next(iter(read_bag(path, OUSTER_TOPIC, base_frame="base_link")))
    # Poses from /tf in a bag with only /tf_static: every cloud the same pose, which is said.
    with pytest.warns(UserWarning, match=r"no /tf topic \(only /tf_static\): every cloud gets the same"):
        tf_poses = [pose for _, _, pose in read_bag(path, OUSTER_TOPIC, "/tf", base_frame="os1_sensor")]
    for pose in tf_poses:
        np.testing.assert_allclose(pose, expected, atol=1e-12)


# ------------------------------------------------------------------------------ decoding layouts


def test_pointcloud2_layouts_decode_to_the_same_points():
    store = typestore()
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(12, 3)) * 10
    xyz[4] = 0.0  # a no-return stored as zeros
    xyz[7, 1] = np.nan  # and one as NaN
    valid = np.ones(12, bool)
    valid[[4, 7]] = False

    # float64 coordinates in z, x, y order behind an intensity, with padding, little-endian.
    wide = np.dtype(
        {
            "names": ["i", "z", "x", "y"],
            "formats": ["<f4", "<f8", "<f8", "<f8"],
            "offsets": [0, 8, 16, 24],
            "itemsize": 40,
        }
    )
    records = np.zeros(12, wide)
    records["x"], records["y"], records["z"], records["i"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], np.arange(12)
    msg = cloud_message(store, records, [("i", 0, 7), ("z", 8, 8), ("x", 16, 8), ("y", 24, 8)])
    points, fields, dropped = decode_pointcloud2(msg)
    assert points.dtype == np.float64 and dropped == 2
    np.testing.assert_array_equal(points, xyz[valid])
    np.testing.assert_array_equal(fields["i"], np.arange(12)[valid])

    # Big-endian float32, organised 3 x 4 with 7 bytes of padding after every row.
    big = np.dtype(
        {
            "names": ["x", "y", "z", "ring"],
            "formats": [">f4", ">f4", ">f4", ">u2"],
            "offsets": [0, 4, 8, 12],
            "itemsize": 16,
        }
    )
    records = np.zeros(12, big)
    records["x"], records["y"], records["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    records["ring"] = np.repeat(np.arange(3), 4)
    msg = cloud_message(
        store,
        records,
        [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("ring", 12, 4)],
        height=3,
        row_step=4 * 16 + 7,
        bigendian=True,
    )
    points, fields, dropped = decode_pointcloud2(msg, keep_invalid=True)
    assert points.dtype == np.float32 and dropped == 2 and points.shape == (12, 3)
    np.testing.assert_array_equal(points, xyz.astype(np.float32))
    np.testing.assert_array_equal(fields["ring"], np.repeat(np.arange(3), 4))
    assert fields["ring"].dtype == np.dtype("=u2")


def test_pointcloud2_empty_clouds_and_fields_of_several_values():
    store = typestore()
    layout = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("normal", "<f4", (3,))])
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
    empty = cloud_message(store, np.zeros(0, layout), fields)
    points, extra, dropped = decode_pointcloud2(empty)
    assert points.shape == (0, 3) and extra == {} and dropped == 0
    records = np.zeros(2, layout)
    records["x"], records["normal"] = [1.0, 2.0], [[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]]
    msg = cloud_message(store, records, fields)
    msg.fields.append(
        store.types["sensor_msgs/msg/PointField"](name="normal", offset=12, datatype=7, count=3)
    )
    points, extra, _ = decode_pointcloud2(msg)
    np.testing.assert_array_equal(points, [[1, 0, 0], [2, 0, 0]])
    np.testing.assert_array_equal(extra["normal"], np.float32([[0, 0, 1], [0.6, 0.8, 0]]))


def test_pointcloud2_without_xyz_or_short_data_is_refused():
    store = typestore()
    records = np.zeros(4, np.dtype([("a", "<f4"), ("b", "<f4")]))
    msg = cloud_message(store, records, [("a", 0, 7), ("b", 4, 7)])
    with pytest.raises(ValueError, match=r"no x, y, z field \(its fields: a, b\)"):
        decode_pointcloud2(msg)
    records = np.zeros(4, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")]))
    msg = cloud_message(store, records, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)])
    msg.data = msg.data[:-1]
    with pytest.raises(ValueError, match="holds 47 bytes, its 1 x 4 points need 48"):
        decode_pointcloud2(msg)


# ------------------------------------------------------------------------------ KITTI bags with poses

FRAMES = 3
T0_NS = 1_600_000_000 * 10**9


def kitti_velodyne_poses(root: Path) -> np.ndarray:
    """KITTI ground truth as Velodyne poses, inv(Tr) P Tr, with each rotation made exactly orthonormal
    (KITTI prints 7 digits, so its matrices are rotations to ~1e-7 only; a quaternion is exact)."""
    from terracube.mapping import read_kitti_calibration, read_pose_file
    from terracube.poses import matrix_from_quaternion, quaternion_from_matrix

    folder = root / "kitti_seq00"
    poses = read_pose_file(folder / "poses.txt", "kitti", read_kitti_calibration(folder / "calib.txt"))[1]
    for pose in poses:
        pose[:3, :3] = matrix_from_quaternion(quaternion_from_matrix(pose[:3, :3]))
    return poses


def base_to_velodyne() -> np.ndarray:
    """A made-up mounting: the Velodyne 1.73 m above and 0.3 m ahead of base_link, turned 5 degrees."""
    yaw = math.radians(5.0)
    pose = np.eye(4)
    pose[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    pose[:3, 3] = [0.3, 0.0, 1.73]
    return pose


def transform_message(store, parent: str, child: str, pose: np.ndarray, stamp_ns: int, ros1=False):
    from terracube.poses import quaternion_from_matrix

    types = store.types
    q = quaternion_from_matrix(pose[:3, :3])
    return types["geometry_msgs/msg/TransformStamped"](
        header=header(store, stamp_ns, parent, ros1),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
            rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )


def odometry_message(store, pose: np.ndarray, stamp_ns: int):
    from terracube.poses import quaternion_from_matrix

    types = store.types
    q = quaternion_from_matrix(pose[:3, :3])
    covariance = np.zeros(36)
    return types["nav_msgs/msg/Odometry"](
        header=header(store, stamp_ns, "world"),
        child_frame_id="base_link",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
                orientation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
            covariance=covariance,
        ),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](
                linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            ),
            covariance=covariance,
        ),
    )


def kitti_cloud_message(store, root: Path, frame: int, stamp_ns: int, ros1=False):
    xyzi = np.fromfile(root / "kitti_seq00" / "velodyne" / f"{frame:06d}.bin", dtype=np.float32).reshape(
        -1, 4
    )
    records = xyzi.view(np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])).reshape(
        -1
    )
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7)]
    return cloud_message(store, records, fields, stamp_ns=stamp_ns, frame="velodyne", ros1=ros1), xyzi


def stamp_of(frame: int) -> int:
    return T0_NS + frame * 100_000_000  # 10 Hz


def write_kitti_odometry_bag(
    root: Path, path: Path, odometry_frames=None, cloud_frames=range(FRAMES)
) -> None:
    """ROS 2 (mcap) bag: KITTI clouds in 'velodyne', world -> base_link odometry, static
    base_link -> velodyne on /tf_static."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    truth = kitti_velodyne_poses(root)
    mount = base_to_velodyne()
    odometry_frames = range(FRAMES) if odometry_frames is None else odometry_frames
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        clouds = writer.add_connection("/velodyne_points", "sensor_msgs/msg/PointCloud2", typestore=store)
        odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=store)
        pose_topic = writer.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=store)
        static = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=store)
        tf = store.types["tf2_msgs/msg/TFMessage"](
            transforms=[transform_message(store, "base_link", "velodyne", mount, T0_NS)]
        )
        writer.write(static, T0_NS, store.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
        for frame in odometry_frames:
            msg = odometry_message(store, truth[frame] @ np.linalg.inv(mount), stamp_of(frame))
            writer.write(odom, stamp_of(frame), store.serialize_cdr(msg, "nav_msgs/msg/Odometry"))
            stamped = store.types["geometry_msgs/msg/PoseStamped"](header=msg.header, pose=msg.pose.pose)
            writer.write(
                pose_topic, stamp_of(frame), store.serialize_cdr(stamped, "geometry_msgs/msg/PoseStamped")
            )
        for frame in cloud_frames:
            msg, _ = kitti_cloud_message(store, root, frame, stamp_of(frame))
            writer.write(clouds, stamp_of(frame), store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))


def write_kitti_tf_bag(root: Path, path: Path) -> None:
    """ROS 1 bag: KITTI clouds, a /tf chain map -> odom (static offset, on /tf) -> base_link
    (moving) and a static base_link -> velodyne on /tf_static."""
    from rosbags.rosbag1 import Writer

    store = typestore(ros1=True)
    truth = kitti_velodyne_poses(root)
    mount = base_to_velodyne()
    map_odom = np.eye(4)
    map_odom[:3, 3] = [100.0, -50.0, 2.0]
    with Writer(path) as writer:
        clouds = writer.add_connection("/velodyne_points", "sensor_msgs/msg/PointCloud2", typestore=store)
        tf_topic = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=store)
        static = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=store, latching=1)
        message = store.types["tf2_msgs/msg/TFMessage"]
        tf = message(transforms=[transform_message(store, "base_link", "velodyne", mount, T0_NS, ros1=True)])
        writer.write(static, T0_NS, store.serialize_ros1(tf, "tf2_msgs/msg/TFMessage"))
        for frame in range(FRAMES):
            odom_base = np.linalg.inv(map_odom) @ truth[frame] @ np.linalg.inv(mount)
            tf = message(
                transforms=[
                    transform_message(store, "map", "odom", map_odom, stamp_of(frame), ros1=True),
                    transform_message(store, "odom", "base_link", odom_base, stamp_of(frame), ros1=True),
                ]
            )
            writer.write(tf_topic, stamp_of(frame), store.serialize_ros1(tf, "tf2_msgs/msg/TFMessage"))
            msg, _ = kitti_cloud_message(store, root, frame, stamp_of(frame), ros1=True)
            writer.write(clouds, stamp_of(frame), store.serialize_ros1(msg, "sensor_msgs/msg/PointCloud2"))


@pytest.fixture(scope="module")
def kitti_bags(shared_data, tmp_path_factory) -> dict[str, Path]:
    root = shared_data.root
    if not (root / "kitti_seq00" / "velodyne" / "000002.bin").is_file():
        pytest.skip("KITTI frames not found")
    folder = tmp_path_factory.mktemp("kitti_bags")
    write_kitti_odometry_bag(root, folder / "odometry")
    write_kitti_tf_bag(root, folder / "tf.bag")
    return {"odometry": folder / "odometry", "tf": folder / "tf.bag", "root": root}


def test_kitti_bag_poses_from_odometry_and_static_mount_are_the_velodyne_poses(kitti_bags):
    truth = kitti_velodyne_poses(kitti_bags["root"])
    clouds = read_bag(kitti_bags["odometry"], "/velodyne_points", "/odom")
    frames = list(clouds)
    assert len(frames) == FRAMES
    for frame, (stamp, points, pose) in enumerate(frames):
        assert stamp == pytest.approx(stamp_of(frame) * 1e-9, abs=1e-9)
        xyzi = np.fromfile(kitti_bags["root"] / f"kitti_seq00/velodyne/{frame:06d}.bin", np.float32)
        np.testing.assert_array_equal(points, xyzi.reshape(-1, 4)[:, :3])
        np.testing.assert_allclose(pose, truth[frame], atol=1e-9)
    # A PoseStamped names no child frame: base_frame says which frame it poses.
    poses = [
        p for _, _, p in read_bag(kitti_bags["odometry"], "/velodyne_points", "/pose", base_frame="base_link")
    ]
    np.testing.assert_allclose(np.stack(poses), truth[:FRAMES], atol=1e-9)


def test_kitti_bag_poses_from_a_tf_chain_are_the_velodyne_poses(kitti_bags):
    truth = kitti_velodyne_poses(kitti_bags["root"])
    for base_frame in (None, "base_link"):
        poses = [
            p for _, _, p in read_bag(kitti_bags["tf"], "/velodyne_points", "/tf", base_frame=base_frame)
        ]
        np.testing.assert_allclose(np.stack(poses), truth[:FRAMES], atol=1e-9)
    # In the odom frame instead of the root (map): the static map -> odom offset is taken off.
    poses = [p for _, _, p in read_bag(kitti_bags["tf"], "/velodyne_points", "/tf", fixed_frame="odom")]
    np.testing.assert_allclose(poses[1][:3, 3], truth[1][:3, 3] - [100.0, -50.0, 2.0], atol=1e-9)
    with pytest.raises(
        ValueError,
        match=r"frame 'base_footprint' is not in the TF tree; known frames: "
        r"base_link, map, odom, velodyne",
    ):
        list(read_bag(kitti_bags["tf"], "/velodyne_points", "/tf", base_frame="base_footprint"))


def test_odometry_is_interpolated_by_slerp_and_refused_outside_its_span(kitti_bags, tmp_path):
    root = kitti_bags["root"]
    truth = kitti_velodyne_poses(root)
    # Odometry at frames 0 and 2 only: the cloud of frame 1 falls half way between them.
    write_kitti_odometry_bag(root, tmp_path / "sparse", odometry_frames=[0, 2], cloud_frames=[1])
    ((_, _, pose),) = list(read_bag(tmp_path / "sparse", "/velodyne_points", "/odom"))
    mount = base_to_velodyne()
    base0, base2 = truth[0] @ np.linalg.inv(mount), truth[2] @ np.linalg.inv(mount)
    # Reference: half the relative rotation, by Rodrigues' formula on its axis and angle.
    relative = base0[:3, :3].T @ base2[:3, :3]
    angle = math.acos((np.trace(relative) - 1) / 2)
    axis = np.array(
        [relative[2, 1] - relative[1, 2], relative[0, 2] - relative[2, 0], relative[1, 0] - relative[0, 1]]
    ) / (2 * math.sin(angle))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    half = np.eye(3) + math.sin(angle / 2) * k + (1 - math.cos(angle / 2)) * k @ k
    expected = np.eye(4)
    expected[:3, :3] = base0[:3, :3] @ half
    expected[:3, 3] = (base0[:3, 3] + base2[:3, 3]) / 2
    np.testing.assert_allclose(pose, expected @ mount, atol=1e-9)

    write_kitti_odometry_bag(root, tmp_path / "early", odometry_frames=[0, 1], cloud_frames=[2])
    with pytest.raises(
        ValueError,
        match=r"outside the span of the poses of /odom: \[1600000000.000000000, "
        r"1600000000.100000000\] s \(2 poses\)",
    ):
        list(read_bag(tmp_path / "early", "/velodyne_points", "/odom"))


# ------------------------------------------------------------------------------ bad input


def test_an_unknown_topic_lists_the_available_ones(bags):
    with pytest.raises(
        ValueError,
        match=r"no point-cloud topic '/points' in the bag; its topics: "
        r"/base_pose_ground_truth \(nav_msgs/msg/Odometry, 5\), ",
    ):
        read_bag(bags / "luminar_embag.bag", "/points")
    with pytest.raises(ValueError, match=r"'/base_scan' holds sensor_msgs/msg/LaserScan, expected"):
        read_bag(bags / "luminar_embag_ros2_mcap", "/base_scan")
    with pytest.raises(ValueError, match=r"no pose topic '/odom'"):
        read_bag(bags / "luminar_embag_ros2_db3", LUMINAR_TOPIC, "/odom")
    with pytest.raises(FileNotFoundError, match="no such bag"):
        read_bag(bags / "nothing.bag", LUMINAR_TOPIC)


def test_truncated_bags_raise_a_clear_error(bags, tmp_path):
    for name, size in (("luminar_embag.bag", 2_000_000), ("ouster_os1_pointcloudset_ros1.mcap", 1_000_000)):
        truncated = tmp_path / name
        truncated.write_bytes((bags / name).read_bytes()[:size])
        topic = OUSTER_TOPIC if "ouster" in name else LUMINAR_TOPIC
        with pytest.raises(ValueError, match=rf"{truncated}: cannot read"):
            list(read_bag(truncated, topic))
    folder = tmp_path / "luminar_mcap"
    shutil.copytree(bags / "luminar_embag_ros2_mcap", folder)
    storage = next(folder.glob("*.mcap"))
    storage.write_bytes(storage.read_bytes()[:1_500_000])
    with pytest.raises(ValueError, match=rf"{folder}: cannot read"):
        list(read_bag(folder, LUMINAR_TOPIC))


def test_a_bag_cloud_without_xyz_names_its_fields(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    records = np.zeros(3, np.dtype([("u", "<f4"), ("v", "<f4")]))
    msg = cloud_message(store, records, [("u", 0, 7), ("v", 4, 7)], stamp_ns=T0_NS)
    with Writer(tmp_path / "uv", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/uv", "sensor_msgs/msg/PointCloud2", typestore=store)
        writer.write(connection, T0_NS, store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    with pytest.raises(
        ValueError, match=r"/uv at 1600000000.000000000 s: the PointCloud2 has no x, y, z field"
    ):
        list(read_bag(tmp_path / "uv", "/uv"))


# ------------------------------------------------------------------------------ writing


def asymmetric_map() -> tc.ElevationMap:
    """A 4 x 3 map at 0.5 m whose cell (i, j) holds 10 i + j in 'max' and a class in 'class'."""
    elevation_map = tc.ElevationMap.empty(0.5, (10.0, -2.0), (4, 3))
    elevation_map["max"] = [[0, 1, 2], [10, 11, 12], [20, 21, 22], [30, 31, np.nan]]
    elevation_map["class"] = [[0, 1, 2], [3, 4, 5], [1, 1, 1], [2, 2, 0]]
    return elevation_map


# grid_map: index (0, 0) is the cell at the maximum x and y; rows run along -x, columns along -y,
# stored column by column. Written out by hand for the map above (NaN is cell (3, 2), index (0, 0)).
GRID_MAP_MAX = [np.nan, 22, 12, 2, 31, 21, 11, 1, 30, 20, 10, 0]
GRID_MAP_CLASS = [0, 1, 5, 2, 2, 1, 4, 1, 2, 1, 3, 0]
# OccupancyGrid: index i + 4 j from cell (0, 0) at the origin; classes by CLASS_OCCUPANCY.
OCCUPANCY = [-1, 100, 0, 100, 0, 100, 0, 100, 100, 50, 0, -1]


def write_all(path: Path, storage: str) -> Path:
    elevation_map = asymmetric_map()
    with MapBagWriter(path, storage) as writer:
        writer.write_grid_map(elevation_map, stamp=12.25, frame_id="odom", basic_layers=["max"])
        writer.write_occupancy_grid(
            elevation_map, occupancy_from_classes(elevation_map["class"]), stamp=12.25, frame_id="odom"
        )
        writer.write_cloud([[1.0, 2.0, 3.0], [4.0, 5.0, 6.5]], [1, 4], stamp=12.25, frame_id="odom")
    return path


def test_grid_map_layout_is_column_major_from_the_maximum_corner():
    elevation_map = asymmetric_map()
    np.testing.assert_array_equal(grid_map_layer_data(elevation_map["max"]), np.float32(GRID_MAP_MAX))
    np.testing.assert_array_equal(grid_map_layer_data(elevation_map["class"]), np.float32(GRID_MAP_CLASS))
    np.testing.assert_array_equal(layer_from_grid_map_data(GRID_MAP_MAX, 4, 3), elevation_map["max"])
    np.testing.assert_array_equal(occupancy_from_classes(elevation_map["class"]).ravel(order="F"), OCCUPANCY)
    np.testing.assert_array_equal(
        occupancy_from_traversability([[1.0, 0.25], [0.0, np.nan]]), [[0, 75], [100, -1]]
    )


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_ros2_bag_round_trip_through_rosbags(tmp_path, storage):
    from rosbags.highlevel import AnyReader

    path = write_all(tmp_path / "maps", storage)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["maps"]  # no temporary left behind
    assert next(path.glob("*.mcap" if storage == "mcap" else "*.db3"))
    with AnyReader([path]) as reader:
        messages = {
            c.topic: (c.msgtype, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()
        }
    msgtype, time, grid = messages["/terracube/grid_map"]
    assert msgtype == "grid_map_msgs/msg/GridMap" and time == 12_250_000_000
    assert grid.header.frame_id == "odom" and (grid.header.stamp.sec, grid.header.stamp.nanosec) == (
        12,
        250_000_000,
    )
    assert grid.layers == ["max", "class"] and grid.basic_layers == ["max"]
    assert (grid.info.resolution, grid.info.length_x, grid.info.length_y) == (0.5, 2.0, 1.5)
    assert (grid.info.pose.position.x, grid.info.pose.position.y, grid.info.pose.orientation.w) == (
        11.0,
        -1.25,
        1.0,
    )
    np.testing.assert_array_equal(grid.data[0].data, np.float32(GRID_MAP_MAX))
    np.testing.assert_array_equal(grid.data[1].data, np.float32(GRID_MAP_CLASS))
    dims = [(d.label, d.size, d.stride) for d in grid.data[0].layout.dim]
    assert dims == [("column_index", 3, 12), ("row_index", 4, 4)]
    assert (grid.outer_start_index, grid.inner_start_index) == (0, 0)

    msgtype, _, occupancy = messages["/terracube/occupancy"]
    assert msgtype == "nav_msgs/msg/OccupancyGrid"
    assert (occupancy.info.width, occupancy.info.height, occupancy.info.resolution) == (4, 3, 0.5)
    assert (occupancy.info.origin.position.x, occupancy.info.origin.position.y) == (10.0, -2.0)
    assert occupancy.data.tolist() == OCCUPANCY

    msgtype, _, cloud = messages["/terracube/classified_cloud"]
    assert msgtype == "sensor_msgs/msg/PointCloud2"
    points, fields, dropped = decode_pointcloud2(cloud)
    np.testing.assert_array_equal(points, np.float32([[1, 2, 3], [4, 5, 6.5]]))
    assert fields["label"].tolist() == [1, 4] and dropped == 0
    assert [(f.name, f.offset, f.datatype) for f in cloud.fields] == [
        ("x", 0, 7),
        ("y", 4, 7),
        ("z", 8, 7),
        ("label", 12, 6),
    ]

    with pytest.raises(FileExistsError):
        MapBagWriter(path, storage)


ROS1_DUMP = r"""
import json, math, sys, rosbag
def number(v):
    return None if math.isnan(v) else v
out = {}
with rosbag.Bag(sys.argv[1]) as bag:
    for topic, msg, t in bag.read_messages():
        entry = {"type": msg._type, "md5": msg._md5sum, "time": t.to_nsec()}
        if msg._type == "grid_map_msgs/GridMap":
            info = msg.info
            entry.update(
                info_md5=info._md5sum,
                frame=info.header.frame_id, stamp=info.header.stamp.to_nsec(), layers=list(msg.layers),
                basic=list(msg.basic_layers), resolution=info.resolution,
                length=[info.length_x, info.length_y], centre=[info.pose.position.x, info.pose.position.y],
                data=[[number(v) for v in a.data] for a in msg.data],
                dims=[[d.label, d.size, d.stride] for d in msg.data[0].layout.dim],
            )
        elif msg._type == "nav_msgs/OccupancyGrid":
            entry.update(
                frame=msg.header.frame_id, size=[msg.info.width, msg.info.height], data=list(msg.data),
                origin=[msg.info.origin.position.x, msg.info.origin.position.y],
            )
        else:
            entry.update(
                fields=[[f.name, f.offset, f.datatype] for f in msg.fields],
                data=list(bytearray(msg.data)), size=[msg.height, msg.width, msg.point_step],
            )
        out[topic] = entry
print(json.dumps(out))
"""


def test_ros1_bag_round_trip_through_debians_python3_rosbag(tmp_path):
    probe = (
        subprocess.run([str(SYSTEM_PYTHON), "-c", "import rosbag"], capture_output=True)
        if SYSTEM_PYTHON.exists()
        else None
    )
    if probe is None or probe.returncode != 0:
        pytest.skip("Debian's python3-rosbag is not installed (scripts/setup.sh installs it)")
    path = write_all(tmp_path / "maps.bag", "ros1")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["maps.bag"]
    result = subprocess.run(
        [str(SYSTEM_PYTHON), "-c", ROS1_DUMP, str(path)], capture_output=True, text=True, check=True
    )
    topics = json.loads(result.stdout)
    grid = topics["/terracube/grid_map"]
    # The upstream grid_map_msgs/GridMap MD5 sum: our definition is the one ROS 1 nodes expect.
    assert grid["type"] == "grid_map_msgs/GridMap" and grid["md5"] == "95681e052b1f73bf87b7eb984382b401"
    assert grid["info_md5"] == "43ee5430e1c253682111cb6bedac0ef9"
    assert grid["frame"] == "odom" and grid["stamp"] == 12_250_000_000 == grid["time"]
    assert grid["layers"] == ["max", "class"] and grid["basic"] == ["max"]
    assert grid["resolution"] == 0.5 and grid["length"] == [2.0, 1.5] and grid["centre"] == [11.0, -1.25]
    assert grid["data"] == [[None, *GRID_MAP_MAX[1:]], GRID_MAP_CLASS]
    assert grid["dims"] == [["column_index", 3, 12], ["row_index", 4, 4]]
    occupancy = topics["/terracube/occupancy"]
    assert (
        occupancy["type"] == "nav_msgs/OccupancyGrid"
        and occupancy["md5"] == "3381f2d731d4076ec5c71b0759edbe4e"
    )
    assert (
        occupancy["size"] == [4, 3] and occupancy["origin"] == [10.0, -2.0] and occupancy["data"] == OCCUPANCY
    )
    cloud = topics["/terracube/classified_cloud"]
    assert cloud["type"] == "sensor_msgs/PointCloud2" and cloud["md5"] == "1158d486dd51d683ce2f1be655c3c181"
    assert cloud["fields"] == [["x", 0, 7], ["y", 4, 7], ["z", 8, 7], ["label", 12, 6]] and cloud["size"] == [
        1,
        2,
        16,
    ]
    assert bytes(cloud["data"]) == struct.pack("<fffIfffI", 1, 2, 3, 1, 4, 5, 6.5, 4)


def test_a_failed_write_leaves_nothing_behind(tmp_path):
    elevation_map = asymmetric_map()
    for storage, name in (("mcap", "maps"), ("sqlite3", "maps"), ("ros1", "maps.bag")):
        with pytest.raises(KeyError, match="no layer 'height'"):
            with MapBagWriter(tmp_path / name, storage) as writer:
                writer.write_grid_map(elevation_map)
                writer.write_grid_map(elevation_map, layers=["height"])
        assert list(tmp_path.iterdir()) == [], storage
    # Replacing an existing bag happens only on success, and only when asked.
    write_all(tmp_path / "maps", "mcap")
    with pytest.raises(RuntimeError):
        with MapBagWriter(tmp_path / "maps", "mcap", overwrite=True) as writer:
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["maps"]
    assert [t.count for t in bag_info(tmp_path / "maps")] == [1, 1, 1]
    with MapBagWriter(tmp_path / "maps", "mcap", overwrite=True) as writer:
        writer.write_grid_map(elevation_map, layers=["max"])
    assert [t.name for t in bag_info(tmp_path / "maps")] == ["/terracube/grid_map"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["maps"]


def sparse_map() -> tc.ElevationMap:
    """A 400 x 300 map at 0.1 m with data in 0.5 % of its cells (like a long-range scan's DEM)."""
    elevation_map = tc.ElevationMap.empty(0.1, (0.0, 0.0), (400, 300))
    heights = np.full((400, 300), np.nan, np.float32)
    rng = np.random.default_rng(7)
    cells = rng.choice(heights.size, 600, replace=False)
    heights.flat[cells] = rng.uniform(-2.0, 5.0, 600)
    elevation_map["max"] = heights
    return elevation_map


@pytest.mark.parametrize(("storage", "name"), [("mcap", "maps"), ("sqlite3", "maps"), ("ros1", "maps.bag")])
def test_written_bags_are_compressed_so_a_sparse_grid_map_is_small_and_reads_back_unchanged(
    tmp_path, storage, name
):
    from rosbags.highlevel import AnyReader

    elevation_map = sparse_map()
    with MapBagWriter(tmp_path / name, storage) as writer:
        writer.write_grid_map(elevation_map, stamp=3.5, layers=["max"])
    path = tmp_path / name
    files = [path] if path.is_file() else [f for f in path.iterdir() if f.suffix in (".mcap", ".db3")]
    raw_bytes = 4 * 400 * 300
    assert sum(f.stat().st_size for f in files) < raw_bytes / 10  # uncompressed it is > raw_bytes
    if storage == "mcap":  # zstd chunks, read back by the mcap package as well
        from mcap.reader import make_reader

        with files[0].open("rb") as stream:
            reader = make_reader(stream)
            assert {c.compression for c in reader.get_summary().chunk_indexes} == {"zstd"}
            assert len([m for _, _, m in reader.iter_messages()]) == 1
    elif storage == "sqlite3":  # rosbag2's message compression, declared in metadata.yaml
        metadata = (path / "metadata.yaml").read_text()
        assert "compression_format: zstd" in metadata and "compression_mode: message" in metadata
    else:  # ROS 1 chunks, as `rosbag record --lz4` writes them
        assert b"compression=lz4" in path.read_bytes()
    with AnyReader([path]) as reader:
        [(connection, time, raw)] = list(reader.messages())
        grid = reader.deserialize(raw, connection.msgtype)
    assert time == 3_500_000_000 and grid.layers == ["max"]
    np.testing.assert_array_equal(grid.data[0].data, grid_map_layer_data(elevation_map["max"]))
    np.testing.assert_array_equal(layer_from_grid_map_data(grid.data[0].data, 400, 300), elevation_map["max"])


# ------------------------------------------------------------------------------ the command line


@pytest.fixture(scope="module")
def cli():
    from terracube.cli import app
    from typer.testing import CliRunner

    runner = CliRunner()

    def run(*args):
        return runner.invoke(app, [str(a) for a in args])

    return run


def test_bag_info_command_lists_topics(cli, bags):
    result = cli("bag-info", bags / "ouster_os1_pointcloudset_ros1.mcap")
    assert result.exit_code == 0, result.output
    assert re.search(r"\n/os1_cloud_node/points +2  sensor_msgs/msg/PointCloud2\n", result.output)
    assert re.search(r"\n/tf_static +1  tf2_msgs/msg/TFMessage\n", result.output)
    result = cli("bag-info", bags / "missing.bag")
    assert result.exit_code == 2 and "no such bag" in result.output


def test_map_on_a_kitti_bag_gives_the_map_of_the_loose_files_and_pose_file(cli, kitti_bags, tmp_path):
    from terracube.poses import write_tum_poses

    root = kitti_bags["root"]
    truth = kitti_velodyne_poses(root)[:FRAMES]
    tum = tmp_path / "velodyne_tum.txt"
    write_tum_poses(tum, [stamp_of(f) * 1e-9 for f in range(FRAMES)], truth)
    options = ["--keyframe-distance", "0.5", "--no-png"]
    loose = cli(
        "map",
        root / "kitti_seq00" / "velodyne",
        "--poses",
        tum,
        "--limit",
        FRAMES,
        "-o",
        tmp_path / "loose",
        *options,
    )
    assert loose.exit_code == 0, loose.output
    expected = tc.ElevationMap.load(tmp_path / "loose" / "global_map.npz")
    runs = {
        "odom": ["--odom", "/odom"],
        "tf": ["--tf", "base_link"],
    }
    for name, pose_options in runs.items():
        bag = kitti_bags["odometry" if name == "odom" else "tf"]
        result = cli(
            "map", bag, "--points", "/velodyne_points", *pose_options, "--out", tmp_path / name, *options
        )
        assert result.exit_code == 0, result.output
        assert f"{FRAMES} clouds of /velodyne_points, {FRAMES} keyframes" in result.output
        # The same summary as the files' (pipeline.write_global_map): the map, its ground, the steps.
        for start in ("global map: ", "ground reference: ", "odometry fallbacks: "):
            lines = [
                [ln for ln in run.output.splitlines() if ln.startswith(start)] for run in (loose, result)
            ]
            assert len(lines[0]) == 1 and lines[0] == lines[1], start
        got = tc.ElevationMap.load(tmp_path / name / "global_map.npz")
        assert got.layers == expected.layers
        np.testing.assert_allclose(got.geometry.origin, expected.geometry.origin, atol=1e-9)
        assert tuple(got.geometry.size) == tuple(expected.geometry.size)
        np.testing.assert_array_equal(got["count"], expected["count"], err_msg=name)
        for layer in expected.layers:
            np.testing.assert_allclose(got[layer], expected[layer], atol=1e-5, equal_nan=True, err_msg=layer)
        for trajectory in ("trajectory_kitti.txt", "keyframes_kitti.txt"):
            np.testing.assert_allclose(
                np.loadtxt(tmp_path / name / trajectory),
                np.loadtxt(tmp_path / "loose" / trajectory),
                atol=1e-6,
            )
        # Every cloud's pose, stamped with the bag's times.
        tum = np.loadtxt(tmp_path / name / "trajectory_tum.txt")
        np.testing.assert_allclose(tum[:, 0], [stamp_of(f) * 1e-9 for f in range(FRAMES)], atol=1e-6)
        # The bag beside the files holds the map as GridMap and its classes as OccupancyGrid.
        topics = {t.name: t.msgtype for t in bag_info(tmp_path / name / "global_map")}
        assert topics == {
            "/terracube/grid_map": "grid_map_msgs/msg/GridMap",
            "/terracube/occupancy": "nav_msgs/msg/OccupancyGrid",
        }


def test_stream_on_a_kitti_bag_gives_the_local_map_of_the_loose_files_and_publishes_it(
    cli, kitti_bags, tmp_path
):
    from rosbags.highlevel import AnyReader
    from terracube.poses import write_tum_poses

    root = kitti_bags["root"]
    tum = tmp_path / "velodyne_tum.txt"
    write_tum_poses(tum, [stamp_of(f) * 1e-9 for f in range(FRAMES)], kitti_velodyne_poses(root)[:FRAMES])
    options = ["--length", "12", "--resolution", "0.2", "--no-png"]
    velodyne = root / "kitti_seq00" / "velodyne"
    loose = cli("stream", velodyne, "--poses", tum, "--limit", FRAMES, "-o", tmp_path / "loose", *options)
    assert loose.exit_code == 0, loose.output
    expected = tc.ElevationMap.load(tmp_path / "loose" / "local_map.npz")
    for name, pose_options in {"odom": ["--odom", "/odom"], "tf": ["--tf", "base_link"]}.items():
        bag = kitti_bags["odometry" if name == "odom" else "tf"]
        result = cli(
            "stream", bag, "--points", "/velodyne_points", *pose_options, "--out", tmp_path / name, *options
        )
        assert result.exit_code == 0, result.output
        got = tc.ElevationMap.load(tmp_path / name / "local_map.npz")
        assert got.layers == expected.layers
        np.testing.assert_allclose(got.geometry.origin, expected.geometry.origin, atol=1e-9)
        np.testing.assert_array_equal(got["count"], expected["count"], err_msg=name)
        for layer in expected.layers:
            np.testing.assert_allclose(got[layer], expected[layer], atol=1e-5, equal_nan=True, err_msg=layer)
        # The bag beside the files: the local map after every cloud, with its traversability as
        # an OccupancyGrid (-1 unknown, 0 open ground ... 100 blocked), in the poses' frame.
        with AnyReader([tmp_path / name / f"{bag.stem}_stream"]) as reader:
            counts = {c.topic: c.msgcount for c in reader.connections}
            grids = [
                reader.deserialize(raw, c.msgtype)
                for c, _, raw in reader.messages()
                if c.topic.endswith("occupancy")
            ]
        assert counts == {"/terracube/grid_map": FRAMES, "/terracube/occupancy": FRAMES}
        occupancy = np.asarray(grids[-1].data)
        traversable = np.isfinite(expected["traversability"])
        assert np.count_nonzero(occupancy >= 0) == np.count_nonzero(traversable)
        # In the poses' frame: the odometry's, or the TF tree's root.
        assert grids[-1].header.frame_id == {"odom": "world", "tf": "map"}[name]
    bag = kitti_bags["odometry"]
    # --every N: the map after every N-th cloud, and the final map (local_map.npz) once at the end.
    assert FRAMES == 3
    for every, published in ((2, [2, 3]), (3, [3])):
        folder = tmp_path / f"every{every}"
        result = cli("stream", bag, "--odom", "/odom", "--every", every, "--out", folder, *options)
        assert result.exit_code == 0, result.output
        with AnyReader([folder / "odometry_stream"]) as reader:
            stamps = {
                c.topic: [
                    reader.deserialize(raw, c.msgtype).header.stamp for _, _, raw in reader.messages([c])
                ]
                for c in reader.connections
            }
        expected = [stamp_of(k - 1) * 1e-9 for k in published]  # stamps pass through float seconds
        for topic in ("/terracube/grid_map", "/terracube/occupancy"):
            got = [s.sec + s.nanosec * 1e-9 for s in stamps[topic]]
            assert got == pytest.approx(expected, abs=1e-6), topic
    result = cli("stream", kitti_bags["odometry"], "--points", "/velodyne_points", "-o", tmp_path / "x")
    assert result.exit_code == 2 and "--odom TOPIC" in result.output and "--lidar-only" in result.output
    (tmp_path / "file").write_text("")  # an animation that cannot be written: refused before any cloud
    result = cli(
        "stream", bag, "--odom", "/odom", "--animation", tmp_path / "file" / "a.gif", "--out", tmp_path / "y"
    )
    assert result.exit_code == 2 and "is not a folder" in result.output, result.output
    assert "streaming" not in result.output and not (tmp_path / "y").exists()
    result = cli("stream", kitti_bags["odometry"], "--odom", "/odom", "--poses", tum, "-o", tmp_path / "x")
    assert result.exit_code == 2 and "--poses is for a folder of scans" in result.output


def test_lidar_only_map_and_stream_of_a_bag_equal_those_of_the_loose_files(cli, kitti_bags, tmp_path):
    """Without a pose source (--lidar-only) a bag's clouds are posed by the mapper's registrations,
    as the loose files are."""
    velodyne = kitti_bags["root"] / "kitti_seq00" / "velodyne"
    bag = kitti_bags["odometry"]
    for command, options, result_file in (
        ("map", ["--keyframe-distance", "0.5", "--no-png"], "global_map.npz"),
        ("stream", ["--length", "12", "--resolution", "0.2", "--no-png"], "local_map.npz"),
    ):
        loose = cli(command, velodyne, "--lidar-only", "--limit", FRAMES, "-o", tmp_path / command, *options)
        assert loose.exit_code == 0, loose.output
        result = cli(
            command, bag, "--points", "/velodyne_points", "--lidar-only", "-o", tmp_path / "b", *options
        )
        assert result.exit_code == 0, result.output
        assert f"{FRAMES - 1} of {FRAMES - 1} scans registered" in result.output
        expected = tc.ElevationMap.load(tmp_path / command / result_file)
        got = tc.ElevationMap.load(tmp_path / "b" / result_file)
        np.testing.assert_allclose(got.geometry.origin, expected.geometry.origin, atol=1e-9)
        for layer in set(expected.layers) - {"time"}:  # the bag's stamps, the files' indices
            np.testing.assert_allclose(got[layer], expected[layer], atol=1e-5, equal_nan=True, err_msg=layer)
    trajectory = np.loadtxt(tmp_path / "b" / "trajectory_kitti.txt").reshape(-1, 3, 4)
    np.testing.assert_allclose(
        trajectory, np.loadtxt(tmp_path / "map" / "trajectory_kitti.txt").reshape(-1, 3, 4)
    )
    assert np.linalg.norm(trajectory[-1, :, 3]) > 1.0  # the car moved 1.7 m (the scans say 1.4 m)
    result = cli("stream", bag, "--odom", "/odom", "--tf", "base_link", "-o", tmp_path / "x")
    assert result.exit_code == 2 and "not both" in result.output


def test_classify_on_every_cloud_of_a_bag_writes_files_and_a_bag(cli, bags, tmp_path):
    from rosbags.highlevel import AnyReader

    out = tmp_path / "out"
    result = cli(
        "classify",
        bags / "ouster_os1_pointcloudset_ros1.mcap",
        "--points",
        OUSTER_TOPIC,
        "--out",
        out,
        "--no-png",
        "--resolution",
        "0.2",
    )
    assert result.exit_code == 0, result.output
    assert "85,356 no-returns dropped" in result.output
    stem = "ouster_os1_pointcloudset_ros1"
    for index in range(2):
        assert (out / f"{stem}_{index:04d}_classes.npz").is_file()
    with AnyReader([out / f"{stem}_classify"]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        clouds = [
            reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages() if c.topic.endswith("cloud")
        ]
    assert counts == {"/terracube/grid_map": 2, "/terracube/occupancy": 2, "/terracube/classified_cloud": 2}
    points, fields, _ = decode_pointcloud2(clouds[0])
    assert len(points) == 45716 and set(np.unique(fields["label"])) <= set(range(6))
    assert clouds[0].header.frame_id == "os1_lidar"


def test_map_on_a_bag_reports_bad_input(cli, kitti_bags, bags, tmp_path):
    result = cli("map", kitti_bags["odometry"], "--points", "/velodyne_points", "-o", tmp_path)
    assert result.exit_code == 2 and "--odom TOPIC" in result.output
    result = cli("map", kitti_bags["odometry"], "--points", "/lidar", "--odom", "/odom", "-o", tmp_path)
    assert (
        result.exit_code == 2
        and "no point-cloud topic '/lidar'" in result.output
        and "/velodyne_points" in result.output
    )
    result = cli("map", kitti_bags["tf"], "--tf", "base_footprint", "-o", tmp_path / "x")
    assert result.exit_code == 2 and "'base_footprint' is not in the TF tree" in result.output
    assert not (tmp_path / "x").exists()
    result = cli("dem", bags / "luminar_embag.bag", "--tf", "base_link")
    assert result.exit_code != 0


def test_collapse_on_every_cloud_of_a_ros2_bag_writes_a_ros1_bag(cli, bags, tmp_path):
    out = tmp_path / "out"
    result = cli(
        "collapse", bags / "luminar_embag_ros2_db3", "--out", out, "--bag-storage", "ros1", "--no-png"
    )
    assert result.exit_code == 0, result.output
    assert all(f"luminar_embag_ros2_db3_{i:04d}: " in result.output for i in range(5))
    clouds = list(
        read_bag(out / "luminar_embag_ros2_db3_collapse.bag", "/terracube/classified_cloud").clouds()
    )
    assert [len(c.points) for c in clouds] == LUMINAR_COUNTS
    assert all(set(np.unique(c.fields["label"])) <= {0, 1} for c in clouds)
    assert {c.frame_id for c in clouds} == {"luminar_lidar"}
    assert sorted(p.name for p in out.iterdir())[:2] == [
        "luminar_embag_ros2_db3_0000_classified.ply",
        "luminar_embag_ros2_db3_0001_classified.ply",
    ]
    # Bag options on a loose file are refused.
    result = cli("dem", bags / "LICENSE.embag", "--points", "/x")
    assert result.exit_code == 2 and "--points: only for a bag input" in result.output


def test_stream_shadow_aware_on_an_organised_bag_uses_its_beams_without_a_return(cli, bags, tmp_path):
    """The OS1-64 recording (ring field, (0, 0, 0) for no return): with --method shadow_aware the
    empty pixels become beams for the overhang removal; the returns alone are fused."""
    from terracube.bag import read_bag
    from terracube.cli_bag import returns_and_empty_beams

    path = bags / "ouster_os1_pointcloudset_ros1.mcap"
    cloud = next(read_bag(path, OUSTER_TOPIC, keep_invalid=True).clouds())
    points, beams = returns_and_empty_beams(cloud)
    assert len(points) == 64 * 2048 - 85356 and len(beams) == 85356
    np.testing.assert_allclose(np.linalg.norm(beams, axis=1), 1.0)
    assert returns_and_empty_beams(next(read_bag(path, OUSTER_TOPIC).clouds()))[1] is None  # no empty pixel
    options = ["--tf", "os1_sensor", "--length", "20", "--resolution", "0.2", "--no-png"]
    with pytest.warns(UserWarning, match="no /tf topic"):  # the recording's sensor stands still
        result = cli(
            "stream",
            path,
            "--points",
            OUSTER_TOPIC,
            "--method",
            "shadow_aware",
            "-o",
            tmp_path / "s",
            *options,
        )
        paper = cli("stream", path, "--points", OUSTER_TOPIC, "-o", tmp_path / "p", *options)
    assert result.exit_code == 0, result.output
    assert f"{85356 + 85263:,} beams without a return" in result.output
    assert paper.exit_code == 0 and "170,619 no-returns dropped" in paper.output
    for name in ("s", "p"):
        assert tc.ElevationMap.load(tmp_path / name / "local_map.npz")["count"].sum() > 0


def test_a_per_scan_stage_on_an_organised_bag_uses_its_beams_without_a_return(cli, bags, tmp_path):
    """``terracube collapse BAG --method shadow_aware``: each cloud's empty pixels are its beams, as
    collapse_overhangs given returns_and_empty_beams of the cloud; the paper's rule drops them."""
    from terracube.bag import read_bag
    from terracube.cli_bag import returns_and_empty_beams

    path = bags / "ouster_os1_pointcloudset_ros1.mcap"
    common = ["--points", OUSTER_TOPIC, "-e", "0.5", "-s", "4", "-f", "npz", "--no-png"]
    result = cli("collapse", path, "--method", "shadow_aware", "-o", tmp_path / "s", *common)
    assert result.exit_code == 0, result.output
    assert (
        "85,356 beams without a return" in result.output and "85,263 beams without a return" in result.output
    )
    params = tc.CollapseParams(edge=0.5, sigma=4, method="shadow_aware")
    changed = 0
    for index, cloud in enumerate(read_bag(path, OUSTER_TOPIC, keep_invalid=True).clouds()):
        points, beams = returns_and_empty_beams(cloud)
        saved = np.load(tmp_path / "s" / f"{path.stem}_{index:04d}_classified.npz")
        np.testing.assert_array_equal(saved["xyz"], points)
        expected = tc.collapse_overhangs(points, params=params, no_returns=beams).overhang
        np.testing.assert_array_equal(saved["overhang"].astype(bool), expected)
        changed += np.count_nonzero(expected != tc.collapse_overhangs(points, params=params).overhang)
    assert changed > 0  # the beams decide some cubes of this recording
    paper = cli("collapse", path, "-o", tmp_path / "p", *common)
    assert paper.exit_code == 0 and "85,356 no-returns dropped" in paper.output
    assert "beams without a return" not in paper.output


# ------------------------------------------------------------------------------ IMU leveling

IMU_UPTIME_NS = 500 * 10**9  # an IMU stamped by its own uptime: another clock than the clouds'


def rotation(axis: str, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


TILT = rotation("x", 7.0) @ rotation("y", -5.0)  # lidar <- velodyne: a sensor mounted askew
LIDAR_IMU = rotation("z", 90.0) @ rotation("x", 180.0)  # lidar <- imu: upside down, turned


def tilted_truth(root: Path) -> np.ndarray:
    """World <- lidar rotations of the tilted sensor (KITTI's Velodyne rotations times TILT^T)."""
    return np.array([pose[:3, :3] @ TILT.T for pose in kitti_velodyne_poses(root)[:FRAMES]])


def roll_pitch_zyx(r: np.ndarray) -> tuple[float, float]:
    """Roll and pitch of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return math.atan2(r[2, 1], r[2, 2]), -math.asin(r[2, 0])


def imu_message(store, stamp_ns: int, world_imu: np.ndarray, with_orientation: bool):
    """A sensor_msgs/Imu at rest: gravity read along the IMU's up; with_orientation also gives the
    orientation and then a misleading acceleration (the reader must prefer the orientation)."""
    from terracube.poses import quaternion_from_matrix

    types = store.types
    up = world_imu.T @ np.array([0.0, 0.0, 1.0])
    vector = types["geometry_msgs/msg/Vector3"]
    accel = np.array([9.81, 0.0, 0.0]) if with_orientation else 9.81 * up
    q = quaternion_from_matrix(world_imu) if with_orientation else np.zeros(4)
    covariance = np.zeros(9)
    orientation_covariance = covariance.copy()
    orientation_covariance[0] = 0.0 if with_orientation else -1.0  # REP 145: -1 is "no orientation"
    return types["sensor_msgs/msg/Imu"](
        header=header(store, stamp_ns, "imu"),
        orientation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        orientation_covariance=orientation_covariance,
        angular_velocity=vector(x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=covariance,
        linear_acceleration=vector(x=accel[0], y=accel[1], z=accel[2]),
        linear_acceleration_covariance=covariance,
    )


def write_imu_bag(root: Path, path: Path, with_orientation: bool) -> list[np.ndarray]:
    """ROS 2 bag: KITTI clouds seen by the tilted 'lidar', an IMU in frame 'imu' at 100 Hz holding
    each cloud's attitude for +-50 ms round its stamp (stamped by its uptime when it reports only
    accelerations), the mount lidar -> imu on /tf_static, and planar odometry world -> base_link
    (the lidar's true position and heading, no roll or pitch; base_link = lidar). Returns the
    clouds' (N, 4) rows."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    truth = tilted_truth(root)
    mount = np.eye(4)
    mount[:3, :3], mount[:3, 3] = LIDAR_IMU, [0.05, 0.0, -0.1]
    rows = []
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        clouds = writer.add_connection("/lidar_points", "sensor_msgs/msg/PointCloud2", typestore=store)
        imu = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
        static = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=store)
        odom = writer.add_connection("/odom2d", "nav_msgs/msg/Odometry", typestore=store)
        tf = store.types["tf2_msgs/msg/TFMessage"](
            transforms=[
                transform_message(store, "lidar", "imu", mount, T0_NS),
                transform_message(store, "base_link", "lidar", np.eye(4), T0_NS),
            ]
        )
        writer.write(static, T0_NS - 10**9, store.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
        for frame, pose in enumerate(kitti_velodyne_poses(root)[:FRAMES]):
            planar = np.eye(4)
            yaw = math.atan2(truth[frame][1, 0], truth[frame][0, 0])
            planar[:3, :3], planar[:3, 3] = rotation("z", math.degrees(yaw)), pose[:3, 3]
            msg = odometry_message(store, planar, stamp_of(frame))
            writer.write(odom, stamp_of(frame), store.serialize_cdr(msg, "nav_msgs/msg/Odometry"))
        for k in range(-30, 10 * FRAMES + 20):  # every 10 ms from 0.3 s before the first cloud
            record = T0_NS + k * 10_000_000
            frame = min(max(round(k / 10), 0), FRAMES - 1)  # the cloud nearest in time
            stamp = record if with_orientation else record - T0_NS + IMU_UPTIME_NS
            msg = imu_message(store, stamp, truth[frame] @ LIDAR_IMU, with_orientation)
            writer.write(imu, record, store.serialize_cdr(msg, "sensor_msgs/msg/Imu"))
        for frame in range(FRAMES):
            xyzi = np.fromfile(root / "kitti_seq00" / "velodyne" / f"{frame:06d}.bin", np.float32).reshape(
                -1, 4
            )
            xyzi[:, :3] = (xyzi[:, :3].astype(np.float64) @ TILT.T).astype(np.float32)
            records = xyzi.view(np.dtype([(n, "<f4") for n in ("x", "y", "z", "intensity")])).reshape(-1)
            fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7)]
            msg = cloud_message(store, records, fields, stamp_ns=stamp_of(frame), frame="lidar")
            writer.write(clouds, stamp_of(frame), store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
            rows.append(xyzi)
    return rows


@pytest.fixture(scope="module")
def imu_bags(shared_data, tmp_path_factory) -> dict:
    root = shared_data.root
    if not (root / "kitti_seq00" / "velodyne" / "000002.bin").is_file():
        pytest.skip("KITTI frames not found")
    folder = tmp_path_factory.mktemp("imu_bags")
    rows = write_imu_bag(root, folder / "accelerations", with_orientation=False)
    write_imu_bag(root, folder / "orientations", with_orientation=True)
    velodyne = folder / "tilted"
    velodyne.mkdir()
    for frame, xyzi in enumerate(rows):
        xyzi.tofile(velodyne / f"{frame:06d}.bin")
    return {
        "accelerations": folder / "accelerations",
        "orientations": folder / "orientations",
        "tilted": velodyne,
        "truth": tilted_truth(root),
        "root": root,
    }


def test_imu_attitude_of_each_cloud_is_its_true_roll_and_pitch(imu_bags):
    """From the accelerations (IMU on its uptime clock: matched by record times) and from the
    orientations (accelerations misleading), turned into the cloud's frame by the mount."""
    expected = [roll_pitch_zyx(r) for r in imu_bags["truth"]]
    for name, clock, source in (
        ("accelerations", "record", "acceleration"),
        ("orientations", "header", "orientation"),
    ):
        clouds = read_bag(imu_bags[name], "/lidar_points", imu="/imu", imu_window=0.04)
        got = [cloud.attitude for cloud in clouds.clouds()]
        np.testing.assert_allclose(got, expected, atol=1e-9, err_msg=name)
        assert (clouds.imu_clock, clouds.imu_source) == (clock, source)
        # The attitude levels the tilted cloud: leveled, its rotation from the world is a heading.
        for (roll, pitch), world_lidar in zip(got, imu_bags["truth"], strict=True):
            heading = tc.leveling_transform(roll, pitch)[:3, :3] @ world_lidar.T
            np.testing.assert_allclose(heading[2], [0.0, 0.0, 1.0], atol=1e-9)
    assert min(abs(a) for angles in expected for a in angles) > math.radians(3.0)  # a real tilt
    # with_attitude: the pose's position and heading, the given roll and pitch.
    from terracube.bag import with_attitude

    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = (
        rotation("z", 130.0) @ rotation("y", 20.0) @ rotation("x", -9.0),
        [1.0, 2.0, 3.0],
    )
    leveled = with_attitude(pose, 0.1, -0.2)
    np.testing.assert_allclose(roll_pitch_zyx(leveled[:3, :3]), (0.1, -0.2), atol=1e-12)
    np.testing.assert_allclose(leveled[:3, 3], [1.0, 2.0, 3.0])
    assert math.isclose(math.atan2(leveled[1, 0], leveled[0, 0]), math.radians(130.0), abs_tol=1e-12)
    with pytest.raises(ValueError, match="imu_window must be a positive"):
        read_bag(imu_bags["accelerations"], "/lidar_points", imu="/imu", imu_window=0.0)
    with pytest.raises(ValueError, match="IMU topic '/lidar_points' holds sensor_msgs/msg/PointCloud2"):
        read_bag(imu_bags["accelerations"], "/lidar_points", imu="/lidar_points")


def test_imu_window_averages_the_up_directions_near_each_cloud(imu_bags):
    """The default window (+-0.1 s) takes the neighbouring clouds' attitudes too: the attitude is
    the mean of the unit up vectors of the messages within it, written plainly here."""
    truth = imu_bags["truth"]
    clouds = read_bag(imu_bags["accelerations"], "/lidar_points", imu="/imu")
    for frame, cloud in enumerate(clouds.clouds()):
        ups = []
        for k in range(-30, 10 * FRAMES + 20):
            if abs(k * 10_000_000 - (stamp_of(frame) - T0_NS)) <= 100_000_000:
                nearest = min(max(round(k / 10), 0), FRAMES - 1)
                ups.append(truth[nearest].T @ [0.0, 0.0, 1.0])
        up = np.mean(ups, axis=0)
        assert len(ups) == 21
        np.testing.assert_allclose(
            cloud.attitude,
            (math.atan2(up[1], up[2]), math.atan2(-up[0], math.hypot(up[1], up[2]))),
            atol=1e-9,
        )


def test_the_ouster_imu_on_another_clock_is_matched_by_record_times(bags):
    """The real OS1 recording stamps its IMU by the sensor's uptime (1622 s) and its clouds by
    another clock: matched by record times, its gravity (no orientation) turned by /tf_static
    (os1_lidar is os1_sensor turned half round, os1_imu is not turned)."""
    from terracube.bag import _Bag

    path = bags / "ouster_os1_pointcloudset_ros1.mcap"
    clouds = read_bag(path, OUSTER_TOPIC, imu="/os1_cloud_node/imu")
    got = [(cloud.attitude, cloud.frame_id) for cloud in clouds.clouds()]
    assert (clouds.imu_clock, clouds.imu_source) == ("record", "acceleration")
    with _Bag(path) as bag:
        imu = [(record, m.linear_acceleration) for _, _, record, m in bag.messages(["/os1_cloud_node/imu"])]
        cloud_records = [record for _, _, record, _ in bag.messages([OUSTER_TOPIC])]
    for (attitude, frame), record in zip(got, cloud_records, strict=True):
        near = [np.array([a.x, a.y, a.z]) for t, a in imu if abs(t - record) <= 100_000_000]
        up = np.mean([v / np.linalg.norm(v) for v in near], axis=0)
        up = np.array([-up[0], -up[1], up[2]])  # into os1_lidar: half a turn about z
        assert frame == "os1_lidar" and len(near) >= 5
        np.testing.assert_allclose(
            attitude, (math.atan2(up[1], up[2]), math.atan2(-up[0], math.hypot(up[1], up[2]))), atol=1e-9
        )
        assert math.degrees(math.hypot(*attitude)) > 4.0  # the recording's sensor leans by ~5 degrees


def test_dem_map_and_stream_of_a_bag_are_leveled_by_its_imu(cli, imu_bags, tmp_path):
    """A per-scan stage with --imu equals the loose files with --roll/--pitch of the IMU's
    attitude; map and stream --lidar-only with --imu equal the loose files leveled by a pose
    file of those attitudes."""
    from terracube.poses import write_tum_poses

    bag, tilted = imu_bags["accelerations"], imu_bags["tilted"]
    attitudes = [c.attitude for c in read_bag(bag, "/lidar_points", imu="/imu").clouds()]
    result = cli("dem", bag, "--imu", "/imu", "--no-png", "-o", tmp_path / "bag")
    assert result.exit_code == 0, result.output
    assert "IMU /imu: each cloud leveled" in result.output and "record times" in result.output
    for frame, (roll, pitch) in enumerate(attitudes):
        loose = cli(
            "dem", tilted / f"{frame:06d}.bin", "--roll", math.degrees(roll), "--pitch", math.degrees(pitch),
            "--no-png", "-o", tmp_path / "loose",
        )  # fmt: skip
        assert loose.exit_code == 0, loose.output
        expected = tc.ElevationMap.load(tmp_path / "loose" / f"{frame:06d}_dem.npz")
        got = tc.ElevationMap.load(tmp_path / "bag" / f"accelerations_{frame:04d}_dem.npz")
        np.testing.assert_allclose(got.geometry.origin, expected.geometry.origin, atol=1e-9)
        for layer in expected.layers:
            np.testing.assert_allclose(got[layer], expected[layer], atol=1e-5, equal_nan=True, err_msg=layer)
    # map and stream, LiDAR-only: the IMU's attitudes as the poses' rotations.
    levels = [tc.leveling_transform(*attitude) for attitude in attitudes]
    tum = tmp_path / "attitudes_tum.txt"
    write_tum_poses(tum, [stamp_of(f) * 1e-9 for f in range(FRAMES)], levels)
    for command, options, result_file in (
        ("map", ["--keyframe-distance", "0.5", "--no-png"], "global_map.npz"),
        ("stream", ["--length", "12", "--resolution", "0.2", "--no-png"], "local_map.npz"),
    ):
        loose = cli(command, tilted, "--lidar-only", "--poses", tum, "-o", tmp_path / f"l{command}", *options)
        assert loose.exit_code == 0, loose.output
        result = cli(command, bag, "--lidar-only", "--imu", "/imu", "-o", tmp_path / f"b{command}", *options)
        assert result.exit_code == 0, result.output
        assert "IMU /imu: each cloud leveled" in result.output
        expected = tc.ElevationMap.load(tmp_path / f"l{command}" / result_file)
        got = tc.ElevationMap.load(tmp_path / f"b{command}" / result_file)
        np.testing.assert_allclose(got.geometry.origin, expected.geometry.origin, atol=1e-9)
        for layer in set(expected.layers) - {"time"}:
            np.testing.assert_allclose(got[layer], expected[layer], atol=1e-5, equal_nan=True, err_msg=layer)
    # The map's trajectory keeps the IMU's roll and pitch (the true ones to the window's mean).
    trajectory = np.loadtxt(tmp_path / "bmap" / "trajectory_kitti.txt").reshape(-1, 3, 4)
    for pose, world_lidar in zip(trajectory, imu_bags["truth"], strict=True):
        np.testing.assert_allclose(
            roll_pitch_zyx(pose[:, :3]), roll_pitch_zyx(world_lidar), atol=math.radians(0.05)
        )
    # Planar odometry (a wheeled robot's) with the IMU: the odometry's position and heading, the
    # IMU's roll and pitch: the true poses.
    truth_poses = kitti_velodyne_poses(imu_bags["root"])[:FRAMES]
    for imu_options, tilt in (([], 0.0), (["--imu", "/imu"], 1.0)):
        out = tmp_path / f"odom{len(imu_options)}"
        result = cli("map", bag, "--odom", "/odom2d", *imu_options, "--odometry-only", "--no-png", "-o", out)
        assert result.exit_code == 0, result.output
        trajectory = np.loadtxt(out / "trajectory_kitti.txt").reshape(-1, 3, 4)
        np.testing.assert_allclose(trajectory[:, :, 3], truth_poses[:, :3, 3], atol=1e-6)
        for pose, world_lidar in zip(trajectory, imu_bags["truth"], strict=True):
            expected = np.multiply(roll_pitch_zyx(world_lidar), tilt)  # without the IMU: level
            np.testing.assert_allclose(roll_pitch_zyx(pose[:, :3]), expected, atol=math.radians(0.05))
            heading = math.atan2(pose[1, 0], pose[0, 0]) - math.atan2(world_lidar[1, 0], world_lidar[0, 0])
            assert abs(math.remainder(heading, 2 * math.pi)) < 1e-6
    refused = cli("dem", bag, "--imu", "/imu", "--roll", "3", "-o", tmp_path / "x")
    assert refused.exit_code == 2 and "--imu TOPIC or --roll/--pitch" in refused.output
    config = tmp_path / "tilted.yaml"
    config.write_text("frame:\n  pitch_deg: 2.5\n")
    refused = cli("dem", bag, "--imu", "/imu", "--config", config, "-o", tmp_path / "x")
    assert refused.exit_code == 2 and "pitch_deg 2.5 ('frame' section)" in refused.output
    refused = cli("dem", tilted / "000000.bin", "--imu", "/imu", "-o", tmp_path / "x")
    assert refused.exit_code == 2 and "--imu: only for a bag input" in refused.output


def test_an_unusable_imu_topic_stops_with_the_reason(imu_bags, tmp_path):
    """Accelerations that are zero or NaN, up directions that contradict each other, an IMU frame
    the TF tree does not know, an IMU whose stamps and record times both lie elsewhere, and one
    that stops before a cloud: each a ValueError naming the topic and the problem."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    level = np.eye(3)
    cases = {  # name: IMU attitudes every 10 ms from the offset, clouds at these offsets [s]
        "zero": ([0.0 * level] * 4, 0, [0]),
        "flipped": ([level, rotation("x", 180.0)] * 2, 0, [0]),  # up and down in turn: no attitude
        "unknown_frame": ([level] * 4, 0, [0]),
        "elsewhere": ([level] * 4, 100, [0]),
        "stopped": ([level] * 4, 0, [0, 1]),
    }
    for name, (attitudes, offset, cloud_offsets) in cases.items():
        path = tmp_path / name
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            clouds = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=store)
            imu = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
            for k, attitude in enumerate(attitudes):
                stamp = T0_NS + offset * 10**9 + k * 10_000_000
                msg = imu_message(store, stamp, attitude, with_orientation=False)
                if name == "zero":
                    msg.linear_acceleration.z = 0.0 if k % 2 else float("nan")
                if name != "unknown_frame":
                    msg.header.frame_id = "lidar"
                writer.write(imu, stamp, store.serialize_cdr(msg, "sensor_msgs/msg/Imu"))
            records = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
            for cloud_offset in cloud_offsets:
                stamp = T0_NS + cloud_offset * 10**9
                msg = cloud_message(
                    store, records, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], stamp_ns=stamp, frame="lidar"
                )
                writer.write(clouds, stamp, store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
        expected = {
            "zero": "the IMU topic /imu holds no usable message",
            "flipped": "up directions of its 4 messages within 0.1 s of the cloud disagree",
            "unknown_frame": "no transform from the IMU frame 'imu': frame 'lidar' is not in the TF tree",
            "elsewhere": "the IMU topic /imu does not cover the cloud at 1600000000.000000000 s",
            "stopped": "/imu has no message within 0.1 s of the cloud at 1600000001.000000000 s",
        }[name]
        with pytest.raises(ValueError, match=re.escape(expected)):
            list(read_bag(path, "/points", imu="/imu").clouds())


def test_a_long_range_forward_sensor_is_told_to_widen_the_local_map_and_then_registers(cli, bags, tmp_path):
    """The Luminar truck recording sees nothing within 13 m of the sensor and most returns beyond
    50 m: the default 40 m local map holds too little of each scan for registration. The map
    command says so, for a bag and for loose files, and the settings it suggests register every
    cloud at a steady speed (10 Hz clouds of a truck on a highway; the bag has no odometry)."""
    bag = bags / "luminar_embag.bag"
    loose = tmp_path / "clouds"
    loose.mkdir()
    for index, cloud in enumerate(read_bag(bag, LUMINAR_TOPIC).clouds()):
        np.save(loose / f"{index:04d}.npy", cloud.points)
    pattern = (
        r"warning: the median return lies (\d+) m .* "
        r"set mapper\.local_map_size (\S+) and mapper\.resolution (\S+)"
    )
    suggested = set()
    for source in (bag, loose):
        result = cli("map", source, "--lidar-only", "--no-png", "-o", tmp_path / "default")
        assert result.exit_code == 0, result.output
        found = re.search(pattern, result.output)
        assert found and 40 < int(found[1]) < 70, result.output
        suggested.add(found.groups())
    ((reach, size, resolution),) = suggested
    # The LiDAR-only poses of stream come from the same mapper: the same warning.
    result = cli("stream", bag, "--lidar-only", "--no-png", "-o", tmp_path / "stream")
    assert result.exit_code == 0, result.output
    assert re.search(pattern, result.output).groups() == (reach, size, resolution), result.output
    config = tmp_path / "long_range.yaml"
    config.write_text(f"mapper:\n  local_map_size: {size}\n  resolution: {resolution}\n")
    result = cli("map", bag, "--lidar-only", "-c", config, "--no-png", "-o", tmp_path / "long")
    assert result.exit_code == 0, result.output
    assert "4 of 4 scans registered" in result.output and "warning" not in result.output
    positions = np.loadtxt(tmp_path / "long" / "trajectory_kitti.txt").reshape(-1, 3, 4)[:, :, 3]
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert 2.0 < np.median(steps) < 2.8  # 72-100 km/h
    np.testing.assert_allclose(steps, np.median(steps), rtol=0.02)


def test_a_sparse_cloud_of_a_cars_lidar_in_a_bag_gets_no_airborne_hint(bags, tmp_path):
    """The Luminar's road scan reaches 252 m: a 0.1 m map is mostly empty, and the fill warning says
    so, but a car's forward-looking sensor frame is no airborne tile (--preset airborne_las)."""
    from terracube.pipeline import run_stage

    cloud = next(iter(read_bag(bags / "luminar_embag.bag", LUMINAR_TOPIC).clouds()))
    report = run_stage("dem", cloud.points, "luminar", tmp_path, png=False)
    fill = [line for line in report.lines if "cells hold data" in line]
    assert len(fill) == 1 and "airborne" not in fill[0], report.lines
