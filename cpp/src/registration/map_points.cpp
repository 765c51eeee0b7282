// The cells of a classified map as registration points.
#include "map_points.hpp"

#include <cmath>
#include <cstdint>
#include <vector>

namespace terracube {

namespace {

/// The class of a "class" value: NaN or out of range is unknown (0).
std::uint8_t class_of(float value) {
  return value >= 0.0F && value < static_cast<float>(kNumTerrainClasses) ? static_cast<std::uint8_t>(value) : 0;
}

}  // namespace

namespace detail {

/// The cells of points_of_map, only those of classes with a positive weight when `weights` is
/// given; `cells_with_data` receives the number of all cells with data.
ClassifiedPoints cells_of_map(const ElevationMap& map, const ClassWeights* weights, std::size_t& cells_with_data) {
  const Layer& highest = map.get("max");
  const Layer* classes = map.exists("class") ? &map.get("class") : nullptr;
  const MapGeometry& geometry = map.geometry();
  // Row-major: cell (i, j) at i * cols + j.
  const float* z = highest.data();
  const float* class_values = classes != nullptr ? classes->data() : nullptr;
  const auto cells = static_cast<std::size_t>(highest.size());
  const auto cols = static_cast<std::size_t>(highest.cols());
  std::vector<std::uint8_t> class_of_cell(cells, 0);  // kNumTerrainClasses: takes no part
  std::size_t count = 0;
  cells_with_data = 0;
  for (std::size_t k = 0; k < cells; ++k) {
    const std::uint8_t c = class_values != nullptr ? class_of(class_values[k]) : 0;
    const bool has_data = std::isfinite(z[k]);
    const bool takes_part = has_data && (weights == nullptr || (*weights)[c] > 0.0);
    class_of_cell[k] = takes_part ? c : static_cast<std::uint8_t>(kNumTerrainClasses);
    cells_with_data += has_data ? 1 : 0;
    count += takes_part ? 1 : 0;
  }
  ClassifiedPoints set;
  set.points.reserve(count);
  set.classes.reserve(count);
  for (std::size_t k = 0; k < cells; ++k) {
    if (class_of_cell[k] == kNumTerrainClasses) continue;
    const Eigen::Vector2d centre =
        geometry.position_of(CellIndex(static_cast<int>(k / cols), static_cast<int>(k % cols)));
    set.points.emplace_back(centre.x(), centre.y(), static_cast<double>(z[k]));
    set.classes.push_back(class_of_cell[k]);
  }
  return set;
}

}  // namespace detail

ClassifiedPoints points_of_map(const ElevationMap& map) {
  std::size_t cells_with_data = 0;
  return detail::cells_of_map(map, nullptr, cells_with_data);
}

}  // namespace terracube
