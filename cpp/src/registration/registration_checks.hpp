// The checks at the registration's boundary (point sets; check_registration_params is public),
// std::invalid_argument naming the problem, and the verdict on a registration's result (not in
// [TC]): overlap, inlier share per class, how firmly the scene holds each motion, and the trusted
// flag with its reason in plain words.
#pragma once

#include <array>
#include <cstddef>

#include "terracube/icp.hpp"

namespace terracube::detail {

/// Throws std::invalid_argument when `set` has not one class per point, a non-finite point or a
/// class value >= kNumTerrainClasses; `what` names the set.
void check_points(const ClassifiedPoints& set, const char* what);

/// Checks the trust thresholds of RegistrationParams (std::invalid_argument naming the field).
void check_trust_params(const RegistrationParams& params);

/// The share of the source's object points (classes from kObstacle up; every class without
/// classes) with a partner: sum inliers / sum points over those classes (0 without points).
double object_overlap(const std::array<std::size_t, kNumTerrainClasses>& inliers_per_class,
                      const std::array<std::size_t, kNumTerrainClasses>& source_points_per_class, bool use_classes);

/// The class pairs' total weight and rms radius about their centroid at the final estimate (the
/// ground planes of RegistrationParams::ground_weight not counted).
struct PairWeight {
  double weight = 0.0, radius = 0.0;
};

/// Fills result.overlap, inlier_share_per_class, held, held_directions, trusted and verdict from
/// the rest of the result and the class pairs' weight (the units of `held`). `source_points_per_class`: the source
/// points of each class that take part (a class of weight 0 takes none; without classes every point counts under its
/// class); `inliers_per_class`: those with a partner within min_correspondence_distance_m at the result.
/// result.chance_overlap must be set.
void judge_registration(RegistrationResult& result,
                        const std::array<std::size_t, kNumTerrainClasses>& source_points_per_class,
                        const std::array<std::size_t, kNumTerrainClasses>& inliers_per_class,
                        const RegistrationParams& params, const PairWeight& pairs);

}  // namespace terracube::detail
