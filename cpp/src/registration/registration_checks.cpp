// The checks at the registration's boundary and the verdict on its result (not in [TC]).
#include "registration_checks.hpp"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>
#include <string>

namespace terracube {

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
  if (p.max_iterations < 1 || p.max_iterations > kMaxIterationsLimit) {
    throw std::invalid_argument("max_iterations must lie in [1, " + std::to_string(kMaxIterationsLimit) + "], got " +
                                std::to_string(p.max_iterations));
  }
  if (!non_negative(p.rotation_tolerance_rad) || !non_negative(p.translation_tolerance_m) ||
      !non_negative(p.error_threshold_m)) {
    throw std::invalid_argument("tolerances and the error threshold must be finite and >= 0");
  }
  if (p.coarse_subsample < 1) throw std::invalid_argument("coarse subsample must be at least 1");
  if (!non_negative(p.coarse_until_motion_m)) {
    throw std::invalid_argument("coarse-until motion must be finite and >= 0 [m]");
  }
  if (p.min_correspondences < 3) throw std::invalid_argument("min correspondences must be at least 3");
  if (!non_negative(p.structure_radius_m)) {
    throw std::invalid_argument("structure_radius_m must be finite and >= 0 [m]");
  }
  if (!(p.degeneracy_threshold >= 0.0 && p.degeneracy_threshold < 1.0)) {
    throw std::invalid_argument("degeneracy threshold must lie in [0, 1)");
  }
  for (const double w : p.class_weights) {
    if (!non_negative(w)) throw std::invalid_argument("class weights must be finite and >= 0");
  }
  if (!non_negative(p.ground_weight)) throw std::invalid_argument("ground weight must be finite and >= 0");
  if (!positive(p.ground_cell_m)) throw std::invalid_argument("ground cell must be positive and finite [m]");
  check_correlative_search_params(p.search);  // validated even when correlative_search is off
  detail::check_trust_params(p);
}

}  // namespace terracube

namespace terracube::detail {

void check_points(const ClassifiedPoints& set, const char* what) {
  if (set.classes.size() != set.points.size()) {
    throw std::invalid_argument(std::string(what) + " has " + std::to_string(set.points.size()) + " points but " +
                                std::to_string(set.classes.size()) + " classes");
  }
  // One sweep without branches (x - x is 0 for a finite x and NaN for NaN and Inf, and NaN
  // propagates); the offending point is looked up only when there is one.
  double poison = 0.0;
  std::uint8_t largest = 0;
  for (std::size_t k = 0; k < set.size(); ++k) {
    const Eigen::Vector3d& p = set.points[k];
    poison += (p.x() - p.x()) + (p.y() - p.y()) + (p.z() - p.z());
    largest = std::max(largest, set.classes[k]);
  }
  if (poison == 0.0 && largest < kNumTerrainClasses) return;
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

namespace {

/// "12 %": a share in whole percent.
std::string percent(double share) { return std::to_string(static_cast<long>(std::lround(100.0 * share))) + " %"; }

std::string number(double value) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.3g", value);
  return text;
}

std::string metres(double value) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.3f m", value);
  return text;
}

/// The motion along a unit direction of the scaled unknowns, named by its largest component.
std::string motion_name(const Eigen::Matrix<double, 6, 1>& direction, const char*& unknown) {
  static const char* const kUnknowns[6] = {"roll", "pitch", "yaw", "x", "y", "z"};
  static const char* const kMotions[6] = {"turning about x (roll)", "turning about y (pitch)", "turning about z (yaw)",
                                          "sliding along x",        "sliding along y",         "moving along z"};
  Eigen::Index axis = 0;
  direction.cwiseAbs().maxCoeff(&axis);
  unknown = kUnknowns[axis];
  return kMotions[axis];
}

}  // namespace

double object_overlap(const std::array<std::size_t, kNumTerrainClasses>& inliers_per_class,
                      const std::array<std::size_t, kNumTerrainClasses>& source_points_per_class, bool use_classes) {
  std::size_t objects = 0, paired = 0;
  for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
    if (use_classes && c < static_cast<std::size_t>(TerrainClass::kObstacle)) continue;
    objects += source_points_per_class[c];
    paired += std::min(inliers_per_class[c], source_points_per_class[c]);
  }
  return objects > 0 ? static_cast<double>(paired) / static_cast<double>(objects) : 0.0;
}

void check_trust_params(const RegistrationParams& p) {
  const auto share = [](double v) { return v >= 0.0 && v <= 1.0; };
  if (!share(p.trust_min_overlap)) throw std::invalid_argument("trust_min_overlap must lie in [0, 1]");
  if (!share(p.trust_min_held)) throw std::invalid_argument("trust_min_held must lie in [0, 1]");
  if (!(p.trust_min_contrast >= 0.0) || !std::isfinite(p.trust_min_contrast)) {
    throw std::invalid_argument("trust_min_contrast must be finite and >= 0");
  }
  if (!(p.trust_max_rmse_m > 0.0) || !std::isfinite(p.trust_max_rmse_m)) {
    throw std::invalid_argument("trust_max_rmse_m must be positive and finite [m]");
  }
}

void judge_registration(RegistrationResult& result,
                        const std::array<std::size_t, kNumTerrainClasses>& source_points_per_class,
                        const std::array<std::size_t, kNumTerrainClasses>& inliers_per_class,
                        const RegistrationParams& params, const PairWeight& pairs) {
  // Overlap and inlier shares, by source class.
  for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
    const std::size_t points = source_points_per_class[c];
    const std::size_t pairs = std::min(inliers_per_class[c], points);
    result.inlier_share_per_class[c] = points > 0 ? static_cast<double>(pairs) / static_cast<double>(points) : 0.0;
  }
  result.overlap = object_overlap(inliers_per_class, source_points_per_class, params.use_classes);
  // How firmly each motion is held: constraint_matrix per unit of the class pairs' weight,
  // rotations scaled by their rms radius (the normalisation of terracube.constrained_directions).
  // Ground planes hold only height, roll and pitch: counting their weight too would make every
  // other motion look weakly held wherever ground fills the maps.
  const bool analysed = params.structure_radius_m > 0.0 && result.constraint_matrix.any();
  const double weight = pairs.weight;
  if (analysed && weight > 0.0) {
    const double radius = std::max(pairs.radius, 1e-6);
    Eigen::Matrix<double, 6, 1> scale;
    scale << Eigen::Vector3d::Constant(1.0 / radius), Eigen::Vector3d::Ones();
    const Eigen::Matrix<double, 6, 6> normalised =
        scale.asDiagonal() * result.constraint_matrix * scale.asDiagonal() / weight;
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 6, 6>> solver(normalised);
    result.held = solver.eigenvalues();
    result.held_directions = solver.eigenvectors();
  } else {
    result.held.setZero();
    result.held_directions.setZero();
  }

  // The verdict: every failed test, in plain words.
  std::string reasons;
  const auto fail = [&](const std::string& why) { reasons += (reasons.empty() ? "" : "; ") + why; };
  if (!(result.converged || result.reason == StopReason::kMaxIterations)) {
    fail(std::string("the ICP stopped: ") + to_string(result.reason));
  }
  const bool low_overlap = !(result.overlap >= params.trust_min_overlap);
  if (low_overlap) {
    fail("only " + percent(result.overlap) + " of the source's object cells found a partner (at least " +
         percent(params.trust_min_overlap) + " needed): the maps may not show the same place");
  }
  if (!(result.overlap >= params.trust_min_contrast * result.chance_overlap)) {
    // After the overlap's own clause, the share is not said twice.
    fail((low_overlap ? "" : percent(result.overlap) + " of the source's object cells found a partner, ") +
         percent(result.chance_overlap) + " 1 m away (at least " + number(params.trust_min_contrast) +
         " times as many needed): the match is no better than chance");
  }
  if (!(result.rmse_m <= params.trust_max_rmse_m)) {
    fail("RMSE " + metres(result.rmse_m) + " above " + metres(params.trust_max_rmse_m));
  }
  if (analysed && weight > 0.0) {
    for (int k = 0; k < 6 && result.held(k) < params.trust_min_held; ++k) {
      const char* unknown = nullptr;
      const std::string motion = motion_name(result.held_directions.col(k), unknown);
      fail(motion + " is held by " + percent(std::max(result.held(k), 0.0)) +
           " of the pairs' weight: the result along " + unknown + " is not trustworthy");
    }
  }
  result.trusted = reasons.empty();
  if (result.trusted) {
    result.verdict = "trusted: overlap " + percent(result.overlap) + " (" + percent(result.chance_overlap) +
                     " 1 m away), RMSE " + metres(result.rmse_m);
    if (analysed && weight > 0.0) {
      result.verdict += ", every direction held by at least " + percent(result.held(0)) + " of the pairs' weight";
    }
  } else {
    result.verdict = "not trusted: " + reasons;
  }
}

}  // namespace terracube::detail
