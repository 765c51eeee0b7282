#include "terracube/pose_graph.hpp"

#include <ceres/autodiff_cost_function.h>
#include <ceres/loss_function.h>
#include <ceres/manifold.h>
#include <ceres/problem.h>
#include <ceres/rotation.h>
#include <ceres/solver.h>
#include <ceres/types.h>

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <cmath>
#include <memory>
#include <stdexcept>
#include <string>

#include "cloud_frame.hpp"
#include "terracube/icp.hpp"

namespace terracube {

namespace {

using Matrix6d = Eigen::Matrix<double, 6, 6>;

void check_params(const PoseGraphParams& p, std::size_t num_poses) {
  if (p.max_iterations < 1 || p.max_iterations > kMaxIterationsLimit) {
    throw std::invalid_argument("max_iterations must lie in [1, " + std::to_string(kMaxIterationsLimit) + "], got " +
                                std::to_string(p.max_iterations));
  }
  if (!(p.robust_loss_scale > 0.0) || !std::isfinite(p.robust_loss_scale)) {
    throw std::invalid_argument("robust_loss_scale must be positive and finite");
  }
  if (p.robust_loss != RobustLoss::kHuber && p.robust_loss != RobustLoss::kCauchy) {
    throw std::invalid_argument("unknown robust loss");
  }
  const auto non_negative = [](double v) { return v >= 0.0 && std::isfinite(v); };
  if (!non_negative(p.function_tolerance) || !non_negative(p.gradient_tolerance) ||
      !non_negative(p.parameter_tolerance)) {
    throw std::invalid_argument("tolerances must be finite and >= 0");
  }
  if (p.num_threads < 1) throw std::invalid_argument("num_threads must be at least 1");
  if (p.fixed.empty()) {
    throw std::invalid_argument("at least one pose must be fixed (the graph is otherwise free to drift as a whole)");
  }
  for (const auto* nodes : {&p.fixed, &p.fixed_rotations}) {
    for (std::size_t node : *nodes) {
      if (node >= num_poses) {
        throw std::invalid_argument(std::string(nodes == &p.fixed ? "fixed pose " : "fixed rotation of pose ") +
                                    std::to_string(node) + " is out of range for " + std::to_string(num_poses) +
                                    " poses");
      }
    }
  }
}

/// Upper-triangular square root L^T of the information I = L L^T, so |L^T r|^2 = r^T I r.
Matrix6d information_root(const Matrix6d& information, std::size_t edge) {
  const std::string what = "edge " + std::to_string(edge) + " information";
  if (!information.allFinite()) throw std::invalid_argument(what + " contains NaN or Inf");
  const double scale = information.cwiseAbs().maxCoeff();
  if (!((information - information.transpose()).cwiseAbs().maxCoeff() <= 1e-9 * scale)) {
    throw std::invalid_argument(what + " is not symmetric");
  }
  const Eigen::LLT<Matrix6d> llt(information);
  if (scale == 0.0 || llt.info() != Eigen::Success) {
    throw std::invalid_argument(what + " is not positive definite");
  }
  const Matrix6d root = llt.matrixU();
  if (!(root.diagonal().minCoeff() > 0.0)) throw std::invalid_argument(what + " is not positive definite");
  return root;
}

/// The whitened relative-pose residual of one edge (see optimize_pose_graph).
class RelativePoseResidual {
 public:
  RelativePoseResidual(const Eigen::Matrix4d& measurement, const Matrix6d& root)
      : translation_(measurement.topRightCorner<3, 1>()),
        rotation_(Eigen::Quaterniond(Eigen::Matrix3d(measurement.topLeftCorner<3, 3>())).normalized()),
        root_(root) {}

  template <typename T>
  bool operator()(const T* from_translation, const T* from_rotation, const T* to_translation, const T* to_rotation,
                  T* residual) const {
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> t_from(from_translation), t_to(to_translation);
    const Eigen::Map<const Eigen::Quaternion<T>> q_from(from_rotation), q_to(to_rotation);
    const Eigen::Quaternion<T> q_from_inverse = q_from.conjugate();
    // X = inverse(pose[from]) * pose[to].
    const Eigen::Matrix<T, 3, 1> t_relative = q_from_inverse * (t_to - t_from);
    const Eigen::Quaternion<T> q_relative = q_from_inverse * q_to;
    // Rotation error q(Z)^-1 q(X) as a rotation vector (ceres' quaternion order is w, x, y, z).
    const Eigen::Quaternion<T> q_error = rotation_.template cast<T>().conjugate() * q_relative;
    const T wxyz[4] = {q_error.w(), q_error.x(), q_error.y(), q_error.z()};
    Eigen::Matrix<T, 6, 1> error;
    error.template head<3>() = t_relative - translation_.template cast<T>();
    ceres::QuaternionToAngleAxis(wxyz, error.data() + 3);
    Eigen::Map<Eigen::Matrix<T, 6, 1>> whitened(residual);
    whitened = root_.template cast<T>() * error;
    return true;
  }

 private:
  Eigen::Vector3d translation_;
  Eigen::Quaterniond rotation_;
  Matrix6d root_;
};

/// Sparse Cholesky with the best sparse library this Ceres has; dense QR as the last resort.
void choose_linear_solver(ceres::Solver::Options& options) {
  for (const auto library : {ceres::SUITE_SPARSE, ceres::EIGEN_SPARSE, ceres::CX_SPARSE}) {
    if (ceres::IsSparseLinearAlgebraLibraryTypeAvailable(library)) {
      options.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
      options.sparse_linear_algebra_library_type = library;
      return;
    }
  }
  options.linear_solver_type = ceres::DENSE_QR;
}

/// Throws std::invalid_argument naming the first edge that refers to a missing pose, joins a pose
/// to itself or has a bad measurement or information; returns each edge's information root.
std::vector<Matrix6d> checked_information_roots(const std::vector<PoseGraphEdge>& edges, std::size_t num_poses) {
  std::vector<Matrix6d> roots;
  roots.reserve(edges.size());
  for (std::size_t e = 0; e < edges.size(); ++e) {
    const PoseGraphEdge& edge = edges[e];
    if (edge.from >= num_poses || edge.to >= num_poses) {
      throw std::invalid_argument("edge " + std::to_string(e) + " (" + std::to_string(edge.from) + " -> " +
                                  std::to_string(edge.to) + ") refers to a pose out of range for " +
                                  std::to_string(num_poses) + " poses");
    }
    if (edge.from == edge.to) throw std::invalid_argument("edge " + std::to_string(e) + " joins a pose to itself");
    detail::check_rigid_transform(edge.measurement, "edge " + std::to_string(e) + " measurement");
    roots.push_back(information_root(edge.information, e));
  }
  return roots;
}

/// Levenberg-Marquardt with the params' tolerances, silent.
ceres::Solver::Options solver_options(const PoseGraphParams& params) {
  ceres::Solver::Options options;
  choose_linear_solver(options);
  options.minimizer_type = ceres::TRUST_REGION;
  options.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
  options.max_num_iterations = params.max_iterations;
  options.function_tolerance = params.function_tolerance;
  options.gradient_tolerance = params.gradient_tolerance;
  options.parameter_tolerance = params.parameter_tolerance;
  options.num_threads = params.num_threads;
  options.logging_type = ceres::SILENT;
  options.minimizer_progress_to_stdout = false;
  return options;
}

}  // namespace

PoseGraphResult optimize_pose_graph(const std::vector<Eigen::Matrix4d>& initial_poses,
                                    const std::vector<PoseGraphEdge>& edges, const PoseGraphParams& params) {
  if (initial_poses.empty()) throw std::invalid_argument("the pose graph has no poses");
  check_params(params, initial_poses.size());
  for (std::size_t k = 0; k < initial_poses.size(); ++k)
    detail::check_rigid_transform(initial_poses[k], "pose " + std::to_string(k));
  const std::vector<Matrix6d> roots = checked_information_roots(edges, initial_poses.size());

  PoseGraphResult result;
  result.poses = initial_poses;
  if (edges.empty()) {
    result.converged = true;
    result.message = "no edges: poses unchanged";
    return result;
  }

  // Parameter blocks: translation (3) and Eigen-ordered unit quaternion (x, y, z, w) per pose.
  std::vector<Eigen::Vector3d> translations(initial_poses.size());
  std::vector<Eigen::Quaterniond> rotations(initial_poses.size());
  for (std::size_t k = 0; k < initial_poses.size(); ++k) {
    translations[k] = initial_poses[k].topRightCorner<3, 1>();
    rotations[k] = Eigen::Quaterniond(Eigen::Matrix3d(initial_poses[k].topLeftCorner<3, 3>())).normalized();
  }

  ceres::Problem::Options problem_options;
  problem_options.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  ceres::EigenQuaternionManifold quaternion_manifold;
  std::vector<bool> in_problem(initial_poses.size(), false);
  for (std::size_t e = 0; e < edges.size(); ++e) {
    const PoseGraphEdge& edge = edges[e];
    ceres::LossFunction* loss = nullptr;  // the problem takes ownership
    if (edge.robust) {
      const double a = params.robust_loss_scale;
      loss = params.robust_loss == RobustLoss::kHuber ? static_cast<ceres::LossFunction*>(new ceres::HuberLoss(a))
                                                      : static_cast<ceres::LossFunction*>(new ceres::CauchyLoss(a));
    }
    auto* cost = new ceres::AutoDiffCostFunction<RelativePoseResidual, 6, 3, 4, 3, 4>(
        new RelativePoseResidual(edge.measurement, roots[e]));
    problem.AddResidualBlock(cost, loss, translations[edge.from].data(), rotations[edge.from].coeffs().data(),
                             translations[edge.to].data(), rotations[edge.to].coeffs().data());
    for (const std::size_t node : {edge.from, edge.to}) {
      if (!in_problem[node]) {
        problem.SetManifold(rotations[node].coeffs().data(), &quaternion_manifold);
        in_problem[node] = true;
      }
    }
  }
  for (std::size_t node : params.fixed) {
    if (!in_problem[node]) continue;
    problem.SetParameterBlockConstant(translations[node].data());
    problem.SetParameterBlockConstant(rotations[node].coeffs().data());
  }
  for (std::size_t node : params.fixed_rotations) {
    if (in_problem[node]) problem.SetParameterBlockConstant(rotations[node].coeffs().data());
  }

  ceres::Solver::Summary summary;
  ceres::Solve(solver_options(params), &problem, &summary);

  result.initial_cost = summary.initial_cost;
  result.final_cost = summary.final_cost;
  result.iterations = summary.num_successful_steps + summary.num_unsuccessful_steps;
  result.converged = summary.termination_type == ceres::CONVERGENCE;
  result.message = summary.BriefReport() + ": " + summary.message;
  if (summary.termination_type == ceres::FAILURE) {
    throw std::runtime_error("pose graph optimisation failed: " + summary.message);
  }

  std::vector<bool> fixed(initial_poses.size(), false);
  std::vector<bool> rotation_fixed(initial_poses.size(), false);
  for (std::size_t node : params.fixed) fixed[node] = true;
  for (std::size_t node : params.fixed_rotations) rotation_fixed[node] = true;
  for (std::size_t k = 0; k < initial_poses.size(); ++k) {
    if (!in_problem[k] || fixed[k]) continue;  // untouched and fixed poses are returned bit for bit
    Eigen::Matrix4d pose = initial_poses[k];
    if (!rotation_fixed[k]) pose.topLeftCorner<3, 3>() = rotations[k].normalized().toRotationMatrix();
    pose.topRightCorner<3, 1>() = translations[k];
    result.poses[k] = pose;
  }
  return result;
}

}  // namespace terracube
