"""Reading point clouds and writing classified clouds."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["read_points", "write_classified", "sample_scan_path", "load_sample_scan"]

PathLike = str | Path


def sample_scan_path() -> Path:
    """The bundled Ouster OS-128 sample (MIT licence, see terracube/data/README.md)."""
    return Path(__file__).parent / "data" / "ouster128_sample.npz"


def load_sample_scan() -> np.ndarray:
    """(N, 3) float32 points of the bundled sample scan."""
    return read_points(sample_scan_path())


def read_points(path: PathLike) -> np.ndarray:
    """Read an (N, 3) array of x, y, z [m] from a point-cloud file.

    Supported: KITTI-style ``.bin`` (float32 rows of x, y, z, intensity), ``.npy`` ((N, >=3)),
    ``.npz`` (key ``xyz`` or ``points``, else the first array) and whitespace- or comma-separated
    text (``.txt``, ``.xyz``, ``.csv``, ``.asc``; the first three columns). Raises ``ValueError``
    naming the file for a malformed file and ``FileNotFoundError`` for a missing one.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".bin":
            raw = np.fromfile(path, dtype=np.float32)
            if raw.size % 4 != 0:
                raise ValueError(
                    f"{path}: {path.stat().st_size} bytes is not a whole number of float32 (x, y, z, i) rows"
                )
            return raw.reshape(-1, 4)[:, :3]
        if suffix == ".npy":
            points = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as archive:
                keys = list(archive.keys())
                if not keys:
                    raise ValueError(f"{path}: the archive holds no arrays")
                key = next((k for k in ("xyz", "points") if k in archive), keys[0])
                points = archive[key]
        elif suffix in (".txt", ".xyz", ".csv", ".asc"):
            delimiter = "," if suffix == ".csv" else None
            points = np.loadtxt(path, delimiter=delimiter, ndmin=2, usecols=(0, 1, 2))
        else:
            raise ValueError(
                f"{path}: unknown point-cloud format {suffix!r} (use .bin, .npy, .npz, .txt, .xyz, .csv)"
            )
    except (OSError, EOFError) as error:
        raise ValueError(f"{path}: cannot read: {error}") from error
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"{path}: expected an (N, >=3) array of points, got shape {points.shape}")
    if points.dtype not in (np.float32, np.float64):
        points = points.astype(np.float64)
    return points[:, :3]


def write_classified(path: PathLike, points: np.ndarray, overhang: np.ndarray) -> Path:
    """Write points with a per-point label (0 = retained, 1 = overhang).

    The format follows the suffix: ``.ply`` (binary, float x y z, uchar ``overhang`` and an RGB
    colour: retained grey, overhang red), ``.npz`` (``xyz`` and ``overhang``) or ``.txt``
    (``x y z overhang`` per line).
    """
    path = Path(path)
    points = np.asarray(points)
    overhang = np.asarray(overhang, dtype=bool)
    if points.ndim != 2 or points.shape[1] < 3 or overhang.shape != (points.shape[0],):
        raise ValueError(f"need (N, 3) points and an (N,) mask, got {points.shape} and {overhang.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        from plyfile import PlyData, PlyElement

        vertex = np.empty(
            points.shape[0],
            dtype=[
                ("x", "f4"),
                ("y", "f4"),
                ("z", "f4"),
                ("overhang", "u1"),
                ("red", "u1"),
                ("green", "u1"),
                ("blue", "u1"),
            ],
        )
        vertex["x"], vertex["y"], vertex["z"] = (points[:, i] for i in range(3))
        vertex["overhang"] = overhang
        vertex["red"] = np.where(overhang, 230, 150)
        vertex["green"] = np.where(overhang, 30, 150)
        vertex["blue"] = np.where(overhang, 30, 150)
        PlyData([PlyElement.describe(vertex, "vertex")], text=False).write(str(path))
    elif suffix == ".npz":
        np.savez_compressed(path, xyz=points[:, :3], overhang=overhang)
    elif suffix == ".txt":
        np.savetxt(path, np.column_stack([points[:, :3], overhang]), fmt=["%.4f", "%.4f", "%.4f", "%d"])
    else:
        raise ValueError(f"{path}: unknown output format {suffix!r} (use .ply, .npz or .txt)")
    return path
