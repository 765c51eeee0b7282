"""Synthetic LiDAR sequences (terracube.simulation) against analytic answers and numpy references.

Single rays against hand-computed distances; whole scans of boxes and cylinders against a
vectorised numpy ray caster written here; sensor geometry from the parameters; noise statistics;
trajectories (loop closure, spacing, mount height, exact odometry, drift); the library's
collapsible cubes on a tunnel scan; bad input.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import terracube as tc
from terracube import _core
from terracube.simulation import (
    OVERHANG_LABELS,
    Label,
    LoopSceneParams,
    Primitive,
    RotatingLidar,
    SyntheticSequence,
    Tilting2DScanner,
    TrajectoryParams,
    cast_scan,
    generate_sequence,
    generate_trajectory,
    make_loop_scene,
    make_scene,
    sensor_rays,
)


def pose(x=0.0, y=0.0, z=0.0, yaw=0.0, pitch=0.0, roll=0.0) -> np.ndarray:
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    t = np.eye(4)
    t[:3, :3] = rz @ ry @ rx
    t[:3, 3] = (x, y, z)
    return t


def yaw_of(t: np.ndarray) -> float:
    return math.atan2(t[1, 0], t[0, 0])


# --- single rays ---------------------------------------------------------------------------------


def test_labels_mirror_the_core_enum():
    assert [name.lower() for name in Label.__members__] == list(_core.simulation.label_names)


def test_ray_down_onto_flat_ground_and_to_a_wall():
    world = make_scene([Primitive.box((10.0, 0.0, 2.0), (0.5, 8.0, 2.0), 0.0, Label.WALL)], base_height=1.5)
    r, label, index = world.intersect((3.0, 4.0, 10.0), (0, 0, -1))
    assert r == pytest.approx(8.5, abs=1e-9) and label == Label.GROUND and index == -1
    r, label, index = world.intersect((0, 0, 2.0), (1, 0, 0))
    assert r == pytest.approx(9.5, abs=1e-9) and label == Label.WALL and index == 0
    # 30 degrees off the wall's normal: 9.5 / cos(30 deg).
    r, _, _ = world.intersect((0, 0, 2.0), (math.cos(math.pi / 6), math.sin(math.pi / 6), 0))
    assert r == pytest.approx(9.5 / math.cos(math.pi / 6), abs=1e-9)


def test_cylinder_and_ellipsoid_distances():
    world = make_scene(
        [
            Primitive.cylinder(5.0, 0.0, 0.5, 0.0, 3.0, Label.TRUNK),
            Primitive.ellipsoid((0.0, 0.0, 10.0), (2.0, 3.0, 1.0), Label.CANOPY),
        ],
        base_height=-1.0,
    )
    assert world.intersect((0, 0.3, 1.0), (1, 0, 0))[0] == pytest.approx(
        5.0 - math.sqrt(0.25 - 0.09), abs=1e-9
    )
    assert world.intersect((5.0, 0.2, 10.0), (0, 0, -1))[0] == pytest.approx(7.0, abs=1e-9)  # top cap
    assert world.intersect((0, 0, 0), (0, 0, 1))[:2] == (pytest.approx(9.0, abs=1e-9), Label.CANOPY)
    # (x/2)^2 + (1/3)^2 = 1 on the line y = 1, z = 10 coming from x = -10.
    assert world.intersect((-10, 1, 10), (1, 0, 0))[0] == pytest.approx(10 - 2 * math.sqrt(8 / 9), abs=1e-9)


def test_slope_intersection_matches_the_plane():
    ramp = dict(
        center=(0, 0),
        heading=0.0,
        height=3.0,
        ramp_length=15.0,
        plateau_length=6.0,
        half_width=100.0,
        side_falloff=10.0,
    )
    world = make_scene([], ramps=[ramp])
    # Rising part x in [-18, -3]: z = 0.2 (x + 18).
    assert world.terrain_height(np.array([-10.0, 0.0, 10.0]), np.zeros(3)) == pytest.approx([1.6, 3.0, 1.6])
    origin = np.array([-15.0, 1.0, 5.0])
    for d in ([1, 0, -1], [1, 0.3, -0.6], [0, 0, -1]):
        d = np.asarray(d, float) / np.linalg.norm(d)
        expected = (origin[2] - 0.2 * (origin[0] + 18)) / (0.2 * d[0] - d[2])
        assert world.intersect(origin, d)[0] == pytest.approx(expected, abs=1e-7)


def test_ray_under_the_bridge_meets_the_ground_beyond_and_nearest_wins():
    deck = Primitive.box((20, 0, 5.4), (3, 10, 0.4), 0.0, Label.BRIDGE_DECK)
    inner = Primitive.box((19, 0, 5.4), (1, 1, 0.2), 0.0, Label.WALL)  # inside the deck: never first
    world = make_scene([inner, deck])
    r, label, _ = world.intersect((0, 0, 1), (1, 0, -0.02))
    assert label == Label.GROUND and r == pytest.approx(50 * math.sqrt(1 + 0.02**2), abs=1e-7)
    r, label, index = world.intersect((0, 0, 1), (1, 0, 0.25))
    assert (
        label == Label.BRIDGE_DECK
        and index == 1
        and r == pytest.approx(17 * math.sqrt(1 + 0.25**2), abs=1e-9)
    )


# --- whole scans against a numpy ray caster ---------------------------------------------------------


def numpy_cast(origin, directions, boxes, cylinders, ground_z, max_range):
    """Nearest of: yaw-rotated boxes (slabs), vertical cylinders (side + caps), the plane z = ground_z."""
    n = len(directions)
    best = np.full(n, np.inf)
    label = np.zeros(n, np.uint8)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ground_z - origin[2]) / directions[:, 2]
        t[~(t > 1e-9)] = np.inf
        best = t.copy()
        for centre, half, yaw, lab in boxes:
            c, s = math.cos(yaw), math.sin(yaw)
            rot = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
            q = rot @ (origin - centre)
            d = directions @ rot.T
            t0 = (-np.asarray(half) - q) / d
            t1 = (np.asarray(half) - q) / d
            near = np.nanmax(np.minimum(t0, t1), axis=1)
            far = np.nanmin(np.maximum(t0, t1), axis=1)
            t = np.where(
                (near <= far) & (near > 1e-9), near, np.where((near <= far) & (far > 1e-9), far, np.inf)
            )
            closer = t < best
            best[closer], label[closer] = t[closer], lab
        for (x, y, r, z0, z1), lab in cylinders:
            qx, qy = origin[0] - x, origin[1] - y
            a = directions[:, 0] ** 2 + directions[:, 1] ** 2
            b = 2 * (qx * directions[:, 0] + qy * directions[:, 1])
            cc = qx * qx + qy * qy - r * r
            disc = b * b - 4 * a * cc
            t = np.full(n, np.inf)
            for sign in (-1, 1):
                root = (-b + sign * np.sqrt(disc)) / (2 * a)
                z = origin[2] + root * directions[:, 2]
                ok = (disc >= 0) & (root > 1e-9) & (z >= z0) & (z <= z1)
                t = np.where(ok & (root < t), root, t)
            for zc in (z0, z1):
                root = (zc - origin[2]) / directions[:, 2]
                px, py = qx + root * directions[:, 0], qy + root * directions[:, 1]
                ok = (root > 1e-9) & (px * px + py * py <= r * r)
                t = np.where(ok & (root < t), root, t)
            closer = t < best
            best[closer], label[closer] = t[closer], lab
    best[best > max_range] = np.inf
    return best, label


def test_scan_matches_a_numpy_ray_caster():
    rng = np.random.default_rng(4)
    boxes, cylinders, primitives = [], [], []
    for _ in range(60):
        centre = np.array([*rng.uniform(-40, 40, 2), rng.uniform(0, 3)])
        half = rng.uniform(0.2, 4, 3)
        yaw = rng.uniform(-np.pi, np.pi)
        lab = int(rng.choice([Label.WALL, Label.BUILDING, Label.BRIDGE_DECK]))
        boxes.append((centre, half, yaw, lab))
        primitives.append(Primitive.box(centre, half, yaw, lab))
    for _ in range(40):
        x, y = rng.uniform(-40, 40, 2)
        r, z0 = rng.uniform(0.1, 1.0), rng.uniform(-1, 1)
        z1 = z0 + rng.uniform(1, 6)
        cylinders.append(((x, y, r, z0, z1), int(Label.TRUNK)))
        primitives.append(Primitive.cylinder(x, y, r, z0, z1, Label.TRUNK))
    world = make_scene(primitives, base_height=-1.2, grid_cell=3.0)
    lidar = RotatingLidar(channels=32, steps_per_revolution=512, range_noise_sigma=0.0, max_range=60.0)
    t = pose(1.0, -2.0, 0.5, yaw=0.3, pitch=0.02, roll=-0.01)
    scan = cast_scan(world, t, lidar)
    rays = sensor_rays(lidar)
    best, label = numpy_cast(t[:3, 3], rays @ t[:3, :3].T, boxes, cylinders, -1.2, 60.0)
    hit = np.flatnonzero(np.isfinite(best) & (best >= lidar.min_range))
    np.testing.assert_array_equal(scan.ray_indices, hit)
    np.testing.assert_allclose(scan.points, rays[hit] * best[hit, None], atol=2e-5)
    np.testing.assert_array_equal(scan.labels, label[hit])
    assert len(hit) > 10000


# --- sensors -------------------------------------------------------------------------------------


def test_rotating_lidar_rays_and_elevations():
    lidar = RotatingLidar(channels=16, vertical_fov_min=-15, vertical_fov_max=15, steps_per_revolution=360)
    rays = sensor_rays(lidar).reshape(360, 16, 3)
    elevation = np.degrees(np.arctan2(rays[..., 2], np.hypot(rays[..., 0], rays[..., 1])))
    np.testing.assert_allclose(elevation, np.broadcast_to(np.linspace(-15, 15, 16), (360, 16)), atol=1e-9)
    azimuth = np.degrees(np.arctan2(rays[..., 1], rays[..., 0])) % 360
    np.testing.assert_allclose(np.abs(((azimuth - np.arange(360)[:, None]) + 180) % 360 - 180), 0, atol=1e-9)


def test_tilting_scanner_lines():
    scanner = Tilting2DScanner(beams_per_line=91, horizontal_fov=180, tilt_from=-20, tilt_to=20, lines=5)
    rays = sensor_rays(scanner).reshape(5, 91, 3)
    for line, tilt in enumerate(np.radians(np.linspace(-20, 20, 5))):
        normal = np.array([-np.sin(tilt), 0, np.cos(tilt)])
        np.testing.assert_allclose(rays[line] @ normal, 0, atol=1e-12)
        np.testing.assert_allclose(rays[line, 45], [np.cos(tilt), 0, np.sin(tilt)], atol=1e-12)
    # In a closed room every ray of either sensor returns.
    room = make_scene([Primitive.box((0, 0, 1), (6, 5, 4), 0.3, Label.BUILDING)], base_height=-2)
    assert len(cast_scan(room, pose(1, 1), scanner).points) == 5 * 91
    assert len(cast_scan(room, pose(1, 1), RotatingLidar(channels=8, steps_per_revolution=90)).points) == 720


def test_range_noise_statistics_and_seeds():
    bubble = make_scene([Primitive.ellipsoid((0, 0, 0), (20, 20, 20), Label.BUILDING)], base_height=-100)
    lidar = RotatingLidar(range_noise_sigma=0.05)
    scan = cast_scan(bubble, np.eye(4), lidar, seed=3)
    error = np.linalg.norm(scan.points.astype(np.float64), axis=1) - 20.0
    assert len(error) == 64 * 1024
    assert abs(error.mean()) < 4 * 0.05 / math.sqrt(len(error))
    assert error.std() == pytest.approx(0.05, rel=0.02)
    again, other = cast_scan(bubble, np.eye(4), lidar, seed=3), cast_scan(bubble, np.eye(4), lidar, seed=4)
    np.testing.assert_array_equal(again.points, scan.points)
    assert not np.array_equal(other.points, scan.points)
    assert scan.points.dtype == np.float32 and scan.labels.dtype == np.uint8


# --- trajectories ----------------------------------------------------------------------------------


def test_loop_closes_with_spacing_and_mount_height():
    world = make_loop_scene()
    length = 2 * (60 + 30) + 2 * math.pi * 10
    assert world.road.length == pytest.approx(length)
    traj = generate_trajectory(world, TrajectoryParams(laps=2))
    assert len(traj.poses) == math.floor(2 * length / 0.5) + 1
    xyz = traj.poses[:, :3, 3]
    assert 0 < np.linalg.norm(xyz[-1] - xyz[0]) <= 0.5 + 1e-9
    chords = np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1)
    assert chords.max() <= 0.5 + 1e-9 and chords.min() >= 20 * math.sin(0.025) - 1e-9
    np.testing.assert_allclose(xyz[:, 2] - world.terrain_height(xyz[:, 0], xyz[:, 1]), 0.8, atol=1e-12)
    np.testing.assert_allclose(
        traj.poses[:, :3, :3].transpose(0, 2, 1) @ traj.poses[:, :3, :3],
        np.broadcast_to(np.eye(3), (len(xyz), 3, 3)),
        atol=1e-12,
    )


def test_pitch_follows_the_ramp_and_exact_odometry_is_the_truth():
    world = make_loop_scene()
    traj = generate_trajectory(world, TrajectoryParams.exact())
    np.testing.assert_allclose(traj.odometry, traj.poses, atol=1e-9)
    xyz = traj.poses[:, :3, 3]
    rising = (traj.arc_length < 60) & (xyz[:, 0] > -15.5) & (xyz[:, 0] < -4.5)
    pitch = np.arcsin(-traj.poses[:, 2, 0])
    np.testing.assert_allclose(pitch[rising], -math.atan(2 / 12), atol=1e-12)
    assert rising.sum() > 20


def test_odometry_drift_grows_as_parameterised():
    world = make_loop_scene(path="straight")
    traj = generate_trajectory(world, TrajectoryParams.exact(translation_scale_error=0.03))
    xyz, odo = traj.poses[:, :3, 3], traj.odometry[:, :3, 3]
    np.testing.assert_allclose(
        np.linalg.norm(odo - xyz, axis=1), 0.03 * np.linalg.norm(xyz - xyz[0], axis=1), atol=1e-9
    )
    traj = generate_trajectory(world, TrajectoryParams.exact(yaw_bias=2e-3))
    travelled = np.concatenate(
        [[0], np.cumsum(np.linalg.norm(np.diff(traj.poses[:, :3, 3], axis=0), axis=1))]
    )
    error = np.array([yaw_of(o) - yaw_of(p) for o, p in zip(traj.odometry, traj.poses, strict=True)])
    np.testing.assert_allclose(np.remainder(error + np.pi, 2 * np.pi) - np.pi, 2e-3 * travelled, atol=1e-9)
    # Default drift: seeded, and the position error grows with distance.
    a = generate_trajectory(world, TrajectoryParams(seed=5))
    b = generate_trajectory(world, TrajectoryParams(seed=5))
    np.testing.assert_array_equal(a.odometry, b.odometry)
    drift = np.linalg.norm(a.odometry[:, :3, 3] - a.poses[:, :3, 3], axis=1)
    assert drift[0] == 0 and drift[-1] > drift[len(drift) // 4] > 0


# --- sequences and the library on simulated scans -----------------------------------------------------


def test_sequence_casts_scans_on_demand():
    lidar = RotatingLidar(channels=8, steps_per_revolution=128)
    sequence = generate_sequence(
        LoopSceneParams(path="straight", straight_length=20.0),
        TrajectoryParams(scan_spacing=5.0),
        lidar,
        seed=2,
    )
    assert len(sequence) == 5 and sequence.poses.shape == (5, 4, 4) and sequence.odometry.shape == (5, 4, 4)
    scans = list(sequence)
    assert len(scans) == 5
    np.testing.assert_array_equal(scans[3].points, sequence.scan(3).points)
    np.testing.assert_array_equal(sequence[-1].points, scans[4].points)
    with pytest.raises(IndexError):
        sequence.scan(5)
    exact = SyntheticSequence(
        sequence.world,
        RotatingLidar(channels=8, steps_per_revolution=128, range_noise_sigma=0),
        TrajectoryParams(scan_spacing=5.0),
    )
    np.testing.assert_array_equal(
        exact.scan(2).points, cast_scan(sequence.world, exact.poses[2], exact.sensor).points
    )
    assert "5 scans" in repr(sequence)


def test_primitives_list_the_scene():
    world = make_loop_scene()
    primitives = world.primitives()
    labels = {p.label for p in primitives}
    assert {
        Label.WALL,
        Label.BUILDING,
        Label.TRUNK,
        Label.CANOPY,
        Label.TUNNEL_WALL,
        Label.TUNNEL_CEILING,
        Label.BRIDGE_DECK,
        Label.PILLAR,
    } <= labels
    canopies = [p for p in primitives if p.label == Label.CANOPY]
    bottoms = np.array(
        [p.center[2] - p.half_extents[2] - world.terrain_height(p.center[0], p.center[1]) for p in canopies]
    )
    np.testing.assert_allclose(bottoms, 3.2, atol=1e-9)  # above the robot: overhangs


def test_collapsible_cubes_remove_the_tunnel_ceiling():
    world = make_loop_scene()
    traj = generate_trajectory(world, TrajectoryParams.exact())
    k = int(np.argmin(np.linalg.norm(traj.poses[:, :2, 3] - [40.0, 0.0], axis=1)))
    lidar = RotatingLidar(channels=128, vertical_fov_min=-45, vertical_fov_max=45)
    scan = cast_scan(world, traj.poses[k], lidar, seed=1)
    r = traj.poses[k][:3, :3]
    level = tc.leveling_transform(math.atan2(r[2, 1], r[2, 2]), math.asin(-r[2, 0]))
    result = tc.collapse_overhangs(
        scan.points,
        0.5,
        tc.sigma_from_robot_height(1.2, 0.5),
        transform=level,
        crop=((-12, -12, -5), (12, 12, 15)),
    )
    leveled = scan.points.astype(np.float64) @ level[:3, :3].T
    inside = np.all(np.abs(leveled[:, :2]) <= 12, axis=1)
    overhang = np.isin(scan.labels, [int(label) for label in OVERHANG_LABELS]) & inside
    other = ~np.isin(scan.labels, [int(label) for label in OVERHANG_LABELS]) & inside
    assert (scan.labels[inside] == Label.TUNNEL_CEILING).sum() > 5000
    removed = result.overhang[overhang].mean()
    kept = 1 - result.overhang[other].mean()
    assert removed > 0.7, removed  # measured 0.77: the rest lies over columns without ground returns
    assert kept > 0.995, kept


# --- bad input -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("model", "message"),
    [
        (RotatingLidar(channels=0), "channels"),
        (RotatingLidar(steps_per_revolution=-1), "steps_per_revolution"),
        (RotatingLidar(max_range=0.0), "max_range_m"),
        (RotatingLidar(min_range=-0.5), "min_range_m"),
        (RotatingLidar(min_range=10.0, max_range=5.0), "below max_range_m"),
        (RotatingLidar(range_noise_sigma=float("nan")), "range_noise_sigma_m"),
        (RotatingLidar(vertical_fov_min=10, vertical_fov_max=-10), "vertical_fov"),
        (Tilting2DScanner(lines=0), "lines"),
        (Tilting2DScanner(beams_per_line=0), "beams_per_line"),
        (Tilting2DScanner(tilt_from=-100), "tilt_from_deg"),
    ],
)
def test_bad_sensor_parameters_raise(model, message):
    world = make_scene([])
    with pytest.raises(ValueError, match=message):
        cast_scan(world, np.eye(4), model)


def test_bad_poses_and_parameters_raise():
    world = make_scene([])
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        cast_scan(world, bad, RotatingLidar())
    with pytest.raises(ValueError, match="rigid"):
        cast_scan(world, np.diag([1.0, 1.2, 1.0, 1.0]), RotatingLidar())
    with pytest.raises(ValueError, match="shape"):
        cast_scan(world, np.eye(3), RotatingLidar())
    with pytest.raises(ValueError, match="whole number"):
        cast_scan(world, np.eye(4), RotatingLidar(channels=2.5))
    with pytest.raises(TypeError, match="RotatingLidar"):
        cast_scan(world, np.eye(4), "velodyne")
    with pytest.raises(ValueError, match="path"):
        make_loop_scene(path="circle")
    with pytest.raises(ValueError, match="corner_radius"):
        make_loop_scene(loop_length=15.0)
    with pytest.raises(ValueError, match="scan_spacing_m"):
        generate_trajectory(make_loop_scene(), TrajectoryParams(scan_spacing=0.0))
    with pytest.raises(ValueError, match="half extents"):
        make_scene([Primitive.box((0, 0, 0), (1, 0, 1), 0.0, Label.WALL)])
