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

}  // namespace

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

namespace {

/// Running minimum of a line of `n` values (`stride` apart) over windows [k - r, k + r] clipped to
/// the line, in O(1) per value whatever r (van Herk 1992; Gil and Werman 1993): cut the line,
/// padded with r infinities each side, into blocks of w = 2r + 1; a window then spans the tail of
/// one block and the head of the next, so its minimum is min(suffix minimum at its first value,
/// prefix minimum at its last). `line`, `prefix` and `suffix` are scratch of n + 2r values.
void running_min(const float* in, float* out, Eigen::Index n, Eigen::Index stride, Eigen::Index r,
                 std::vector<float>& line, std::vector<float>& prefix, std::vector<float>& suffix) {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  const Eigen::Index padded = n + 2 * r;
  const Eigen::Index w = 2 * r + 1;
  line.assign(static_cast<std::size_t>(padded), kInf);
  prefix.resize(static_cast<std::size_t>(padded));
  suffix.resize(static_cast<std::size_t>(padded));
  for (Eigen::Index k = 0; k < n; ++k) line[r + k] = in[k * stride];
  for (Eigen::Index first = 0; first < padded; first += w) {
    const Eigen::Index last = std::min(first + w, padded) - 1;
    prefix[first] = line[first];
    for (Eigen::Index k = first + 1; k <= last; ++k) prefix[k] = std::min(prefix[k - 1], line[k]);
    suffix[last] = line[last];
    for (Eigen::Index k = last - 1; k >= first; --k) suffix[k] = std::min(suffix[k + 1], line[k]);
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
  std::vector<float> line, prefix, suffix;
  for (Eigen::Index i = 0; i < nx; ++i) {
    running_min(values.data() + i * ny, along_y.data() + i * ny, ny, 1, r, line, prefix, suffix);
  }
  for (Eigen::Index j = 0; j < ny; ++j) {
    running_min(along_y.data() + j, out.data() + j, nx, ny, r, line, prefix, suffix);
  }
  out = (out.array() == kInf).select(std::numeric_limits<float>::quiet_NaN(), out.array());
}

/// Thresholds of [TC] Table 1 in float: for a float x and a double t, x < t exactly when x <
/// above(t), the least float >= t, and x > t exactly when x > below(t), the greatest float <= t.
/// So the float comparisons of the cells give what comparing them in double with the thresholds as
/// the paper states them gives, and a cell's class is a few selects (no branches to mispredict).
/// (The thresholds are positive and finite: check_terrain_params.)
float above(double t) {
  constexpr float kMax = std::numeric_limits<float>::max();
  if (t > kMax) return std::numeric_limits<float>::infinity();
  const auto f = static_cast<float>(t);
  return static_cast<double>(f) < t ? std::nextafter(f, std::numeric_limits<float>::infinity()) : f;
}
float below(double t) {
  constexpr float kMax = std::numeric_limits<float>::max();
  if (t > kMax) return kMax;
  const auto f = static_cast<float>(t);
  return static_cast<double>(f) > t ? std::nextafter(f, -std::numeric_limits<float>::infinity()) : f;
}
struct Table1 {
  float ground_height, robot_height, std_dev;  // above(ground), below(robot), above(std-dev)

  explicit Table1(const TerrainParams& p)
      : ground_height(above(p.ground_height_m)), robot_height(below(p.robot_height_m)), std_dev(above(p.std_dev_m)) {}

  /// [TC] Table 1 for one cell; `height` is the highest elevation above the ground reference, NaN
  /// without data (unknown).
  ///   - A discontinuity makes an overhanging object whatever else holds ([TC] section 3.2, class
  ///     3: "a grid that has a discontinuity").
  ///   - A large spread is the table's "Large" row, whose two entries span all three height
  ///     columns: a vertical object without a discontinuity (the one with one was handled above).
  ///   - A small spread reads the height columns: low (< ground_height_m) is ground, high
  ///     (strictly higher than robot_height_m, class 3 "higher than the height of the robot") an
  ///     overhanging object, and middle (in between, both ends included) an obstacle.
  std::uint8_t operator()(float height, float std_dev_m, bool discontinuity) const {
    const std::uint8_t by_height =
        height < ground_height ? kGround : (height > robot_height ? kOverhanging : kObstacle);
    const std::uint8_t by_spread = std_dev_m < std_dev ? by_height : kVertical;
    const std::uint8_t known = discontinuity ? kOverhanging : by_spread;
    return std::isnan(height) ? kUnknown : known;
  }
};

/// [TC] section 3.2, class 5: a ground cell with an obstacle, overhanging or vertical cell among
/// its 8 neighbours (inside the map) is a horizontal edge. `table` is nx x ny, row-major; rows
/// [begin, end) of `out` get the classes, of `class_layer` the same as floats (NaN for unknown).
/// An object's 3 x 3 neighbourhood is found separably: per row, whether the row or the rows above
/// and below hold an object in the column (`near`), then whether that holds in the column or the
/// columns beside it.
void mark_edges(const std::uint8_t* table, Eigen::Index nx, Eigen::Index ny, Eigen::Index begin, Eigen::Index end,
                std::uint8_t* out, float* class_layer) {
  const auto object = [](std::uint8_t c) -> std::uint8_t {
    return static_cast<std::uint8_t>((c == kObstacle) | (c == kOverhanging) | (c == kVertical));
  };
  // The "class" layer's value of each class: NaN for unknown.
  constexpr float kValue[] = {std::numeric_limits<float>::quiet_NaN(), 1.0F, 2.0F, 3.0F, 4.0F, 5.0F};
  std::vector<std::uint8_t> near(static_cast<std::size_t>(ny) + 2, 0);  // padded by a column each side
  for (Eigen::Index i = begin; i < end; ++i) {
    const std::uint8_t* row = table + i * ny;
    const std::uint8_t* up = i > 0 ? row - ny : row;
    const std::uint8_t* down = i + 1 < nx ? row + ny : row;
    for (Eigen::Index j = 0; j < ny; ++j) near[j + 1] = object(up[j]) | object(row[j]) | object(down[j]);
    for (Eigen::Index j = 0; j < ny; ++j) {
      const bool edge = (row[j] == kGround) & ((near[j] | near[j + 1] | near[j + 2]) != 0);
      out[i * ny + j] = edge ? kEdge : row[j];
    }
    for (Eigen::Index j = 0; j < ny; ++j) class_layer[i * ny + j] = kValue[out[i * ny + j]];
  }
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
  const Table1 table_1(params);
  for_row_blocks(nx, ny, params.num_threads, [&](Eigen::Index begin, Eigen::Index end) {
    const float* const h = relative_height.data();
    const float* const s = spread.data();
    const float* const d = gap.data();
    std::uint8_t* const t = table.data();
    const Table1 rule = table_1;
    const Eigen::Index first = begin * ny, count = (end - begin) * ny;  // a trip count the vectorizer sees
    for (Eigen::Index k = 0; k < count; ++k) t[first + k] = rule(h[first + k], s[first + k], d[first + k] == 1.0F);
  });
  TerrainClasses out(nx, ny);
  for_row_blocks(nx, ny, params.num_threads, [&](Eigen::Index begin, Eigen::Index end) {
    mark_edges(table.data(), nx, ny, begin, end, out.data(), class_layer.data());
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
