"""Pose files: the KITTI odometry format and the TUM RGB-D format.

KITTI: one pose per line, the 12 numbers of the 3x4 row-major matrix ``[R | t]`` (the last row
``0 0 0 1`` is implied). TUM: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` starts a
comment line. Poses are (K, 4, 4) float64 arrays of rigid sensor-to-world transforms. Malformed
lines raise ``ValueError`` naming the file and the line number.

The core takes a rotation R as one when no entry of R^T R - I exceeds :data:`RIGID_TOLERANCE`
(1e-5: six significant digits). Files round further (``%.4f``, ``%.3f``): their rotations, up to
1e-3 off, are replaced by the nearest rotation (:func:`nearest_rigid`), with a warning.
"""

from __future__ import annotations

import math
import warnings
from os import PathLike
from pathlib import Path

import numpy as np

__all__ = [
    "RIGID_TOLERANCE",
    "matrix_from_quaternion",
    "nearest_rigid",
    "quaternion_from_matrix",
    "read_kitti_poses",
    "read_times",
    "read_tum_poses",
    "write_kitti_poses",
    "write_tum_poses",
]

#: Largest |R^T R - I| entry the core accepts in a rigid transform (cloud_frame.cpp's
#: check_rigid_transform): poses written with six significant digits pass as they are.
RIGID_TOLERANCE = 1e-5
#: Largest |R^T R - I| entry read from a file (rounded to 3 decimals); beyond RIGID_TOLERANCE the
#: nearest rotation replaces it.
_FILE_TOLERANCE = 1e-3


def _numbers(path: Path, number: int, line: str, expected: int, what: str) -> list[float]:
    fields = line.split()
    if len(fields) != expected:
        raise ValueError(f"{path}, line {number}: expected {expected} numbers ({what}), got {len(fields)}")
    values = []
    for field in fields:
        try:
            value = float(field)
        except ValueError:
            raise ValueError(f"{path}, line {number}: cannot read {field!r} as a number") from None
        if not math.isfinite(value):
            raise ValueError(f"{path}, line {number}: {field!r} is not a finite number")
        values.append(value)
    return values


def _deviation(rotation: np.ndarray) -> float:
    return float(np.abs(rotation.T @ rotation - np.eye(3)).max())


def nearest_rigid(transform) -> np.ndarray:
    """The (4, 4) rigid transform nearest to ``transform`` (4 x 4 or 3 x 4): its rotation block
    replaced by the rotation nearest in the Frobenius norm (U V^T of its SVD), the translation kept.
    ValueError for a block that is not finite or is a reflection (negative determinant)."""
    matrix = np.asarray(transform, dtype=np.float64)
    if matrix.shape not in ((4, 4), (3, 4)) or not np.isfinite(matrix).all():
        raise ValueError(f"a transform must be a finite 4x4 or 3x4 array, got shape {matrix.shape}")
    u, _, vt = np.linalg.svd(matrix[:3, :3])
    if np.linalg.det(u @ vt) < 0.0:
        raise ValueError("the 3x3 block is a reflection (negative determinant), not a rotation")
    rigid = np.eye(4)
    rigid[:3, :3] = u @ vt
    rigid[:3, 3] = matrix[:3, 3]
    return rigid


def _rigid_from_file(transform: np.ndarray, where: str) -> tuple[np.ndarray, float]:
    """(transform with a rotation the core accepts, the deviation it had): the nearest rotation
    when it deviates by over RIGID_TOLERANCE; ValueError naming ``where`` beyond _FILE_TOLERANCE."""
    deviation = _deviation(transform[:3, :3])
    if deviation > _FILE_TOLERANCE or np.linalg.det(transform[:3, :3]) < 0.0:
        raise ValueError(
            f"{where}: the 3x3 block is not a rotation "
            f"(|R^T R - I| = {deviation:.3g}, over {_FILE_TOLERANCE:g})"
        )
    if deviation <= RIGID_TOLERANCE:
        return transform, deviation
    return nearest_rigid(transform), deviation


def rigid_from_file(transform, where: str) -> np.ndarray:
    """A 4 x 4 transform read from a file, made rigid for the core: rotations off by up to 1e-3 per
    entry of R^T R - I (coarse rounding) are replaced by the nearest rotation, with a warning naming
    ``where``; further off, or a reflection, ValueError."""
    rigid, deviation = _rigid_from_file(np.asarray(transform, dtype=np.float64), where)
    if deviation > RIGID_TOLERANCE:
        _warn_rounding(where, 1, deviation)
    return rigid


def _warn_rounding(where: str, count: int, deviation: float) -> None:
    rotations = "its rotation" if count == 1 else f"{count} rotations"
    warnings.warn(
        f"{where}: {rotations} rounded beyond six digits (|R^T R - I| up to {deviation:.2g}): the nearest "
        "rotations are used",
        UserWarning,
        stacklevel=3,
    )


def read_kitti_poses(path: str | PathLike) -> np.ndarray:
    """Reads a KITTI pose file into a (K, 4, 4) float64 array; blank lines are skipped.

    Raises
    ------
    ValueError
        A line without exactly 12 finite numbers, a 3x3 block that is not a rotation (see the
        module's note on rounding), or no pose.
    """
    path = Path(path)
    poses, rounded = [], []
    with path.open("r", encoding="utf-8") as file:
        for number, line in enumerate(file, start=1):
            if not line.strip():
                continue
            values = _numbers(path, number, line, 12, "a 3x4 row-major pose")
            pose = np.eye(4)
            pose[:3, :] = np.reshape(values, (3, 4))
            pose, deviation = _rigid_from_file(pose, f"{path}, line {number}")
            if deviation > RIGID_TOLERANCE:
                rounded.append(deviation)
            poses.append(pose)
    if not poses:
        raise ValueError(f"{path} holds no poses")
    if rounded:
        _warn_rounding(str(path), len(rounded), max(rounded))
    return np.stack(poses)


def matrix_from_quaternion(quaternion) -> np.ndarray:
    """The 3x3 rotation of a quaternion given as (qx, qy, qz, qw) (normalised here; not zero)."""
    x, y, z, w = np.asarray(quaternion, dtype=np.float64)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not norm > 0.0 or not math.isfinite(norm):
        raise ValueError(f"quaternion {quaternion} has no direction (zero or non-finite norm)")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quaternion_from_matrix(rotation) -> np.ndarray:
    """The unit quaternion (qx, qy, qz, qw) of a 3x3 rotation, with qw >= 0.

    Shepperd's method: the largest of the four squared components is taken from the diagonal and
    the others from the off-diagonal sums, which keeps the division well conditioned.
    """
    r = np.asarray(rotation, dtype=np.float64)
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    candidates = [trace, r[0, 0], r[1, 1], r[2, 2]]
    largest = int(np.argmax(candidates))
    if largest == 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    elif largest == 1:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif largest == 2:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0.0 else q


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (x, y, z, w), the shorter way round."""
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly parallel: normalised linear interpolation is exact to 1e-7
        q = q0 + alpha * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(dot)
    return (math.sin((1.0 - alpha) * theta) * q0 + math.sin(alpha * theta) * q1) / math.sin(theta)


def interpolate_poses(stamps, poses, times, what: str = "the poses") -> np.ndarray:
    """(M, 4, 4) poses at ``times`` [s] from (K,) ``stamps`` [s] and their (K, 4, 4) ``poses``:
    linear in translation, SLERP in rotation between the two stamps around each time. ValueError
    naming ``what`` for stamps that do not increase or a time outside their span."""
    stamps = np.asarray(stamps, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    if len(stamps) == 0 or np.any(np.diff(stamps) <= 0.0):
        raise ValueError(f"{what}: times must increase to be interpolated")
    out = np.empty((len(times), 4, 4))
    for k, time in enumerate(np.asarray(times, dtype=np.float64)):
        if not stamps[0] <= time <= stamps[-1]:
            raise ValueError(
                f"time {time:.9f} s is outside the span of {what}: [{stamps[0]:.9f}, {stamps[-1]:.9f}] s"
            )
        i = int(np.searchsorted(stamps, time, side="right")) - 1  # stamps[i] <= time
        if time == stamps[i]:  # also the last stamp: no pose after it to interpolate towards
            out[k] = poses[i]
            continue
        alpha = (time - stamps[i]) / (stamps[i + 1] - stamps[i])
        q0, q1 = (quaternion_from_matrix(poses[j, :3, :3]) for j in (i, i + 1))
        out[k] = np.eye(4)
        out[k, :3, :3] = matrix_from_quaternion(slerp(q0, q1, alpha))
        out[k, :3, 3] = (1.0 - alpha) * poses[i, :3, 3] + alpha * poses[i + 1, :3, 3]
    return out


def read_tum_poses(path: str | PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Reads a TUM trajectory: ((K,) timestamps [s], (K, 4, 4) poses). ``#`` lines and blank lines
    are skipped; quaternions are normalised.

    Raises
    ------
    ValueError
        A line without exactly 8 finite numbers, a zero quaternion, or no pose.
    """
    path = Path(path)
    stamps, poses = [], []
    with path.open("r", encoding="utf-8") as file:
        for number, line in enumerate(file, start=1):
            stripped = line.strip()
            if not stripped or stripped.startswith("#"):
                continue
            values = _numbers(path, number, stripped, 8, "timestamp tx ty tz qx qy qz qw")
            pose = np.eye(4)
            try:
                pose[:3, :3] = matrix_from_quaternion(values[4:8])
            except ValueError as error:
                raise ValueError(f"{path}, line {number}: {error}") from None
            pose[:3, 3] = values[1:4]
            stamps.append(values[0])
            poses.append(pose)
    if not poses:
        raise ValueError(f"{path} holds no poses")
    return np.asarray(stamps), np.stack(poses)


def _as_poses(poses) -> np.ndarray:
    array = np.asarray(poses, dtype=np.float64)
    if array.ndim != 3 or array.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"poses must be a (K, 4, 4) or (K, 3, 4) array, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError("poses contain NaN or Inf")
    return array


def write_kitti_poses(path: str | PathLike, poses) -> None:
    """Writes (K, 4, 4) or (K, 3, 4) poses as a KITTI pose file (shortest exact decimals)."""
    from .io import atomic_path

    array = _as_poses(poses)
    with atomic_path(path) as temporary, temporary.open("w", encoding="utf-8") as file:
        for pose in array:
            file.write(" ".join(repr(float(v)) for v in pose[:3, :].ravel()) + "\n")


def write_tum_poses(path: str | PathLike, timestamps, poses) -> None:
    """Writes poses with their timestamps [s] as a TUM trajectory (qw >= 0)."""
    array = _as_poses(poses)
    stamps = np.asarray(timestamps, dtype=np.float64)
    if stamps.shape != (array.shape[0],):
        raise ValueError(f"need one timestamp per pose: {stamps.shape} timestamps for {array.shape[0]} poses")
    if not np.isfinite(stamps).all():
        raise ValueError("timestamps contain NaN or Inf")
    from .io import atomic_path

    with atomic_path(path) as temporary, temporary.open("w", encoding="utf-8") as file:
        file.write("# timestamp tx ty tz qx qy qz qw\n")
        for stamp, pose in zip(stamps, array, strict=True):
            values = [stamp, *pose[:3, 3], *quaternion_from_matrix(pose[:3, :3])]
            file.write(" ".join(repr(float(v)) for v in values) + "\n")


def read_times(path: str | PathLike, count: int) -> np.ndarray:
    """(count,) float64 timestamps [s] of a KITTI ``times.txt`` (one number a line, line k the time of
    pose k). ValueError naming the file and line for a malformed line, too few lines, or times that
    go backwards."""
    path = Path(path)
    stamps = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if line.strip() and not line.lstrip().startswith("#"):
            stamps.append(_numbers(path, number, line, 1, "a time [s]")[0])
    stamps = np.asarray(stamps, dtype=np.float64)
    if len(stamps) < count:
        raise ValueError(f"{path}: {len(stamps)} times for {count} poses")
    stamps = stamps[:count]
    if np.any(np.diff(stamps) < 0):
        first = int(np.argmax(np.diff(stamps) < 0)) + 2
        raise ValueError(f"{path}: the times go backwards at time {first}")
    return stamps
