"""Bad paths and options give one ``error:`` line and exit code 2, never a traceback (issue 39,
item 8). Run as a user runs them: ``python -m terracube ...`` in a subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import terracube

# The folder of the terracube these tests import (installed, or the source tree with its built core).
PYTHON_DIR = Path(terracube.__file__).resolve().parents[1]


def _terracube(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(PYTHON_DIR), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run(
        [sys.executable, "-m", "terracube", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.fixture
def workspace(tmp_path):
    rng = np.random.default_rng(8)
    np.save(tmp_path / "scan.npy", rng.uniform(0, 5, (2000, 3)).astype(np.float32))
    np.save(tmp_path / "empty.npy", np.zeros((0, 3), np.float32))
    (tmp_path / "e.bin").write_bytes(b"")
    (tmp_path / "afile").write_text("not a folder")
    (tmp_path / "scans").mkdir()
    np.save(tmp_path / "scans" / "000000.npy", rng.uniform(0, 5, (2000, 3)).astype(np.float32))
    (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    (tmp_path / "deep.yaml").write_text("collapse:\n  edge: " + "[" * 20000 + "]" * 20000 + "\n")
    return tmp_path


LONG = "x" * 300

CASES = {  # id: (command line, the error line holds)
    "output folder is a file": (
        "dem scan.npy -o afile",
        "error: --output-dir afile: exists and is not a folder",
    ),
    "output folder under a file": (
        "dem scan.npy -o afile/sub",
        "error: --output-dir afile/sub: not a directory",
    ),
    "output name too long": (f"dem scan.npy -o out/{LONG}", "file name too long"),
    "input name too long": (f"dem {LONG}.npy", "file name too long"),
    "empty scan, one prefix": ("dem empty.npy -o out", "error: empty.npy: the file holds no points"),
    **{
        f"0-byte scan, {command}": (f"{command} e.bin -o out", "error: e.bin: the file holds no points")
        for command in ("collapse", "dem", "classify", "fem", "view")
    },
    "0-byte scan, register": ("register e.bin scan.npy", "error: e.bin: the file holds no points"),
    "0-byte scan, shadow-aware collapse": (
        "collapse e.bin --method shadow_aware -o out",
        "error: e.bin: the file holds no points",
    ),
    "missing --calib": (
        "map scans -p poses.txt --calib no.txt -o out",
        "error: --calib no.txt: no such file",
    ),
    "missing --ground-truth": (
        "map scans -p poses.txt --ground-truth no.txt",
        "--ground-truth no.txt: no such",
    ),
    **{
        f"--limit {n}, {command}": (
            f"{command} scans --lidar-only --limit {n} -o out",
            f"error: --limit {n}: give how many scans to use, at least 1",
        )
        for command in ("map", "stream")
        for n in (0, -1)
    },
    "--high-height below --ground-height": (
        "classify scan.npy --ground-height 1 --high-height 0.5 -o out",
        "error: --high-height 0.5 is below --ground-height 1: cells above --high-height are high",
    ),
    "--high-height below the configured ground height": (
        "classify scan.npy --high-height 0.1 -o out",
        "error: --high-height 0.1 is below --ground-height 0.2 (terrain.ground_height of the configuration)",
    ),
    "config -o a folder": ("config -o .", "error: --output .: is a folder"),
    "batch --out a file": (
        "batch dem scan.npy --out afile",
        "error: --out afile: exists and is not a folder",
    ),
    "bad --scheduler": (
        "batch dem scan.npy --out out --scheduler x",
        "error: --scheduler must be an address",
    ),
    "deeply nested YAML": (
        "dem scan.npy -c deep.yaml",
        "error: deep.yaml: not valid YAML at line 2, column 71",
    ),
}


@pytest.mark.parametrize("args, message", CASES.values(), ids=CASES.keys())
def test_a_bad_path_or_option_is_one_error_line_and_exit_2(workspace, args, message):
    args = args.split()
    completed = _terracube(*args, cwd=workspace)
    assert completed.returncode == 2, completed.stderr
    assert "Traceback" not in completed.stderr and "─" not in completed.stderr
    errors = [line for line in completed.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and message in errors[0], completed.stderr
    assert errors[0].count(": empty:") <= 1
    assert not (workspace / "out").exists() or args[0] == "map" or not any((workspace / "out").iterdir())


def test_a_full_disk_is_an_error_line_and_leaves_no_half_written_map(workspace, monkeypatch):
    import errno

    from terracube.cli import app
    from typer.testing import CliRunner

    def disk_full(file, *args, **kwargs):
        Path(file).write_bytes(b"PK\x03\x04 half")
        raise OSError(errno.ENOSPC, "No space left on device", str(file))

    monkeypatch.setattr(np, "savez_compressed", disk_full)
    out = workspace / "out"
    result = CliRunner().invoke(app, ["dem", str(workspace / "scan.npy"), "-o", str(out), "--no-png"])
    assert result.exit_code == 2, result.output
    assert "no space left on device" in result.output and "Traceback" not in result.output
    assert list(out.iterdir()) == []  # neither scan_dem.npz nor its temporary file
