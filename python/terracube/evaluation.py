"""Accuracy measures: absolute and relative trajectory errors and the DSM region-layout comparison.

* :func:`absolute_trajectory_error`: per-pose translation and rotation errors after no alignment,
  first-pose alignment or the least-squares rigid alignment (Umeyama 1991, without scale).
* :func:`relative_pose_error`: the KITTI odometry devkit's measure, translation error in % of the
  segment length and rotation error in degrees per 100 m, averaged over segments of given
  path lengths (100-800 m by default; short sequences need e.g. 5, 10, 20 m).
* :func:`compare_region_layouts`: [TC] section 4.2 compares the global elevation map with an
  aerial DSM through the distances between matched regions ([TC] eq. (5)) and the angles they
  form ([TC] eq. (6)), over the consecutive pairs 1-2, ..., K-1 and triples K-1-2, ..., (K-1)-K-1
  of [TC] Tables 4-5 (or every pair and triple, ``relations="all_pairs"``).

Pose files (KITTI, TUM) are read and written by :mod:`terracube.poses`, re-exported here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from . import _core
from .poses import read_kitti_poses, read_tum_poses, write_kitti_poses, write_tum_poses

__all__ = [
    "KITTI_SEGMENT_LENGTHS",
    "AbsoluteTrajectoryError",
    "RegionLayoutComparison",
    "RelativePoseError",
    "RelativePoseErrorParams",
    "TrajectoryAlignment",
    "absolute_trajectory_error",
    "compare_region_layouts",
    "error_statistics",
    "read_kitti_poses",
    "read_tum_poses",
    "relative_pose_error",
    "rigid_alignment",
    "write_kitti_poses",
    "write_tum_poses",
]

TrajectoryAlignment = _core.TrajectoryAlignment
AbsoluteTrajectoryError = _core.AbsoluteTrajectoryError
RelativePoseError = _core.RelativePoseError
RegionLayoutComparison = _core.RegionLayoutComparison

#: The KITTI odometry benchmark's segment lengths [m].
KITTI_SEGMENT_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)


def _alignment(alignment) -> _core.TrajectoryAlignment:
    if isinstance(alignment, _core.TrajectoryAlignment):
        return alignment
    names = {"none": _core.TrajectoryAlignment.none, "first_pose": _core.TrajectoryAlignment.first_pose}
    names["rigid"] = _core.TrajectoryAlignment.rigid
    if alignment is None:
        return names["none"]
    if str(alignment) not in names:
        raise ValueError(f"alignment must be one of {sorted(names)}, got {alignment!r}")
    return names[str(alignment)]


def absolute_trajectory_error(estimate, ground_truth, alignment: str = "rigid") -> AbsoluteTrajectoryError:
    """Absolute trajectory error of ``estimate`` against ``ground_truth``.

    Parameters
    ----------
    estimate, ground_truth : (K, 4, 4) array
        Rigid sensor-to-world poses, pose k of one matched with pose k of the other.
    alignment : {"rigid", "first_pose", "none"}
        How the estimate is moved onto the truth first: least-squares rotation and translation of
        the positions (Umeyama, no scale), the first pose onto the first true pose, or not at all.

    Returns
    -------
    AbsoluteTrajectoryError
        ``alignment`` (4, 4) applied to the estimate, ``translation_errors`` (K,) [m],
        ``rotation_errors`` (K,) [deg], and their statistics ``translation`` / ``rotation``
        (``rmse``, ``mean``, ``median``, ``max``, ``count``).

    Raises
    ------
    ValueError
        Empty or unequal trajectories, a wrong shape, non-finite or non-rigid poses.
    """
    return _core.absolute_trajectory_error(
        np.asarray(estimate), np.asarray(ground_truth), _alignment(alignment)
    )


@dataclass
class RelativePoseErrorParams:
    """Parameters of :func:`relative_pose_error`, mirroring ``terracube::RelativePoseErrorParams``.

    Attributes
    ----------
    lengths : sequence of float
        Segment lengths along the ground-truth path [m] (positive); KITTI's by default.
    step_frames : int
        A segment starts every ``step_frames`` frames (>= 1; KITTI uses 10).
    """

    lengths: Sequence[float] = field(default_factory=lambda: list(KITTI_SEGMENT_LENGTHS))
    step_frames: int = 10

    def to_core(self) -> _core.RelativePoseErrorParams:
        if int(self.step_frames) < 1:
            raise ValueError(f"step_frames must be at least 1, got {self.step_frames}")
        params = _core.RelativePoseErrorParams()
        params.lengths_m = [float(length) for length in self.lengths]
        params.step_frames = int(self.step_frames)
        return params


def relative_pose_error(
    estimate, ground_truth, params: RelativePoseErrorParams | None = None, **kwargs
) -> RelativePoseError:
    """KITTI-devkit relative pose error over path-length segments.

    For first frames 0, step, 2 step, ... and each length L, the segment ends at the first frame
    whose ground-truth path length from the start is >= L; its error is
    ``E = inv(inv(gt_i) gt_j) @ (inv(est_i) est_j)``, reported as ``100 |t(E)| / L`` [%] and
    ``100 angle(E) / L`` [deg / 100 m].

    Returns
    -------
    RelativePoseError
        ``num_segments``, the averages ``translation_percent`` and ``rotation_deg_per_100m`` over
        all segments (NaN when no segment fits: the sequence is shorter than every length),
        ``per_length`` (one entry per length) and every segment in ``segments``.
    """
    params = params or RelativePoseErrorParams(**kwargs)
    return _core.relative_pose_error(np.asarray(estimate), np.asarray(ground_truth), params.to_core())


def compare_region_layouts(
    map_centres, dsm_centres, relations: str = "consecutive"
) -> RegionLayoutComparison:
    """The DSM comparison of [TC] section 4.2: distance errors (eq. 5) and angle errors (eq. 6).

    Parameters
    ----------
    map_centres, dsm_centres : (K, 2) or (K, 3) array
        The same K regions, listed in order around the site, located in the global elevation map
        and in the reference DSM [m]. [TC] Table 3 gives 3-D centres.
    relations : {"consecutive", "all_pairs"}
        ``"consecutive"`` ([TC] Tables 4-5): the K pairs 1-2, 2-3, ..., K-1 and the K
        triples K-1-2, 1-2-3, ..., (K-1)-K-1, wrapping around. ``"all_pairs"``: every pair
        i < j and every triple i < j < k (angle at j).

    Returns
    -------
    RegionLayoutComparison
        ``pairs`` (``i``, ``j`` 0-based, ``map_distance``, ``dsm_distance``, signed ``error`` =
        map - DSM [m], as [TC] Table 4), ``triples`` (``i``, ``j``, ``k``, the angle at ``j``:
        ``map_angle``, ``dsm_angle``, signed ``error`` [deg], as [TC] Table 5), and the mean and
        maximum of the absolute errors: ``mean_distance_error``, ``max_distance_error`` [m],
        ``mean_angle_error``, ``max_angle_error`` [deg] (NaN without triples: K = 2).

    Raises
    ------
    ValueError
        Fewer than two regions, unequal counts or dimensions, non-finite coordinates, two
        regions at the same place, or an unknown ``relations``.
    """
    choices = {"consecutive": _core.RegionRelations.consecutive, "all_pairs": _core.RegionRelations.all_pairs}
    if relations not in choices:
        raise ValueError(f"relations must be one of {sorted(choices)}, got {relations!r}")
    return _core.compare_region_layouts(np.asarray(map_centres), np.asarray(dsm_centres), choices[relations])


def rigid_alignment(source, target) -> np.ndarray:
    """The (4, 4) rigid transform T minimising sum |T source_k - target_k|^2 over (N, 3) points."""
    return _core.rigid_alignment(np.asarray(source), np.asarray(target))


def error_statistics(errors):
    """``rmse``, ``mean``, ``median``, ``max`` and ``count`` of a list of errors (NaN when empty)."""
    return _core.error_statistics([float(e) for e in np.ravel(errors)])
