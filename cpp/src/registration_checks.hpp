// The checks at the registration's boundary: point sets (check_registration_params is public) (std::invalid_argument
// naming the problem).
#pragma once

#include "terracube/icp.hpp"

namespace terracube::detail {

/// Throws std::invalid_argument when `set` has not one class per point, a non-finite point or a
/// class value >= kNumTerrainClasses; `what` names the set.
void check_points(const ClassifiedPoints& set, const char* what);

}  // namespace terracube::detail
