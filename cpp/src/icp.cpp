#include "terracube/icp.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <stdexcept>
#include <string>

#include "cloud_frame.hpp"

namespace terracube {

namespace {

constexpr std::uint32_t kLeafSize = 8;

using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Vector6d = Eigen::Matrix<double, 6, 1>;

void check_registration_params(const RegistrationParams& p) {
  const auto positive = [](double v) { return v > 0.0 && std::isfinite(v); };
  const auto non_negative = [](double v) { return v >= 0.0 && std::isfinite(v); };
  if (!positive(p.max_correspondence_distance_m) || !positive(p.min_correspondence_distance_m)) {
    throw std::invalid_argument("correspondence distances must be positive and finite [m]");
  }
  if (p.min_correspondence_distance_m > p.max_correspondence_distance_m) {
    throw std::invalid_argument("min correspondence distance must not exceed the max correspondence distance");
  }
  if (!(p.correspondence_distance_decay > 0.0 && p.correspondence_distance_decay <= 1.0)) {
    throw std::invalid_argument("correspondence distance decay must lie in (0, 1]");
  }
  if (p.max_iterations < 1) throw std::invalid_argument("max iterations must be at least 1");
  if (!non_negative(p.rotation_tolerance_rad) || !non_negative(p.translation_tolerance_m) ||
      !non_negative(p.error_threshold_m)) {
    throw std::invalid_argument("tolerances and the error threshold must be finite and >= 0");
  }
  if (p.min_correspondences < 3) throw std::invalid_argument("min correspondences must be at least 3");
  if (!(p.degeneracy_threshold >= 0.0 && p.degeneracy_threshold < 1.0)) {
    throw std::invalid_argument("degeneracy threshold must lie in [0, 1)");
  }
  for (const double w : p.class_weights) {
    if (!non_negative(w)) throw std::invalid_argument("class weights must be finite and >= 0");
  }
}

void check_points(const ClassifiedPoints& set, const char* what) {
  if (set.classes.size() != set.points.size()) {
    throw std::invalid_argument(std::string(what) + " has " + std::to_string(set.points.size()) + " points but " +
                                std::to_string(set.classes.size()) + " classes");
  }
  for (std::size_t k = 0; k < set.size(); ++k) {
    if (!set.points[k].allFinite()) {
      throw std::invalid_argument(std::string(what) + " point " + std::to_string(k) + " is NaN or Inf");
    }
    if (set.classes[k] >= kNumTerrainClasses) {
      throw std::invalid_argument(std::string(what) + " class " + std::to_string(set.classes[k]) + " at point " +
                                  std::to_string(k) + " is not a TerrainClass");
    }
  }
}

Eigen::Matrix3d skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0.0, -v.z(), v.y(), v.z(), 0.0, -v.x(), -v.y(), v.x(), 0.0;
  return m;
}

/// One correspondence pass: weighted sums of the normal equations about the source centroid.
struct Pass {
  Matrix6d normal = Matrix6d::Zero();
  Vector6d gradient = Vector6d::Zero();
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  double weight_sum = 0.0;
  double weighted_squared_error = 0.0;
  std::size_t count = 0;
  std::array<std::size_t, kNumTerrainClasses> per_class{};
};

class Registration {
 public:
  Registration(const ClassifiedPoints& source, const ClassifiedPoints& target, const RegistrationParams& params)
      : source_(source), params_(params) {
    // One tree per class (or one for all): buckets of target points.
    std::array<std::vector<Eigen::Vector3d>, kNumTerrainClasses> buckets;
    for (std::size_t k = 0; k < target.size(); ++k) {
      const std::size_t c = params.use_classes ? target.classes[k] : 0;
      if (!params.use_classes || params.class_weights[c] > 0.0) buckets[c].push_back(target.points[k]);
    }
    for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
      if (!buckets[c].empty()) trees_[c] = NearestNeighbor3d(std::move(buckets[c]));
    }
    for (std::size_t k = 0; k < source.size(); ++k) {
      const std::size_t tree = params.use_classes ? source.classes[k] : 0;
      const double w = params.use_classes ? params.class_weights[tree] : 1.0;
      if (w > 0.0 && trees_[tree].size() > 0) active_.push_back(static_cast<std::uint32_t>(k));
    }
    scratch_.resize(active_.size());
    hints_.assign(active_.size(), -1);
  }

  bool has_common_class() const { return !active_.empty(); }

  /// Correspondences of the source moved by `transform`; sums about their weighted centroid.
  Pass pass(const Eigen::Matrix4d& transform, double max_distance) {
    const Eigen::Matrix3d rotation = transform.topLeftCorner<3, 3>();
    const Eigen::Vector3d translation = transform.topRightCorner<3, 1>();
    const double max_squared = max_distance * max_distance;
    Pass result;
    // First sweep: pairs, weights, the weighted centroid and error.
    std::size_t used = 0;
    std::size_t slot = 0;
    for (const std::uint32_t k : active_) {
      const std::uint8_t c = source_.classes[k];
      const std::size_t tree = params_.use_classes ? c : 0;
      const double w = params_.use_classes ? params_.class_weights[c] : 1.0;
      const Eigen::Vector3d p = rotation * source_.points[k] + translation;
      // Last pass's partner, if still within the limit, bounds the search: far fewer nodes are
      // visited and the result is still the exact nearest.
      double bound = max_squared;
      std::int64_t& hint = hints_[slot++];
      if (hint >= 0) {
        const double d = (trees_[tree].point(static_cast<std::size_t>(hint)) - p).squaredNorm();
        if (d <= bound) bound = d;
      }
      double squared = 0.0;
      const std::ptrdiff_t nearest = trees_[tree].nearest(p, bound, squared);
      hint = nearest;
      if (nearest < 0) continue;
      scratch_[used++] = {p, trees_[tree].point(static_cast<std::size_t>(nearest)), w};
      result.weight_sum += w;
      result.weighted_squared_error += w * squared;
      result.centroid += w * p;
      ++result.per_class[c];
    }
    result.count = used;
    if (used == 0) return result;
    result.centroid /= result.weight_sum;
    // Second sweep: eq. (A6) with per-class weights (eq. 4). Unknowns x = (omega, t) about the
    // centroid; residual r_i = p_i + omega x p_i + t - q_i, so J_i = [-[p_i]x, I] and
    // H = sum w J^T J, g = sum w J^T (q - p).
    Eigen::Matrix3d rot_rot = Eigen::Matrix3d::Zero();
    Eigen::Vector3d weighted_p = Eigen::Vector3d::Zero();
    Eigen::Vector3d g_rot = Eigen::Vector3d::Zero();
    Eigen::Vector3d g_trans = Eigen::Vector3d::Zero();
    for (std::size_t k = 0; k < used; ++k) {
      const Pair& pair = scratch_[k];
      const Eigen::Vector3d p = pair.p - result.centroid;
      const Eigen::Vector3d d = pair.q - pair.p;
      // [p]x^T [p]x = |p|^2 I - p p^T
      rot_rot += pair.w * (p.squaredNorm() * Eigen::Matrix3d::Identity() - p * p.transpose());
      weighted_p += pair.w * p;
      g_rot += pair.w * p.cross(d);  // (-[p]x)^T d = p x d
      g_trans += pair.w * d;
    }
    const Eigen::Matrix3d rot_trans = skew(weighted_p);  // (-[p]x)^T I summed = [sum w p]x
    result.normal.topLeftCorner<3, 3>() = rot_rot;
    result.normal.topRightCorner<3, 3>() = rot_trans;
    result.normal.bottomLeftCorner<3, 3>() = rot_trans.transpose();
    result.normal.bottomRightCorner<3, 3>() = result.weight_sum * Eigen::Matrix3d::Identity();
    result.gradient << g_rot, g_trans;
    return result;
  }

 private:
  struct Pair {
    Eigen::Vector3d p, q;
    double w = 0.0;
  };
  const ClassifiedPoints& source_;
  const RegistrationParams& params_;
  std::array<NearestNeighbor3d, kNumTerrainClasses> trees_;
  std::vector<std::uint32_t> active_;  // source points that can take part
  std::vector<Pair> scratch_;
  std::vector<std::int64_t> hints_;  // per active source point: its last partner in its tree, or -1
};

/// Rodrigues: the exact rotation exp([omega]x).
Eigen::Matrix3d rotation_of(const Eigen::Vector3d& omega) {
  const double angle = omega.norm();
  if (angle < 1e-12) return Eigen::Matrix3d::Identity() + skew(omega);
  return Eigen::AngleAxisd(angle, omega / angle).toRotationMatrix();
}

/// Re-orthonormalises a rotation that has accumulated rounding (nearest rotation via SVD-free
/// quaternion normalisation).
Eigen::Matrix3d orthonormalised(const Eigen::Matrix3d& rotation) {
  return Eigen::Quaterniond(rotation).normalized().toRotationMatrix();
}

void fill(RegistrationResult& result, const Pass& pass, double distance) {
  result.num_correspondences = pass.count;
  result.correspondences_per_class = pass.per_class;
  result.correspondence_distance_m = distance;
  result.rmse_m = pass.count > 0 ? std::sqrt(pass.weighted_squared_error / pass.weight_sum)
                                 : std::numeric_limits<double>::quiet_NaN();
  result.normal_matrix = pass.normal;
  if (pass.count > 0) {
    Eigen::SelfAdjointEigenSolver<Matrix6d> solver(pass.normal, Eigen::EigenvaluesOnly);
    result.eigenvalues = solver.eigenvalues();
  } else {
    result.eigenvalues.setZero();
  }
}

}  // namespace

const char* to_string(StopReason reason) {
  switch (reason) {
    case StopReason::kConverged:
      return "converged";
    case StopReason::kErrorBelowThreshold:
      return "error_below_threshold";
    case StopReason::kMaxIterations:
      return "max_iterations";
    case StopReason::kTooFewCorrespondences:
      return "too_few_correspondences";
    case StopReason::kNoCommonClass:
      return "no_common_class";
    case StopReason::kDegenerate:
      return "degenerate";
  }
  return "unknown";
}

ClassifiedPoints points_of_map(const ElevationMap& map) {
  const Layer& highest = map.get("max");
  const Layer* classes = map.exists("class") ? &map.get("class") : nullptr;
  const MapGeometry& geometry = map.geometry();
  ClassifiedPoints set;
  for (Eigen::Index i = 0; i < highest.rows(); ++i) {
    for (Eigen::Index j = 0; j < highest.cols(); ++j) {
      const float z = highest(i, j);
      if (!std::isfinite(z)) continue;
      const Eigen::Vector2d xy = geometry.position_of({static_cast<int>(i), static_cast<int>(j)});
      set.points.emplace_back(xy.x(), xy.y(), static_cast<double>(z));
      float c = classes ? (*classes)(i, j) : 0.0F;
      if (!(c >= 0.0F && c < static_cast<float>(kNumTerrainClasses))) c = 0.0F;  // NaN: unknown
      set.classes.push_back(static_cast<std::uint8_t>(c));
    }
  }
  return set;
}

RegistrationResult register_points(const ClassifiedPoints& source, const ClassifiedPoints& target,
                                   const Eigen::Matrix4d& initial, const RegistrationParams& params) {
  check_registration_params(params);
  detail::check_rigid_transform(initial, "initial transform");
  check_points(source, "source");
  check_points(target, "target");

  RegistrationResult result;
  result.transform = initial;
  Registration registration(source, target, params);
  if (!registration.has_common_class()) {
    result.reason =
        source.size() == 0 || target.size() == 0 ? StopReason::kTooFewCorrespondences : StopReason::kNoCommonClass;
    result.rmse_m = std::numeric_limits<double>::quiet_NaN();
    return result;
  }

  Eigen::Matrix4d transform = initial;
  double distance = params.max_correspondence_distance_m;
  for (int iteration = 0;; ++iteration) {
    distance =
        std::max(params.min_correspondence_distance_m,
                 params.max_correspondence_distance_m * std::pow(params.correspondence_distance_decay, iteration));
    const Pass pass = registration.pass(transform, distance);
    result.transform = transform;
    result.iterations = iteration;
    fill(result, pass, distance);
    if (pass.count < params.min_correspondences) {
      result.reason = StopReason::kTooFewCorrespondences;
      return result;
    }
    if (result.rmse_m < params.error_threshold_m) {
      result.reason = StopReason::kErrorBelowThreshold;
      result.converged = true;
      return result;
    }
    if (result.eigenvalues(0) <= params.degeneracy_threshold * result.eigenvalues(5)) {
      result.reason = StopReason::kDegenerate;
      return result;
    }
    if (iteration == params.max_iterations) {
      result.reason = StopReason::kMaxIterations;
      return result;
    }
    const Vector6d x = pass.normal.ldlt().solve(pass.gradient);
    if (!x.allFinite()) {
      result.reason = StopReason::kDegenerate;
      return result;
    }
    // The update about the centroid c: p -> R (p - c) + c + t, composed exactly (no small-angle matrix).
    const Eigen::Matrix3d rotation = rotation_of(x.head<3>());
    Eigen::Matrix4d update = Eigen::Matrix4d::Identity();
    update.topLeftCorner<3, 3>() = rotation;
    update.topRightCorner<3, 1>() = pass.centroid + x.tail<3>() - rotation * pass.centroid;
    transform = update * transform;
    transform.topLeftCorner<3, 3>() = orthonormalised(transform.topLeftCorner<3, 3>());
    if (x.head<3>().norm() < params.rotation_tolerance_rad && x.tail<3>().norm() < params.translation_tolerance_m) {
      // Converged: report the statistics at the final estimate.
      const Pass last = registration.pass(transform, distance);
      result.transform = transform;
      result.iterations = iteration + 1;
      if (last.count > 0) fill(result, last, distance);
      result.reason = StopReason::kConverged;
      result.converged = true;
      return result;
    }
  }
}

RegistrationResult register_maps(const ElevationMap& source, const ElevationMap& target, const Eigen::Matrix4d& initial,
                                 const RegistrationParams& params) {
  if (params.use_classes && (!source.exists("class") || !target.exists("class"))) {
    throw std::invalid_argument(
        "class-weighted registration needs the \"class\" layer in both maps: run classify_terrain first");
  }
  return register_points(points_of_map(source), points_of_map(target), initial, params);
}

RegistrationResult register_maps_all_cells(const ElevationMap& source, const ElevationMap& target,
                                           const Eigen::Matrix4d& initial, RegistrationParams params) {
  params.use_classes = false;
  return register_maps(source, target, initial, params);
}

// --- k-d tree ---------------------------------------------------------------------------------

NearestNeighbor3d::NearestNeighbor3d(std::vector<Eigen::Vector3d> points) {
  if (points.size() >= std::numeric_limits<std::uint32_t>::max()) {
    throw std::invalid_argument("too many points for the nearest-neighbour index");
  }
  points_ = std::move(points);
  original_.resize(points_.size());
  std::iota(original_.begin(), original_.end(), std::uint32_t{0});
  if (points_.empty()) return;
  nodes_.reserve(2 * (points_.size() / kLeafSize + 1));
  build(0, static_cast<std::uint32_t>(points_.size()));
  // Store the points in leaf order so that a leaf scan reads contiguous memory.
  std::vector<Eigen::Vector3d> ordered(points_.size());
  position_.resize(points_.size());
  for (std::size_t k = 0; k < points_.size(); ++k) {
    ordered[k] = points_[original_[k]];
    position_[original_[k]] = static_cast<std::uint32_t>(k);
  }
  points_ = std::move(ordered);
}

std::int32_t NearestNeighbor3d::build(std::uint32_t begin, std::uint32_t end) {
  // original_ holds the permutation being partitioned; points_ is still in input order.
  const auto index = static_cast<std::int32_t>(nodes_.size());
  nodes_.emplace_back();
  if (end - begin <= kLeafSize) {
    nodes_[static_cast<std::size_t>(index)].begin = begin;
    nodes_[static_cast<std::size_t>(index)].end = end;
    return index;
  }
  Eigen::Vector3d low = points_[original_[begin]], high = low;
  for (std::uint32_t k = begin + 1; k < end; ++k) {
    low = low.cwiseMin(points_[original_[k]]);
    high = high.cwiseMax(points_[original_[k]]);
  }
  int axis = 0;
  (high - low).maxCoeff(&axis);
  const std::uint32_t middle = begin + (end - begin) / 2;
  std::nth_element(original_.begin() + begin, original_.begin() + middle, original_.begin() + end,
                   [&](std::uint32_t a, std::uint32_t b) { return points_[a][axis] < points_[b][axis]; });
  const double split = points_[original_[middle]][axis];
  const std::int32_t left = build(begin, middle);
  const std::int32_t right = build(middle, end);
  Node& node = nodes_[static_cast<std::size_t>(index)];
  node.axis = static_cast<std::int8_t>(axis);
  node.split = split;
  node.left = left;
  node.right = right;
  return index;
}

std::ptrdiff_t NearestNeighbor3d::nearest(const Eigen::Vector3d& query, double max_squared_distance,
                                          double& squared_distance) const {
  std::ptrdiff_t best = -1;
  double best_squared = max_squared_distance;
  if (nodes_.empty()) return best;
  // Depth-first with an explicit stack of (node, lower bound on its squared distance).
  struct Entry {
    std::int32_t node;
    double bound;
  };
  Entry stack[64];
  int top = 0;
  stack[top++] = {0, 0.0};
  while (top > 0) {
    const Entry entry = stack[--top];
    if (entry.bound > best_squared) continue;
    // Descend to the leaf on the query's side, pushing each far side that may still hold a
    // nearer point (its bound: the squared distance to the splitting plane).
    const Node* node = &nodes_[static_cast<std::size_t>(entry.node)];
    while (node->axis >= 0) {
      const double offset = query[node->axis] - node->split;
      const double far_bound = std::max(entry.bound, offset * offset);
      if (far_bound <= best_squared) stack[top++] = {offset < 0.0 ? node->right : node->left, far_bound};
      node = &nodes_[static_cast<std::size_t>(offset < 0.0 ? node->left : node->right)];
    }
    for (std::uint32_t k = node->begin; k < node->end; ++k) {
      const double d = (points_[k] - query).squaredNorm();
      if (d <= best_squared) {
        best_squared = d;
        best = static_cast<std::ptrdiff_t>(k);
      }
    }
  }
  if (best >= 0) {
    squared_distance = best_squared;
    return static_cast<std::ptrdiff_t>(original_[static_cast<std::size_t>(best)]);
  }
  return -1;
}

}  // namespace terracube
