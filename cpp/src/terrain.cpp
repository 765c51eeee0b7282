#include "terracube/terrain.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace terracube {

namespace {

void check_terrain_params(const TerrainParams& params) {
  const auto positive = [](double v) { return v > 0.0 && std::isfinite(v); };
  if (!positive(params.ground_height_m) || !positive(params.std_dev_m) || !positive(params.robot_height_m)) {
    throw std::invalid_argument("ground height, std-dev and robot height thresholds must be positive and finite");
  }
  if (params.robot_height_m < params.ground_height_m) {
    throw std::invalid_argument("robot height must not be below the ground-height threshold");
  }
  if (!std::isfinite(params.sensor_height_m)) throw std::invalid_argument("sensor height must be finite");
  if (params.local_ground_radius_cells < 0) throw std::invalid_argument("local ground radius must be >= 0 cells");
}

/// Lowest value within `radius` cells (a square window), ignoring NaN: a separable min filter.
Layer window_min(const Layer& layer, int radius) {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  const Eigen::Index nx = layer.rows();
  const Eigen::Index ny = layer.cols();
  Layer along_y(nx, ny);
  for (Eigen::Index i = 0; i < nx; ++i) {
    for (Eigen::Index j = 0; j < ny; ++j) {
      float lowest = kInf;
      for (Eigen::Index b = std::max<Eigen::Index>(0, j - radius); b <= std::min(ny - 1, j + radius); ++b) {
        const float v = layer(i, b);
        if (!std::isnan(v)) lowest = std::min(lowest, v);
      }
      along_y(i, j) = lowest;
    }
  }
  Layer out(nx, ny);
  for (Eigen::Index i = 0; i < nx; ++i) {
    for (Eigen::Index j = 0; j < ny; ++j) {
      float lowest = kInf;
      for (Eigen::Index a = std::max<Eigen::Index>(0, i - radius); a <= std::min(nx - 1, i + radius); ++a) {
        lowest = std::min(lowest, along_y(a, j));
      }
      out(i, j) = lowest == kInf ? std::numeric_limits<float>::quiet_NaN() : lowest;
    }
  }
  return out;
}

}  // namespace

TerrainClassification classify_terrain(ElevationMap& map, const TerrainParams& params) {
  check_terrain_params(params);
  const Layer& highest = map.get("max");
  const Layer& spread = map.get("std_dev");
  const Layer& gap = map.get("discontinuity");
  const Eigen::Index nx = highest.rows();
  const Eigen::Index ny = highest.cols();

  TerrainClassification out;
  if (params.reference == GroundReference::kSensorHeight) {
    out.ground = Layer::Constant(nx, ny, static_cast<float>(-params.sensor_height_m));
  } else {
    out.ground = window_min(map.get("min"), params.local_ground_radius_cells);
  }
  out.relative_height = highest - out.ground;  // NaN stays NaN
  out.classes.setConstant(nx, ny, static_cast<std::uint8_t>(TerrainClass::kUnknown));

  // Thresholds compare in double, so a 0.7 m threshold means 0.7, not float(0.7) = 0.69999999.
  const double low = params.ground_height_m;
  const double high = params.robot_height_m;
  const double small = params.std_dev_m;
  for (Eigen::Index k = 0; k < highest.size(); ++k) {
    const double h = out.relative_height.data()[k];
    if (std::isnan(h)) continue;
    const bool small_spread = static_cast<double>(spread.data()[k]) < small;
    TerrainClass c;
    if (gap.data()[k] == 1.0F) {
      c = TerrainClass::kOverhangingObject;
    } else if (h < low) {
      c = small_spread ? TerrainClass::kGround : TerrainClass::kObstacle;
    } else if (h < high) {
      c = TerrainClass::kObstacle;
    } else {
      c = small_spread ? TerrainClass::kObstacle : TerrainClass::kVerticalObject;
    }
    out.classes.data()[k] = static_cast<std::uint8_t>(c);
  }

  // Horizontal edges: ground cells beside obstacle, overhanging or vertical cells.
  const auto is_object = [](std::uint8_t c) {
    return c == static_cast<std::uint8_t>(TerrainClass::kObstacle) ||
           c == static_cast<std::uint8_t>(TerrainClass::kOverhangingObject) ||
           c == static_cast<std::uint8_t>(TerrainClass::kVerticalObject);
  };
  // In place: a ground cell that becomes an edge is not an object, so it changes no other cell's test.
  for (Eigen::Index i = 0; i < nx; ++i) {
    for (Eigen::Index j = 0; j < ny; ++j) {
      if (out.classes(i, j) != static_cast<std::uint8_t>(TerrainClass::kGround)) continue;
      bool beside = false;
      for (Eigen::Index a = std::max<Eigen::Index>(0, i - 1); a <= std::min(nx - 1, i + 1) && !beside; ++a) {
        for (Eigen::Index b = std::max<Eigen::Index>(0, j - 1); b <= std::min(ny - 1, j + 1) && !beside; ++b) {
          beside = is_object(out.classes(a, b));
        }
      }
      if (beside) out.classes(i, j) = static_cast<std::uint8_t>(TerrainClass::kHorizontalEdge);
    }
  }
  Layer class_layer = out.classes.cast<float>();
  for (Eigen::Index k = 0; k < class_layer.size(); ++k) {
    if (out.classes.data()[k] == 0) class_layer.data()[k] = std::numeric_limits<float>::quiet_NaN();
  }
  map.add("class", std::move(class_layer));
  map.add("relative_height", out.relative_height);
  map.add("ground", out.ground);
  return out;
}

}  // namespace terracube
