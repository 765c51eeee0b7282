"""The terracube command line, run as a user would (typer's CliRunner, in-process)."""

from __future__ import annotations

import numpy as np
import pytest
import terracube as tc
from terracube.cli import app
from typer.testing import CliRunner

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def runner():
    return CliRunner()


def _scan(tmp_path):
    """A small synthetic scan: ground, a canopy 3 m up over part of it, a wall."""
    rng = np.random.default_rng(3)
    ground = np.c_[rng.uniform(0, 10, (4000, 2)), rng.normal(0, 0.02, 4000)]
    canopy = np.c_[rng.uniform(2, 5, (800, 2)), rng.uniform(3.0, 3.5, 800)]
    wall = np.c_[np.full(500, 8.0), rng.uniform(0, 10, 500), rng.uniform(0, 2.5, 500)]
    points = np.vstack([ground, canopy, wall]).astype(np.float32)
    path = tmp_path / "scan.npy"
    np.save(path, points)
    return path, points


def test_collapse_writes_the_classified_cloud_and_a_picture(runner, tmp_path):
    path, points = _scan(tmp_path)
    out = tmp_path / "out"
    result = runner.invoke(
        app, ["collapse", str(path), "-o", str(out), "--edge", "0.5", "--sigma", "2", "-f", "npz"]
    )
    assert result.exit_code == 0, result.output
    saved = np.load(out / "scan_classified.npz")
    expected = tc.collapse_overhangs(points, 0.5, 2).overhang
    np.testing.assert_array_equal(saved["overhang"], expected)
    assert 700 <= expected.sum() <= 800  # the canopy goes, ground and wall stay
    assert (out / "scan_overhangs.png").read_bytes()[:8] == PNG_MAGIC


def test_demo_runs_on_the_bundled_sample(runner, tmp_path):
    result = runner.invoke(app, ["demo", "-o", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "ouster128_sample_classified.ply").stat().st_size > 1_000_000
    assert (tmp_path / "ouster128_sample_overhangs.png").read_bytes()[:8] == PNG_MAGIC
    assert "points are overhang" in result.output


def test_dem_writes_the_overhang_free_map_and_its_pictures(runner, tmp_path):
    path, points = _scan(tmp_path)
    out = tmp_path / "dem"
    result = runner.invoke(app, ["dem", str(path), "-o", str(out), "--resolution", "0.5", "--sigma", "2"])
    assert result.exit_code == 0, result.output
    saved = tc.ElevationMap.load(out / "scan_dem.npz")
    expected, _ = tc.dem_without_overhangs(points, 0.5, 2, 0.5)
    for name in ("count", "max", "mean", "clearance", "step"):
        np.testing.assert_array_equal(saved[name], expected[name], err_msg=name)
    for picture in ("dem_comparison", "clearance", "step"):
        assert (out / f"scan_{picture}.png").read_bytes()[:8] == PNG_MAGIC


def test_classify_writes_classes_and_a_class_picture(runner, tmp_path):
    path, points = _scan(tmp_path)
    out = tmp_path / "classes"
    result = runner.invoke(app, ["classify", str(path), "-o", str(out), "--resolution", "0.5"])
    assert result.exit_code == 0, result.output
    saved = tc.ElevationMap.load(out / "scan_classes.npz")
    raw = tc.build_elevation_map(points, 0.5)
    classes = tc.classify_terrain(raw)
    np.testing.assert_array_equal(np.nan_to_num(saved["class"]), classes.astype(np.float32))
    assert (out / "scan_classes.png").read_bytes()[:8] == PNG_MAGIC


def test_classify_notes_a_sensor_height_that_misses_the_ground(runner, tmp_path):
    # The synthetic scan's ground is at z = 0; a sensor 1.7 m above it sees it at z = -1.7.
    _, points = _scan(tmp_path)
    lowered = points - np.float32([0.0, 0.0, 1.7])
    path = tmp_path / "lowered.npy"
    np.save(path, lowered)
    args = ["classify", str(path), "-o", str(tmp_path / "out"), "-r", "0.5", "--no-cloud", "--no-png"]
    result = runner.invoke(app, args + ["--sensor-height", "0.3"])  # a wrong height: 1.4 m off
    assert result.exit_code == 0, result.output
    note = [line for line in result.output.splitlines() if "note:" in line]
    assert len(note) == 1, result.output
    # The median lowest point per cell is the ground (about -1.7 m; a few cells are wall or canopy).
    suggested = float(note[0].split("--sensor-height ")[1].split(",")[0])
    assert suggested == pytest.approx(1.7, abs=0.1)
    for fitting in (["--sensor-height", "1.7"], ["--reference", "local_ground"]):
        result = runner.invoke(app, args + fitting)
        assert result.exit_code == 0, result.output
        assert "note:" not in result.output, fitting
    # Without a sensor height the ground is estimated (local ground) and said so: no note either.
    result = runner.invoke(
        app, ["classify", str(_scan(tmp_path)[0]), "-o", str(tmp_path / "o2"), "-r", "0.5"]
    )
    assert result.exit_code == 0 and "note:" not in result.output, result.output


@pytest.mark.parametrize("command", ["collapse", "dem", "classify"])
def test_a_missing_file_exits_with_code_2_and_names_it(runner, tmp_path, command):
    result = runner.invoke(app, [command, str(tmp_path / "nope.bin"), "-o", str(tmp_path)])
    assert result.exit_code == 2
    assert "nope.bin" in result.output


def test_a_truncated_kitti_file_exits_with_code_2(runner, tmp_path):
    path = tmp_path / "broken.bin"
    path.write_bytes(b"\x00" * 10)
    result = runner.invoke(app, ["collapse", str(path), "-o", str(tmp_path)])
    assert result.exit_code == 2
    assert "float32" in result.output


def test_a_bad_edge_exits_with_code_2(runner, tmp_path):
    path, _ = _scan(tmp_path)
    result = runner.invoke(app, ["collapse", str(path), "-o", str(tmp_path), "--edge", "-1"])
    assert result.exit_code == 2
    assert "edge" in result.output


@pytest.mark.parametrize("command", ["dem", "classify"])
@pytest.mark.parametrize("resolution", ["nan", "0", "-0.1", "inf"])
def test_a_bad_resolution_is_named_not_blamed_on_the_map_window(runner, tmp_path, command, resolution):
    # The automatic map window and classify's ground window divide by it: NaN came out as "origin
    # must be two finite coordinates", 0 as a ZeroDivisionError traceback.
    path, _ = _scan(tmp_path)
    result = runner.invoke(app, [command, str(path), "-o", str(tmp_path), "-r", resolution, "--no-png"])
    assert result.exit_code == 2, result.output
    assert "resolution must be a positive finite length in metres" in result.output


@pytest.mark.parametrize(
    "options",
    [["--max-range", "1e300"], ["--min-range", "1e300"], ["-r", "1e300"]],
    ids=lambda o: " ".join(o),
)
def test_huge_ranges_and_cells_end_with_a_map_or_an_error_line_not_an_overflow(runner, tmp_path, options):
    # 1e300 ** 2 raised OverflowError in the range filter and in the fill note (found by fuzzing).
    path, _ = _scan(tmp_path)
    result = runner.invoke(app, ["classify", str(path), "-o", str(tmp_path), "--no-png", *options])
    assert result.exit_code in (0, 2) and not isinstance(result.exception, OverflowError), result.output
    assert result.exit_code == 0 or "error:" in result.output


# --------------------------------------------------------------------------------------------
# register, fem, view, classified clouds, GeoTIFF, the console script
# --------------------------------------------------------------------------------------------


def _rigid_errors(estimate, truth):
    delta = estimate[:3, :3].T @ truth[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(delta) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3])), float(angle)


@pytest.fixture(scope="module")
def street_scans(tmp_path_factory):
    """The registration tests' street seen from two poses 3 m and 20 degrees apart, as .npy scans."""
    from test_registration import SENSOR_HEIGHT, apply, pose, street

    folder = tmp_path_factory.mktemp("street")
    world = street()
    source_pose = pose(-1.0, 0.0, SENSOR_HEIGHT, -10.0)
    target_pose = pose(1.95, 0.5, SENSOR_HEIGHT, 10.0)
    truth = np.linalg.inv(target_pose) @ source_pose
    np.save(folder / "source.npy", apply(np.linalg.inv(source_pose), world))
    np.save(folder / "target.npy", apply(np.linalg.inv(target_pose), world))
    return folder, truth, SENSOR_HEIGHT


def test_register_recovers_a_known_motion_and_writes_json_and_txt(runner, tmp_path, street_scans):
    import json

    folder, truth, sensor_height = street_scans
    yaw = np.degrees(np.arctan2(truth[1, 0], truth[0, 0]))
    guess = f"{truth[0, 3] + 0.3},{truth[1, 3] - 0.2},{yaw + 3.0}"  # the truth perturbed (odometry)
    args = ["register", str(folder / "source.npy"), str(folder / "target.npy"), "-r", "0.2"]
    args += ["--sensor-height", str(sensor_height), "--initial", guess]
    result = runner.invoke(app, [*args, "--output", str(tmp_path / "r.json")])
    assert result.exit_code == 0, result.output
    record = json.loads((tmp_path / "r.json").read_text())
    estimate = np.array(record["transform"])
    translation_error, rotation_error = _rigid_errors(estimate, truth)
    # within one 0.2 m cell and half a degree (whole-scan maps, no fixed extent as in test_registration)
    assert translation_error < 0.2 and rotation_error < 0.5, (translation_error, rotation_error)
    assert record["converged"] and record["reason"] == "converged"
    # the same as the library on the same maps
    maps = []
    for name in ("source", "target"):
        elevation_map = tc.build_elevation_map(np.load(folder / f"{name}.npy"), 0.2)
        tc.classify_terrain(elevation_map, sensor_height=sensor_height)
        maps.append(elevation_map)
    from terracube.cli import parse_initial

    direct = tc.register_maps(maps[0], maps[1], parse_initial(guess))
    np.testing.assert_array_equal(estimate, direct.transform)
    assert record["iterations"] == direct.iterations and record["rmse"] == direct.rmse
    counts = list(direct.correspondences_per_class)
    assert record["correspondences_per_class"]["obstacle"] == counts[int(tc.TerrainClass.OBSTACLE)]
    assert record["correspondences_per_class"]["ground"] == 0  # ground takes no part (Table 2)
    for text in ("converged: yes (converged)", "RMSE:", "correspondences per class:", "transform:"):
        assert text in result.output
    result = runner.invoke(app, [*args, "--method", "all-cells", "--output", str(tmp_path / "r.txt")])
    # The all-cells ICP slides on the road: the verdict says so and the exit code is 1 (issue 38),
    # the result still written.
    assert result.exit_code == 1, result.output
    assert "registration not trusted: " in result.output and "sliding along" in result.output
    all_cells = tc.register_maps_all_cells(maps[0], maps[1], parse_initial(guess))
    np.testing.assert_allclose(np.loadtxt(tmp_path / "r.txt"), all_cells.transform, rtol=0, atol=1e-11)


def test_register_reports_what_the_scene_constrains(runner, tmp_path, street_scans):
    import json

    folder, truth, sensor_height = street_scans
    args = ["register", str(folder / "source.npy"), str(folder / "target.npy"), "-r", "0.2"]
    args += ["--sensor-height", str(sensor_height), "--structure-radius", "0.6"]
    result = runner.invoke(app, [*args, "--output", str(tmp_path / "r.json")])
    # Neighbourhoods of 0.6 m (three 0.2 m cells) see the house fronts as planes: sliding along the
    # street is held by a few % of the pairs' weight, below trust_min_held (exit code 1, issue 38).
    assert result.exit_code == 1, result.output
    assert "least held" in result.output and "sliding along x is held by" in result.output
    constraints = json.loads((tmp_path / "r.json").read_text())["constraints"]
    held = [c["held"] for c in constraints]
    assert len(held) == 6 and held == sorted(held) and held[0] >= -1e-9
    plain = runner.invoke(app, [*args[:-2], "--structure-radius", "0"])  # the analysis off (0.3 by default)
    assert plain.exit_code == 0 and "least held" not in plain.output


def test_register_with_pcl_or_a_clear_message(runner, tmp_path, street_scans):
    folder, truth, sensor_height = street_scans
    args = ["register", str(folder / "source.npy"), str(folder / "target.npy"), "-r", "0.2", "-m", "pcl"]
    initial = tmp_path / "guess.txt"
    np.savetxt(initial, truth[:3])  # KITTI-style 3x4
    result = runner.invoke(app, [*args, "--sensor-height", str(sensor_height), "-i", str(initial)])
    if not tc.has_pcl():
        assert result.exit_code == 2 and "PCL" in result.output
        return
    assert result.exit_code == 0, result.output
    assert "fitness:" in result.output and "iterations:" in result.output


def test_initial_guesses_from_files_and_x_y_yaw(tmp_path):
    import json

    from terracube.cli import parse_initial

    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    expected = np.array([[c, -s, 0, 1.5], [s, c, 0, -2.0], [0, 0, 1, 0], [0, 0, 0, 1]])
    np.testing.assert_allclose(parse_initial("1.5,-2,30"), expected, atol=1e-15)
    np.testing.assert_allclose(parse_initial("1.5 -2 30"), expected, atol=1e-15)
    np.savetxt(tmp_path / "m.txt", expected)
    np.testing.assert_array_equal(parse_initial(str(tmp_path / "m.txt")), expected)
    (tmp_path / "m.json").write_text(json.dumps({"transform": expected.tolist()}))
    np.testing.assert_array_equal(parse_initial(str(tmp_path / "m.json")), expected)
    np.testing.assert_array_equal(parse_initial(None), np.eye(4))
    (tmp_path / "bad.txt").write_text("1 2 3\n4 5 6\n")
    with pytest.raises(ValueError, match=r"bad\.txt: expected a finite 4x4"):
        parse_initial(str(tmp_path / "bad.txt"))
    with pytest.raises(ValueError, match="neither a file nor x,y,yaw"):
        parse_initial("1,2")


def test_register_refuses_an_unknown_method_and_a_bad_output_suffix(runner, tmp_path, street_scans):
    folder, _, _ = street_scans
    pair = [str(folder / "source.npy"), str(folder / "target.npy")]
    result = runner.invoke(app, ["register", *pair, "-m", "ndt"])
    assert result.exit_code == 2 and "--method must be one of classes, all-cells, pcl" in result.output
    result = runner.invoke(app, ["register", *pair, "--output", str(tmp_path / "r.csv")])
    assert result.exit_code == 2 and "use a .json or .txt file" in result.output


def test_fem_writes_the_fuzzy_layers_the_library_computes_and_pictures(runner, tmp_path):
    path, points = _scan(tmp_path)
    out = tmp_path / "fem"
    result = runner.invoke(
        app, ["fem", str(path), "-o", str(out), "-r", "0.5", "--rules", "6", "5", "--epochs", "3"]
    )
    assert result.exit_code == 0, result.output
    saved = tc.ElevationMap.load(out / "scan_fem.npz")
    dem, collapse = tc.dem_without_overhangs(points, 0.5, 2, 0.5)
    fem = tc.fit_fuzzy_elevation_map(
        points.astype(np.float64), rules_x=6, rules_y=5, epochs=3, use=~collapse.overhang
    )
    fem.to_layer(dem, 3.0)
    for layer in ("fem", "fem_confidence", "max"):
        np.testing.assert_array_equal(saved[layer], dem[layer], err_msg=layer)
    # the ground is flat at z = 0 under the canopy (removed): the surface stays near it but at the wall
    assert np.nanmedian(np.abs(saved["fem"])) < 0.1
    assert "30 rules (41 parameters)" in result.output
    for picture in ("fem", "fem_confidence"):
        assert (out / f"scan_{picture}.png").read_bytes()[:8] == PNG_MAGIC


def test_classify_writes_each_point_with_the_class_of_its_cell(runner, tmp_path):
    path, points = _scan(tmp_path)
    out = tmp_path / "classes"
    result = runner.invoke(app, ["classify", str(path), "-o", str(out), "-r", "0.5", "-f", "las", "--no-png"])
    assert result.exit_code == 0, result.output
    from terracube.io import TERRAIN_LAS_CLASSES, read_cloud

    cloud = read_cloud(out / "scan_classes.las")
    raw = tc.build_elevation_map(points, 0.5)
    classes = tc.classify_terrain(raw)
    # reference: the cell of every 7th point by MapGeometry.index_of, one point at a time
    for k in range(0, len(points), 7):
        i, j = raw.geometry.index_of(float(points[k, 0]), float(points[k, 1]))
        assert cloud["label"][k] == classes[i, j], k
    np.testing.assert_array_equal(cloud["classification"], [TERRAIN_LAS_CLASSES[c] for c in cloud["label"]])
    assert set(np.unique(cloud["label"])) >= {1, 3}  # ground and the canopy's overhanging cells


def test_dem_geotiff_holds_the_max_layer_north_up(runner, tmp_path):
    rasterio = pytest.importorskip("rasterio")
    path, _ = _scan(tmp_path)
    out = tmp_path / "dem"
    result = runner.invoke(app, ["dem", str(path), "-o", str(out), "-r", "0.5", "--geotiff", "--no-png"])
    assert result.exit_code == 0, result.output
    saved = tc.ElevationMap.load(out / "scan_dem.npz")
    with rasterio.open(out / "scan_dem_max.tif") as tif:
        band = tif.read(1)
        g = saved.geometry
        assert tif.transform.c == g.origin[0] and tif.transform.a == g.resolution
    np.testing.assert_array_equal(band, saved["max"].T[::-1, :])


def test_collapse_writes_a_kitti_bin_with_a_label_file(runner, tmp_path):
    path, points = _scan(tmp_path)
    result = runner.invoke(app, ["collapse", str(path), "-o", str(tmp_path), "-f", "bin", "--no-png"])
    assert result.exit_code == 0, result.output
    labels = np.fromfile(tmp_path / "scan_classified.label", np.uint32)
    np.testing.assert_array_equal(labels, tc.collapse_overhangs(points, 0.5, 2).overhang)
    np.testing.assert_array_equal(
        np.fromfile(tmp_path / "scan_classified.bin", np.float32).reshape(-1, 4)[:, :3], points
    )


def test_view_draws_one_picture_per_map_layer_and_three_for_a_scan(runner, tmp_path):
    path, _ = _scan(tmp_path)
    assert (
        runner.invoke(app, ["classify", str(path), "-o", str(tmp_path), "-r", "0.5", "--no-cloud"]).exit_code
        == 0
    )
    result = runner.invoke(app, ["view", str(tmp_path / "scan_classes.npz"), "-o", str(tmp_path / "v")])
    assert result.exit_code == 0, result.output
    layers = tc.ElevationMap.load(tmp_path / "scan_classes.npz").layers
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == sorted(
        f"scan_classes_{n}.png" for n in layers
    )
    result = runner.invoke(
        app, ["view", str(tmp_path / "scan_classes.npz"), "-o", str(tmp_path), "-l", "height"]
    )
    assert result.exit_code == 2 and "no layer height" in result.output
    result = runner.invoke(app, ["view", str(path), "-o", str(tmp_path / "s"), "-r", "0.5"])
    assert result.exit_code == 0, result.output
    for picture in ("overhangs", "max", "classes"):
        assert (tmp_path / "s" / f"scan_{picture}.png").read_bytes()[:8] == PNG_MAGIC


def test_view_3d_without_rerun_names_the_extra_to_install(runner, tmp_path, monkeypatch):
    import sys

    path, _ = _scan(tmp_path)
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun now raises ImportError
    result = runner.invoke(
        app, ["view", str(path), "-o", str(tmp_path), "--no-png", "--3d", "--save", "x.rrd"]
    )
    assert result.exit_code == 2
    assert 'pip install "terracube[viewer]"' in result.output
    result = runner.invoke(app, ["view", str(path), "--save", "x.rrd"])
    assert result.exit_code == 2 and "give --3d too" in result.output


def test_view_3d_saves_a_rerun_recording(runner, tmp_path):
    pytest.importorskip("rerun", reason="the viewer extra (rerun-sdk) is not installed")
    path, _ = _scan(tmp_path)
    recording = tmp_path / "scan.rrd"
    result = runner.invoke(
        app, ["view", str(path), "-o", str(tmp_path), "--no-png", "--3d", "--save", str(recording)]
    )
    assert result.exit_code == 0, result.output
    assert recording.stat().st_size > 1000


@pytest.mark.parametrize(
    "relative", ["ouster128/ouster128_000000.pcd", "als_classified/laspy_wkt_geotiff_ground_veg_building.las"]
)
@pytest.mark.parametrize("command", ["collapse", "dem", "classify", "fem", "view"])
def test_a_truncated_real_pcd_or_las_exits_2_naming_the_file(
    runner, tmp_path, shared_data, relative, command
):
    data = shared_data.path(relative).read_bytes()
    path = tmp_path / f"cut_{command}{relative[-4:]}"
    path.write_bytes(data[: len(data) // 2])
    result = runner.invoke(app, [command, str(path), "-o", str(tmp_path)])
    assert result.exit_code == 2
    assert path.name in result.output and "truncated" in result.output


def test_the_console_script_runs_as_a_subprocess(tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    import yaml

    env = dict(os.environ)
    # The subprocess imports the same terracube as this test (installed, or a source tree with _core).
    package_root = str(Path(tc.__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [package_root, env.get("PYTHONPATH")]))
    path, points = _scan(tmp_path)
    run = [sys.executable, "-m", "terracube"]
    help_text = subprocess.run([*run, "--help"], capture_output=True, text=True, env=env, timeout=120)
    assert help_text.returncode == 0
    for command in ("collapse", "dem", "classify", "fem", "register", "view", "config", "batch"):
        assert command in help_text.stdout
    printed = subprocess.run([*run, "config"], capture_output=True, text=True, env=env, timeout=120)
    assert printed.returncode == 0 and yaml.safe_load(printed.stdout)["collapse"]["edge"] == 0.5
    done = subprocess.run(
        [*run, "collapse", str(path), "-o", str(tmp_path / "o"), "-f", "npz", "--no-png"],
        capture_output=True, text=True, env=env, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    expected = tc.collapse_overhangs(points, 0.5, 2).overhang
    np.testing.assert_array_equal(np.load(tmp_path / "o" / "scan_classified.npz")["overhang"], expected)


def test_dem_and_classify_on_every_processor_write_the_one_thread_results(runner, tmp_path):
    rng = np.random.default_rng(11)
    _, points = _scan(tmp_path)
    tiles = [points + np.array([10.0 * (k % 5), 10.0 * (k // 5), 0.0], np.float32) for k in range(20)]
    big = np.vstack(tiles) + rng.normal(0, 0.01, (len(points) * 20, 3)).astype(np.float32)
    path = tmp_path / "big.npy"
    np.save(path, big)
    outputs = {}
    for threads in ("1", "0"):
        out = tmp_path / f"threads_{threads}"
        for command in ("dem", "classify"):
            result = runner.invoke(
                app, [command, str(path), "-o", str(out), "-r", "0.5", "--num-threads", threads, "--no-png"]
            )
            assert result.exit_code == 0, result.output
        outputs[threads] = (
            tc.ElevationMap.load(out / "big_dem.npz"),
            tc.ElevationMap.load(out / "big_classes.npz"),
        )
    for one, every in zip(outputs["1"], outputs["0"], strict=True):
        assert one.layers == every.layers
        for name in one.layers:
            np.testing.assert_array_equal(every[name], one[name], err_msg=name)


def test_a_negative_number_of_threads_exits_with_status_2_naming_it(runner, tmp_path):
    path, _ = _scan(tmp_path)
    result = runner.invoke(app, ["dem", str(path), "-o", str(tmp_path / "out"), "--num-threads", "-1"])
    assert result.exit_code == 2
    assert "num_threads" in result.output


def test_a_missing_extra_exits_2_naming_it(runner, tmp_path, monkeypatch):
    import sys

    path, _ = _scan(tmp_path)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # pictures need the plot extra
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    result = runner.invoke(app, ["collapse", str(path), "-o", str(tmp_path)])
    assert result.exit_code == 2 and "terracube[plot]" in result.output
    result = runner.invoke(app, ["collapse", str(path), "-o", str(tmp_path), "--no-png"])
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize("command", ["collapse", "dem", "classify", "fem"])
def test_every_stage_command_lists_its_shared_options_in_help(runner, command):
    from terracube.cli import STAGE_OPTIONS

    result = runner.invoke(app, [command, "--help"], terminal_width=200)
    assert result.exit_code == 0
    assert "--config" in result.output and "--crop" in result.output and "--png" in result.output
    assert len(STAGE_OPTIONS[command]) >= 10


def test_sensor_origin_reaches_the_shadow_aware_rule(runner, tmp_path):
    """--sensor-origin X Y Z sets collapse.sensor_origin: the CLI writes the mask the library gives
    for that origin, and an origin far below every point is refused by the library's check."""
    path, points = _scan(tmp_path)
    # A crown over a 0.3 m curb that hides the ground under it from a sensor 1.8 m up at the origin.
    rng = np.random.default_rng(5)
    curb = np.c_[np.full(300, 3.0), rng.uniform(0, 10, 300), rng.uniform(0, 0.3, 300)]
    crown = np.c_[rng.uniform(3.5, 6.0, (600, 2)), rng.uniform(3.0, 3.6, 600)]
    ground = points[(points[:, 0] < 3.0) & (points[:, 2] < 0.5)]
    points = np.vstack([ground, curb, crown]).astype(np.float32)
    np.save(path, points)
    common = ["--edge", "0.5", "--sigma", "2", "--method", "shadow_aware", "-f", "npz", "--no-png"]
    masks = {}
    for origin in ((0.0, 0.0, 1.8), (20.0, 5.0, 1.8)):
        out = tmp_path / f"out{origin[0]:.0f}"
        args = ["collapse", str(path), "-o", str(out), *common, "--sensor-origin", *map(str, origin)]
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
        masks[origin] = np.load(out / "scan_classified.npz")["overhang"]
        expected = tc.collapse_overhangs(points, 0.5, 2, method="shadow_aware", sensor_origin=origin).overhang
        np.testing.assert_array_equal(masks[origin], expected)
    assert not np.array_equal(*masks.values())  # the origin changes what the rays prove
    args = ["collapse", str(path), "-o", str(tmp_path / "low"), *common, "--sensor-origin", "0", "0", "-50"]
    result = runner.invoke(app, args)
    assert result.exit_code == 2 and "sensor" in result.output


# ------------------------------------------------------------------------------------------ units


def _ground_ring(scale: float = 1.0) -> np.ndarray:
    """A sensor's ground returns within 8 m (float64), times ``scale`` (1000: in millimetres)."""
    rng = np.random.default_rng(7)
    xy = rng.uniform(-8.0, 8.0, (3000, 2))
    return np.c_[xy, np.full(len(xy), -1.7) + rng.normal(0.0, 0.01, len(xy))] * scale


def _sequence(tmp_path, scale: float) -> tuple:
    """Two scans 1 m apart as 000000.npy, 000001.npy and their KITTI poses.txt (identity rotations)."""
    folder = tmp_path / f"scans_{scale:g}"
    folder.mkdir()
    for k in range(2):
        np.save(folder / f"{k:06d}.npy", _ground_ring(scale))
    poses = tmp_path / f"poses_{scale:g}.txt"
    poses.write_text("".join(f"1 0 0 0 0 1 0 {k} 0 0 1 0\n" for k in range(2)))
    return folder, poses


def test_a_scan_in_millimetres_is_flagged_by_collapse_and_named_by_the_dem_error(runner, tmp_path):
    path = tmp_path / "mm.npy"
    np.save(path, _ground_ring(1000.0))
    collapse = runner.invoke(app, ["collapse", str(path), "-o", str(tmp_path / "c"), "--no-png"])
    assert collapse.exit_code == 0, collapse.output
    assert "warning: the scan spans 16 km" in collapse.output
    assert "are the coordinates in millimetres? terracube expects metres" in collapse.output
    dem = runner.invoke(app, ["dem", str(path), "-o", str(tmp_path / "d"), "--no-png"])
    assert dem.exit_code == 2
    assert "over max_cells" in dem.output and "are the coordinates in millimetres?" in dem.output


def test_a_scan_in_metres_is_not_flagged_as_millimetres(runner, tmp_path):
    path = tmp_path / "m.npy"
    np.save(path, _ground_ring())
    result = runner.invoke(app, ["dem", str(path), "-o", str(tmp_path / "d"), "--no-png"])
    assert result.exit_code == 0, result.output
    assert "millimetres" not in result.output


def _run_sequence(runner, tmp_path, command: str, scale: float):
    """(result, output folder) of `terracube stream` or `map` (odometry only) over _sequence's scans."""
    folder, poses = _sequence(tmp_path, scale)
    out = tmp_path / "out"
    options = ["--odometry-only", "--no-loop-closing"] if command == "map" else []
    result = runner.invoke(
        app, [command, str(folder), "--poses", str(poses), "-o", str(out), "--no-png", *options]
    )
    return result, out


@pytest.mark.parametrize("command", ["stream", "map"])
def test_scans_in_millimetres_stop_stream_and_map_before_an_empty_map_is_written(runner, tmp_path, command):
    result, out = _run_sequence(runner, tmp_path, command, 1000.0)
    assert result.exit_code == 2, result.output
    assert "no point of the 2 scans fell in the" in result.output
    assert "2 of 2 scans span over 10 km (the widest 16 km)" in result.output
    assert "are the coordinates in millimetres?" in result.output
    assert not list(out.glob("*.npz"))


@pytest.mark.parametrize("command", ["stream", "map"])
def test_scans_in_metres_stream_and_map_without_a_unit_warning(runner, tmp_path, command):
    result, out = _run_sequence(runner, tmp_path, command, 1.0)
    assert result.exit_code == 0, result.output
    assert "millimetres" not in result.output and "knows no cell" not in result.output
    assert len(list(out.glob("*.npz"))) == 1


def test_a_stream_that_ends_with_no_known_cell_warns(tmp_path):
    from terracube.stream import run_stream

    far = np.eye(4)
    far[0, 3] = 1000.0  # the map follows the sensor 1 km away: every filled cell is left behind
    scans = [("near", _ground_ring(), np.eye(4), 0.0), ("far", np.empty((0, 3)), far, 1.0)]
    report = run_stream(scans, tmp_path, tc.LocalMapParams(), png=False)
    assert "warning: the local map knows no cell at the end" in "\n".join(report.lines)
    assert not np.isfinite(tc.ElevationMap.load(tmp_path / "local_map.npz")["elevation"]).any()


def test_a_few_far_returns_do_not_make_a_scan_in_metres_look_like_millimetres():
    from terracube.pipeline import scan_span, scan_span_warning

    points = np.vstack([_ground_ring(), np.full((20, 3), 1e6)])  # 20 of 3020 returns at 1000 km
    assert scan_span(points) < 20.0
    assert scan_span_warning([scan_span(points)]) is None
    assert scan_span(np.full((3, 3), np.nan)) == 0.0
