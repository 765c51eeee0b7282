#include "terracube/terrain.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "parallel.hpp"

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
  detail::check_num_threads(params.num_threads, "TerrainParams");
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

/// Lowest value within `radius` cells (a square window) of `layer`, ignoring NaN, into every cell of
/// `out` (not `layer`); NaN where the window holds no value. Separable: running minima along j,
/// then along i, each O(1) per cell. The two intermediate layers come from (and go back to) the
/// thread's kept layer buffers: fresh 320 kB buffers would cost page faults at every call.
void window_min(const Layer& layer, int radius, Layer& out) {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  const Eigen::Index nx = layer.rows();
  const Eigen::Index ny = layer.cols();
  // A radius of max(nx, ny) already spans the whole map: larger ones change nothing.
  const Eigen::Index r = std::min<Eigen::Index>(radius, std::max(nx, ny));
  Layer values = Layer(nx, ny);
  Layer along_y = Layer(nx, ny);
  values.array() = layer.array().isNaN().select(kInf, layer.array());
  std::vector<float> prefix(static_cast<std::size_t>(std::max(nx, ny) + 2 * r));
  std::vector<float> suffix(prefix.size());
  for (Eigen::Index i = 0; i < nx; ++i)
    running_min(values.data() + i * ny, along_y.data() + i * ny, ny, 1, r, prefix, suffix);
  for (Eigen::Index j = 0; j < ny; ++j) running_min(along_y.data() + j, out.data() + j, nx, ny, r, prefix, suffix);
  for (Eigen::Index k = 0; k < out.size(); ++k) {
    if (out.data()[k] == kInf) out.data()[k] = std::numeric_limits<float>::quiet_NaN();
  }
}

/// The smallest float that is >= `threshold`: for every float v, v < threshold (compared in
/// double) exactly when v < this float, and v >= threshold exactly when v >= it.
float smallest_float_at_least(double threshold) {
  float rounded = static_cast<float>(threshold);
  if (static_cast<double>(rounded) < threshold)
    rounded = std::nextafter(rounded, std::numeric_limits<float>::infinity());
  return rounded;
}

constexpr std::uint8_t kUnknown = static_cast<std::uint8_t>(TerrainClass::kUnknown);
constexpr std::uint8_t kGround = static_cast<std::uint8_t>(TerrainClass::kGround);
constexpr std::uint8_t kObstacle = static_cast<std::uint8_t>(TerrainClass::kObstacle);
constexpr std::uint8_t kOverhanging = static_cast<std::uint8_t>(TerrainClass::kOverhangingObject);
constexpr std::uint8_t kVertical = static_cast<std::uint8_t>(TerrainClass::kVerticalObject);
constexpr std::uint8_t kEdge = static_cast<std::uint8_t>(TerrainClass::kHorizontalEdge);

/// What Table 1 reads and writes, per cell (see classify_terrain_layers).
struct Table1 {
  const float* top;        ///< "max"
  const float* deviation;  ///< "std_dev"
  const float* flag;       ///< "discontinuity"
  const float* reference;  ///< "ground"
  float* height;           ///< "relative_height"
  std::uint8_t* classes;   ///< before the edge test
  float low, high, small;  ///< the thresholds as floats (smallest_float_at_least)
};

/// Table 1 for the cells [begin, end). Quiet comparisons (std::isless...) leave no branches, so the
/// loop vectorises; a NaN height (no data) gives unknown whatever the other layers hold. The
/// pointers are copied to __restrict locals: a byte store may alias them otherwise, which would
/// keep the loop from vectorising. Inlined into table_1 and table_1_avx2 (the same operations, so
/// the same results, in SSE2 or AVX2 registers).
__attribute__((always_inline)) inline void table_1_cells(const Table1& t, Eigen::Index begin, Eigen::Index end) {
  const float low_height = t.low, high_height = t.high, small_spread_below = t.small;
  const float* __restrict in_top = t.top;
  const float* __restrict in_deviation = t.deviation;
  const float* __restrict in_flag = t.flag;
  const float* __restrict in_reference = t.reference;
  float* __restrict out_height = t.height;
  std::uint8_t* __restrict out_class = t.classes;
  for (Eigen::Index k = begin; k < end; ++k) {
    const float h = in_top[k] - in_reference[k];
    out_height[k] = h;
    const int small_spread = std::isless(in_deviation[k], small_spread_below);
    const int ground_cell = std::isless(h, low_height) & small_spread;  // low and smooth
    const int vertical = std::isgreaterequal(h, high_height) & (1 - small_spread);
    const int overhanging = in_flag[k] == 1.0F;
    const int c = overhanging ? kOverhanging : kObstacle - ground_cell + (kVertical - kObstacle) * vertical;
    out_class[k] = static_cast<std::uint8_t>(std::isunordered(h, h) ? kUnknown : c);
  }
}

void table_1(const Table1& t, Eigen::Index begin, Eigen::Index end) { table_1_cells(t, begin, end); }

/// A row of the edge test (classify_terrain_layers' pass 2): `in` (the row's classes before it)
/// with ground cells next to an object (`above`, `here` or `below` non-zero: the widened object
/// masks of rows i - 1, i, i + 1) made edges, into `row`, and as floats into `values` (the bits of
/// float(c), a quiet NaN's for unknown).
__attribute__((always_inline)) inline void edge_row_cells(
    const std::uint8_t* __restrict above, const std::uint8_t* __restrict here, const std::uint8_t* __restrict below,
    const std::uint8_t* __restrict in, std::uint8_t* __restrict row, float* __restrict values, Eigen::Index n) {
  for (Eigen::Index j = 0; j < n; ++j) {
    const bool near = (above[j] | here[j] | below[j]) != 0;
    row[j] = in[j] == kGround && near ? kEdge : in[j];
  }
  for (Eigen::Index j = 0; j < n; ++j) {
    const float value = static_cast<float>(row[j]);
    std::uint32_t bits = 0;
    std::memcpy(&bits, &value, sizeof bits);
    bits |= row[j] == kUnknown ? 0x7fc00000U : 0U;
    std::memcpy(values + j, &bits, sizeof bits);
  }
}

/// Row i's objects (classes >= obstacle) widened along j into `row` (a 1 x 3 dilation); `object`
/// is scratch of n bytes.
__attribute__((always_inline)) inline void widen_cells(const std::uint8_t* __restrict in,
                                                       std::uint8_t* __restrict object, std::uint8_t* __restrict row,
                                                       Eigen::Index n) {
  for (Eigen::Index j = 0; j < n; ++j) object[j] = in[j] >= kObstacle ? 1 : 0;
  row[0] = object[0] | (n > 1 ? object[1] : 0);
  for (Eigen::Index j = 1; j + 1 < n; ++j) row[j] = object[j - 1] | object[j] | object[j + 1];
  if (n > 1) row[n - 1] = object[n - 2] | object[n - 1];
}

void edge_row(const std::uint8_t* above, const std::uint8_t* here, const std::uint8_t* below, const std::uint8_t* in,
              std::uint8_t* row, float* values, Eigen::Index n) {
  edge_row_cells(above, here, below, in, row, values, n);
}
void widen(const std::uint8_t* in, std::uint8_t* object, std::uint8_t* row, Eigen::Index n) {
  widen_cells(in, object, row, n);
}

#if defined(__x86_64__) && defined(__GNUC__)
__attribute__((target("avx2"))) void table_1_avx2(const Table1& t, Eigen::Index begin, Eigen::Index end) {
  table_1_cells(t, begin, end);
}
__attribute__((target("avx2"))) void edge_row_avx2(const std::uint8_t* above, const std::uint8_t* here,
                                                   const std::uint8_t* below, const std::uint8_t* in, std::uint8_t* row,
                                                   float* values, Eigen::Index n) {
  edge_row_cells(above, here, below, in, row, values, n);
}
__attribute__((target("avx2"))) void widen_avx2(const std::uint8_t* in, std::uint8_t* object, std::uint8_t* row,
                                                Eigen::Index n) {
  widen_cells(in, object, row, n);
}
#endif

}  // namespace

TerrainClasses classify_terrain_layers(ElevationMap& map, const TerrainParams& params) {
  check_terrain_params(params);
  map.get("max");  // throws std::out_of_range naming a missing input layer before any is added
  map.get("std_dev");
  map.get("discontinuity");
  if (params.reference == GroundReference::kLocalGround) map.get("min");
  // Results go straight into the map's layers (reused in place when the map was classified
  // before: fresh 320 kB buffers per call cost page faults). New ones are not filled first: every
  // cell of all three is written below (filling them would write about 1 MB more on a fresh KITTI
  // map). Adding layers can move them, so every reference is taken after the last add.
  for (const char* name : {"class", "relative_height", "ground"}) {
    if (!map.exists(name)) map.add(name, Layer(map.geometry().size.x(), map.geometry().size.y()));
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
  TerrainClasses out(nx, ny);
  if (cells == 0) return out;
  if (params.reference == GroundReference::kLocalGround) {
    window_min(map.get("min"), params.local_ground_radius_cells, ground);
  }

  // Table 1. The thresholds are doubles (a 0.7 m threshold means 0.7, not float(0.7) =
  // 0.69999999); for a float v, v < t exactly when v < the smallest float >= t, so the per-cell
  // tests run on floats, branch-free, and vectorise.
  const float low = smallest_float_at_least(params.ground_height_m);
  const float high = smallest_float_at_least(params.robot_height_m);
  const float small = smallest_float_at_least(params.std_dev_m);
  const bool sensor_height = params.reference == GroundReference::kSensorHeight;
  const auto sensor_ground = static_cast<float>(-params.sensor_height_m);
  const float* top = highest.data();
  const float* deviation = spread.data();
  const float* flag = gap.data();
  float* reference = ground.data();
  float* height = relative_height.data();
  // The classes before the edge test, for the whole map: the edge test of a row reads the rows
  // beside it, which another thread may be classifying.
  thread_local std::vector<std::uint8_t> table_classes;  // kept for the next call up to 16 MB
  table_classes.resize(static_cast<std::size_t>(cells));
  struct ReleaseIfLarge {
    std::vector<std::uint8_t>& buffer;
    ~ReleaseIfLarge() {
      if (buffer.capacity() > (std::size_t{16} << 20)) buffer = std::vector<std::uint8_t>();
    }
  } release_if_large{table_classes};
  std::uint8_t* first = table_classes.data();
  std::uint8_t* classes = out.data();
  float* class_value = class_layer.data();
  // Rows are split into parts of kCellsPerThread cells or more: about 0.03 ms of work each. Waking
  // a sleeping thread costs tens of microseconds, but right after a threaded map build (the usual
  // caller) the pool's threads are still spinning: there two threads took the 80,000-cell KITTI
  // map's classes from 0.18 to 0.09 ms (bench/bench_elevation.py). Sleeping ones are not woken for
  // a call this small alone (see detail::thread_count).
  constexpr std::size_t kCellsPerThread = std::size_t{1} << 15;
  const int parts = detail::fixed_parts(static_cast<std::size_t>(cells), kCellsPerThread);
  const auto rows_of = [&](int part) { return std::make_pair(nx * part / parts, nx * (part + 1) / parts); };
  // Pass 1: ground reference, relative height ("max" minus the ground; NaN stays NaN) and Table 1
  // (table_1), in AVX2 where the processor has it.
  const Table1 cells_in{top, deviation, flag, reference, height, first, low, high, small};
#if defined(__x86_64__) && defined(__GNUC__)
  const bool avx2 = __builtin_cpu_supports("avx2");
  const auto table_1_of = [&](Eigen::Index begin, Eigen::Index end) {
    avx2 ? table_1_avx2(cells_in, begin, end) : table_1(cells_in, begin, end);
  };
#else
  const auto table_1_of = [&](Eigen::Index begin, Eigen::Index end) { table_1(cells_in, begin, end); };
#endif
  detail::for_each_part(params.num_threads, parts, [&](int part) {
    const auto [row_begin, row_end] = rows_of(part);
    constexpr Eigen::Index kChunk = 2048;  // the ground of a chunk is written, then read from L1
    for (Eigen::Index begin = row_begin * ny; begin < row_end * ny; begin += kChunk) {
      const Eigen::Index end = std::min(row_end * ny, begin + kChunk);
      if (sensor_height) std::fill(reference + begin, reference + end, sensor_ground);
      table_1_of(begin, end);
    }
  });
  // Pass 2: horizontal edges, ground cells with an obstacle, overhanging or vertical cell (2, 3,
  // 4) among their 8 neighbours -- a 3 x 3 dilation of the object mask, separable: each row's mask
  // widened along j, then rows i - 1, i and i + 1 combined -- and the class as a float, NaN for
  // unknown (the bits of float(c), or a quiet NaN's for c = 0).
  detail::for_each_part(params.num_threads, parts, [&](int part) {
    const auto [row_begin, row_end] = rows_of(part);
    std::vector<std::uint8_t> objects(static_cast<std::size_t>(ny));
    std::vector<std::uint8_t> widened(static_cast<std::size_t>(3 * ny));
    const Eigen::Index n = ny;
    const auto widen_row = [&, n](Eigen::Index i) {  // row i's objects widened along j, into slot i % 3
      std::uint8_t* row = widened.data() + (i % 3) * n;
#if defined(__x86_64__) && defined(__GNUC__)
      avx2 ? widen_avx2(first + i * n, objects.data(), row, n) : widen(first + i * n, objects.data(), row, n);
#else
      widen(first + i * n, objects.data(), row, n);
#endif
    };
    if (row_begin < row_end) {
      if (row_begin > 0) widen_row(row_begin - 1);
      widen_row(row_begin);
    }
    for (Eigen::Index i = row_begin; i < row_end; ++i) {
      if (i + 1 < nx) widen_row(i + 1);  // the ring buffer holds rows i - 1, i and i + 1
      const std::uint8_t* above = widened.data() + (std::max<Eigen::Index>(i - 1, 0) % 3) * n;
      const std::uint8_t* here = widened.data() + (i % 3) * n;
      const std::uint8_t* below = widened.data() + (std::min(i + 1, nx - 1) % 3) * n;
#if defined(__x86_64__) && defined(__GNUC__)
      (avx2 ? edge_row_avx2 : edge_row)(above, here, below, first + i * n, classes + i * n, class_value + i * n, n);
#else
      edge_row(above, here, below, first + i * n, classes + i * n, class_value + i * n, n);
#endif
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
