"""Shared fixtures for terracube's Python tests: the real-data folder and its readers.

The real scans live outside the repository (KITTI is CC BY-NC-SA and must not be copied in).
The folder is found through, in order: the environment variable ``TERRACUBE_DATA_DIR``,
``<repo>/../shared/data`` and ``/work/shared/data``. Tests that need a file that is absent are
skipped with a message naming the file and the places searched.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]


def data_dir_candidates() -> list[Path]:
    """Folders searched for the real data, in priority order."""
    candidates = []
    if os.environ.get("TERRACUBE_DATA_DIR"):
        candidates.append(Path(os.environ["TERRACUBE_DATA_DIR"]))
    candidates.append(REPO_ROOT.parent / "shared" / "data")
    candidates.append(Path("/work/shared/data"))
    return candidates


def find_data_dir() -> Path | None:
    """The first candidate folder that exists, or None."""
    for candidate in data_dir_candidates():
        if candidate.is_dir():
            return candidate
    return None


def read_kitti_bin(path: Path) -> np.ndarray:
    """A KITTI/Ouster ``.bin``: float32 rows (x, y, z, intensity), returned as the (N, 4) array.

    Tests pass ``xyzi[:, :3]``, a strided view, to exercise the zero-copy path of the bindings.
    """
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % 4 != 0:
        raise ValueError(f"{path} holds {raw.size} float32 values, not a multiple of 4")
    return raw.reshape(-1, 4)


def read_semantic_kitti_label(path: Path) -> np.ndarray:
    """A SemanticKITTI ``.label``: uint32 per point; the semantic class is ``value & 0xFFFF``."""
    return np.fromfile(path, dtype=np.uint32) & np.uint32(0xFFFF)


class SharedData:
    """Paths and readers for the real-data folder; missing files skip the calling test."""

    def __init__(self, root: Path):
        self.root = root

    def path(self, relative: str) -> Path:
        path = self.root / relative
        if not path.is_file():
            pytest.skip(f"real data file {relative} not found under {self.root}")
        return path

    def kitti_xyzi(self, frame: int) -> np.ndarray:
        """KITTI odometry seq 00 frame `frame`: (N, 4) float32 x, y, z, intensity."""
        return read_kitti_bin(self.path(f"kitti_seq00/velodyne/{frame:06d}.bin"))

    def kitti_labels(self, frame: int) -> np.ndarray:
        """SemanticKITTI semantic classes of frame `frame` (uint32, value & 0xFFFF)."""
        return read_semantic_kitti_label(self.path(f"kitti_seq00/labels/{frame:06d}.label"))

    def kitti_poses(self) -> np.ndarray:
        """(K, 4, 4) KITTI 00 ground-truth poses as Velodyne poses (odometry <- sensor), via calib.txt."""
        from terracube.mapping import read_kitti_calibration, read_pose_file

        calibration = read_kitti_calibration(self.path("kitti_seq00/calib.txt"))
        return read_pose_file(self.path("kitti_seq00/poses.txt"), "kitti", calibration)[1]

    def ouster_xyzi(self) -> np.ndarray:
        """The Ouster 128-beam scan 000000 with invalid returns dropped: (N, 4) float32."""
        return read_kitti_bin(self.path("ouster128/ouster128_000000_xyzi_valid.bin"))


@pytest.fixture(scope="session")
def shared_data() -> SharedData:
    """The real-data folder; skips the test when none of the candidate folders exists."""
    root = find_data_dir()
    if root is None:
        searched = ", ".join(str(c) for c in data_dir_candidates())
        pytest.skip(f"real data folder not found (set TERRACUBE_DATA_DIR); searched: {searched}")
    return SharedData(root)
