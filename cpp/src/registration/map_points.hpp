// The cells of a classified map as registration points (points_of_map and register_maps).
#pragma once

#include <cstddef>

#include "terracube/elevation_map.hpp"
#include "terracube/icp.hpp"

namespace terracube::detail {

/// The cells of points_of_map, only those of classes with a positive weight when `weights` is
/// given; `cells_with_data` receives the number of all cells with data.
ClassifiedPoints cells_of_map(const ElevationMap& map, const ClassWeights* weights, std::size_t& cells_with_data);

}  // namespace terracube::detail
