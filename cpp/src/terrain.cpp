#include "terracube/terrain.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

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

/// Running minimum of a line of `n` values (`stride` apart) over windows [k - r, k + r] clipped to
/// the line, in O(1) per value whatever r (van Herk 1992; Gil and Werman 1993): cut the line,
/// padded with r infinities each side, into blocks of w = 2r + 1; a window then spans the tail of
/// one block and the head of the next, so its minimum is min(suffix minimum at its first value,
/// prefix minimum at its last). `prefix` and `suffix` hold n + 2r values each.
void running_min(const float* in, float* out, Eigen::Index n, Eigen::Index stride, Eigen::Index r,
                 std::vector<float>& prefix, std::vector<float>& suffix) {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  const Eigen::Index padded = n + 2 * r;
  const Eigen::Index w = 2 * r + 1;
  const auto value = [&](Eigen::Index k) { return k < r || k >= r + n ? kInf : in[(k - r) * stride]; };
  for (Eigen::Index k = 0; k < padded; ++k) {
    prefix[k] = k % w == 0 ? value(k) : std::min(prefix[k - 1], value(k));
  }
  for (Eigen::Index k = padded - 1; k >= 0; --k) {
    suffix[k] = k % w == w - 1 || k == padded - 1 ? value(k) : std::min(suffix[k + 1], value(k));
  }
  for (Eigen::Index j = 0; j < n; ++j) out[j * stride] = std::min(suffix[j], prefix[j + w - 1]);
}

/// Lowest value within `radius` cells (a square window), ignoring NaN; NaN where the window holds
/// no value. Separable: running minima along j, then along i, each O(1) per cell.
Layer window_min(const Layer& layer, int radius) {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  const Eigen::Index nx = layer.rows();
  const Eigen::Index ny = layer.cols();
  // A radius of max(nx, ny) already spans the whole map: larger ones change nothing.
  const Eigen::Index r = std::min<Eigen::Index>(radius, std::max(nx, ny));
  Layer values = layer.array().isNaN().select(kInf, layer.array()).matrix();
  Layer along_y(nx, ny);
  std::vector<float> prefix(static_cast<std::size_t>(std::max(nx, ny) + 2 * r));
  std::vector<float> suffix(prefix.size());
  for (Eigen::Index i = 0; i < nx; ++i)
    running_min(values.data() + i * ny, along_y.data() + i * ny, ny, 1, r, prefix, suffix);
  Layer out(nx, ny);
  for (Eigen::Index j = 0; j < ny; ++j) running_min(along_y.data() + j, out.data() + j, nx, ny, r, prefix, suffix);
  for (Eigen::Index k = 0; k < out.size(); ++k) {
    if (out.data()[k] == kInf) out.data()[k] = std::numeric_limits<float>::quiet_NaN();
  }
  return out;
}

/// The smallest float that is >= `threshold`: for every float v, v < threshold (compared in
/// double) exactly when v < this float, and v >= threshold exactly when v >= it.
float smallest_float_at_least(double threshold) {
  float rounded = static_cast<float>(threshold);
  if (static_cast<double>(rounded) < threshold)
    rounded = std::nextafter(rounded, std::numeric_limits<float>::infinity());
  return rounded;
}

}  // namespace

TerrainClasses classify_terrain_layers(ElevationMap& map, const TerrainParams& params) {
  check_terrain_params(params);
  map.get("max");  // throws std::out_of_range naming a missing input layer before any is added
  map.get("std_dev");
  map.get("discontinuity");
  if (params.reference == GroundReference::kLocalGround) map.get("min");
  // Results go straight into the map's layers (reused in place when the map was classified
  // before: fresh 320 kB buffers per call cost page faults). Adding layers can move them, so every
  // reference is taken after the last add.
  for (const char* name : {"class", "relative_height", "ground"}) {
    if (!map.exists(name)) map.add(name);
  }
  const Layer& highest = map.get("max");
  const Layer& spread = map.get("std_dev");
  const Layer& gap = map.get("discontinuity");
  Layer& class_layer = map.get("class");
  Layer& relative_height = map.get("relative_height");
  Layer& ground = map.get("ground");
  const Eigen::Index nx = highest.rows();
  const Eigen::Index ny = highest.cols();
  const Eigen::Index cells = highest.size();

  if (params.reference == GroundReference::kSensorHeight) {
    ground.setConstant(static_cast<float>(-params.sensor_height_m));
  } else {
    ground = window_min(map.get("min"), params.local_ground_radius_cells);
  }
  relative_height = highest - ground;  // NaN stays NaN
  TerrainClasses out(nx, ny);

  // Table 1. The thresholds are doubles (a 0.7 m threshold means 0.7, not float(0.7) =
  // 0.69999999); for a float v, v < t exactly when v < the smallest float >= t, so the per-cell
  // tests run on floats, branch-free, and vectorise.
  const float low = smallest_float_at_least(params.ground_height_m);
  const float high = smallest_float_at_least(params.robot_height_m);
  const float small = smallest_float_at_least(params.std_dev_m);
  const float* height = relative_height.data();
  const float* deviation = spread.data();
  const float* flag = gap.data();
  std::uint8_t* classes = out.data();
  // kObject marks obstacle, overhanging and vertical cells for the edge pass below.
  constexpr std::uint8_t kUnknown = static_cast<std::uint8_t>(TerrainClass::kUnknown);
  constexpr std::uint8_t kGround = static_cast<std::uint8_t>(TerrainClass::kGround);
  constexpr std::uint8_t kObstacle = static_cast<std::uint8_t>(TerrainClass::kObstacle);
  constexpr std::uint8_t kOverhanging = static_cast<std::uint8_t>(TerrainClass::kOverhangingObject);
  constexpr std::uint8_t kVertical = static_cast<std::uint8_t>(TerrainClass::kVerticalObject);
  constexpr std::uint8_t kEdge = static_cast<std::uint8_t>(TerrainClass::kHorizontalEdge);
  // Quiet comparisons (std::isless...) leave no branches, so the loop vectorises; a NaN height
  // (no data) gives unknown whatever the other layers hold.
  for (Eigen::Index k = 0; k < cells; ++k) {
    const float h = height[k];
    const int small_spread = std::isless(deviation[k], small);
    const int ground = std::isless(h, low) & small_spread;  // low and smooth
    const int vertical = std::isgreaterequal(h, high) & (1 - small_spread);
    const int overhanging = flag[k] == 1.0F;
    const int c = overhanging ? kOverhanging : kObstacle - ground + (kVertical - kObstacle) * vertical;
    classes[k] = static_cast<std::uint8_t>(std::isunordered(h, h) ? kUnknown : c);
  }

  // Horizontal edges: ground cells with an obstacle, overhanging or vertical cell among their 8
  // neighbours. A 3 x 3 dilation of the object mask, separable: each row's mask is first widened
  // along j (three rolling rows), then rows i - 1, i and i + 1 are combined. Ground that becomes
  // an edge is no object, so the order of cells does not matter.
  if (cells > 0) {
    std::vector<std::uint8_t> objects(static_cast<std::size_t>(ny));
    std::vector<std::uint8_t> widened(static_cast<std::size_t>(3 * ny));
    const auto widen = [&](Eigen::Index i) {  // row i's objects (2, 3, 4) widened along j
      const std::uint8_t* in = classes + i * ny;
      std::uint8_t* object = objects.data();
      std::uint8_t* row = widened.data() + (i % 3) * ny;
      for (Eigen::Index j = 0; j < ny; ++j) object[j] = in[j] >= kObstacle ? 1 : 0;
      row[0] = object[0] | (ny > 1 ? object[1] : 0);
      for (Eigen::Index j = 1; j + 1 < ny; ++j) row[j] = object[j - 1] | object[j] | object[j + 1];
      if (ny > 1) row[ny - 1] = object[ny - 2] | object[ny - 1];
    };
    widen(0);
    for (Eigen::Index i = 0; i < nx; ++i) {
      if (i + 1 < nx) widen(i + 1);  // the ring buffer holds rows i - 1, i and i + 1
      const std::uint8_t* above = widened.data() + (std::max<Eigen::Index>(i - 1, 0) % 3) * ny;
      const std::uint8_t* here = widened.data() + (i % 3) * ny;
      const std::uint8_t* below = widened.data() + (std::min(i + 1, nx - 1) % 3) * ny;
      std::uint8_t* row = classes + i * ny;
      for (Eigen::Index j = 0; j < ny; ++j) {
        const bool near = (above[j] | here[j] | below[j]) != 0;
        row[j] = row[j] == kGround && near ? kEdge : row[j];
      }
    }
  }

  // The class as a float, NaN for unknown: the bits of float(c), or a quiet NaN's for c = 0.
  for (Eigen::Index k = 0; k < cells; ++k) {
    const float value = static_cast<float>(classes[k]);
    std::uint32_t bits = 0;
    std::memcpy(&bits, &value, sizeof bits);
    bits |= classes[k] == kUnknown ? 0x7fc00000U : 0U;
    std::memcpy(class_layer.data() + k, &bits, sizeof bits);
  }
  return out;
}

TerrainClassification classify_terrain(ElevationMap& map, const TerrainParams& params) {
  TerrainClassification out;
  out.classes = classify_terrain_layers(map, params);
  out.relative_height = map.get("relative_height");
  out.ground = map.get("ground");
  return out;
}

}  // namespace terracube
