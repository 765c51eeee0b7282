"""Issue 37 through real ``python -m terracube`` subprocesses: the rendered help of every command,
--version, presets on the bundled Ouster scan, --origin as its help writes it, the viewer check
before any output, and ``terracube map``'s trajectories as evo reads them."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import terracube as tc


def _env() -> dict[str, str]:
    env = dict(os.environ)
    # The subprocess imports the same terracube as this test (installed, or a source tree with _core).
    package_root = str(Path(tc.__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [package_root, env.get("PYTHONPATH")]))
    env.update(COLUMNS="100", TERM="xterm-256color")  # a terminal as a user's, where Rich would render
    return env


def _terracube(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "terracube", *args],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=timeout,
    )


# Renders `terracube COMMAND --help` of every command in one process, as the console script does.
_RENDER_HELP = r"""
import contextlib, io, json, sys
import typer
from terracube.cli import app

declared, rendered = {}, {}
group = typer.main.get_command(app)
for name in ["", *group.commands]:
    command = group.commands[name] if name else group
    declared[name] = [(p.opts, p.help or "", bool(p.show_default) and p.default not in (None, False, ()))
                      for p in command.params if getattr(p, "help", None) is not None]
    declared[name].append(((), command.help or "", False))
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        try:
            app([name, "--help"] if name else ["--help"], prog_name="terracube")
        except SystemExit:
            pass
    rendered[name] = out.getvalue()
print(json.dumps({"declared": declared, "rendered": rendered}))
"""


def _flat(text: str) -> str:
    return " ".join(re.sub(r"\x1b\[[0-9;]*m", "", text).split())


def test_the_rendered_help_of_every_command_keeps_units_defaults_and_extras():
    done = subprocess.run(
        [sys.executable, "-c", _RENDER_HELP], capture_output=True, text=True, env=_env(), timeout=120
    )
    assert done.returncode == 0, done.stderr
    help_texts = json.loads(done.stdout)
    declared, rendered = help_texts["declared"], help_texts["rendered"]
    assert {"collapse", "dem", "classify", "fem", "register", "view", "map", "batch", "config"} <= set(
        rendered
    )
    checked = 0
    for name, params in declared.items():
        text = _flat(rendered[name])
        assert text, f"terracube {name} --help printed nothing"
        for opts, help_text, shows_default in params:
            # every bracketed part of the declared help ([m], [deg], [cells], [config ...], [viewer])
            for bracketed in re.findall(r"\[[^\[\]]+\]", help_text):
                assert _flat(bracketed) in text, f"terracube {name} --help lost {bracketed} of {opts}"
                checked += 1
            if shows_default:  # "[default: ...]" ends the option's own help, before the next option
                start = text.find(f"{max(opts, key=len)} ")
                end = text.find("[default:", start)
                assert start >= 0 and 0 <= end - start <= len(" ".join(opts)) + len(help_text) + 150, (
                    f"terracube {name} --help lost the default of {opts}"
                )
    assert checked > 100  # units, config keys and defaults of every shared option
    for units in ("[m]", "[deg]", "[cells]"):
        assert units in _flat(rendered["classify"])
    assert 'pip install "terracube[viewer]"' in _flat(rendered["view"])
    # one meaning for --robot-height (sigma); classify's "high" threshold is --high-height
    for name in ("collapse", "dem", "classify", "fem"):
        assert "--robot-height <float> Robot height [m]: sets σ" in _flat(rendered[name]), name
    assert "--high-height <float> Cells higher than this above the ground [m] are high" in _flat(
        rendered["classify"]
    )
    assert "--origin X Y" in _flat(rendered["dem"]) and "--origin -20 -20" in _flat(rendered["dem"])
    # the defaults estimate the ground (pipeline.terrain_params): the help says so, not "z = 0"
    assert "the ground is estimated instead: the lowest point within 0.5 m of each cell" in _flat(
        rendered["classify"]
    )


def test_version_and_a_preset_on_the_bundled_ouster_scan_with_the_origin_as_its_help_writes_it(
    tmp_path, shared_data
):
    version = _terracube("--version")
    assert version.returncode == 0 and version.stdout.strip() == f"terracube {tc.__version__}"
    scan = shared_data.path("ouster128/ouster128_000000.pcd")
    done = _terracube(
        "classify", str(scan), "--preset", "ouster128", "--origin", "-20", "-20", "--size", "400", "400",
        "-o", str(tmp_path), "--no-png", "--no-cloud",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    from terracube.io import read_points

    points = read_points(scan)
    distance = np.linalg.norm(points, axis=1)
    zeros = int(np.count_nonzero(np.all(points == 0, axis=1)))
    far = int(np.count_nonzero(distance > 40.0))
    assert zeros == 34_102
    assert (
        f"range filter: {zeros + far:,} of {len(points):,} points left out "
        f"({zeros:,} no-returns at (0, 0, 0), {far:,} beyond 40 m)"
    ) in done.stdout
    assert "400 x 400 cells at 0.1 m" in done.stdout
    assert "ground reference: local ground, 5 cells (estimated" in done.stdout
    unknown = _terracube("dem", str(scan), "--preset", "oustr128", "-o", str(tmp_path))
    assert unknown.returncode == 2 and "unknown preset 'oustr128'; did you mean 'ouster128'" in unknown.stderr


def test_view_3d_save_without_the_viewer_extra_stops_before_writing_anything(tmp_path):
    if importlib.util.find_spec("rerun") is not None:
        pytest.skip("rerun-sdk is installed: the check has nothing to refuse")
    scan = tmp_path / "scan.npy"
    np.save(scan, np.random.default_rng(0).uniform(-5, 5, (2000, 3)))
    out = tmp_path / "out"
    done = _terracube("view", str(scan), "-o", str(out), "--3d", "--save", str(out / "x.rrd"))
    assert done.returncode == 2
    assert 'pip install "terracube[viewer]"' in done.stderr
    assert not out.exists() or not any(out.iterdir())  # no picture, no recording


def test_map_writes_every_scan_pose_with_the_kitti_times_and_evo_reads_them(tmp_path, shared_data):
    from terracube.mapping import read_kitti_calibration, read_pose_file
    from terracube.poses import write_kitti_poses, write_tum_poses

    kitti = shared_data.path("kitti_seq00/poses.txt").parent
    out = tmp_path / "map"
    done = _terracube(
        "map", str(kitti / "velodyne"), "-p", str(kitti / "poses.txt"), "--ground-truth",
        str(kitti / "poses.txt"), "-o", str(out), "--no-png",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    times = np.loadtxt(kitti / "times.txt")
    tum = np.loadtxt(out / "trajectory_tum.txt")
    assert tum.shape == (6, 8)
    np.testing.assert_array_equal(tum[:, 0], times[:6])
    assert np.loadtxt(out / "trajectory_kitti.txt").shape == (6, 12)
    assert re.search(r"odometry fallbacks: \d+ of \d+ keyframe steps", done.stdout), done.stdout
    ate = float(re.search(r"mapper RMSE ([0-9.]+) m", done.stdout).group(1))
    # the trajectory is the estimate of every scan: the odometry moved by the keyframes' corrections
    truth = read_pose_file(kitti / "poses.txt", "kitti", read_kitti_calibration(kitti / "calib.txt"))[1]
    estimate = np.loadtxt(out / "trajectory_kitti.txt").reshape(-1, 3, 4)
    errors = np.linalg.norm(estimate[:, :, 3] - truth[:6, :3, 3], axis=1)
    assert ate == pytest.approx(float(np.sqrt(np.mean(errors**2))), abs=2e-3)
    if importlib.util.find_spec("evo") is not None and shutil.which("evo_ape", path=_evo_path()):
        write_kitti_poses(tmp_path / "truth_kitti.txt", truth[:6])
        write_tum_poses(tmp_path / "truth_tum.txt", times[:6], truth[:6])
        for kind in ("kitti", "tum"):
            evo = subprocess.run(
                [shutil.which("evo_ape", path=_evo_path()), kind, str(tmp_path / f"truth_{kind}.txt"),
                 str(out / f"trajectory_{kind}.txt")],
                capture_output=True, text=True, timeout=120,
            )  # fmt: skip
            assert evo.returncode == 0, evo.stderr
            rmse = float(re.search(r"rmse\s+([0-9.]+)", evo.stdout).group(1))
            assert rmse == pytest.approx(ate, abs=2e-3), kind
    # without calib.txt beside the poses: a warning, not silent camera-frame poses
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(kitti / "poses.txt", bare / "poses.txt")
    done = _terracube(
        "map", str(kitti / "velodyne"), "-p", str(bare / "poses.txt"), "--limit", "2", "--no-png",
        "--odometry-only", "-o", str(tmp_path / "bare_map"),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "warning: no calib.txt beside" in done.stderr and "--calib" in done.stderr
    assert "timestamps: none (the pose index)" in done.stdout


def test_the_kitti_car_maps_as_steps_on_its_path_unless_its_returns_are_left_out(tmp_path, shared_data):
    """KITTI's own returns (bonnet, mirrors: up to 2.8 m from the Velodyne) pass the default range
    limits and land ahead of the car in every scan: `map` warns of them, and --preset kitti (its
    min_range 3 m) leaves no step on the path."""
    kitti = shared_data.path("kitti_seq00/poses.txt").parent
    steps = {}
    for name, extra in (("default", []), ("preset", ["--preset", "kitti"])):
        out = tmp_path / name
        done = _terracube(
            "map", str(kitti / "velodyne"), "-p", str(kitti / "poses.txt"), "--odometry-only", "--no-png",
            "-o", str(out), *extra,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        assert ("warning: KITTI .bin scans with min_range 0.1 m" in done.stderr) == (name == "default"), name
        path = np.loadtxt(out / "trajectory_kitti.txt").reshape(-1, 3, 4)[:, :2, 3]  # x, y of each scan
        elevation = tc.ElevationMap.load(out / "global_map.npz")
        x, y = np.meshgrid(*elevation.cell_centers(), indexing="ij")
        ahead = (x > path[0, 0] - 1.0) & (x < path[-1, 0] + 3.0)  # the car drives along +x here
        on_path = ahead & (np.abs(y - np.interp(x, path[:, 0], path[:, 1])) < 1.2)  # the car and its mirrors
        road = np.nanmedian(elevation["min"][on_path])
        steps[name] = int(np.count_nonzero(elevation["max"][on_path] > road + 0.5))
    assert steps["default"] >= 3 and steps["preset"] == 0, steps


def _evo_path() -> str:
    return os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])


def test_collapse_clouds_carry_the_inputs_fields_and_an_organised_pcd_its_image_layout(tmp_path):
    """-f pcd/ply/txt/npz/bin write the input's intensity and ring beside the overhang field, in
    input order, and a PCD from an organised PCD keeps HEIGHT x WIDTH (so shadow_aware can read it
    again); a .bin keeps the real intensity, not 0."""
    from plyfile import PlyData
    from terracube.cli import app
    from terracube.io import read_cloud, write_pcd
    from typer.testing import CliRunner

    rng = np.random.default_rng(7)
    height, width = 8, 500
    azimuth = np.linspace(0, 2 * np.pi, width, endpoint=False)
    elevation = np.radians(np.linspace(-15, 5, height))[:, None]
    ranges = rng.uniform(4.0, 20.0, (height, width))
    xyz = np.stack(
        [ranges * np.cos(elevation) * np.cos(azimuth), ranges * np.cos(elevation) * np.sin(azimuth),
         ranges * np.sin(elevation)], axis=-1,
    ).reshape(-1, 3).astype(np.float32)  # fmt: skip
    xyz[rng.random(len(xyz)) < 0.1] = 0.0  # empty pixels
    intensity = rng.integers(0, 256, len(xyz)).astype(np.uint8)
    ring = np.repeat(np.arange(height, dtype=np.uint16), width)
    write_pcd(tmp_path / "scan.pcd", {"xyz": xyz, "intensity": intensity, "ring": ring})
    data = (tmp_path / "scan.pcd").read_bytes()  # organised, as a driver writes it
    data = data.replace(
        f"WIDTH {len(xyz)}\nHEIGHT 1\n".encode(), f"WIDTH {width}\nHEIGHT {height}\n".encode()
    )
    (tmp_path / "scan.pcd").write_bytes(data)
    runner = CliRunner()
    for fmt in ("pcd", "ply", "txt", "npz"):
        out = tmp_path / fmt
        args = ["collapse", str(tmp_path / "scan.pcd"), "-o", str(out), "-f", fmt, "--no-png", "-e", "0.5"]
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
        written = out / f"scan_classified.{fmt}"
        if fmt == "ply":  # independent of terracube's reader
            vertex = PlyData.read(str(written))["vertex"].data
            np.testing.assert_array_equal(vertex["intensity"], intensity)
            np.testing.assert_array_equal(vertex["ring"], ring)
        back = read_cloud(written)
        np.testing.assert_array_equal(back["intensity"], intensity)
        np.testing.assert_array_equal(back["ring"], ring)
        assert "overhang" in back and len(back["overhang"]) == len(xyz)
    header = (tmp_path / "pcd" / "scan_classified.pcd").read_bytes().split(b"DATA")[0].decode()
    assert "FIELDS x y z intensity ring overhang\n" in header
    assert f"WIDTH {width}\nHEIGHT {height}\n" in header

    # A KITTI .bin keeps its intensity column (float32 rows x, y, z, intensity).
    rows = np.column_stack([xyz[xyz.any(axis=1)], rng.uniform(0, 1, np.count_nonzero(xyz.any(axis=1)))])
    rows.astype("<f4").tofile(tmp_path / "scan.bin")
    result = runner.invoke(
        app, ["collapse", str(tmp_path / "scan.bin"), "-o", str(tmp_path / "bin"), "-f", "bin", "--no-png"]
    )
    assert result.exit_code == 0, result.output
    written = np.fromfile(tmp_path / "bin" / "scan_classified.bin", dtype="<f4").reshape(-1, 4)
    np.testing.assert_array_equal(written, rows.astype("<f4"))


def test_collapse_of_the_real_kitti_scan_to_bin_keeps_its_intensities(shared_data, tmp_path):
    from terracube.cli import app
    from typer.testing import CliRunner

    path = shared_data.path("kitti_seq00/velodyne/000000.bin")
    args = ["collapse", str(path), "--preset", "kitti", "-f", "bin", "-o", str(tmp_path), "--no-png"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    written = np.fromfile(tmp_path / "000000_classified.bin", dtype="<f4").reshape(-1, 4)
    np.testing.assert_array_equal(written, shared_data.kitti_xyzi(0))
    assert np.count_nonzero(written[:, 3]) > 0.9 * len(written)


@pytest.fixture
def kitti_beside_its_text_files(tmp_path, shared_data) -> Path:
    """KITTI's velodyne scans in one folder with the sequence's README.txt and calib.txt."""
    kitti = shared_data.path("kitti_seq00/poses.txt").parent
    folder = tmp_path / "mixseq"
    folder.mkdir()
    for path in [*sorted((kitti / "velodyne").glob("*.bin")), kitti / "README.txt", kitti / "calib.txt"]:
        shutil.copy(path, folder / path.name)
    return folder


@pytest.mark.parametrize("command", ["map", "stream"])
def test_a_folder_of_scans_and_text_files_maps_its_most_common_suffix_and_names_what_it_left_out(
    tmp_path, kitti_beside_its_text_files, command
):
    out = tmp_path / "out"
    done = _terracube(
        command,
        str(kitti_beside_its_text_files),
        "--lidar-only",
        "--preset",
        "kitti",
        "--no-png",
        "-o",
        str(out),
    )
    assert done.returncode == 0, done.stderr
    assert f"{kitti_beside_its_text_files}: 6 .bin scans; 2 other files left out (.txt)" in done.stdout
    assert any(out.iterdir())


def test_a_glob_keeps_every_file_it_matches_and_the_error_starts_its_own_line(
    tmp_path, kitti_beside_its_text_files, shared_data
):
    pattern = str(kitti_beside_its_text_files / "*")
    done = _terracube(
        "map", pattern, "--lidar-only", "--preset", "kitti", "--no-png", "-o", str(tmp_path / "a")
    )
    assert done.returncode == 2
    readme = kitti_beside_its_text_files / "README.txt"
    assert f"\nerror: {readme}: cannot read as .txt" in done.stderr, done.stderr  # not glued onto the bar
    poses = shared_data.path("kitti_seq00/poses.txt")
    done = _terracube("map", pattern, "-p", str(poses), "--no-png", "-o", str(tmp_path / "b"))
    assert done.returncode == 2
    assert f"error: 8 scans (6 .bin, 2 .txt) and 6 poses in {poses}" in done.stderr


def test_an_untrusted_registration_of_unrelated_scans_says_not_trusted_once(shared_data):
    done = _terracube(
        "register",
        str(shared_data.path("ouster128/ouster128_000000.pcd")),
        str(shared_data.path("kitti_seq00/velodyne/000000.bin")),
    )
    assert done.returncode == 1, done.stderr
    line = done.stderr.strip().splitlines()[-1]
    assert line.startswith("registration not trusted: only ") and line.count("not trusted") == 1, line
    assert line.count("found a partner") == 1 and "no better than chance" in line, line  # said once
