"""terracube.LocalMap: numpy views, a numpy reference of one scan's fusion, moves, bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import terracube


def pose_at(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[:3, 3] = (x, y, z)
    return pose


def gentle_ground(seed: int = 3, n: int = 20000, half: float = 4.0) -> np.ndarray:
    """Points of a smooth surface in the odometry frame (no overhangs, nothing seen through)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-half, half, size=(n, 2))
    z = 0.05 * np.sin(xy[:, 0]) + 0.03 * xy[:, 1] + rng.normal(0.0, 0.01, n)
    return np.column_stack([xy, z])


def test_layers_are_read_only_views_that_follow_the_updates():
    m = terracube.LocalMap(length=4.0, resolution=0.1)
    elevation = m["elevation"]
    assert elevation.shape == (40, 40) and elevation.dtype == np.float32
    assert np.isnan(elevation).all()
    assert not elevation.flags.writeable
    sensor = pose_at(0.3, -0.2, 1.0)
    points = gentle_ground() - sensor[:3, 3]
    report = m.update(points, sensor)
    assert report.num_fused_cells > 1000
    assert np.shares_memory(elevation, m["elevation"])  # the same buffer, no copy
    stamped = terracube.LocalMap(length=4.0)
    stamped.update(points, sensor, stamp=1.7e9 + 0.25)  # ROS stamps: "time" keeps their milliseconds
    stamped.update(points[:5000], sensor, stamp=1.7e9 + 0.375)
    assert stamped.time_origin == 1.7e9 + 0.25
    assert set(np.unique(stamped["time"][np.isfinite(stamped["time"])])) == {0.0, 0.125}
    assert np.isfinite(elevation).sum() == report.num_fused_cells
    with pytest.raises(KeyError, match="no layer 'nope'"):
        m["nope"]
    for name in ("variance", "clearance", "traversability", "max", "std_dev", "discontinuity"):
        assert name in m.layers


def test_one_scan_matches_a_numpy_binning_of_its_points():
    m = terracube.LocalMap(length=6.0, resolution=0.1, range_sigma=0.02, angle_sigma=0.001, cell_sigma=0.004)
    sensor = pose_at(0.25, 0.05, 1.0, yaw=0.4)
    world = gentle_ground()
    # Into the sensor frame: p_sensor = R^T (p - t).
    points = (world - sensor[:3, 3]) @ sensor[:3, :3]
    m.update(points.astype(np.float64), sensor)
    res = 0.1
    cells = np.floor(world[:, :2] / res).astype(np.int64)
    origin = np.floor(sensor[:2, 3] / res).astype(np.int64) - 30
    inside = np.all((cells >= origin) & (cells < origin + 60), axis=1)
    v = world - sensor[:3, 3]
    horizontal = (v[:, :2] ** 2).sum(axis=1)
    var_z = 0.02**2 * v[:, 2] ** 2 / (horizontal + v[:, 2] ** 2) + 0.001**2 * horizontal
    checked = 0
    keys = cells[inside]
    order = np.lexsort((keys[:, 1], keys[:, 0]))
    keys, z, var = keys[order], world[inside][order, 2], var_z[inside][order]
    starts = np.flatnonzero(np.r_[True, np.any(np.diff(keys, axis=0) != 0, axis=1)])
    for begin, end in zip(starts, np.r_[starts[1:], len(keys)], strict=True):
        gx, gy = keys[begin]
        index = m.index_of(((gx + 0.5) * res, (gy + 0.5) * res))
        heights = z[begin:end]
        n = len(heights)
        expected_variance = (var[begin:end].mean() + heights.var()) / n + 0.004**2
        assert m["elevation"][index] == pytest.approx(heights.mean(), abs=1e-5)
        assert m["variance"][index] == pytest.approx(expected_variance, rel=1e-4)
        assert m["count"][index] == n
        assert m["max"][index] == pytest.approx(heights.max(), abs=1e-6)
        assert m["std_dev"][index] == pytest.approx(heights.std(), abs=1e-5)
        checked += 1
    assert checked > 3000
    assert np.isfinite(m["elevation"]).sum() == checked


def test_float32_and_float64_scans_give_the_same_map_and_index_round_trips():
    sensor = pose_at(1.0, 2.0, 1.0)
    points = gentle_ground() - sensor[:3, 3]
    maps = []
    for dtype in (np.float64, np.float32):
        m = terracube.LocalMap(length=4.0)
        wide = np.column_stack([points, np.ones(len(points))]).astype(dtype)  # x, y, z, intensity
        m.update(wide if dtype == np.float32 else points.astype(dtype), sensor)
        maps.append(m)
    assert np.isfinite(maps[0]["elevation"]).sum() > 1000
    np.testing.assert_allclose(maps[0]["elevation"], maps[1]["elevation"], atol=1e-5, equal_nan=True)
    m = maps[0]
    index = m.index_of((1.23, 2.46))
    assert m.position_of(index) == pytest.approx((1.25, 2.45))
    assert m.index_of((100.0, 0.0)) is None
    ordered = m.to_elevation_map()
    assert ordered.geometry.origin == pytest.approx((-1.0, 0.0))
    i, j = ordered.geometry.index_of(1.25, 2.45)
    assert ordered["elevation"][i, j] == m["elevation"][index]
    classes = terracube.classify_terrain(ordered, reference="local_ground")
    assert (classes == terracube.TerrainClass.GROUND).sum() > 1000


def test_moving_drops_what_leaves_and_keeps_the_rest_in_place():
    m = terracube.LocalMap(length=4.0, compute_planner_layers=False)
    sensor = pose_at(0.0, 0.0, 1.0)
    m.update(gentle_ground() - sensor[:3, 3], sensor)
    before = m.to_elevation_map()["elevation"].copy()
    assert m.move_to((0.5, -0.3)) is False
    after = m.to_elevation_map()["elevation"]
    # The map moved 5 cells along +x and 3 along -y: kept cells shift by those amounts.
    np.testing.assert_array_equal(after[:35, 3:], before[5:, :37])
    assert np.isnan(after[35:, :]).all() and np.isnan(after[:, :3]).all()
    assert m.move_to((50.0, 0.0)) is True
    assert np.isnan(m["elevation"]).all()


def test_bad_input_is_refused_and_leaves_the_map_unchanged():
    m = terracube.LocalMap(length=4.0)
    sensor = pose_at(0.0, 0.0, 1.0)
    points = gentle_ground() - sensor[:3, 3]
    m.update(points, sensor)
    before = {name: m[name].copy() for name in m.layers}
    bad_poses = {
        "4x4": np.eye(3),
        "NaN or Inf": pose_at(math.nan, 0.0, 1.0),
        "rigid": np.diag([2.0, 1.0, 1.0, 1.0]),
    }
    for message, pose in bad_poses.items():
        with pytest.raises(ValueError, match=message):
            m.update(points, pose)
    nan_rows = points.copy()
    nan_rows[5, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        m.update(nan_rows, sensor)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        m.update(points[:, :2], sensor)
    with pytest.raises(ValueError, match="stamp"):
        m.update(points, sensor, stamp=math.inf)
    with pytest.raises(ValueError, match="length_m"):
        terracube.LocalMap(length=-1.0)
    # A map too large for memory is refused with its size, before anything is allocated.
    with pytest.raises(ValueError, match=r"10000 x 10000 cells \(about 7200 MB\), over max_cells = 16777216"):
        terracube.LocalMap(length=1e4, resolution=1.0)
    with pytest.raises(ValueError, match="max_cells = 100"):
        terracube.LocalMap(length=2.0, max_cells=100)
    assert terracube.LocalMap(length=2.0, max_cells=400).geometry.size.tolist() == [20, 20]
    with pytest.raises(ValueError, match="clearing_depth_m must exceed"):
        terracube.LocalMap(clearing_depth=0.05)
    with pytest.raises(ValueError, match="max_slope"):
        terracube.LocalMap(traversability=terracube.TraversabilityParams(max_slope=0.0))
    for name, layer in before.items():
        np.testing.assert_array_equal(layer, m[name], err_msg=name)
    # An empty scan only moves the map.
    report = m.update(np.empty((0, 3)), pose_at(0.2, 0.0, 1.0))
    assert report.num_fused_cells == 0 and not report.map_reset
    assert "LocalMap(length=4.0" in repr(m)


def test_position_of_refuses_a_cell_index_that_is_not_a_whole_number():
    m = terracube.LocalMap(length=4.0)
    assert m.position_of((1, 2)) == pytest.approx(m.position_of(np.array([1, 2])))
    for index in ((1.5, 2.0), (1, 2.0), (True, 2), ("1", 2)):
        with pytest.raises(TypeError, match=r"index must be two whole cell numbers \(i, j\)"):
            m.position_of(index)
    with pytest.raises(ValueError, match=r"index must be two whole cell numbers \(i, j\), got 3 values"):
        m.position_of((1, 2, 3))


def _drive(count: int, consumed: list[str] | None = None):
    """``count`` scans of gentle ground, the sensor 0.2 m further along x each time."""
    for k in range(count):
        sensor = pose_at(0.2 * k, 0.0, 1.0)
        if consumed is not None:
            consumed.append(f"scan{k}")
        yield f"scans/scan{k}.npy", gentle_ground(seed=k, n=4000) - sensor[:3, 3], sensor, float(k)


@pytest.mark.parametrize("target", ["ffmpeg", "a file as folder", "proc"])
def test_a_bad_animation_target_is_refused_before_the_first_scan_with_nothing_written(
    tmp_path, monkeypatch, target
):
    import gc
    import warnings

    from matplotlib import animation
    from terracube.stream import run_stream

    if target == "ffmpeg":
        monkeypatch.setattr(animation.FFMpegWriter, "isAvailable", classmethod(lambda cls: False))
        movie, match = tmp_path / "a.mp4", "an .mp4 needs ffmpeg on the PATH"
    elif target == "a file as folder":
        (tmp_path / "file").write_text("")
        movie, match = tmp_path / "file" / "a.gif", "is not a folder"
    else:
        if not Path("/proc").is_dir():
            pytest.skip("no /proc")
        movie, match = Path("/proc/nope/a.gif"), "cannot write in /proc"
    consumed: list[str] = []
    out = tmp_path / "out"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(ValueError, match=match):
            run_stream(_drive(3, consumed), out, terracube.LocalMapParams(length=4.0), animation=movie)
        gc.collect()  # matplotlib warns of an animation never saved when it is collected
    assert consumed == []
    assert not out.exists() or list(out.iterdir()) == []
    assert not movie.exists()
    assert [str(w.message) for w in caught] == []


def test_stream_command_checks_the_animation_before_reading_a_scan(shared_data, tmp_path, monkeypatch):
    from matplotlib import animation
    from terracube.cli import app
    from typer.testing import CliRunner

    monkeypatch.setattr(animation.FFMpegWriter, "isAvailable", classmethod(lambda cls: False))
    kitti = shared_data.root / "kitti_seq00"
    (tmp_path / "file").write_text("")
    out = tmp_path / "stream"
    args = ["stream", str(kitti / "velodyne"), "--poses", str(kitti / "poses.txt"), "-o", str(out)]
    for movie, message in (
        (tmp_path / "a.mp4", "error: stream: a.mp4: an .mp4 needs ffmpeg on the PATH"),
        (tmp_path / "file" / "a.gif", "is not a folder"),
    ):
        result = CliRunner().invoke(app, [*args, "--animation", str(movie)])
        assert result.exit_code == 2, result.output
        assert message in result.output.replace("\n", "")
        assert "streaming" not in result.output and "Animation was deleted" not in result.output
        assert not out.exists()
    result = CliRunner().invoke(app, [*args, "--every", "-1"])  # refused as it is parsed, nothing read
    assert result.exit_code == 2, result.output
    assert "--every" in result.output and "calib" not in result.output
    assert not out.exists()


@pytest.mark.parametrize(
    ("count", "every", "published"), [(7, 2, [1, 3, 5, 6]), (6, 2, [1, 3, 5]), (3, 0, [0, 1, 2])]
)
def test_on_update_also_gets_the_final_map_once(tmp_path, count, every, published):
    from terracube.stream import run_stream

    calls = []

    def on_update(local_map, name, stamp):
        calls.append((name, stamp, local_map.to_elevation_map()["elevation"].copy()))

    params = terracube.LocalMapParams(length=4.0)
    run_stream(_drive(count), tmp_path, params, every=every, png=False, on_update=on_update)
    assert [stamp for _, stamp, _ in calls] == published
    assert calls[-1][0] == f"scans/scan{count - 1}.npy"
    final = terracube.ElevationMap.load(tmp_path / "local_map.npz")["elevation"]
    np.testing.assert_array_equal(calls[-1][2], final)


def test_stream_pictures_and_animation_frames_are_named_by_the_scans_0_based_index(tmp_path, monkeypatch):
    from terracube import stream

    titles = []
    monkeypatch.setattr(stream, "_write_animation", lambda frames, path, resolution: titles.extend(frames))
    params = terracube.LocalMapParams(length=4.0)
    report = stream.run_stream(_drive(5), tmp_path, params, every=2, png=True)
    assert sorted(p.name for p in tmp_path.glob("local_elevation_0*.png")) == [
        "local_elevation_000001.png",
        "local_elevation_000003.png",
    ]
    assert "(local_elevation_000001.png ... local_elevation_000003.png)" in "\n".join(report.lines)
    stream.run_stream(_drive(5), tmp_path / "a", params, every=2, animation=tmp_path / "a.gif", png=False)
    # every 2nd scan, then the final map (scan 4 is no 2nd scan)
    assert [title for title, _, _ in titles] == ["scan1 (scan 1)", "scan3 (scan 3)", "scan4 (scan 4)"]
    final = terracube.ElevationMap.load(tmp_path / "a" / "local_map.npz")
    np.testing.assert_array_equal(titles[-1][1], final["elevation"])
    titles.clear()  # fewer scans than --every: the animation is the final map alone, not missing
    stream.run_stream(_drive(5), tmp_path / "b", params, every=10, animation=tmp_path / "b.gif", png=False)
    assert [title for title, _, _ in titles] == ["scan4 (scan 4)"]


def test_stream_command_on_kitti_frames_writes_the_map_pictures_and_an_animation(shared_data, tmp_path):
    from terracube.cli import app
    from typer.testing import CliRunner

    kitti = shared_data.root / "kitti_seq00"
    out = tmp_path / "stream"
    args = ["stream", str(kitti / "velodyne"), "--poses", str(kitti / "poses.txt"), "-o", str(out)]
    result = CliRunner().invoke(app, [*args, "--every", "2", "--length", "10"])
    assert result.exit_code == 0, result.output
    assert "6 scans into a 100 x 100 local map" in result.output
    pictures = sorted(p.name for p in out.glob("local_elevation_*.png"))
    assert pictures == [  # after the 2nd, 4th and 6th scan, named like their files (0-based)
        "local_elevation_000001.png",
        "local_elevation_000003.png",
        "local_elevation_000005.png",
    ]
    assert (
        f"pictures every 2 scans: 3 in {out} (local_elevation_000001.png ... local_elevation_000005.png)"
        in (result.output.replace("\n", ""))
    )
    for name in ("local_map.npz", "local_elevation.png", "local_traversability.png"):
        assert (out / name).is_file(), name
    # KITTI's calib.txt and times.txt beside its poses: Velodyne poses, and times in seconds.
    assert f"calibration: {kitti / 'calib.txt'}" in result.output
    assert f"timestamps: {kitti / 'times.txt'}" in result.output
    # KITTI .bin scans at the default range limits: the car's own returns are named, with the preset
    assert (
        "warning: KITTI .bin scans with min_range 0.1 m" in result.output
        and "--preset kitti" in result.output
    )
    saved = terracube.ElevationMap.load(out / "local_map.npz")
    times = np.loadtxt(kitti / "times.txt")[:6]
    assert np.nanmax(saved["time"]) == pytest.approx(times[-1] - times[0], abs=1e-6)
    assert {"elevation", "variance", "clearance", "traversability"} <= set(saved.layers)
    assert np.isfinite(saved["elevation"]).sum() > 3000
    traversability = saved["traversability"][np.isfinite(saved["traversability"])]
    assert traversability.size > 3000 and traversability.min() >= 0.0 and traversability.max() <= 1.0

    movie = tmp_path / "drive.gif"
    result = CliRunner().invoke(
        app, [*args, "--length", "10", "--no-png", "--animation", str(movie), "--limit", "3"]
    )
    assert result.exit_code == 0, result.output
    assert movie.stat().st_size > 1000
    assert not (out / "local_elevation_000002.png").exists()
    result = CliRunner().invoke(
        app, [*args, "--length", "10", "--no-png", "--limit", "2", "--preset", "kitti"]
    )
    assert result.exit_code == 0 and "KITTI .bin scans" not in result.output, result.output
    result = CliRunner().invoke(app, [*args, "--resolution", "-1"])
    assert result.exit_code != 0 and "resolution" in result.output
    alone = tmp_path / "poses.txt"  # KITTI's camera poses without their calib.txt: said, not silent
    alone.write_text((kitti / "poses.txt").read_text())
    result = CliRunner().invoke(
        app,
        [
            "stream",
            str(kitti / "velodyne"),
            "--poses",
            str(alone),
            "--limit",
            "1",
            "--no-png",
            "-o",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "the KITTI poses are used as they are" in result.output
    assert "timestamps: none (the pose index)" in result.output


def test_stream_command_takes_the_overhang_rule(shared_data, tmp_path):
    from terracube.cli import app
    from typer.testing import CliRunner

    kitti = shared_data.root / "kitti_seq00"
    args = [
        "stream",
        str(kitti / "velodyne"),
        "--poses",
        str(kitti / "poses.txt"),
        "--limit",
        "2",
        "--no-png",
    ]
    maps = {}
    for method in ("paper", "shadow_aware"):
        out = tmp_path / method
        result = CliRunner().invoke(app, [*args, "-o", str(out), "--method", method, "--robot-height", "2.0"])
        assert result.exit_code == 0, result.output
        maps[method] = terracube.ElevationMap.load(out / "local_map.npz")
    # σ = ceil(2.0 / 0.5) = 4 either way; shadow_aware also removes canopy over unseen ground.
    paper, shadow_aware = (np.isfinite(maps[m]["elevation"]) for m in ("paper", "shadow_aware"))
    assert paper.sum() > 3000 and (paper != shadow_aware).any()
    result = CliRunner().invoke(app, [*args, "-o", str(tmp_path / "bad"), "--method", "junk"])
    assert result.exit_code != 0 and "method" in result.output


def test_shadow_aware_removal_keeps_a_crown_over_hidden_ground_out_of_the_map():
    """The crown-over-a-curb scene of test_shadow_aware.py (sensor at the origin, a 0.3 m curb at
    x = 5 hiding the ground behind it, a tree at x = 9, lit ground at x 14-20): with the paper's
    rule the crown's columns hold its height (an obstacle the robot could drive under), with
    ``method="shadow_aware"`` they hold no height, only the overhang above."""
    from test_shadow_aware import ground_patch, slab, vertical_face

    ground = np.vstack([ground_patch(1, 5, -5, 5), ground_patch(14, 20, -5, 5)])
    curb = np.vstack([vertical_face(5.0, -5, 5, -1.7, -1.4), slab(5, 5.5, -5, 5, -1.4)])
    trunk = vertical_face(9.0, -0.2, 0.2, -1.4, 1.5, step=0.1)
    crown = np.vstack([slab(7.75, 10.25, -1.25, 1.25, z) for z in (1.6, 2.4, 3.2, 3.8)])
    points = np.vstack([ground, curb, trunk, crown])
    # the crown's inner columns beside the trunk (its corner columns are thin: kept, see there)
    under_crown = [(x, y) for x in (8.4, 8.6, 9.4, 9.6) for y in (-0.6, 0.0, 0.6)]
    heights = {}
    for method in ("paper", "shadow_aware"):
        m = terracube.LocalMap(
            length=44.0, resolution=0.25, collapse=terracube.CollapseParams(edge=0.5, sigma=4, method=method)
        )
        m.update(points, np.eye(4))
        cells = [m.index_of(xy) for xy in under_crown]
        heights[method] = np.array([m["elevation"][i, j] for i, j in cells])
        overhang = np.array([m["overhang_min"][i, j] for i, j in cells])
    assert (heights["paper"] > 1.0).all()  # the crown as the cells' height
    assert np.isnan(heights["shadow_aware"]).all()  # no height: the ground there was never seen
    assert (overhang > 1.0).all()  # the crown is kept as the overhang above


def test_beams_without_a_return_keep_a_crown_behind_a_hedge_out_of_the_map():
    """The crown-behind-a-hedge scene of test_shadow_aware.py seen from a sensor yawed 30 degrees:
    no ray to a point passes under the crown, a fan of level beams without a return (sensor frame)
    does. Given them, the crown's columns hold no height; without them, the crown's."""
    from test_shadow_aware import beams, crown_behind_a_hedge

    kept, crown = crown_behind_a_hedge()
    pose = pose_at(0.0, 0.0, 0.0)
    yaw = np.radians(30.0)
    pose[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]]
    world = np.vstack([kept, crown]) @ pose[:3, :3]  # x R: rows in the yawed sensor frame
    fan = beams(0.5, np.arange(-50.0, -9.95, 0.1))  # the world's -20..20 degrees, seen yawed by 30
    collapse = terracube.CollapseParams(edge=0.5, sigma=4, method="shadow_aware")
    inner = [(x, y) for x in (11.6, 12.4) for y in (-0.6, 0.0, 0.6)]
    heights = {}
    for given in (False, True):
        m = terracube.LocalMap(length=30.0, resolution=0.25, collapse=collapse)
        m.update(world, pose, no_returns=fan if given else None)
        heights[given] = np.array([m["elevation"][m.index_of(xy)] for xy in inner])
    assert (heights[False] > 1.0).all()  # the crown as the cells' height
    assert np.isnan(heights[True]).all()
    m = terracube.LocalMap(length=30.0, resolution=0.25, collapse=collapse)
    for bad, message in (([[0.0, 0.0, 0.0]], "no_returns row 0"), (np.ones(3), r"\(M, 3\)")):
        with pytest.raises(ValueError, match=message):
            m.update(world, pose, no_returns=bad)
    assert m.num_updates == 0


def test_min_range_leaves_the_kitti_cars_own_body_out_of_the_map(shared_data, tmp_path):
    # KITTI's HDL-64 sees its car within 3 m (the roof rack, and the hood whose front edge returns
    # at 2.7-2.8 m): with the default 0.1 m those returns stand about a metre above the road in
    # front of the robot, with 2.5 m the hood's edge still does (a phantom obstacle in its path).
    from terracube.cli import app
    from typer.testing import CliRunner

    poses = shared_data.kitti_poses()
    scans = [shared_data.kitti_xyzi(frame)[:, :3] for frame in range(6)]
    distances = [np.linalg.norm(scan, axis=1) for scan in scans]

    def world(lowest, highest):  # the returns at [lowest, highest) m of every scan, in the world
        parts = [
            scan[(d >= lowest) & (d < highest)].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
            for scan, d, pose in zip(scans, distances, poses, strict=False)
        ]
        return np.vstack(parts)

    body, edge = world(0.0, 3.0), world(2.5, 3.0)
    last = scans[5][distances[5] < 3.0].astype(np.float64) @ poses[5][:3, :3].T + poses[5][:3, 3]
    assert len(body) > 200 and len(edge) > 10 and len(last) > 20
    road = poses[5][2, 3] - 1.73  # the sensor's height above the road
    heights = {}
    for min_range in (0.1, 2.5, 3.0):
        local = terracube.LocalMap(min_range=min_range)
        for scan, pose in zip(scans, poses[:6], strict=True):
            update = local.update(scan, pose)
        assert update.num_out_of_range == np.count_nonzero(distances[5] < min_range)
        for name, points in (("body", body), ("edge", edge), ("last", last)):
            cells = {local.index_of(p[:2]) for p in points}
            heights[name, min_range] = np.array([local["max"][c] for c in cells]) - road
    assert np.all(heights["last", 0.1] > 0.8)  # the last scan's car
    assert np.any(heights["edge", 2.5] > 0.8)  # the hood's edge of earlier scans
    assert np.all(~(heights["body", 3.0] > 0.1))  # the road under it, or nothing

    kitti = shared_data.root / "kitti_seq00"
    args = [
        "stream",
        str(kitti / "velodyne"),
        "--poses",
        str(kitti / "poses.txt"),
        "-o",
        str(tmp_path),
        "--no-png",
    ]
    result = CliRunner().invoke(app, [*args, "--limit", "2", "--min-range", "2.5", "--max-range", "40"])
    assert result.exit_code == 0, result.output
    assert "returns outside 2.5..40 m from the sensor left out" in result.output
    result = CliRunner().invoke(app, [*args, "--limit", "1", "--preset", "kitti"])  # min_range 3
    assert result.exit_code == 0 and f"{np.count_nonzero(distances[0] < 3.0)} returns" in result.output
    # The preset's crop, around the sensor of the leveled scan: under the road and beyond 40 m.
    leveled = scans[0].astype(np.float64) @ poses[0][:3, :3].T
    outside = np.any((leveled < [-40.0, -40.0, -3.0]) | (leveled > [40.0, 40.0, 20.0]), axis=1)
    assert outside.sum() > 1000
    assert f"{outside.sum():,} returns outside the crop box around the sensor were left out" in result.output
    result = CliRunner().invoke(app, [*args, "--min-range", "5", "--max-range", "4"])
    assert result.exit_code != 0 and "max_range must be a distance [m] beyond min_range" in result.output


def test_planner_layers_on_demand_equal_those_of_every_update(shared_data):
    # A planner slower than the sensor: compute_planner_layers=False, then update_planner_layers()
    # when it plans gives the layers a map refreshed after every scan holds.
    scans = [shared_data.kitti_xyzi(frame)[:, :3] for frame in range(2)]
    every, on_demand = (
        terracube.LocalMap(length=10.0),
        terracube.LocalMap(length=10.0, compute_planner_layers=False),
    )
    for k, scan in enumerate(scans):
        every.update(scan, pose_at(0.5 * k, 0.0, 0.0))
        on_demand.update(scan, pose_at(0.5 * k, 0.0, 0.0))
    assert np.all(np.isnan(on_demand["traversability"]))
    on_demand.update_planner_layers()
    for name in ("step", "slope", "roughness", "traversability"):
        np.testing.assert_array_equal(on_demand[name], every[name], err_msg=name)
    assert np.isfinite(every["traversability"]).sum() > 2000


def test_a_crop_around_the_sensor_leaves_a_return_under_the_road_out():
    # Independent reference: the same scan without the stray return. A multipath return 2.5 m under
    # the road would be a pit; the crop (z >= -1.5 m from the sensor, which sits 0.8 m up at
    # (100, 50)) leaves it out, whatever the pose's translation.
    sensor = pose_at(100.0, 50.0, 0.8, yaw=0.3)
    ground = gentle_ground() + [100.0, 50.0, 0.0]  # around the sensor, in the odometry frame
    scan = (ground - sensor[:3, 3]) @ sensor[:3, :3]  # the odometry-frame ground in the sensor frame
    stray = np.array([[2.0, 0.5, -3.3]])  # in the sensor frame: 2.5 m under the road
    crop = terracube.CollapseParams(crop=((-40.0, -40.0, -1.5), (40.0, 40.0, 20.0)))
    cropped = terracube.LocalMap(length=8.0, collapse=crop)
    report = cropped.update(np.vstack([scan, stray]), sensor)
    clean = terracube.LocalMap(length=8.0, collapse=crop)
    clean.update(scan, sensor)
    assert report.num_cropped == 1 and "num_cropped=1" in repr(report)
    for name in cropped.layers:
        np.testing.assert_array_equal(cropped[name], clean[name], err_msg=name)
    pitted = terracube.LocalMap(length=8.0)
    pitted.update(np.vstack([scan, stray]), sensor)
    where = (sensor[:3, :3] @ stray[0] + sensor[:3, 3])[:2]
    assert pitted["elevation"][pitted.index_of(where)] < -2.0  # without the crop: the pit


def test_stamps_are_all_given_or_all_nan_and_fit_the_time_layer():
    sensor = pose_at(0.0, 0.0, 1.0)
    points = gentle_ground() - sensor[:3, 3]
    stamped = terracube.LocalMap(length=4.0)
    nan_rows = points.copy()
    nan_rows[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        stamped.update(nan_rows, sensor, stamp=1.7e9)  # a failed first update sets no time origin
    assert math.isnan(stamped.time_origin)
    stamped.update(points, sensor, stamp=1.7e9)
    stamped.update(points, sensor, stamp=1.7e9 + 30.0)
    assert stamped.time_origin == 1.7e9 and np.nanmax(stamped["time"]) == 30.0
    with pytest.raises(ValueError, match=r"no stamp \(NaN\) after updates with one"):
        stamped.update(points, sensor)
    with pytest.raises(ValueError, match="over 1e30 s"):
        stamped.update(points, sensor, stamp=1e39)
    counted = terracube.LocalMap(length=4.0)
    counted.update(points, sensor)
    with pytest.raises(ValueError, match="a stamp after updates without one"):
        counted.update(points, sensor, stamp=1.7e9)
    counted.update(points, sensor)
    assert np.nanmax(counted["time"]) == 1.0 and np.isfinite(counted["time"][counted["count"] > 0]).all()


def test_cells_coarser_than_the_footprint_still_get_planner_layers():
    # At 0.7 m a 0.3 m footprint rounds to no neighbour: the window is the 3 x 3 cells around.
    points = gentle_ground(half=10.0, n=40000)
    sensor = pose_at(0.0, 0.0, 1.0)
    m = terracube.LocalMap(length=14.0, resolution=0.7)
    m.update(points - sensor[:3, 3], sensor)
    known = np.isfinite(m["elevation"])
    assert known.sum() > 300 and np.isfinite(m["traversability"][known]).mean() > 0.9
    tiny = terracube.TraversabilityParams(slope_weight=1e-320, step_weight=0.0, roughness_weight=0.0)
    weighted = terracube.LocalMap(length=14.0, resolution=0.7, traversability=tiny)
    weighted.update(points - sensor[:3, 3], sensor)
    values = weighted["traversability"][np.isfinite(weighted["traversability"])]
    assert values.size and values.min() >= 0.0 and values.max() <= 1.0
