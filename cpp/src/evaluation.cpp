#include "terracube/evaluation.hpp"

#include <Eigen/Geometry>
#include <Eigen/SVD>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "cloud_frame.hpp"
#include "number_text.hpp"

namespace terracube {

namespace {

constexpr double kRadToDeg = 57.295779513082320876798;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

void check_trajectories(const std::vector<Eigen::Matrix4d>& estimate,
                        const std::vector<Eigen::Matrix4d>& ground_truth) {
  if (estimate.empty() || ground_truth.empty()) throw std::invalid_argument("trajectories must not be empty");
  if (estimate.size() != ground_truth.size()) {
    throw std::invalid_argument("estimate has " + std::to_string(estimate.size()) + " poses but ground truth has " +
                                std::to_string(ground_truth.size()));
  }
  for (std::size_t k = 0; k < estimate.size(); ++k) {
    detail::check_rigid_transform(estimate[k], "estimate pose " + std::to_string(k));
    detail::check_rigid_transform(ground_truth[k], "ground truth pose " + std::to_string(k));
  }
}

/// Rotation angle of R in [0, pi], accurate near 0 and pi (atan2 of sin and cos).
double rotation_angle(const Eigen::Matrix3d& r) {
  const double cos_angle = 0.5 * (r.trace() - 1.0);
  const Eigen::Vector3d axis(r(2, 1) - r(1, 2), r(0, 2) - r(2, 0), r(1, 0) - r(0, 1));
  return std::atan2(0.5 * axis.norm(), cos_angle);
}

Eigen::Matrix4d inverse_rigid(const Eigen::Matrix4d& t) {
  Eigen::Matrix4d inverse = Eigen::Matrix4d::Identity();
  inverse.topLeftCorner<3, 3>() = t.topLeftCorner<3, 3>().transpose();
  inverse.topRightCorner<3, 1>() = -t.topLeftCorner<3, 3>().transpose() * t.topRightCorner<3, 1>();
  return inverse;
}

double mean_of(const std::vector<double>& values) {
  if (values.empty()) return kNaN;
  double sum = 0.0;
  for (double v : values) sum += v;
  return sum / static_cast<double>(values.size());
}

double angle_between(const Eigen::VectorXd& a, const Eigen::VectorXd& b) {
  // atan2(|a x b|, a.b) in any dimension: |a x b|^2 = |a|^2 |b|^2 - (a.b)^2 (Lagrange).
  const double dot = a.dot(b);
  const double cross = std::sqrt(std::max(0.0, a.squaredNorm() * b.squaredNorm() - dot * dot));
  return std::atan2(cross, dot);
}

}  // namespace

ErrorStatistics error_statistics(const std::vector<double>& errors) {
  ErrorStatistics stats;
  stats.count = errors.size();
  if (errors.empty()) {
    stats.rmse = stats.mean = stats.median = stats.max = kNaN;
    return stats;
  }
  double sum = 0.0, sum_squares = 0.0;
  for (double e : errors) {
    sum += e;
    sum_squares += e * e;
  }
  const auto n = static_cast<double>(errors.size());
  stats.mean = sum / n;
  stats.rmse = std::sqrt(sum_squares / n);
  std::vector<double> sorted = errors;
  std::sort(sorted.begin(), sorted.end());
  const std::size_t half = sorted.size() / 2;
  stats.median = sorted.size() % 2 == 1 ? sorted[half] : 0.5 * (sorted[half - 1] + sorted[half]);
  stats.max = sorted.back();
  return stats;
}

Eigen::Matrix4d rigid_alignment(const std::vector<Eigen::Vector3d>& source,
                                const std::vector<Eigen::Vector3d>& target) {
  if (source.empty() || source.size() != target.size()) {
    throw std::invalid_argument("rigid alignment needs the same non-zero number of source and target points");
  }
  const auto n = static_cast<double>(source.size());
  Eigen::Vector3d source_mean = Eigen::Vector3d::Zero(), target_mean = Eigen::Vector3d::Zero();
  for (std::size_t k = 0; k < source.size(); ++k) {
    source_mean += source[k];
    target_mean += target[k];
  }
  source_mean /= n;
  target_mean /= n;
  // Umeyama (1991): cross-covariance of the centred sets (eq. 38), its SVD, and the sign matrix S
  // that keeps det(R) = +1 (eqs. 39-40); no scale.
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Zero();
  for (std::size_t k = 0; k < source.size(); ++k) {
    covariance += (target[k] - target_mean) * (source[k] - source_mean).transpose();
  }
  covariance /= n;
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();
  if (source.size() > 1) {
    const Eigen::JacobiSVD<Eigen::Matrix3d> svd(covariance, Eigen::ComputeFullU | Eigen::ComputeFullV);
    Eigen::Vector3d sign(1.0, 1.0, 1.0);
    if (svd.matrixU().determinant() * svd.matrixV().determinant() < 0.0) sign(2) = -1.0;
    rotation = svd.matrixU() * sign.asDiagonal() * svd.matrixV().transpose();
  }
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();
  transform.topLeftCorner<3, 3>() = rotation;
  transform.topRightCorner<3, 1>() = target_mean - rotation * source_mean;  // eq. (41)
  return transform;
}

AbsoluteTrajectoryError absolute_trajectory_error(const std::vector<Eigen::Matrix4d>& estimate,
                                                  const std::vector<Eigen::Matrix4d>& ground_truth,
                                                  TrajectoryAlignment alignment) {
  check_trajectories(estimate, ground_truth);
  AbsoluteTrajectoryError result;
  switch (alignment) {
    case TrajectoryAlignment::kNone:
      break;
    case TrajectoryAlignment::kFirstPose:
      result.alignment = ground_truth.front() * inverse_rigid(estimate.front());
      break;
    case TrajectoryAlignment::kRigid: {
      std::vector<Eigen::Vector3d> source, target;
      source.reserve(estimate.size());
      target.reserve(estimate.size());
      for (std::size_t k = 0; k < estimate.size(); ++k) {
        source.emplace_back(estimate[k].topRightCorner<3, 1>());
        target.emplace_back(ground_truth[k].topRightCorner<3, 1>());
      }
      result.alignment = rigid_alignment(source, target);
      break;
    }
    default:
      throw std::invalid_argument("unknown trajectory alignment");
  }
  result.translation_errors_m.reserve(estimate.size());
  result.rotation_errors_deg.reserve(estimate.size());
  for (std::size_t k = 0; k < estimate.size(); ++k) {
    const Eigen::Matrix4d aligned = result.alignment * estimate[k];
    result.translation_errors_m.push_back(
        (ground_truth[k].topRightCorner<3, 1>() - aligned.topRightCorner<3, 1>()).norm());
    const Eigen::Matrix3d delta = ground_truth[k].topLeftCorner<3, 3>().transpose() * aligned.topLeftCorner<3, 3>();
    result.rotation_errors_deg.push_back(rotation_angle(delta) * kRadToDeg);
  }
  result.translation = error_statistics(result.translation_errors_m);
  result.rotation = error_statistics(result.rotation_errors_deg);
  return result;
}

RelativePoseError relative_pose_error(const std::vector<Eigen::Matrix4d>& estimate,
                                      const std::vector<Eigen::Matrix4d>& ground_truth,
                                      const RelativePoseErrorParams& params) {
  if (params.step_frames < 1) throw std::invalid_argument("step_frames must be at least 1");
  if (params.lengths_m.empty()) throw std::invalid_argument("relative pose error needs at least one segment length");
  for (double length : params.lengths_m) {
    if (!(length > 0.0) || !std::isfinite(length)) {
      throw std::invalid_argument("segment lengths must be positive and finite [m], got " +
                                  detail::number_text(length));
    }
  }
  check_trajectories(estimate, ground_truth);

  // Path length along the ground truth up to each frame (the devkit's trajectoryDistances).
  std::vector<double> distance(ground_truth.size(), 0.0);
  for (std::size_t k = 1; k < ground_truth.size(); ++k) {
    distance[k] =
        distance[k - 1] + (ground_truth[k].topRightCorner<3, 1>() - ground_truth[k - 1].topRightCorner<3, 1>()).norm();
  }

  RelativePoseError result;
  std::vector<std::vector<double>> translation_by_length(params.lengths_m.size());
  std::vector<std::vector<double>> rotation_by_length(params.lengths_m.size());
  for (std::size_t first = 0; first < ground_truth.size(); first += params.step_frames) {
    const Eigen::Matrix4d gt_inverse = inverse_rigid(ground_truth[first]);
    const Eigen::Matrix4d est_inverse = inverse_rigid(estimate[first]);
    for (std::size_t l = 0; l < params.lengths_m.size(); ++l) {
      const double length = params.lengths_m[l];
      const double base = distance[first];
      // First frame whose path length from `first` reaches `length` (distance is non-decreasing).
      const auto end = std::lower_bound(distance.begin() + static_cast<std::ptrdiff_t>(first), distance.end(), length,
                                        [base](double d, double limit) { return d - base < limit; });
      if (end == distance.end()) continue;
      const auto last = static_cast<std::size_t>(end - distance.begin());
      const Eigen::Matrix4d true_motion = gt_inverse * ground_truth[last];
      const Eigen::Matrix4d estimated_motion = est_inverse * estimate[last];
      const Eigen::Matrix4d error = inverse_rigid(true_motion) * estimated_motion;
      PoseSegmentError segment;
      segment.first_frame = first;
      segment.last_frame = last;
      segment.length_m = length;
      segment.translation_percent = 100.0 * error.topRightCorner<3, 1>().norm() / length;
      segment.rotation_deg_per_100m = 100.0 * rotation_angle(error.topLeftCorner<3, 3>()) * kRadToDeg / length;
      translation_by_length[l].push_back(segment.translation_percent);
      rotation_by_length[l].push_back(segment.rotation_deg_per_100m);
      result.segments.push_back(segment);
    }
  }

  std::vector<double> all_translation, all_rotation;
  for (const PoseSegmentError& segment : result.segments) {
    all_translation.push_back(segment.translation_percent);
    all_rotation.push_back(segment.rotation_deg_per_100m);
  }
  result.num_segments = result.segments.size();
  result.translation_percent = mean_of(all_translation);
  result.rotation_deg_per_100m = mean_of(all_rotation);
  for (std::size_t l = 0; l < params.lengths_m.size(); ++l) {
    SegmentLengthError entry;
    entry.length_m = params.lengths_m[l];
    entry.num_segments = translation_by_length[l].size();
    entry.translation_percent = mean_of(translation_by_length[l]);
    entry.rotation_deg_per_100m = mean_of(rotation_by_length[l]);
    result.per_length.push_back(entry);
  }
  return result;
}

RegionLayoutComparison compare_region_layouts(const std::vector<Eigen::VectorXd>& map_centres,
                                              const std::vector<Eigen::VectorXd>& dsm_centres,
                                              RegionRelations relations) {
  if (map_centres.size() != dsm_centres.size()) {
    throw std::invalid_argument("map has " + std::to_string(map_centres.size()) + " region centres but the DSM has " +
                                std::to_string(dsm_centres.size()));
  }
  if (map_centres.size() < 2) throw std::invalid_argument("the DSM comparison needs at least two regions");
  const auto dimension = map_centres.front().size();
  if (dimension != 2 && dimension != 3) throw std::invalid_argument("region centres must be 2D or 3D points");
  for (std::size_t k = 0; k < map_centres.size(); ++k) {
    if (map_centres[k].size() != dimension || dsm_centres[k].size() != dimension) {
      throw std::invalid_argument("every region centre must have the same dimension (region " + std::to_string(k) +
                                  ")");
    }
    if (!map_centres[k].allFinite() || !dsm_centres[k].allFinite()) {
      throw std::invalid_argument("region " + std::to_string(k) + " has a NaN or Inf coordinate");
    }
  }
  const std::size_t count = map_centres.size();
  for (std::size_t i = 0; i < count; ++i) {
    for (std::size_t j = i + 1; j < count; ++j) {
      if ((map_centres[i] - map_centres[j]).norm() == 0.0 || (dsm_centres[i] - dsm_centres[j]).norm() == 0.0) {
        throw std::invalid_argument("regions " + std::to_string(i) + " and " + std::to_string(j) +
                                    " are at the same place in one of the sets");
      }
    }
  }

  // The (i, j) pairs and (i, j, k) triples to compare, j the vertex of a triple.
  std::vector<std::array<std::size_t, 2>> pair_indices;
  std::vector<std::array<std::size_t, 3>> triple_indices;
  if (relations == RegionRelations::kConsecutive) {
    for (std::size_t i = 0; i < count; ++i) {
      if (count > 2 || i == 0) pair_indices.push_back({i, (i + 1) % count});                   // 1-2, ..., K-1
      if (count > 2) triple_indices.push_back({(i + count - 1) % count, i, (i + 1) % count});  // K-1-2, ...
    }
  } else {
    for (std::size_t i = 0; i < count; ++i) {
      for (std::size_t j = i + 1; j < count; ++j) {
        pair_indices.push_back({i, j});
        for (std::size_t k = j + 1; k < count; ++k) triple_indices.push_back({i, j, k});
      }
    }
  }
  RegionLayoutComparison result;
  std::vector<double> distance_errors, angle_errors;  // absolute values, for the averages
  for (const auto& [i, j] : pair_indices) {
    RegionPairError pair;  // [TC] eq. (5)
    pair.i = i;
    pair.j = j;
    pair.map_distance_m = (map_centres[i] - map_centres[j]).norm();
    pair.dsm_distance_m = (dsm_centres[i] - dsm_centres[j]).norm();
    pair.error_m = pair.map_distance_m - pair.dsm_distance_m;
    distance_errors.push_back(std::abs(pair.error_m));
    result.pairs.push_back(pair);
  }
  for (const auto& [i, j, k] : triple_indices) {
    RegionTripleError triple;  // [TC] eq. (6): the angle at the middle region j
    triple.i = i;
    triple.j = j;
    triple.k = k;
    triple.map_angle_deg = angle_between(map_centres[i] - map_centres[j], map_centres[k] - map_centres[j]) * kRadToDeg;
    triple.dsm_angle_deg = angle_between(dsm_centres[i] - dsm_centres[j], dsm_centres[k] - dsm_centres[j]) * kRadToDeg;
    triple.error_deg = triple.map_angle_deg - triple.dsm_angle_deg;
    angle_errors.push_back(std::abs(triple.error_deg));
    result.triples.push_back(triple);
  }
  result.mean_distance_error_m = mean_of(distance_errors);
  result.max_distance_error_m =
      distance_errors.empty() ? kNaN : *std::max_element(distance_errors.begin(), distance_errors.end());
  result.mean_angle_error_deg = mean_of(angle_errors);
  result.max_angle_error_deg =
      angle_errors.empty() ? kNaN : *std::max_element(angle_errors.begin(), angle_errors.end());
  return result;
}

}  // namespace terracube
