"""Pose-graph optimisation (Ceres) through terracube.pose_graph.

References: the truth that exact measurements were made from, the composition of the
measurements along a chain, numpy's linear least squares for a translation-only graph, the
hand-computed cost of one edge, and the inliers of a ring against a false loop closure.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from terracube import pose_graph as pg


def rotation(axis, angle_rad: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * k @ k


def pose(x, y, z, yaw_deg=0.0, roll_deg=0.0) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation([0, 0, 1], math.radians(yaw_deg)) @ rotation([1, 0, 0], math.radians(roll_deg))
    t[:3, 3] = (x, y, z)
    return t


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.inv(a) @ b


def noise(rng, sigma_m: float, sigma_rad: float) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation(rng.normal(size=3), rng.normal() * sigma_rad)
    t[:3, 3] = rng.normal(size=3) * sigma_m
    return t


def ring(count: int, radius: float) -> np.ndarray:
    poses = []
    for k in range(count):
        a = 2 * math.pi * k / count
        poses.append(
            pose(radius * math.cos(a), radius * math.sin(a), 0.3 * math.sin(3 * a), math.degrees(a) + 90, 2.0)
        )
    return np.stack(poses)


def information(sigma_m: float, sigma_rad: float) -> np.ndarray:
    return np.diag([sigma_m**-2] * 3 + [sigma_rad**-2] * 3)


def random_information(rng) -> np.ndarray:
    a = rng.uniform(-1, 1, size=(6, 6))
    return a @ a.T + np.eye(6)


def test_one_edge_cost_is_the_hand_computed_whitened_residual():
    start = pose(1, 2, 0.5, 30)
    end = start @ pose(2, 0, 0)
    measurement = pose(1.9, 0.1, 0.0, 10)
    info = np.diag([4.0, 9.0, 1.0, 2.0, 3.0, 5.0])
    result = pg.optimize_pose_graph(
        np.stack([start, end]), [pg.PoseGraphEdge(0, 1, measurement, info)], fixed=[0, 1]
    )
    # r = (0.1, -0.1, 0, 0, 0, -10 deg) in (translation, rotation vector) order.
    expected = 0.5 * (4 * 0.01 + 9 * 0.01 + 5 * math.radians(10) ** 2)
    assert result.initial_cost == pytest.approx(expected, abs=1e-12)
    np.testing.assert_array_equal(result.poses, np.stack([start, end]))


def test_exact_measurements_recover_the_truth_from_perturbed_poses():
    rng = np.random.default_rng(7)
    truth = ring(10, 8.0)
    edges = [
        pg.PoseGraphEdge(k, (k + 1) % 10, relative(truth[k], truth[(k + 1) % 10]), random_information(rng))
        for k in range(10)
    ]
    edges.append(pg.PoseGraphEdge(2, 7, relative(truth[2], truth[7]), random_information(rng)))
    initial = truth.copy()
    for k in range(1, 10):
        initial[k] = truth[k] @ noise(rng, 0.3, math.radians(5))
    result = pg.optimize_pose_graph(initial, edges)
    assert result.converged, result.message
    assert result.final_cost < 1e-16 < 1.0 < result.initial_cost
    np.testing.assert_allclose(result.poses, truth, atol=1e-6)
    assert "converged=True" in repr(result)


def test_chain_without_loops_is_the_composition_of_the_measurements():
    rng = np.random.default_rng(11)
    anchor = pose(5, -3, 1, 40, -3)
    measurements = [pose(1, 0, 0, 15) @ noise(rng, 0.5, 0.3) for _ in range(5)]
    expected = [anchor]
    for z in measurements:
        expected.append(expected[-1] @ z)
    initial = np.stack([anchor] + [np.eye(4)] * 5)
    edges = [(k, k + 1, z, random_information(rng)) for k, z in enumerate(measurements)]  # tuples work too
    result = pg.optimize_pose_graph(initial, edges)
    np.testing.assert_allclose(result.poses, np.stack(expected), atol=1e-9)


def test_translation_only_graph_matches_numpy_weighted_least_squares():
    rng = np.random.default_rng(3)
    count = 6
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (1, 4), (2, 5), (3, 0)]
    edges = []
    for a, b in pairs:
        z = np.eye(4)
        z[:3, 3] = rng.normal(size=3) * 3.0
        edges.append(pg.PoseGraphEdge(a, b, z, random_information(rng)))
    initial = np.stack([np.eye(4)] * count)
    initial[0, :3, 3] = (1.0, 2.0, 3.0)
    result = pg.optimize_pose_graph(
        initial,
        edges,
        fixed_rotations=range(count),
        function_tolerance=1e-16,  # the cost is quadratic: stop at the optimum, not near it
        parameter_tolerance=1e-14,
    )
    # Whitened rows W^(1/2) (t_b - t_a) = W^(1/2) z for the unknowns t_1..t_5 (t_0 known).
    rows, rhs = [], []
    for edge in edges:
        w = edge.information[:3, :3]
        root = np.linalg.cholesky(w).T  # root.T @ root = w
        jacobian = np.zeros((3, 3 * (count - 1)))
        c = edge.measurement[:3, 3].copy()
        for node, sign in ((edge.to, 1.0), (edge.from_, -1.0)):
            if node == 0:
                c -= sign * initial[0, :3, 3]
            else:
                jacobian[:, 3 * (node - 1) : 3 * node] += sign * np.eye(3)
        rows.append(root @ jacobian)
        rhs.append(root @ c)
    solution, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
    np.testing.assert_allclose(result.poses[1:, :3, 3], solution.reshape(-1, 3), atol=1e-8)
    np.testing.assert_array_equal(result.poses[:, :3, :3], np.tile(np.eye(3), (count, 1, 1)))


def test_loop_closure_reduces_the_drift_of_noisy_odometry():
    sigma_m, sigma_rad = 0.05, 0.01
    truth = ring(24, 10.0)
    odometry_sq, optimised_sq = 0.0, 0.0
    for seed in range(1, 11):  # pooled: a single ring can be unlucky
        rng = np.random.default_rng(seed)
        edges, odometry = [], [truth[0]]
        for k in range(23):
            z = relative(truth[k], truth[k + 1]) @ noise(rng, sigma_m, sigma_rad)
            edges.append(pg.PoseGraphEdge(k, k + 1, z, information(sigma_m, sigma_rad)))
            odometry.append(odometry[-1] @ z)
        loop = relative(truth[23], truth[0]) @ noise(rng, sigma_m, sigma_rad)
        edges.append(pg.PoseGraphEdge(23, 0, loop, information(sigma_m, sigma_rad)))
        result = pg.optimize_pose_graph(np.stack(odometry), edges)
        odometry_sq += np.sum((np.stack(odometry)[:, :3, 3] - truth[:, :3, 3]) ** 2)
        optimised_sq += np.sum((result.poses[:, :3, 3] - truth[:, :3, 3]) ** 2)
    assert math.sqrt(odometry_sq / optimised_sq) > 1.5  # measured ~2 (C++ test: 2.04 with its seeds)


def test_robust_false_loop_closure_is_outvoted_by_the_inliers():
    sigma_m, sigma_rad = 0.05, 0.01
    truth = ring(16, 8.0)
    edges = [
        pg.PoseGraphEdge(
            k, (k + 1) % 16, relative(truth[k], truth[(k + 1) % 16]), information(sigma_m, sigma_rad)
        )
        for k in range(16)
    ]
    wrong = relative(truth[0], truth[8]) @ pose(4.0, 0.0, 0.0, 20)  # 4 m and 20 degrees off

    def worst(robust: bool, loss: str = "cauchy") -> float:
        outlier = pg.PoseGraphEdge(0, 8, wrong, information(sigma_m, sigma_rad), robust=robust)
        result = pg.optimize_pose_graph(truth, [*edges, outlier], robust_loss=loss)
        return float(np.max(np.linalg.norm(result.poses[:, :3, 3] - truth[:, :3, 3], axis=1)))

    plain = worst(False)
    assert plain > 0.5  # measured 3.8 m
    assert worst(True, "cauchy") < 0.05  # measured 0.008 m: the inliers win
    assert worst(True, "huber") < plain / 3  # measured 0.73 m: bounded influence, not immune


def test_bad_input_raises_value_error_naming_the_problem():
    poses = np.stack([np.eye(4), pose(1, 0, 0)])
    good = pg.PoseGraphEdge(0, 1, pose(1, 0, 0))
    with pytest.raises(ValueError, match="no poses"):
        pg.optimize_pose_graph(np.zeros((0, 4, 4)), [])
    with pytest.raises(ValueError, match=r"\(K, 4, 4\)"):
        pg.optimize_pose_graph(np.eye(4), [good])
    with pytest.raises(ValueError, match="out of range"):
        pg.optimize_pose_graph(poses, [pg.PoseGraphEdge(0, 2, pose(1, 0, 0))])
    with pytest.raises(ValueError, match="itself"):
        pg.optimize_pose_graph(poses, [pg.PoseGraphEdge(1, 1)])
    with pytest.raises(ValueError, match=">= 0"):
        pg.optimize_pose_graph(poses, [pg.PoseGraphEdge(-1, 1)])
    bad = poses.copy()
    bad[1, 0, 3] = np.inf
    with pytest.raises(ValueError, match="pose 1 contains NaN or Inf"):
        pg.optimize_pose_graph(bad, [good])
    with pytest.raises(ValueError, match="edge 0 measurement must be a rigid 4x4 transform.*last row"):
        pg.optimize_pose_graph(poses, [pg.PoseGraphEdge(0, 1, 2 * np.eye(4))])
    asymmetric = np.eye(6)
    asymmetric[0, 1] = 0.5
    with pytest.raises(ValueError, match="not symmetric"):
        pg.optimize_pose_graph(poses, [pg.PoseGraphEdge(0, 1, pose(1, 0, 0), asymmetric)])
    with pytest.raises(ValueError, match="positive definite"):
        pg.optimize_pose_graph(poses, [pg.PoseGraphEdge(0, 1, pose(1, 0, 0), -np.eye(6))])
    with pytest.raises(ValueError, match="6x6"):
        pg.optimize_pose_graph(poses, [pg.PoseGraphEdge(0, 1, pose(1, 0, 0), np.eye(3))])
    with pytest.raises(ValueError, match="at least one pose must be fixed"):
        pg.optimize_pose_graph(poses, [good], fixed=[])
    with pytest.raises(ValueError, match="fixed pose 5"):
        pg.optimize_pose_graph(poses, [good], fixed=[5])
    with pytest.raises(ValueError, match="robust_loss"):
        pg.optimize_pose_graph(poses, [good], robust_loss="tukey")
    with pytest.raises(ValueError, match="robust_loss_scale"):
        pg.optimize_pose_graph(poses, [good], robust_loss_scale=0.0)
    with pytest.raises(TypeError, match="PoseGraphEdge"):
        pg.optimize_pose_graph(poses, ["0 1"])
