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
