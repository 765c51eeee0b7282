// The checks at the registration's boundary.
#include "registration_checks.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "registration_verdict.hpp"

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

namespace detail {

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

}  // namespace detail
}  // namespace terracube
