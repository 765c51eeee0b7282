// Pose-graph optimisation for loop closing: nodes are rigid poses (sensor to world), edges are
// measured relative poses with an information matrix; Ceres minimises the whitened relative-pose
// errors with poses parameterised as a translation and a unit quaternion on its manifold.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace terracube {

/// A measured relative pose between two nodes.
struct PoseGraphEdge {
  std::size_t from = 0;  ///< node index
  std::size_t to = 0;    ///< node index, != from
  /// The measured inverse(pose[from]) * pose[to] (rigid 4x4).
  Eigen::Matrix4d measurement = Eigen::Matrix4d::Identity();
  /// Inverse covariance of the residual, symmetric positive definite, ordered (translation x y z
  /// [1/m^2], rotation x y z [1/rad^2]) as the residual of optimize_pose_graph.
  Eigen::Matrix<double, 6, 6> information = Eigen::Matrix<double, 6, 6>::Identity();
  /// Put the robust loss of PoseGraphParams on this edge (for loop closures that may be wrong).
  bool robust = false;
};

/// Robust loss applied to edges marked robust; s is the squared whitened residual norm and a the
/// robust_loss_scale (ceres::HuberLoss / ceres::CauchyLoss).
enum class RobustLoss : std::uint8_t {
  kHuber = 0,   ///< rho(s) = s for s <= a^2, 2 a sqrt(s) - a^2 beyond: bounded influence
  kCauchy = 1,  ///< rho(s) = a^2 log(1 + s / a^2): influence falls off for large errors
};

/// Parameters of optimize_pose_graph.
struct PoseGraphParams {
  int max_iterations = 100;  ///< Levenberg-Marquardt iterations at most, in [1, kMaxIterationsLimit] (icp.hpp)
  RobustLoss robust_loss = RobustLoss::kCauchy;
  double robust_loss_scale = 1.0;  ///< a, in whitened residual units (standard deviations), > 0
  /// Nodes held at their initial pose: at least one (the gauge), each < number of poses.
  std::vector<std::size_t> fixed = {0};
  /// Nodes whose rotation is held at its initial value while the translation stays free (e.g.
  /// orientations known from an IMU); each < number of poses. With every rotation held the
  /// problem is linear in the translations.
  std::vector<std::size_t> fixed_rotations = {};
  double function_tolerance = 1e-12;   ///< Ceres: stop when the relative cost decrease is below this
  double gradient_tolerance = 1e-14;   ///< Ceres: stop when the max-norm of the projected gradient is below this
  double parameter_tolerance = 1e-12;  ///< Ceres: stop when the relative step is below this
  int num_threads = 1;                 ///< Ceres' threads, >= 1; results do not depend on it
};

/// Outcome of optimize_pose_graph.
struct PoseGraphResult {
  std::vector<Eigen::Matrix4d> poses;  ///< optimised poses, one per input pose
  double initial_cost = 0.0;           ///< 1/2 sum rho(|L^T r|^2) at the initial poses (Ceres' cost)
  double final_cost = 0.0;             ///< the same at the result
  int iterations = 0;                  ///< Ceres iterations (successful and unsuccessful steps)
  bool converged = false;              ///< Ceres reported convergence (a tolerance was met)
  std::string message;                 ///< Ceres' one-line report and termination message
};

/// Minimises sum over edges of 1/2 rho(|L^T r|^2), where I = L L^T (LLT of the information) and
/// r = (t(E), log(R(E))) with the measured and estimated relative poses Z = edge.measurement,
/// X = inverse(pose[from]) * pose[to], and t(E) = t(X) - t(Z), R(E) = R(Z)^T R(X): the translation
/// difference in the `from` frame and the rotation vector of the quaternion error
/// q(Z)^-1 q(X). rho is the identity on ordinary edges and the robust loss on robust ones.
/// Each pose is a translation plus a unit quaternion on ceres::EigenQuaternionManifold; the
/// normal equations are solved by sparse Cholesky. Nodes that no edge touches keep their pose.
/// Throws std::invalid_argument for no poses, non-finite or non-rigid poses or measurements,
/// node indices out of range, an edge from a node to itself, an information matrix that is not
/// finite, symmetric and positive definite, and invalid parameters.
PoseGraphResult optimize_pose_graph(const std::vector<Eigen::Matrix4d>& initial_poses,
                                    const std::vector<PoseGraphEdge>& edges, const PoseGraphParams& params = {});

}  // namespace terracube
