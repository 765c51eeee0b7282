"""Trajectory errors (ATE, KITTI RPE), the DSM region-layout comparison and the pose files.

References: hand-computed values (constant offsets, linear drift, a known rotation error, a known
rigid transform, a constant scale drift and yaw-rate error), a naive loop-by-loop RPE written
here after the KITTI devkit, and numpy's own parsing of the KITTI ground-truth file.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from terracube import evaluation as ev
from terracube import poses as pf


def rotation(axis, angle_rad: float) -> np.ndarray:
    """Rodrigues' formula."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * k @ k


def pose(x, y, z, yaw_deg=0.0, roll_deg=0.0) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation([0, 0, 1], math.radians(yaw_deg)) @ rotation([1, 0, 0], math.radians(roll_deg))
    t[:3, 3] = (x, y, z)
    return t


def wiggly(count: int) -> np.ndarray:
    return np.stack(
        [
            pose(s, 3 * math.sin(0.3 * s), 0.5 * math.cos(0.2 * s), 20 * math.sin(0.1 * s), 2.0)
            for s in range(count)
        ]
    )


def straight(count: int) -> np.ndarray:
    return np.stack([pose(float(k), 0.0, 0.0) for k in range(count)])


def angle_deg(r: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(r) - 1) / 2))))


# --- absolute trajectory error -------------------------------------------------------------


def test_ate_of_a_constant_offset_is_its_length_unaligned_and_zero_aligned():
    truth = wiggly(20)
    estimate = truth.copy()
    estimate[:, :3, 3] += (0.3, -0.4, 1.2)  # |offset| = 1.3 m
    none = ev.absolute_trajectory_error(estimate, truth, alignment="none")
    np.testing.assert_allclose(none.translation_errors, 1.3, atol=1e-12)
    assert none.translation.rmse == pytest.approx(1.3, abs=1e-12)
    assert none.translation_errors.shape == (20,)
    for alignment in ("first_pose", "rigid"):
        aligned = ev.absolute_trajectory_error(estimate, truth, alignment=alignment)
        assert aligned.translation.max < 1e-9
        np.testing.assert_allclose(aligned.alignment[:3, 3], (-0.3, 0.4, -1.2), atol=1e-9)


def test_ate_of_linear_drift_has_hand_computed_statistics():
    truth = straight(10)
    estimate = truth.copy()
    estimate[:, :3, 3] += np.arange(10)[:, None] * np.array([0.0, 0.06, 0.08])  # 0.1 m per pose
    ate = ev.absolute_trajectory_error(estimate, truth, alignment="none")
    np.testing.assert_allclose(ate.translation_errors, 0.1 * np.arange(10), atol=1e-12)
    assert ate.translation.mean == pytest.approx(0.45)
    assert ate.translation.median == pytest.approx(0.45)
    assert ate.translation.max == pytest.approx(0.9)
    assert ate.translation.rmse == pytest.approx(0.1 * math.sqrt(285 / 10))
    assert ate.translation.count == 10


def test_ate_reports_a_known_rotation_error_in_degrees():
    truth = wiggly(12)
    estimate = truth @ pose(0, 0, 0, roll_deg=2.0)
    ate = ev.absolute_trajectory_error(estimate, truth, alignment="none")
    np.testing.assert_allclose(ate.rotation_errors, 2.0, atol=1e-9)
    assert ate.translation.max < 1e-12


def test_rigid_alignment_recovers_a_known_transform():
    truth = wiggly(25)
    frame = pose(12.0, -7.0, 3.0, yaw_deg=130.0, roll_deg=-20.0)
    estimate = np.linalg.inv(frame) @ truth  # the estimate lives in another frame
    ate = ev.absolute_trajectory_error(estimate, truth, alignment="rigid")
    np.testing.assert_allclose(ate.alignment, frame, atol=1e-9)
    assert ate.translation.max < 1e-9
    assert ate.rotation.max < 1e-6
    np.testing.assert_allclose(ev.rigid_alignment(estimate[:, :3, 3], truth[:, :3, 3]), frame, atol=1e-9)


def test_error_statistics_hand_values_and_empty():
    stats = ev.error_statistics([3.0, 1.0, 2.0, 4.0])
    assert (stats.mean, stats.median, stats.max) == (2.5, 2.5, 4.0)
    assert stats.rmse == pytest.approx(math.sqrt(7.5))
    assert math.isnan(ev.error_statistics([]).rmse)


def test_ate_bad_input_raises_value_error():
    truth = straight(5)
    with pytest.raises(ValueError, match="5 poses but ground truth has 4"):
        ev.absolute_trajectory_error(truth, truth[:4])
    with pytest.raises(ValueError, match=r"\(K, 4, 4\)"):
        ev.absolute_trajectory_error(truth[:, :3, :], truth)
    bad = truth.copy()
    bad[2, 0, 3] = np.nan
    with pytest.raises(ValueError, match="estimate pose 2"):
        ev.absolute_trajectory_error(bad, truth)
    bad = truth.copy()
    bad[1, :3, :3] *= 2.0
    with pytest.raises(ValueError, match="rigid"):
        ev.absolute_trajectory_error(truth, bad)
    with pytest.raises(ValueError, match="alignment"):
        ev.absolute_trajectory_error(truth, truth, alignment="scaled")
    with pytest.raises(ValueError, match="empty"):
        ev.absolute_trajectory_error(np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))


# --- relative pose error --------------------------------------------------------------------


def naive_rpe(estimate, truth, lengths, step):
    """The KITTI devkit's calcSequenceErrors, loop by loop (with >= for the segment end)."""
    distance = [0.0]
    for k in range(1, len(truth)):
        distance.append(distance[-1] + float(np.linalg.norm(truth[k, :3, 3] - truth[k - 1, :3, 3])))
    segments = []
    for first in range(0, len(truth), step):
        for length in lengths:
            last = next(
                (j for j in range(first, len(truth)) if distance[j] - distance[first] >= length), None
            )
            if last is None:
                continue
            error = np.linalg.inv(np.linalg.inv(truth[first]) @ truth[last]) @ (
                np.linalg.inv(estimate[first]) @ estimate[last]
            )
            segments.append(
                (
                    first,
                    last,
                    100 * np.linalg.norm(error[:3, 3]) / length,
                    100 * angle_deg(error[:3, :3]) / length,
                )
            )
    return segments


def test_rpe_matches_a_naive_devkit_loop_on_a_noisy_trajectory():
    rng = np.random.default_rng(4)
    truth = wiggly(60)
    estimate = truth.copy()
    for k in range(1, 60):  # accumulate small random motion errors
        noise = np.eye(4)
        noise[:3, :3] = rotation(rng.normal(size=3), rng.normal() * 0.01)
        noise[:3, 3] = rng.normal(size=3) * 0.02
        estimate[k] = estimate[k - 1] @ (np.linalg.inv(truth[k - 1]) @ truth[k]) @ noise
    lengths, step = [5.0, 12.5, 30.0], 4
    rpe = ev.relative_pose_error(estimate, truth, lengths=lengths, step_frames=step)
    expected = naive_rpe(estimate, truth, lengths, step)
    assert rpe.num_segments == len(expected) > 0
    for segment, (first, last, t_err, r_err) in zip(rpe.segments, expected, strict=True):
        assert (segment.first_frame, segment.last_frame) == (first, last)
        assert segment.translation_percent == pytest.approx(t_err, abs=1e-9)
        assert segment.rotation_deg_per_100m == pytest.approx(r_err, abs=1e-6)
    assert rpe.translation_percent == pytest.approx(np.mean([e[2] for e in expected]), abs=1e-9)
    for entry, length in zip(rpe.per_length, lengths, strict=True):
        mine = [e[2] for e, s in zip(expected, rpe.segments, strict=True) if s.length == length]
        assert entry.num_segments == len(mine)
        assert entry.translation_percent == pytest.approx(np.mean(mine), abs=1e-9)


def test_rpe_of_a_constant_scale_drift_is_that_percent():
    truth = straight(30)
    estimate = truth.copy()
    estimate[:, 0, 3] *= 1.02
    rpe = ev.relative_pose_error(estimate, truth, lengths=[5, 10], step_frames=1)
    assert [e.num_segments for e in rpe.per_length] == [25, 20]
    assert rpe.translation_percent == pytest.approx(2.0, abs=1e-9)
    assert rpe.rotation_deg_per_100m == pytest.approx(0.0, abs=1e-9)


def test_rpe_of_a_constant_yaw_rate_error_is_that_many_degrees_per_100_m():
    truth = straight(40)
    estimate = [truth[0]]
    for _ in range(39):
        estimate.append(estimate[-1] @ pose(1.0, 0.0, 0.0, yaw_deg=0.05))  # 0.05 deg per metre
    rpe = ev.relative_pose_error(np.stack(estimate), truth, lengths=[5, 20], step_frames=3)
    assert rpe.num_segments > 0
    assert all(s.rotation_deg_per_100m == pytest.approx(5.0, abs=1e-9) for s in rpe.segments)


def test_rpe_without_a_fitting_segment_is_nan_with_zero_segments():
    truth = straight(30)
    rpe = ev.relative_pose_error(truth, truth)  # KITTI's 100..800 m on 29 m
    assert rpe.num_segments == 0
    assert math.isnan(rpe.translation_percent) and math.isnan(rpe.rotation_deg_per_100m)
    assert [e.length for e in rpe.per_length] == list(ev.KITTI_SEGMENT_LENGTHS)
    assert "segments=0" in repr(rpe)


def test_rpe_bad_parameters_raise_value_error():
    truth = straight(10)
    with pytest.raises(ValueError, match="positive"):
        ev.relative_pose_error(truth, truth, lengths=[5, 0])
    with pytest.raises(ValueError, match="step_frames"):
        ev.relative_pose_error(truth, truth, step_frames=0)
    with pytest.raises(ValueError, match="at least one"):
        ev.relative_pose_error(truth, truth, lengths=[])


def test_kitti_ground_truth_against_itself_and_against_a_drifting_copy(shared_data):
    truth = pf.read_kitti_poses(shared_data.path("kitti_seq00/KITTI_00_gt_poses_full.txt"))
    rpe = ev.relative_pose_error(truth, truth)
    assert rpe.num_segments > 3000
    assert rpe.translation_percent < 1e-9
    drift = truth.copy()
    drift[:, :3, 3] *= 1.01  # a 1 % scale error everywhere: |t(E)| = 0.01 |chord of the segment|
    scaled = ev.relative_pose_error(drift, truth)
    chords = [
        np.linalg.norm(truth[s.last_frame, :3, 3] - truth[s.first_frame, :3, 3]) / s.length
        for s in scaled.segments
    ]
    assert scaled.num_segments == rpe.num_segments
    # rel 1e-6: the file's rotations are orthonormal to ~1e-7 only, and inverses use the transpose.
    assert scaled.translation_percent == pytest.approx(np.mean(chords), rel=1e-6)
    assert 0.5 < scaled.translation_percent < 1.0  # chords are shorter than the path on curves


# --- DSM region layouts ---------------------------------------------------------------------


def test_region_layout_all_pairs_hand_computed_errors():
    c = ev.compare_region_layouts(
        [[0, 0], [10, 0], [10, 10]], [[0, 0], [10, 0], [9, 10]], relations="all_pairs"
    )
    assert [(p.i, p.j) for p in c.pairs] == [(0, 1), (0, 2), (1, 2)]
    errors = [p.error for p in c.pairs]  # signed: map - DSM
    assert errors == pytest.approx([0.0, math.sqrt(200) - math.sqrt(181), 10 - math.sqrt(101)], abs=1e-12)
    assert c.mean_distance_error == pytest.approx(sum(map(abs, errors)) / 3, abs=1e-12)
    (triple,) = c.triples
    assert (triple.i, triple.j, triple.k) == (0, 1, 2)
    assert triple.map_angle == pytest.approx(90.0, abs=1e-12)
    assert triple.error == pytest.approx(math.degrees(math.atan(0.1)), abs=1e-12)


# [TC] Table 3: region centres in the DSM and in the SLAM map (x, y, z) [m].
TABLE_3_DSM = [
    (116.25, 122.5, 102.54), (79.75, 171.75, 101.62), (47.25, 145, 102.76), (16.25, 124.25, 103.48),
    (48.5, 69.5, 103.43), (79, 28, 103.39), (113.25, 47.75, 103.12), (147, 73, 102.08),
]  # fmt: skip
TABLE_3_SLAM = [
    (51.8, 124.6, 0.603), (53.2, 186.6, 0.002), (97, 191, 0.474), (141, 192.4, 0.273),
    (149, 129.8, -0.70), (151, 69.8, -0.016), (105.8, 66.6, 0.342), (57.2, 67, 0.125),
]  # fmt: skip


def test_region_layout_reproduces_the_papers_tables_4_and_5():
    c = ev.compare_region_layouts(TABLE_3_SLAM, TABLE_3_DSM)
    # Table 4 (signed errors, m); pair 2-3 prints 2 m where Table 3 gives 44.02 - 42.11 = 1.91 m.
    table_4 = [0.71, 1.91, 6.71, -0.43, 8.54, 5.77, 6.44, -0.43]
    assert [(p.i + 1, p.j + 1) for p in c.pairs] == [
        (1, 2),
        (2, 3),
        (3, 4),
        (4, 5),
        (5, 6),
        (6, 7),
        (7, 8),
        (8, 1),
    ]
    assert [p.error for p in c.pairs] == pytest.approx(table_4, abs=0.015)
    table_5 = [-1.86, 9.96, 1.7, 2.16, 0.22, -4.19, 2.33, 0.89]
    assert [(t.i + 1, t.j + 1, t.k + 1) for t in c.triples] == [
        (8, 1, 2), (1, 2, 3), (2, 3, 4), (3, 4, 5), (4, 5, 6), (5, 6, 7), (6, 7, 8), (7, 8, 1)
    ]  # fmt: skip
    assert [t.error for t in c.triples] == pytest.approx(table_5, abs=0.05)
    assert c.mean_angle_error == pytest.approx(2.91, abs=0.005)
    assert c.mean_distance_error == pytest.approx(3.866, abs=0.005)  # 3.88 with Table 4's 2 m row


def test_region_layout_is_blind_to_a_rigid_motion_and_counts_relations():
    rng = np.random.default_rng(2)
    centres = rng.uniform(-50, 50, size=(7, 3))
    moved = centres @ rotation([0.2, 0.1, 1.0], 1.1).T + (100.0, -40.0, 5.0)
    c = ev.compare_region_layouts(centres, moved, relations="all_pairs")
    assert len(c.pairs) == 21 and len(c.triples) == 35
    assert c.max_distance_error < 1e-9 and c.max_angle_error < 1e-6
    c = ev.compare_region_layouts(centres, moved)
    assert len(c.pairs) == 7 and len(c.triples) == 7
    assert c.max_distance_error < 1e-9 and c.max_angle_error < 1e-6
    with pytest.raises(ValueError, match="relations must be one of"):
        ev.compare_region_layouts(centres, moved, relations="every")


def test_region_layout_bad_input():
    three = [[0, 0], [1, 0], [0, 1]]
    with pytest.raises(ValueError, match="3 region centres but the DSM has 2"):
        ev.compare_region_layouts(three, three[:2])
    with pytest.raises(ValueError, match="same place"):
        ev.compare_region_layouts(three, [[0, 0], [0, 0], [0, 1]])
    with pytest.raises(ValueError, match="NaN"):
        ev.compare_region_layouts(three, [[0, 0], [1, 0], [0, np.nan]])
    with pytest.raises(ValueError, match=r"\(K, 2\) or \(K, 3\)"):
        ev.compare_region_layouts(np.zeros((3, 4)), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="at least two"):
        ev.compare_region_layouts([[0, 0]], [[0, 0]])


# --- pose files -----------------------------------------------------------------------------


def test_kitti_ground_truth_round_trips_through_the_reader_and_writer(shared_data, tmp_path):
    path = shared_data.path("kitti_seq00/KITTI_00_gt_poses_full.txt")
    poses = pf.read_kitti_poses(path)
    assert poses.shape == (4541, 4, 4)
    reference = np.loadtxt(path)  # numpy's own parser
    np.testing.assert_array_equal(poses[:, :3, :].reshape(-1, 12), reference)
    np.testing.assert_array_equal(poses[:, 3, :], np.tile([0.0, 0.0, 0.0, 1.0], (4541, 1)))
    out = tmp_path / "poses.txt"
    pf.write_kitti_poses(out, poses)
    np.testing.assert_array_equal(pf.read_kitti_poses(out), poses)
    short = shared_data.path("kitti_seq00/poses.txt")  # the first 6 lines
    np.testing.assert_array_equal(pf.read_kitti_poses(short), poses[:6])


def test_tum_round_trip_and_a_known_quaternion(tmp_path):
    truth = wiggly(8)
    stamps = 1_317_384_506.4 + 0.1 * np.arange(8)
    path = tmp_path / "traj.tum"
    pf.write_tum_poses(path, stamps, truth)
    read_stamps, read_poses = pf.read_tum_poses(path)
    np.testing.assert_array_equal(read_stamps, stamps)
    np.testing.assert_allclose(read_poses, truth, atol=1e-12)
    # 90 degrees about z: (qx, qy, qz, qw) = (0, 0, sin 45, cos 45).
    q = pf.quaternion_from_matrix(rotation([0, 0, 1], math.pi / 2))
    np.testing.assert_allclose(q, (0, 0, math.sqrt(0.5), math.sqrt(0.5)), atol=1e-15)
    # Every Shepperd branch (rotations near 180 degrees about each axis) inverts the matrix.
    for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]):
        r = rotation(axis, 3.0)
        np.testing.assert_allclose(pf.matrix_from_quaternion(pf.quaternion_from_matrix(r)), r, atol=1e-14)
    path.write_text("# comment\n\n0 1 2 3 0 0 0 2\n")  # unnormalised identity quaternion
    _, poses = pf.read_tum_poses(path)
    np.testing.assert_allclose(poses[0], pose(1, 2, 3), atol=1e-15)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1\n", "line 1: expected 12 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 x 0 0 1 0\n", "line 2: cannot read 'x'"),
        ("1 0 0 nan 0 1 0 0 0 0 1 0\n", "line 1: 'nan' is not a finite number"),
        ("2 0 0 0 0 1 0 0 0 0 1 0\n", "line 1: the 3x3 block is not a rotation"),
        ("\n\n", "holds no poses"),
    ],
)
def test_kitti_reader_names_the_file_and_line_of_a_malformed_pose(tmp_path, text, message):
    path = tmp_path / "bad_poses.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as error:
        pf.read_kitti_poses(path)
    assert "bad_poses.txt" in str(error.value)


def _yawed(yaw_deg: float, decimals: int) -> np.ndarray:
    """A pose turned by yaw_deg about z, rounded to `decimals` as a pose file would hold it."""
    return np.round(pose(1.5, -2.0, 0.25, yaw_deg=yaw_deg), decimals)


def _rigid_calls():
    """Every way a pose reaches the core: (name, call(pose))."""
    import terracube as tc

    points = np.random.default_rng(3).uniform(-5.0, 5.0, (400, 3))
    truth = np.stack([np.eye(4), pose(1.0, 0.0, 0.0)])
    cloud_map = tc.build_elevation_map(points, 0.5, origin=(-6, -6), size=(24, 24))
    tc.classify_terrain(cloud_map, sensor_height=0.0)
    return {
        "LocalMap.update": lambda t: tc.LocalMap(length=10.0, resolution=0.5).update(points, t),
        "Mapper.add_scan": lambda t: tc.Mapper(tc.MapperParams()).add_scan(points, t),
        "collapse transform": lambda t: tc.collapse_overhangs(points, 0.5, 2, transform=t),
        "register_maps initial": lambda t: tc.register_maps(cloud_map, cloud_map, initial=t),
        "trajectory error": lambda t: ev.absolute_trajectory_error(np.stack([np.eye(4), t]), truth),
    }


@pytest.mark.parametrize("name", sorted(_rigid_calls()))
def test_every_pose_input_takes_six_digit_rotations_and_names_a_larger_error(name):
    # Independent reference: the rounding error of each pose, computed here. Six decimals (KITTI's
    # files) leave |R^T R - I| < 1e-6 and pass everywhere; four leave ~1e-4, over the one tolerance.
    call = _rigid_calls()[name]
    six, four = _yawed(37.0, 6), _yawed(37.0, 4)
    deviation = np.abs(four[:3, :3].T @ four[:3, :3] - np.eye(3)).max()
    assert np.abs(six[:3, :3].T @ six[:3, :3] - np.eye(3)).max() < 1e-6 < pf.RIGID_TOLERANCE < deviation
    call(six)
    with pytest.raises(ValueError, match=r"rigid 4x4 transform .*\|R\^T R - I\| reaches .*nearest rotation"):
        call(four)


def test_kitti_reader_replaces_coarsely_rounded_rotations_by_the_nearest_with_a_warning(tmp_path):
    exact = np.stack([pose(0, 0, 0, yaw_deg=37.0), pose(3, 1, 0, yaw_deg=-120.0, roll_deg=2.0)])
    path = tmp_path / "poses.txt"
    for decimals, warns in ((9, False), (4, True), (3, True)):
        rows = np.round(exact[:, :3, :].reshape(-1, 12), decimals)
        path.write_text("\n".join(" ".join(f"{v:.{decimals}f}" for v in row) for row in rows) + "\n")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            read = pf.read_kitti_poses(path)
        assert bool(caught) == warns
        # The rotations the core gets are rotations, within the file's rounding of the true ones.
        for got, want in zip(read, exact, strict=True):
            np.testing.assert_allclose(got[:3, :3].T @ got[:3, :3], np.eye(3), atol=1e-12 if warns else 1e-8)
            np.testing.assert_allclose(got, want, atol=2 * 10.0**-decimals)
        if warns:
            assert "poses.txt: 2 rotations rounded beyond six digits" in str(caught[0].message)
    path.write_text("0.99 0 0 0 0 1 0 0 0 0 1 0\n")  # 2e-2 off: not a rounding
    with pytest.raises(
        ValueError, match=r"line 1: the 3x3 block is not a rotation \(\|R\^T R - I\| = 0.0199"
    ):
        pf.read_kitti_poses(path)
    np.testing.assert_allclose(pf.nearest_rigid(np.diag([1.0, 1.001, 0.999, 1.0])), np.eye(4), atol=1e-15)
    with pytest.raises(ValueError, match="reflection"):
        pf.nearest_rigid(np.diag([1.0, 1.0, -1.0, 1.0]))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("0 1 2 3 0 0 0\n", "line 1: expected 8 numbers"),
        ("# header\n0 1 2 3 0 0 0 0\n", "line 2: .*no direction"),
        ("0 1 2 3 0 0 0 inf\n", "line 1: 'inf' is not a finite number"),
    ],
)
def test_tum_reader_names_the_file_and_line_of_a_malformed_pose(tmp_path, text, message):
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        pf.read_tum_poses(path)


def test_pose_writers_reject_bad_arrays(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        pf.write_kitti_poses(tmp_path / "a.txt", np.zeros((3, 4)))
    with pytest.raises(ValueError, match="one timestamp per pose"):
        pf.write_tum_poses(tmp_path / "a.tum", [0.0], straight(2))
