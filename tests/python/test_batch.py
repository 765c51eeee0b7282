"""Batch processing (Dask, or a local process pool): a folder of three small scans and one corrupt file.

Each good file's outputs equal the single-file API's; the corrupt file is reported with its name
and problem while the others finish; the command exits 1. Local clusters are small (1-2 workers).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import terracube as tc
from terracube.batch import FileRecord, expand_inputs, format_summary, run_batch
from terracube.cli import app
from terracube.config import default_config
from terracube.io import read_cloud, write_classified, write_pcd
from terracube.pipeline import read_returns_and_beams, read_scan, read_scan_and_beams
from typer.testing import CliRunner


def _scene(seed: int) -> np.ndarray:
    """Ground, a canopy 3 m up, a wall and five no-returns at (0, 0, 0); a different sample per seed."""
    rng = np.random.default_rng(seed)
    ground = np.c_[rng.uniform(0, 8, (3000, 2)), rng.normal(0, 0.02, 3000)]
    canopy = np.c_[rng.uniform(2, 4, (400, 2)), rng.uniform(3.0, 3.3, 400)]
    wall = np.c_[np.full(300, 7.0), rng.uniform(0, 8, 300), rng.uniform(0, 2.0, 300)]
    return np.vstack([ground, canopy, wall, np.zeros((5, 3))]).astype(np.float32)


@pytest.fixture
def scan_folder(tmp_path):
    """scan_a.npy, scan_b.pcd, scan_c.laz and broken.pcd (a binary PCD cut in half)."""
    folder = tmp_path / "scans"
    folder.mkdir()
    scans = {"scan_a": _scene(1), "scan_b": _scene(2), "scan_c": _scene(3).astype(np.float64)}
    np.save(folder / "scan_a.npy", scans["scan_a"])
    write_pcd(folder / "scan_b.pcd", {"xyz": scans["scan_b"]})
    write_classified(folder / "scan_c.laz", scans["scan_c"], np.zeros(len(scans["scan_c"]), np.uint8))
    scans["scan_c"] = read_cloud(folder / "scan_c.laz")["xyz"]  # as stored, at 0.1 mm
    data = write_pcd(tmp_path / "whole.pcd", {"xyz": _scene(4)}).read_bytes()
    (folder / "broken.pcd").write_bytes(data[: len(data) // 2])
    (folder / "notes.md").write_text("not a scan")  # ignored: not a point-cloud suffix
    return folder, scans


def _check_dem_outputs(out: Path, scans: dict[str, np.ndarray]) -> None:
    for name, points in scans.items():
        saved = tc.ElevationMap.load(out / f"{name}_dem.npz")
        # the stages leave out points within frame.min_range (0.1 m) of the sensor: this scene's corner
        in_range = default_config().frame.in_range(points)
        expected, _ = tc.dem_without_overhangs(points[in_range], 0.5, 2, 0.25)
        for layer in ("count", "max", "clearance"):
            np.testing.assert_array_equal(saved[layer], expected[layer], err_msg=f"{name} {layer}")


def test_run_batch_processes_the_good_files_and_reports_the_corrupt_one(tmp_path, scan_folder):
    folder, scans = scan_folder
    config = default_config().replace("elevation", resolution=0.25)
    out = tmp_path / "out"
    records = run_batch(
        "dem",
        [folder],
        out,
        config=config,
        options={"png": False},
        workers=2,
        processes=False,
        progress=False,
    )
    assert [Path(r.path).name for r in records] == ["broken.pcd", "scan_a.npy", "scan_b.pcd", "scan_c.laz"]
    broken, *good = records
    assert broken.status == "failed" and not broken.ok and broken.outputs == []
    assert "broken.pcd: truncated binary PCD" in broken.error
    for record, (name, points) in zip(good, scans.items(), strict=True):
        assert record.ok, record.error
        assert record.points == len(points)
        assert [Path(p).name for p in record.outputs] == [f"{name}_dem.npz"]
        assert record.seconds > 0
    _check_dem_outputs(out, scans)


@pytest.mark.parametrize("reader", [read_scan, read_scan_and_beams, read_returns_and_beams])
@pytest.mark.parametrize("name", ["e.bin", "e.npy", "e.txt"])
def test_every_scan_reader_refuses_a_file_without_points_naming_it(tmp_path, reader, name):
    path = tmp_path / name
    write_classified(path, np.zeros((0, 3), np.float32), np.zeros(0, bool))
    assert len(read_cloud(path)["xyz"]) == 0  # the file reader itself reads an empty cloud
    with pytest.raises(ValueError, match=f"^{re.escape(str(path))}: the file holds no points$"):
        reader(path)


def test_run_batch_counts_a_scan_without_points_as_failed(tmp_path, scan_folder):
    folder, _ = scan_folder
    (folder / "e.bin").write_bytes(b"")
    records = run_batch(
        "collapse",
        [folder / "e.bin", folder / "scan_a.npy"],
        tmp_path / "out",
        options={"png": False},
        workers=1,
        processes=False,
        progress=False,
    )
    empty, good = records
    assert empty.status == "failed" and empty.outputs == [] and good.ok, good.error
    assert empty.error == f"{folder / 'e.bin'}: the file holds no points"


def test_a_glob_and_files_are_expanded_in_order_without_duplicates(scan_folder):
    folder, _ = scan_folder
    found = expand_inputs([str(folder / "scan_*"), folder / "scan_a.npy", str(folder / "broken.pcd")])
    assert [p.name for p in found] == ["scan_a.npy", "scan_b.pcd", "scan_c.laz", "broken.pcd"]
    assert [p.name for p in expand_inputs([folder])] == [
        "broken.pcd",
        "scan_a.npy",
        "scan_b.pcd",
        "scan_c.laz",
    ]
    with pytest.raises(ValueError, match=r"nothing\.pcd: no such file or folder"):
        expand_inputs([folder / "nothing.pcd"])
    with pytest.raises(ValueError, match=r"\*\.las: the pattern matches no file"):
        expand_inputs([str(folder / "*.las")])
    empty = folder / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="the folder holds no scan"):
        expand_inputs([empty])


def test_run_batch_refuses_an_unknown_stage_before_starting_a_cluster(tmp_path, scan_folder):
    with pytest.raises(ValueError, match="unknown stage 'register'"):
        run_batch("register", [scan_folder[0]], tmp_path)
    with pytest.raises(ValueError, match="workers must be at least 1"):
        run_batch("dem", [scan_folder[0]], tmp_path, workers=0)


def test_the_summary_table_lists_every_file_and_the_failure_in_full():
    records = [
        FileRecord("a/scan_a.npy", "dem", "ok", 3700, 0.5, ["out/scan_a_dem.npz"]),
        FileRecord(
            "a/broken.pcd",
            "dem",
            "failed",
            None,
            0.01,
            error="a/broken.pcd: truncated binary PCD " + "x" * 80,
        ),
    ]
    lines = format_summary(records).splitlines()
    assert lines[0].split() == ["file", "points", "status", "seconds", "outputs"]
    assert lines[2].split() == ["scan_a.npy", "3,700", "ok", "0.50", "scan_a_dem.npz"]
    assert lines[3].split()[:4] == ["broken.pcd", "-", "failed", "0.01"] and lines[3].endswith("...")
    assert lines[4] == "failed: " + records[1].error
    assert lines[5] == "1 of 2 files ok, 1 failed; 3,700 points; 0.51 s of work"


def test_terracube_batch_collapse_as_a_user_runs_it(tmp_path, scan_folder):
    folder, scans = scan_folder
    out = tmp_path / "out"
    result = CliRunner().invoke(
        app,
        ["batch", "collapse", str(folder), "--out", str(out), "--workers", "2", "--threads", "-f", "npz"],
    )
    assert result.exit_code == 1, result.output  # one file failed
    assert "broken.pcd" in result.output and "failed" in result.output
    assert "3 of 4 files ok, 1 failed" in result.output
    for name, points in scans.items():
        saved = np.load(out / f"{name}_classified.npz")
        in_range = default_config().frame.in_range(points)  # the rest is labelled "not overhang"
        expected = np.zeros(len(points), bool)
        expected[in_range] = tc.collapse_overhangs(points[in_range], 0.5, 2).overhang
        np.testing.assert_array_equal(saved["overhang"], expected)
        assert not (out / f"{name}_overhangs.png").exists()  # batch draws no pictures unless --png
        # each file's report notes are under the summary: the points within 0.1 m of the sensor
        dropped = len(points) - int(in_range.sum())
        assert dropped > 0
        assert any(
            line.startswith(f"{name}.") and f"range filter: {dropped:,} of {len(points):,} points" in line
            for line in result.output.splitlines()
        ), result.output


def test_terracube_batch_with_only_good_files_exits_0_and_bad_arguments_exit_2(tmp_path, scan_folder):
    folder, _ = scan_folder
    runner = CliRunner()
    good = [str(folder / "scan_a.npy"), str(folder / "scan_b.pcd")]
    result = runner.invoke(app, ["batch", "classify", *good, "--out", str(tmp_path), "-w", "1", "--threads"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "scan_b_classes.npz").is_file() and (tmp_path / "scan_b_classes.ply").is_file()
    result = runner.invoke(app, ["batch", "view", *good, "--out", str(tmp_path)])
    assert result.exit_code == 2 and "batch runs collapse, dem, classify, fem" in result.output
    result = runner.invoke(app, ["batch", "dem", str(folder / "nope*.pcd"), "--out", str(tmp_path)])
    assert result.exit_code == 2 and "matches no file" in result.output


def test_the_console_script_runs_a_batch_on_local_worker_processes(tmp_path, scan_folder):
    """A real subprocess of ``python -m terracube``, with a LocalCluster of one worker process."""
    folder, scans = scan_folder
    config = tmp_path / "fine.yaml"
    config.write_text("elevation:\n  resolution: 0.25\n")
    env = dict(os.environ)
    # The subprocess imports the same terracube as this test (installed, or a source tree with _core).
    package_root = str(Path(tc.__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [package_root, env.get("PYTHONPATH")]))
    out = tmp_path / "out"
    completed = subprocess.run(
        [sys.executable, "-m", "terracube", "batch", "dem", str(folder), "--out", str(out), "-w", "1",
         "-c", str(config), "--no-png"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )  # fmt: skip
    assert completed.returncode == 1, completed.stderr
    assert "3 of 4 files ok, 1 failed" in completed.stdout
    assert "broken.pcd: truncated binary PCD" in completed.stdout
    assert "1 of 4 files failed" in completed.stderr
    # a normal shutdown of the Dask cluster (or the pool) says nothing: no warnings, no tracebacks
    noise = [
        line
        for line in completed.stderr.splitlines()
        if "warning" in line.lower() or "distributed." in line or "Traceback" in line
    ]
    assert noise == [], completed.stderr
    _check_dem_outputs(out, scans)


@pytest.mark.parametrize("processes", [False, True], ids=["threads", "processes"])
def test_the_local_pool_writes_the_same_maps_as_the_single_file_api(tmp_path, scan_folder, processes):
    folder, scans = scan_folder
    out = tmp_path / "out"
    records = run_batch(
        "dem",
        [folder],
        out,
        config=default_config().replace("elevation", resolution=0.25),
        options={"png": False},
        workers=2,
        processes=processes,
        progress=False,
        backend="pool",
    )
    assert [r.ok for r in records] == [False, True, True, True]
    assert "broken.pcd: truncated binary PCD" in records[0].error
    _check_dem_outputs(out, scans)


def test_without_dask_batch_runs_on_the_local_pool(tmp_path, scan_folder, monkeypatch):
    import terracube.batch as batch

    def no_dask(*args):
        raise AssertionError("Dask was used")

    monkeypatch.setattr(batch, "_dask_available", lambda: False)
    monkeypatch.setattr(batch, "_dask_jobs", no_dask)
    records = run_batch("collapse", [scan_folder[0] / "scan_a.npy"], tmp_path, options={"png": False},
                        workers=1, processes=False, progress=False)  # fmt: skip
    assert records[0].ok, records[0].error
    with pytest.raises(ValueError, match="a Dask scheduler needs the dask backend"):
        run_batch("dem", [scan_folder[0]], tmp_path, scheduler="tcp://127.0.0.1:1", backend="pool")


def test_terracube_batch_takes_the_stage_options_of_the_single_file_command(tmp_path, scan_folder):
    folder, scans = scan_folder
    out = tmp_path / "out"
    args = ["batch", "dem", str(folder), "--out", str(out), "-w", "1", "--threads", "--backend", "pool"]
    result = CliRunner().invoke(app, [*args, "-r", "0.25", "--no-png", "--edge", "0.5", "--sigma", "2"])
    assert result.exit_code == 1, result.output  # broken.pcd
    _check_dem_outputs(out, scans)
    result = CliRunner().invoke(app, [*args, "--reference", "nowhere"])
    assert result.exit_code == 2 and "--reference must be one of" in result.output


# A file that hangs or kills its worker (issue 39, item 7): reported with its cause; the rest finish.

_SABOTAGE = """
import os, signal, time
import terracube.batch as batch

_read_stage_input = batch.read_stage_input

def read_stage_input(path, config):
    name = os.path.basename(str(path))
    if name.startswith("hang"):
        time.sleep(3600)
    if name.startswith("crash"):
        os.kill(os.getpid(), signal.SIGKILL)
    return _read_stage_input(path, config)

batch.read_stage_input = read_stage_input
"""


@pytest.fixture
def sabotaged_workers(tmp_path, monkeypatch):
    """Worker processes (spawned, so they start from the environment) in which reading a file named
    hang* sleeps for an hour and reading one named crash* kills the worker (SIGKILL, as the OOM
    killer does)."""
    hooks = tmp_path / "hooks"
    hooks.mkdir()
    (hooks / "sitecustomize.py").write_text(_SABOTAGE)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(hooks), *sys.path]))
    return hooks


def test_a_hanging_file_times_out_and_the_others_finish(tmp_path, scan_folder, sabotaged_workers):
    folder, scans = scan_folder
    np.save(folder / "hang.npy", scans["scan_a"])
    inputs = [folder / "scan_a.npy", folder / "hang.npy", folder / "scan_b.pcd"]
    start = time.monotonic()
    # 8 s: the good files must finish well within it on a loaded machine
    records = run_batch("dem", inputs, tmp_path / "out", workers=1, progress=False, backend="pool", timeout=8)
    assert time.monotonic() - start < 90
    assert [r.status for r in records] == ["ok", "failed", "ok"], [r.error for r in records]
    assert records[1].error == f"{folder / 'hang.npy'}: timed out after 8 s " + (
        "(its worker was stopped; raise --timeout for bigger scans)"
    )
    assert "timed out after 8 s" in format_summary(records)
    assert 8.0 <= records[1].seconds < 60  # the time it took until the timeout, not 0.00


def test_a_worker_killed_by_a_signal_is_reported_with_the_signal(tmp_path, scan_folder, sabotaged_workers):
    folder, scans = scan_folder
    np.save(folder / "crash.npy", scans["scan_a"])
    inputs = [folder / "crash.npy", folder / "scan_a.npy"]
    records = run_batch("dem", inputs, tmp_path / "out", workers=1, progress=False, backend="pool")
    assert [r.status for r in records] == ["failed", "ok"]
    assert records[0].error.endswith(
        "its worker process died of SIGKILL (killed, e.g. out of memory) while running it"
    )


@pytest.mark.parametrize("backend", ["pool", "dask"])
def test_a_hanging_file_on_a_thread_worker_times_out_and_the_summary_says_so(
    tmp_path, scan_folder, monkeypatch, capfd, backend
):
    if backend == "dask":
        pytest.importorskip("dask.distributed")
    import terracube.batch as batch

    folder, _ = scan_folder
    release = threading.Event()
    real = batch.read_stage_input
    monkeypatch.setattr(
        batch, "read_stage_input", lambda p, c: release.wait() if "scan_a" in str(p) else real(p, c)
    )
    inputs = [folder / "scan_b.pcd", folder / "scan_a.npy"]
    try:  # worker threads in this process (processes=False), so the patch reaches them
        records = run_batch(
            "dem",
            inputs,
            tmp_path / "out",
            workers=1,
            processes=False,
            progress=False,
            backend=backend,
            timeout=8,
        )
    finally:
        release.set()
    assert [r.status for r in records] == ["ok", "failed"], [r.error for r in records]
    assert records[1].error.endswith(
        "timed out after 8 s (its worker thread, which cannot be stopped, was given up; raise --timeout for "
        "bigger scans)"
    )
    assert 8.0 <= records[1].seconds < 60  # the time it took until the timeout, not 0.00
    assert " - WARNING - " not in capfd.readouterr().err  # Dask's own log lines stay off the console


def test_run_batch_draws_no_pictures_unless_asked_like_the_command(tmp_path, scan_folder):
    folder, _ = scan_folder
    inputs = [folder / "scan_a.npy"]
    [plain] = run_batch("dem", inputs, tmp_path / "plain", workers=1, processes=False, progress=False)
    assert [Path(p).name for p in plain.outputs] == ["scan_a_dem.npz"]
    pytest.importorskip("matplotlib")
    [drawn] = run_batch(
        "dem", inputs, tmp_path / "drawn", options={"png": True}, workers=1, processes=False, progress=False
    )
    assert any(p.endswith(".png") for p in drawn.outputs)


def test_run_batch_in_a_script_without_a_main_guard_fails_with_one_clear_error(tmp_path, scan_folder):
    folder, _ = scan_folder
    script = tmp_path / "no_guard.py"
    script.write_text(
        "import terracube.batch\n"
        f"terracube.batch.run_batch('dem', [{str(folder / 'scan_a.npy')!r}], {str(tmp_path / 'out')!r},"
        " workers=1, backend='pool', progress=False)\n"
    )
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert result.stderr.count("Traceback") == 1, result.stderr
    assert 'put the call under `if __name__ == "__main__":`' in result.stderr
    assert "bootstrapping phase" not in result.stderr  # multiprocessing's own error


def test_a_negative_timeout_is_refused(tmp_path, scan_folder):
    with pytest.raises(ValueError, match="timeout must be a number of seconds >= 0"):
        run_batch("dem", [scan_folder[0]], tmp_path / "out", timeout=-1, backend="pool")
