// The checks at the registration's boundary: parameters and point sets (std::invalid_argument
// naming the problem).
#pragma once

#include "terracube/icp.hpp"

namespace terracube::detail {

/// Throws std::invalid_argument naming the first invalid field of `params`.
void check_registration_params(const RegistrationParams& params);

/// Throws std::invalid_argument when `set` has not one class per point, a non-finite point or a
/// class value >= kNumTerrainClasses; `what` names the set.
void check_points(const ClassifiedPoints& set, const char* what);

}  // namespace terracube::detail
