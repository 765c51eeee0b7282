#include "terracube/terrain.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <vector>

#include "parallel.hpp"

namespace terracube {

namespace {

constexpr std::uint8_t kUnknown = static_cast<std::uint8_t>(TerrainClass::kUnknown);
constexpr std::uint8_t kGround = static_cast<std::uint8_t>(TerrainClass::kGround);
constexpr std::uint8_t kObstacle = static_cast<std::uint8_t>(TerrainClass::kObstacle);
constexpr std::uint8_t kOverhanging = static_cast<std::uint8_t>(TerrainClass::kOverhangingObject);
constexpr std::uint8_t kVertical = static_cast<std::uint8_t>(TerrainClass::kVerticalObject);
constexpr std::uint8_t kEdge = static_cast<std::uint8_t>(TerrainClass::kHorizontalEdge);

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
  detail::check_num_threads(params.num_threads, "TerrainParams");
}

/// Running minimum of a line of `n` values (`stride` apart) over windows [k - r, k + r] clipped to
/// the line, in O(1) per value whatever r (van Herk 1992; Gil and Werman 1993): cut the line,
/// padded with r infinities each side, into blocks of w = 2r + 1; a window then spans the tail of
/// one block and the head of the next, so its minimum is min(suffix minimum at its first value,
/// prefix minimum at its last).
void running_min(const float* in, float* out, Eigen::Index n, Eigen::Index stride, Eigen::Index r) {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  const Eigen::Index padded = n + 2 * r;
  const Eigen::Index w = 2 * r + 1;
  std::vector<float> prefix(static_cast<std::size_t>(padded));
  std::vector<float> suffix(static_cast<std::size_t>(padded));
  const auto value = [&](Eigen::Index k) { return k < r || k >= r + n ? kInf : in[(k - r) * stride]; };
  for (Eigen::Index k = 0; k < padded; ++k) {
    prefix[k] = k % w == 0 ? value(k) : std::min(prefix[k - 1], value(k));
  }
  for (Eigen::Index k = padded - 1; k >= 0; --k) {
    suffix[k] = k % w == w - 1 || k == padded - 1 ? value(k) : std::min(suffix[k + 1], value(k));
  }
  for (Eigen::Index j = 0; j < n; ++j) out[j * stride] = std::min(suffix[j], prefix[j + w - 1]);
}

/// The lowest value of `layer` within `radius` cells (a square window), ignoring NaN, into `out`;
/// NaN where the window holds no value. Separable: running minima along j, then along i.
void window_min(const Layer& layer, int radius, Layer& out) {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  const Eigen::Index nx = layer.rows();
  const Eigen::Index ny = layer.cols();
  // A radius of max(nx, ny) already spans the whole map: larger ones change nothing.
  const Eigen::Index r = std::min<Eigen::Index>(radius, std::max(nx, ny));
  const Layer values = layer.array().isNaN().select(kInf, layer.array());
  Layer along_y(nx, ny);
  for (Eigen::Index i = 0; i < nx; ++i) running_min(values.data() + i * ny, along_y.data() + i * ny, ny, 1, r);
  for (Eigen::Index j = 0; j < ny; ++j) running_min(along_y.data() + j, out.data() + j, nx, ny, r);
  out = (out.array() == kInf).select(std::numeric_limits<float>::quiet_NaN(), out.array());
}

/// [TC] Table 1 for one cell with data. `height` is the highest elevation above the ground
/// reference, compared in double with the thresholds as the paper states them.
///   - A discontinuity makes an overhanging object whatever else holds ([TC] section 3.2, class 3:
///     "a grid that has a discontinuity").
///   - A large spread is the table's "Large" row, whose two entries span all three height columns:
///     a vertical object without a discontinuity (the one with one was handled above).
///   - A small spread reads the height columns: low (< ground_height_m) is ground, high (strictly
///     higher than robot_height_m, class 3 "higher than the height of the robot") an overhanging
///     object, and middle (in between, both ends included) an obstacle.
std::uint8_t table_1_class(float height, float std_dev, bool discontinuity, const TerrainParams& params) {
  if (discontinuity) return kOverhanging;
  const bool small_spread = static_cast<double>(std_dev) < params.std_dev_m;
  if (!small_spread) return kVertical;
  const double h = height;
  if (h < params.ground_height_m) return kGround;
  if (h > params.robot_height_m) return kOverhanging;
  return kObstacle;
}

/// [TC] section 3.2, class 5: a ground cell with an obstacle, overhanging or vertical cell among
/// its 8 neighbours (inside the map) is a horizontal edge. `table` is nx x ny, row-major.
bool beside_an_object(const std::uint8_t* table, Eigen::Index nx, Eigen::Index ny, Eigen::Index i, Eigen::Index j) {
  const Eigen::Index i0 = std::max<Eigen::Index>(i - 1, 0), i1 = std::min(i + 1, nx - 1);
  const Eigen::Index j0 = std::max<Eigen::Index>(j - 1, 0), j1 = std::min(j + 1, ny - 1);
  for (Eigen::Index a = i0; a <= i1; ++a) {
    for (Eigen::Index b = j0; b <= j1; ++b) {
      const std::uint8_t c = table[a * ny + b];
      if (c == kObstacle || c == kOverhanging || c == kVertical) return true;
    }
  }
  return false;
}

/// Runs rows(begin, end) over [0, nx) in parts of about 32k cells (fixed by the map, not by the
/// thread count, so the result is the same on any number of threads).
template <typename Rows>
void for_row_blocks(Eigen::Index nx, Eigen::Index ny, int num_threads, const Rows& rows) {
  constexpr std::size_t kCellsPerPart = std::size_t{1} << 15;
  const auto cells = static_cast<std::size_t>(nx * ny);
  const int parts = detail::fixed_parts(cells, kCellsPerPart);
  detail::for_each_part(num_threads, parts, [&](int part) { rows(nx * part / parts, nx * (part + 1) / parts); });
}

}  // namespace

TerrainClasses classify_terrain_layers(ElevationMap& map, const TerrainParams& params) {
  check_terrain_params(params);
  map.get("max");  // throws std::out_of_range naming a missing input layer before any is added
  map.get("std_dev");
  map.get("discontinuity");
  if (params.reference == GroundReference::kLocalGround) map.get("min");
  const float kNaN = std::numeric_limits<float>::quiet_NaN();
  for (const char* name : {"class", "relative_height", "ground"}) {
    if (!map.exists(name)) map.add(name, kNaN);  // adding may move layers: references come after
  }
  const Layer& highest = map.get("max");
  const Layer& spread = map.get("std_dev");
  const Layer& gap = map.get("discontinuity");
  Layer& ground = map.get("ground");
  Layer& relative_height = map.get("relative_height");
  Layer& class_layer = map.get("class");
  const Eigen::Index nx = highest.rows();
  const Eigen::Index ny = highest.cols();
  if (params.reference == GroundReference::kLocalGround) {
    window_min(map.get("min"), params.local_ground_radius_cells, ground);
  } else {
    ground.setConstant(static_cast<float>(-params.sensor_height_m));
  }
  relative_height = highest - ground;  // NaN (no data) stays NaN

  // The loops read and write through plain local pointers: a byte store may alias anything, so
  // through the layers (and params) the compiler would reload their addresses on every cell.
  TerrainClasses table(nx, ny);  // [TC] Table 1, before the edge test
  for_row_blocks(nx, ny, params.num_threads, [&](Eigen::Index begin, Eigen::Index end) {
    const float* const h = relative_height.data();
    const float* const s = spread.data();
    const float* const d = gap.data();
    std::uint8_t* const t = table.data();
    const TerrainParams thresholds = params;
    for (Eigen::Index k = begin * ny; k < end * ny; ++k) {
      t[k] = std::isnan(h[k]) ? kUnknown : table_1_class(h[k], s[k], d[k] == 1.0F, thresholds);
    }
  });
  TerrainClasses out(nx, ny);
  for_row_blocks(nx, ny, params.num_threads, [&](Eigen::Index begin, Eigen::Index end) {
    const std::uint8_t* const t = table.data();
    std::uint8_t* const o = out.data();
    float* const c = class_layer.data();
    for (Eigen::Index i = begin; i < end; ++i) {
      for (Eigen::Index j = 0; j < ny; ++j) {
        const Eigen::Index k = i * ny + j;
        o[k] = t[k] == kGround && beside_an_object(t, nx, ny, i, j) ? kEdge : t[k];
        c[k] = o[k] == kUnknown ? kNaN : static_cast<float>(o[k]);
      }
    }
  });
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
