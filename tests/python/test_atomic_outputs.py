"""Outputs are whole or absent (issue 39, item 6): every writer writes to a temporary name in the
target folder and renames it on success, so a failure half-way leaves neither the final file nor
a temporary one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from terracube.io import WRITE_SUFFIXES, atomic_path, read_cloud, write_classified, write_pcd

RNG = np.random.default_rng(39)
POINTS = RNG.uniform(-5, 5, size=(200, 3)).astype(np.float32)
LABELS = RNG.integers(0, 6, size=200).astype(np.uint8)


class DiskFull(OSError):
    pass


def _fail_half_way(*args, **kwargs):
    """A writer that leaves a partial file under the name it was given, then fails."""
    target = next(a for a in (*args, *kwargs.values()) if isinstance(a, (str, Path)) or hasattr(a, "write"))
    if isinstance(target, (str, Path)):
        Path(target).write_bytes(b"partial")
    raise DiskFull(28, "No space left on device")


def test_atomic_path_renames_on_success_and_keeps_the_suffix(tmp_path):
    final = tmp_path / "sub" / "map.npz"
    with atomic_path(final) as temporary:
        assert temporary.parent == final.parent and temporary.suffix == ".npz"
        np.savez(temporary, a=np.arange(3))  # savez would append .npz to a name without it
    assert sorted(p.name for p in final.parent.iterdir()) == ["map.npz"]


def test_atomic_path_removes_the_temporary_file_on_failure(tmp_path):
    final = tmp_path / "out.txt"
    with pytest.raises(RuntimeError), atomic_path(final) as temporary:
        temporary.write_text("half")
        raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


def test_atomic_path_keeps_the_old_file_when_the_new_one_fails(tmp_path):
    final = tmp_path / "out.txt"
    final.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(final) as temporary:
        temporary.write_text("new, half")
        raise RuntimeError("killed")
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"] and final.read_text() == "old"


@pytest.mark.parametrize(
    "suffix, target",
    [
        (".ply", "plyfile.PlyData.write"),
        (".las", "laspy.LasData.write"),
        (".laz", "laspy.LasData.write"),
        (".npz", "numpy.savez_compressed"),
        (".npy", "numpy.save"),
        (".txt", "numpy.savetxt"),
        (".pcd", "pypcd4.PointCloud.save"),
    ],
)
def test_write_classified_failing_half_way_leaves_no_file(tmp_path, monkeypatch, suffix, target):
    module, _, attribute = target.rpartition(".")
    owner = __import__(module.split(".")[0])
    for part in module.split(".")[1:]:
        owner = getattr(owner, part)
    monkeypatch.setattr(owner, attribute, _fail_half_way)
    with pytest.raises(OSError, match="No space left"):
        write_classified(tmp_path / f"scan_classified{suffix}", POINTS, LABELS)
    assert list(tmp_path.iterdir()) == []


def test_write_kitti_bin_failing_half_way_leaves_no_scan(tmp_path, monkeypatch):
    import terracube.io as io

    real = io.atomic_path

    def failing(path):
        context = real(path)

        class Wrapper:
            def __enter__(self):
                self.temporary = context.__enter__()
                return self.temporary

            def __exit__(self, *exc):
                if exc[0] is None and self.temporary.suffix == ".bin":
                    self.temporary.write_bytes(b"xx")
                    exc = (DiskFull, DiskFull(28, "No space left on device"), None)
                    context.__exit__(*exc)
                    raise exc[1]
                return context.__exit__(*exc)

        return Wrapper()

    monkeypatch.setattr(io, "atomic_path", failing)
    with pytest.raises(OSError, match="No space left"):
        write_classified(tmp_path / "scan.bin", POINTS, LABELS)
    assert not (tmp_path / "scan.bin").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["scan.label"]


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_write_pcd_failing_half_way_leaves_no_file(tmp_path, monkeypatch, encoding):
    target = "numpy.savetxt" if encoding == "ascii" else "pypcd4.PointCloud.save"
    module, _, attribute = target.rpartition(".")
    owner = __import__(module.split(".")[0])
    for part in module.split(".")[1:]:
        owner = getattr(owner, part)
    monkeypatch.setattr(owner, attribute, _fail_half_way)
    with pytest.raises(OSError):
        write_pcd(tmp_path / "cloud.pcd", {"xyz": POINTS}, encoding=encoding)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", WRITE_SUFFIXES)
def test_write_classified_leaves_only_the_final_files(tmp_path, suffix):
    path = write_classified(tmp_path / f"scan{suffix}", POINTS, LABELS)
    expected = {path.name} | ({path.with_suffix(".label").name} if suffix == ".bin" else set())
    assert {p.name for p in tmp_path.iterdir()} == expected
    if suffix != ".npy":
        np.testing.assert_array_equal(read_cloud(path)["label"], LABELS)


def test_elevation_map_save_failing_half_way_leaves_no_file(tmp_path, monkeypatch):
    from terracube import ElevationMap

    elevation_map = ElevationMap.empty(0.5, (0.0, 0.0), (4, 3))
    monkeypatch.setattr(np, "savez_compressed", _fail_half_way)
    with pytest.raises(OSError):
        elevation_map.save(tmp_path / "scan_dem.npz")
    assert list(tmp_path.iterdir()) == []


def test_pose_writers_failing_half_way_leave_no_file(tmp_path, monkeypatch):
    import terracube.poses as poses_module

    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    real = poses_module.quaternion_from_matrix
    calls = []

    def failing_on_the_second_pose(matrix):
        calls.append(1)
        if len(calls) == 2:
            raise DiskFull(28, "No space left on device")
        return real(matrix)

    monkeypatch.setattr(poses_module, "quaternion_from_matrix", failing_on_the_second_pose)
    with pytest.raises(OSError):
        poses_module.write_tum_poses(tmp_path / "poses.txt", [0.0, 0.1, 0.2], poses)
    assert list(tmp_path.iterdir()) == []


def test_atomic_path_under_a_file_says_the_file_is_not_a_folder(tmp_path):
    (tmp_path / "afile").write_text("x")
    with (
        pytest.raises(NotADirectoryError, match="Not a directory") as caught,
        atomic_path(tmp_path / "afile" / "sub" / "x.npz"),
    ):
        pass
    assert caught.value.filename == str(tmp_path / "afile")


class _FakeRerun:
    """Stands in for the rerun module (an extra): save() opens the recording, log() writes to it."""

    def __init__(self, fail: bool):
        self.fail, self.file = fail, None

    def init(self, *args, **kwargs):
        pass

    def save(self, path):
        self.file = open(path, "wb")  # noqa: SIM115 - closed by disconnect, as rerun does

    def Points3D(self, *args, **kwargs):  # noqa: N802 - rerun's name
        return b"points"

    def log(self, entity, data):
        self.file.write(data)
        if self.fail:
            raise RuntimeError("the viewer failed half-way")

    def disconnect(self):
        self.file.close()


@pytest.mark.parametrize("fail", [False, True])
def test_viewer_recordings_are_written_atomically(tmp_path, monkeypatch, fail):
    from terracube import viewer

    rerun = _FakeRerun(fail)
    monkeypatch.setattr(viewer, "_rerun", lambda: rerun)
    target = tmp_path / "scan.rrd"
    if fail:
        with pytest.raises(RuntimeError, match="half-way"):
            viewer.show_cloud(np.zeros((4, 3)), save=target)
        assert list(tmp_path.iterdir()) == []
    else:
        assert viewer.show_cloud(np.zeros((4, 3)), save=target) == target
        assert target.read_bytes() == b"points" and [p.name for p in tmp_path.iterdir()] == ["scan.rrd"]
