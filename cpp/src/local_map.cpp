// The robot-centric local map: circular-buffer moves, per-cell Kalman fusion, see-through
// clearing, and the planner layers of traversability.hpp (local_map.hpp).
#include "terracube/local_map.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "cloud_frame.hpp"
#include "number_text.hpp"
#include "parallel.hpp"

namespace terracube {

namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr float kInfF = std::numeric_limits<float>::infinity();

/// Every layer, in the order they are added; the empty value of each is NaN except "count" (0).
constexpr std::array<const char*, 14> kLayerNames = {
    "elevation",     "variance",     "count",     "time", "min",   "max",       "std_dev",
    "discontinuity", "overhang_min", "clearance", "step", "slope", "roughness", "traversability"};
enum LayerId {
  kElevation,
  kVariance,
  kCount,
  kTime,
  kMin,
  kMax,
  kStdDev,
  kDiscontinuity,
  kOverhangMin,
  kClearance,
  kStep,
  kSlope,
  kRoughness,
  kTraversability,
};
using LayerData = std::array<float*, kLayerNames.size()>;
/// A map's memory per cell: its float layers and an update's per-cell work (Workspace).
constexpr double kBytesPerCell = 4.0 * kLayerNames.size() + 16.0;

LayerData layer_data(ElevationMap& map) {
  LayerData data{};
  for (std::size_t k = 0; k < kLayerNames.size(); ++k) data[k] = map.get(kLayerNames[k]).data();
  return data;
}

int cells_per_side(const LocalMapParams& p) {
  detail::check_positive(p.length_m, "LocalMapParams.length_m");
  detail::check_positive(p.resolution_m, "LocalMapParams.resolution_m");
  const double cells = std::round(p.length_m / p.resolution_m);
  if (!(cells >= 1.0 && cells <= 16384.0)) {
    throw std::invalid_argument("LocalMapParams: length / resolution must give 1 to 16384 cells per side, got " +
                                detail::number_text(cells));
  }
  if (!(cells * cells <= static_cast<double>(p.max_cells))) {
    throw std::invalid_argument("LocalMapParams: a map of " + detail::number_text(p.length_m) + " m at " +
                                detail::number_text(p.resolution_m) + " m would need " + detail::number_text(cells) +
                                " x " + detail::number_text(cells) + " cells (about " +
                                detail::number_text(std::ceil(cells * cells * kBytesPerCell / 1e6)) +
                                " MB), over max_cells = " + std::to_string(p.max_cells) +
                                "; use a shorter length or a coarser resolution (or raise max_cells)");
  }
  return static_cast<int>(cells);
}

}  // namespace

void check_local_map_params(const LocalMapParams& p) {
  const int side = cells_per_side(p);
  check_collapse_params(p.collapse);
  detail::check_non_negative(p.min_range_m, "LocalMapParams.min_range_m");
  if (!(p.max_range_m > p.min_range_m)) {
    throw std::invalid_argument("LocalMapParams.max_range_m must exceed min_range_m (+inf: no limit), got " +
                                detail::number_text(p.max_range_m));
  }
  detail::check_non_negative(p.range_sigma_m, "LocalMapParams.range_sigma_m");
  detail::check_non_negative(p.angle_sigma_rad, "LocalMapParams.angle_sigma_rad");
  detail::check_positive(p.cell_sigma_m, "LocalMapParams.cell_sigma_m");
  detail::check_positive(p.gate_sigmas, "LocalMapParams.gate_sigmas");
  detail::check_non_negative(p.drift_m_per_sqrt_m, "LocalMapParams.drift_m_per_sqrt_m");
  detail::check_non_negative(p.clearing_margin_m, "LocalMapParams.clearing_margin_m");
  detail::check_positive(p.clearing_depth_m, "LocalMapParams.clearing_depth_m");
  detail::check_non_negative(p.clearing_beyond_m, "LocalMapParams.clearing_beyond_m");
  if (p.clearing_depth_m <= p.clearing_margin_m) {
    throw std::invalid_argument("LocalMapParams.clearing_depth_m must exceed clearing_margin_m");
  }
  detail::check_positive(p.visibility_bin_rad, "LocalMapParams.visibility_bin_rad");
  if (!(p.visibility_bin_rad >= 0.001 && p.visibility_bin_rad <= 0.5)) {  // 0.001: 6.3 M bins, 25 MB
    throw std::invalid_argument("LocalMapParams.visibility_bin_rad must lie in [0.001, 0.5] rad, got " +
                                detail::number_text(p.visibility_bin_rad));
  }
  detail::check_positive(p.discontinuity_m, "LocalMapParams.discontinuity_m");
  check_traversability_params(p.traversability);
  traversability_window_radius(p.traversability, p.resolution_m, CellIndex(side, side));
  detail::check_num_threads(p.num_threads, "LocalMapParams");
}

namespace {

/// A monotone stand-in for the azimuth of (x, y), in [0, 4) ("diamond angle"): one division
/// instead of atan2. Bins of it are at most twice as wide in angle as their mean. Quadrant q
/// (counter-clockwise from +x) plus the share |x| / (|x| + |y|) or |y| / (|x| + |y|) of the
/// coordinate that grows through it: selects instead of branches, so that loops over it vectorise.
float diamond_azimuth(float x, float y) {
  const float ax = std::abs(x), ay = std::abs(y);
  const bool south = y < 0.0F, west = x < 0.0F;
  const float quadrant = south ? (west ? 2.0F : 3.0F) : (west ? 1.0F : 0.0F);
  return quadrant + (south != west ? ax : ay) / (ax + ay);
}

/// The bin [0, bins) of `value` >= 0 on a scale of bin widths: its whole part, the last bin at and
/// beyond it. Clamped before the conversion, which then has a result for any input (NaN gives 0):
/// loops compute bins for every cell and select the binnable ones afterwards.
int bin_index(float value, int bins) {
  return static_cast<int>(std::min(std::max(0.0F, value), static_cast<float>(bins - 1)));  // max(0, NaN) is 0
}

/// Whether VisibilityImage bins a direction with this horizontal range squared and height: more
/// than a micrometre off the vertical through the sensor (closer, its float azimuth could be 0 / 0)
/// and less than 1000 km away (float's 1e-7 relative error stays far below a bin).
bool binnable(double horizontal_squared, double z) {
  return (horizontal_squared > 1e-12) & (horizontal_squared + z * z < 1e12);  // & : no branch in the loops
}

/// The nearest horizontal range of the returns in each (azimuth, elevation) bin of one scan,
/// seen from the sensor; elevation binned on sin(phi) (bins of visibility_bin_rad near the horizon).
/// Directions are binned in float (its 1e-7 relative error is far below a bin), which bounds the
/// returns it takes to 1000 km from the sensor. Bins are azimuth-major: an azimuth's elevation bins
/// are adjacent.
class VisibilityImage {
 public:
  static constexpr int kBatch = 256;  ///< returns binned together (their arrays stay in L1)

  void reset(double bin_rad) {
    // Azimuth bins twice as wide: a spinning sensor's columns are denser than its rows.
    quarter_azimuth_bins_ = static_cast<int>(std::ceil(1.5707963267948966 / (2.0 * bin_rad)));
    elevation_bins_ = static_cast<int>(std::ceil(2.0 / bin_rad));
    inverse_bin_ = static_cast<float>(1.0 / bin_rad);
    nearest_squared_.assign(static_cast<std::size_t>(4 * quarter_azimuth_bins_) * elevation_bins_, kInfF);
    pending_ = 0;
  }
  /// The elevation bin of the binnable direction (x, y, z); a bin for any input (see bin_index).
  int elevation_bin(float x, float y, float z) const {
    const float sine = z / std::sqrt(x * x + y * y + z * z);
    return bin_index((sine + 1.0F) * inverse_bin_, elevation_bins_);
  }
  /// The azimuth bin of the binnable direction (x, y, .); a bin for any input (see bin_index).
  int azimuth_bin(float x, float y) const {
    return bin_index(diamond_azimuth(x, y) * static_cast<float>(quarter_azimuth_bins_), 4 * quarter_azimuth_bins_);
  }
  /// Takes the return at v from the sensor. Returns are binned kBatch at a time (bin_pending), in
  /// branch-free loops over arrays that the compiler vectorises: the square root and the two
  /// divisions of each return cost most of the see-through test.
  void add(const Eigen::Vector3d& v) {
    const double horizontal_squared = v.x() * v.x() + v.y() * v.y();
    if (!binnable(horizontal_squared, v.z())) return;
    x_[pending_] = static_cast<float>(v.x());
    y_[pending_] = static_cast<float>(v.y());
    z_[pending_] = static_cast<float>(v.z());
    horizontal_squared_[pending_] = static_cast<float>(horizontal_squared);
    if (++pending_ == kBatch) bin_pending();
  }
  /// Bins the returns add() holds: call it after the last add() of a scan.
  void bin_pending() {
    if (pending_ == 0) return;
    for (int k = 0; k < pending_; ++k) {
      azimuth_[k] = azimuth_bin(x_[k], y_[k]);
      elevation_[k] = elevation_bin(x_[k], y_[k], z_[k]);
    }
    // Neighbours along a ring mostly share a bin: a run's minimum is kept in a register and
    // stored once, not loaded, lowered and stored again through memory for every return.
    std::size_t run = bin(azimuth_[0], elevation_[0]);
    float run_nearest = horizontal_squared_[0];
    for (int k = 1; k < pending_; ++k) {
      const std::size_t next = bin(azimuth_[k], elevation_[k]);
      if (next == run) {
        run_nearest = std::min(run_nearest, horizontal_squared_[k]);
        continue;
      }
      nearest_squared_[run] = std::min(nearest_squared_[run], run_nearest);
      run = next;
      run_nearest = horizontal_squared_[k];
    }
    nearest_squared_[run] = std::min(nearest_squared_[run], run_nearest);
    pending_ = 0;
  }
  /// Marks the empty bins -1 (below any range squared) once the scan is binned: then a bin sees
  /// beyond a reach exactly when its value exceeds the reach squared.
  void finish() {
    for (float& nearest : nearest_squared_) nearest = nearest < kInfF ? nearest : -1.0F;
  }
  /// Whether, in some bin of elevation [bottom, top] of `azimuth`,
  /// every return lies horizontally beyond sqrt(`beyond_squared`): rays passed through that part of
  /// a cell's column on their way further (all returns of a bin, so that a ray beside the direction
  /// that met something nearer vetoes its bin). Beams leave gaps between rows: empty bins say
  /// nothing. After finish(); the loop has no exit (a maximum, which the compiler vectorises):
  /// most cells are not seen through and read every bin anyway.
  bool seen_beyond(int azimuth, int bottom, int top, float beyond_squared) const {
    const float* bins = nearest_squared_.data() + bin(azimuth, 0);
    float farthest = -1.0F;
    for (int e = bottom; e <= top; ++e) farthest = std::max(farthest, bins[e]);
    return farthest > beyond_squared;
  }

 private:
  std::size_t bin(int azimuth, int elevation) const {
    return static_cast<std::size_t>(azimuth) * static_cast<std::size_t>(elevation_bins_) +
           static_cast<std::size_t>(elevation);
  }

  int quarter_azimuth_bins_ = 0, elevation_bins_ = 0;
  float inverse_bin_ = 1.0F;
  std::vector<float> nearest_squared_;  // [m^2]; -1 after finish() where the bin is empty
  // The returns add() took since the last bin_pending(): direction from the sensor, horizontal range squared.
  int pending_ = 0;
  std::array<float, kBatch> x_{}, y_{}, z_{}, horizontal_squared_{};
  std::array<int, kBatch> azimuth_{}, elevation_{};  // their bins
};

/// One scan's statistics of a cell's kept points.
struct ScanCell {
  std::uint32_t count = 0;
  double first = 0.0, sum = 0.0, sum_squares = 0.0, sum_variance = 0.0;
  double lowest = kInf, highest = -kInf;
  bool gap = false;

  void add(double z, double variance) {
    if (count == 0) first = z;
    const double d = z - first;
    ++count;
    sum += d;
    sum_squares += d * d;
    sum_variance += variance;
    lowest = std::min(lowest, z);
    highest = std::max(highest, z);
  }
};

/// A kept point's height and height variance (LocalMapParams' noise model).
struct KeptPoint {
  double z, variance;
};

/// The cell of a point that is not binned: outside the map, or an overhang.
constexpr std::uint32_t kNotKept = std::numeric_limits<std::uint32_t>::max();

/// Buffers of one update, kept by the calling thread for its next one (fresh pages cost more
/// than the work, see elevation_map.cpp).
struct Workspace {
  VisibilityImage visibility;
  std::vector<Eigen::Vector3d> points;    // the leveled scan inside the map's area
  std::vector<Eigen::Vector3d> beams;     // its beams without a return, leveled
  std::vector<std::uint32_t> point_cell;  // per point: its stored cell when kept in the map, else kNotKept
  // Counting sort of the kept points by cell: cell c holds kept[start[c], start[c + 1]), in point order.
  std::vector<std::uint32_t> start, fill;
  std::vector<KeptPoint> kept;
  std::array<std::vector<double>, 2> gap_scratch;  // measure_cell's
  std::vector<double> overhang_min;                // per cell: this scan's lowest overhang point above it, or +inf
  std::vector<std::size_t> row_offset, column;
  // for_each_seen_through's row: per stored column, the cells' y and their azimuth and elevation bins.
  std::vector<double> cell_y;
  std::vector<int> azimuth, bottom, top;
  std::vector<float> beyond_squared;

  /// After a scan that needed over 64 MB of points (a whole survey, not a robot's scan).
  void release_if_large() {
    const std::size_t bytes = points.capacity() * sizeof(Eigen::Vector3d) +
                              point_cell.capacity() * sizeof(std::uint32_t) + kept.capacity() * sizeof(KeptPoint);
    if (bytes > (std::size_t{64} << 20)) *this = Workspace();
  }
};

/// One scan's measurement of a cell from its kept points, in point order. A cell whose sorted
/// heights hold a gap over `threshold` is discontinuous: its measurement is the points below the
/// lowest gap (the ground under whatever [CBC]'s cubes kept above it, e.g. where a cell straddles
/// two cube columns) and the lowest point above the gap is an overhang (into `overhang_min`).
/// `scratch` holds the heights lowest_height_gap searches, then its work memory.
ScanCell measure_cell(const KeptPoint* begin, const KeptPoint* end, double threshold,
                      std::array<std::vector<double>, 2>& scratch, double& overhang_min) {
  ScanCell c;
  for (const KeptPoint* p = begin; p != end; ++p) c.add(p->z, p->variance);
  if (c.count < 2 || c.highest - c.lowest <= threshold) return c;  // no gap can be wider than the span
  std::vector<double>& heights = scratch[0];
  heights.resize(c.count);
  for (std::size_t k = 0; k < c.count; ++k) heights[k] = begin[k].z;
  const auto gap = lowest_height_gap(heights.data(), c.count, threshold, scratch[1]);
  if (!gap) return c;
  overhang_min = std::min(overhang_min, gap->above_m);
  c = ScanCell();
  c.gap = true;
  for (const KeptPoint* p = begin; p != end; ++p) {
    if (p->z <= gap->below_m) c.add(p->z, p->variance);
  }
  return c;
}

Workspace& thread_workspace() {
  thread_local Workspace workspace;
  return workspace;
}

/// Where one scan's points go: the cell of a point, floor(x / res) - origin on each axis through
/// the map's tables (without a call to floor: the truncation of the difference, one lower when
/// rounding carried it up to a whole number), and the height variance of a return.
struct ScanBinning {
  const std::size_t* row_offset;  ///< per geometric row: its stored row times n
  const std::size_t* column;      ///< per geometric column: its stored column
  double origin_x, origin_y, resolution;
  int n;
  Eigen::Vector3d sensor;
  double range_variance, angle_variance;

  std::ptrdiff_t geometric(double q, double origin) const {
    if (!(q >= origin && q < origin + n)) return -1;
    auto k = static_cast<std::ptrdiff_t>(q - origin);
    if (origin + static_cast<double>(k) > q) --k;
    return k;
  }
  /// The stored cell of p, or -1 outside the map.
  std::ptrdiff_t cell_of(const Eigen::Vector3d& p) const {
    if (!(p.z() >= -1e9 && p.z() <= 1e9)) return -1;
    const std::ptrdiff_t gi = geometric(p.x() / resolution, origin_x);
    const std::ptrdiff_t gj = geometric(p.y() / resolution, origin_y);
    if (gi < 0 || gj < 0) return -1;
    return static_cast<std::ptrdiff_t>(row_offset[gi] + column[gj]);
  }
  /// var_z = range_sigma^2 sin^2(phi) + angle_sigma^2 r^2 cos^2(phi) of a return at v from the
  /// sensor (r cos(phi) = |v_xy|).
  double height_variance(const Eigen::Vector3d& v) const {
    const double horizontal_squared = v.x() * v.x() + v.y() * v.y();
    const double range_squared = horizontal_squared + v.z() * v.z();
    return (range_squared > 0.0 ? range_variance * v.z() * v.z() / range_squared : 0.0) +
           angle_variance * horizontal_squared;
  }
};

/// The one pass that levels the scan (by the pose): every finite return within LocalMapParams'
/// crop around the sensor (counted in report.num_cropped otherwise) and its range limits
/// (min_range_m, max_range_m; report.num_out_of_range otherwise) goes into the visibility image
/// (when clearing), those inside `area` (the map's area with a cell to spare) into w.points, the
/// cloud that collapse_overhangs and the binning read. Returns the NaN/Inf rows.
template <typename Scalar>
detail::NonFiniteRows level_scan(const PointsView<Scalar>& points, const Eigen::Matrix4d& pose, const CropBox& area,
                                 const LocalMapParams& params, bool clearing, Workspace& w, LocalMapUpdate& report) {
  detail::NonFiniteRows non_finite;
  w.points.clear();
  const Eigen::Vector3d sensor = pose.block<3, 1>(0, 3);
  const double nearest = params.min_range_m * params.min_range_m;
  const double farthest = params.max_range_m * params.max_range_m;  // +inf without a limit
  const std::optional<CropBox>& crop = params.collapse.crop;        // around the sensor, leveled axes
  detail::visit_leveled(points, pose, area, [&](const auto& leveled) {
    leveled.with_fixed_layout([&](const auto& cloud) {  // KITTI's and numpy's rows at fixed offsets
      Eigen::Vector3d p;
      for (std::size_t row = 0; row < cloud.size(); ++row) {
        const int status = cloud.map(row, p);
        if (status == 1) {
          non_finite.add(row);
          continue;
        }
        const Eigen::Vector3d v = p - sensor;  // the range is the sensor frame's: the pose is rigid
        if (crop && !((v.array() >= crop->min.array()).all() && (v.array() <= crop->max.array()).all())) {
          ++report.num_cropped;
          continue;
        }
        const double range_squared = v.squaredNorm();
        if (!(range_squared >= nearest && range_squared <= farthest)) {
          ++report.num_out_of_range;
          continue;
        }
        if (clearing) w.visibility.add(v);
        if (status == 0) w.points.push_back(p);
      }
    });
  });
  if (clearing) {
    w.visibility.bin_pending();
    w.visibility.finish();
  }
  return non_finite;
}

/// The part of an update before any change to the map (all that can throw): levels the scan into
/// w (level_scan), refuses NaN/Inf rows unless they are dropped, and removes the overhangs of the
/// leveled, bounded cloud ([CBC], or the shadow-aware rule, seen from the pose's position).
template <typename Scalar>
CollapseResult level_and_collapse(const PointsView<Scalar>& points, const Eigen::Matrix4d& pose, const CropBox& area,
                                  const LocalMapParams& params, const PointsView<double>& no_returns, bool clearing,
                                  Workspace& w, LocalMapUpdate& report) {
  const Eigen::Vector3d sensor = pose.block<3, 1>(0, 3);
  const detail::NonFiniteRows non_finite = level_scan(points, pose, area, params, clearing, w, report);
  if (w.points.size() >= kNotKept) {
    throw std::invalid_argument("LocalMap.update: over 2^32 - 1 points inside the map; split the scan");
  }
  if (non_finite.count > 0 && !params.collapse.drop_non_finite) {
    detail::throw_non_finite_rows(non_finite, points.size);
  }
  report.num_dropped_non_finite = non_finite.count;
  CollapseParams collapse = params.collapse;
  collapse.transform = Eigen::Matrix4d::Identity();
  collapse.crop.reset();
  collapse.num_threads = params.num_threads;
  if (!collapse.shadow_aware.sensor_origin) collapse.shadow_aware.sensor_origin = sensor;
  w.beams.clear();
  if (collapse.method == CollapseMethod::kShadowAware) {  // the beams, leveled by the pose as the points were
    for (std::size_t k = 0; k < no_returns.size; ++k)
      w.beams.push_back(pose.topLeftCorner<3, 3>() * no_returns.point(k));
  }
  CollapseResult removed;
  if (!w.points.empty()) removed = collapse_overhangs(w.points, collapse, PointsView<double>(w.beams));
  report.num_overhang = removed.num_overhang;
  return removed;
}

/// Bins the leveled points: overhang points into w.overhang_min, kept points grouped by cell
/// (a counting sort, point order within a cell) into w.start and w.kept. Returns the points in
/// the map.
std::size_t bin_points(const std::vector<std::uint8_t>& overhang, const ScanBinning& binning, std::size_t cells,
                       Workspace& w) {
  std::size_t in_map = 0;
  w.point_cell.assign(w.points.size(), kNotKept);
  w.start.assign(cells + 1, 0);
  w.overhang_min.assign(cells, kInf);
  for (std::size_t k = 0; k < w.points.size(); ++k) {
    const std::ptrdiff_t cell = binning.cell_of(w.points[k]);
    if (cell < 0) continue;
    ++in_map;
    if (overhang[k] != 0) {
      w.overhang_min[cell] = std::min(w.overhang_min[cell], w.points[k].z());
    } else {
      w.point_cell[k] = static_cast<std::uint32_t>(cell);
      ++w.start[cell + 1];
    }
  }
  for (std::size_t cell = 0; cell < cells; ++cell) w.start[cell + 1] += w.start[cell];
  w.kept.resize(w.start[cells]);
  w.fill.assign(w.start.begin(), w.start.end() - 1);  // the next free slot of each cell
  for (std::size_t k = 0; k < w.points.size(); ++k) {
    const std::uint32_t cell = w.point_cell[k];
    if (cell == kNotKept) continue;
    const Eigen::Vector3d& p = w.points[k];
    w.kept[w.fill[cell]++] = {p.z(), binning.height_variance(p - binning.sensor)};
  }
  return in_map;
}

/// The see-through test's distances: LocalMapParams' clearing_margin_m, clearing_depth_m and
/// clearing_beyond_m (at least a cell), and the sensor's height.
struct Clearing {
  double margin, depth, beyond, sensor_z;
};

/// The part of the visibility image that n cells' columns span: cell s at (x, y[s]) from the
/// sensor, with height h[s] and lowest point low[s] (NaN unknown). Out: its azimuth bin, its
/// elevation bins [bottom, top] (top -1: nothing to test, as for an unknown cell) and the squared
/// horizontal reach its bins' returns must lie beyond. Branch-free over arrays (the compiler
/// vectorises it): every bin is computed, from 0 where a direction is not binnable, and selected.
void column_spans(const VisibilityImage& image, int n, double x, const double* y, const float* h, const float* low,
                  const Clearing& c, int* __restrict azimuth, int* __restrict bottom, int* __restrict top,
                  float* __restrict beyond_squared) {
  for (int s = 0; s < n; ++s) {
    const double horizontal_squared = x * x + y[s] * y[s];
    const double z_top = h[s] - c.margin - c.sensor_z;  // NaN for an unknown cell: not binnable
    const double lowest = low[s], deep = h[s] - c.depth;
    const double z_bottom = (deep < lowest ? deep : lowest) - c.sensor_z;  // std::min(lowest, deep)
    const bool top_ok = binnable(horizontal_squared, z_top);
    const bool bottom_ok = top_ok & binnable(horizontal_squared, z_bottom);
    const auto fx = static_cast<float>(x), fy = static_cast<float>(y[s]);
    const int just_below_top = image.elevation_bin(fx, fy, static_cast<float>(top_ok ? z_top : 0.0)) - 1;
    const int lowest_bin = image.elevation_bin(fx, fy, static_cast<float>(bottom_ok ? z_bottom : 0.0));
    azimuth[s] = image.azimuth_bin(fx, fy);
    top[s] = top_ok ? just_below_top : -1;
    bottom[s] = bottom_ok ? lowest_bin : just_below_top;
    const double reach = std::sqrt(horizontal_squared) + c.beyond;
    beyond_squared[s] = static_cast<float>(reach * reach);
  }
}

/// Calls clear(cell) for every cell whose column this scan's rays passed through, on their way to
/// returns at least `beyond` further away horizontally, between its lowest fused point (or `depth`
/// below its height, if lower) and `margin` below its height: where the points it holds would
/// have stopped them. (Rays under a car's body or a table, below everything the cell holds, say
/// nothing about it.) Cells this scan measures are left out: the fusion updates them. Row by row,
/// in storage order: column_spans, then the bins of the cells that span some.
template <typename Clear>
void for_each_seen_through(Workspace& w, const float* elevation, const float* lowest, int n, double res,
                           const Eigen::Vector2d& origin, const Eigen::Vector3d& sensor, const Clearing& c,
                           const Clear& clear) {
  const auto size = static_cast<std::size_t>(n);
  w.cell_y.resize(size);  // per stored column: its cells' centre y relative to the sensor
  for (int gj = 0; gj < n; ++gj) w.cell_y[w.column[gj]] = origin.y() + (gj + 0.5) * res - sensor.y();
  w.azimuth.resize(size);
  w.bottom.resize(size);
  w.top.resize(size);
  w.beyond_squared.resize(size);
  for (int gi = 0; gi < n; ++gi) {
    const double x = origin.x() + (gi + 0.5) * res - sensor.x();
    const std::size_t row = w.row_offset[gi];
    column_spans(w.visibility, n, x, w.cell_y.data(), elevation + row, lowest + row, c, w.azimuth.data(),
                 w.bottom.data(), w.top.data(), w.beyond_squared.data());
    for (std::size_t s = 0; s < size; ++s) {
      const bool measured = w.start[row + s + 1] > w.start[row + s];  // fused, or replaced by the gate
      if (w.top[s] >= 0 && !measured &&
          w.visibility.seen_beyond(w.azimuth[s], w.bottom[s], w.top[s], w.beyond_squared[s])) {
        clear(row + s);
      }
    }
  }
}

/// The cell state kept outside the layers: the reference height and the sums of (z - reference)
/// and its square over the fused points.
struct CellSums {
  std::vector<double>& reference;
  std::vector<double>& sum;
  std::vector<double>& sum_squares;
};

/// The 1-D Kalman update of one cell by one scan's measurement c (its mean height, with the
/// variance of LocalMapParams' noise model), or the cell's replacement when the innovation fails
/// the gate. Returns whether it was replaced.
bool fuse_cell(const ScanCell& c, std::size_t cell, const LayerData& layer, CellSums sums, double cell_variance,
               double gate_squared, double stamp) {
  const double count = c.count;
  const double mean_offset = c.sum / count;
  const double spread = std::max(c.sum_squares / count - mean_offset * mean_offset, 0.0);
  const double z = c.first + mean_offset;
  const double r = (c.sum_variance / count + spread) / count + cell_variance;
  const double h = layer[kElevation][cell];
  const double p = layer[kVariance][cell];
  bool fresh = std::isnan(h), replaced = false;
  if (!fresh && (z - h) * (z - h) > gate_squared * (p + r)) {
    fresh = true;
    replaced = true;
  }
  if (fresh) {
    layer[kElevation][cell] = static_cast<float>(z);
    layer[kVariance][cell] = static_cast<float>(r);
    layer[kCount][cell] = static_cast<float>(count);
    layer[kMin][cell] = static_cast<float>(c.lowest);
    layer[kMax][cell] = static_cast<float>(c.highest);
    sums.reference[cell] = c.first;
    sums.sum[cell] = c.sum;
    sums.sum_squares[cell] = c.sum_squares;
  } else {
    const double gain = p / (p + r);
    layer[kElevation][cell] = static_cast<float>(h + gain * (z - h));
    layer[kVariance][cell] = static_cast<float>(p * r / (p + r));
    layer[kCount][cell] += static_cast<float>(count);
    layer[kMin][cell] = std::min(layer[kMin][cell], static_cast<float>(c.lowest));
    layer[kMax][cell] = std::max(layer[kMax][cell], static_cast<float>(c.highest));
    // The scan's sums are relative to its first height; shift them to the cell's reference.
    const double offset = c.first - sums.reference[cell];
    sums.sum_squares[cell] += count * offset * offset + 2.0 * offset * c.sum + c.sum_squares;
    sums.sum[cell] += count * offset + c.sum;
  }
  const double total = layer[kCount][cell];
  const double mean = sums.sum[cell] / total;
  layer[kStdDev][cell] = static_cast<float>(std::sqrt(std::max(sums.sum_squares[cell] / total - mean * mean, 0.0)));
  layer[kDiscontinuity][cell] = c.gap ? 1.0F : 0.0F;
  layer[kTime][cell] = static_cast<float>(stamp);
  return replaced;
}

/// Empties one cell: NaN in every layer but "count" (0), its sums reset.
void clear_cell(const LayerData& layer, CellSums sums, std::size_t cell) {
  for (std::size_t k = 0; k < layer.size(); ++k) layer[k][cell] = k == kCount ? 0.0F : kNaN;
  sums.reference[cell] = sums.sum[cell] = sums.sum_squares[cell] = 0.0;
}

/// "clearance": the lowest overhang above minus the elevation, +inf without one, NaN without height.
void refresh_clearance(const LayerData& layer, std::size_t cells) {
  for (std::size_t cell = 0; cell < cells; ++cell) {
    const float h = layer[kElevation][cell];
    const float o = layer[kOverhangMin][cell];
    layer[kClearance][cell] =
        std::isnan(h) ? kNaN : (std::isnan(o) ? std::numeric_limits<float>::infinity() : std::max(o - h, 0.0F));
  }
}

/// The lower-left corner of the global cells numbered `cell` [m]: cell x resolution, raised by the
/// few ulps that put it in that cell by index_of's floor(x / resolution) (-58 x 0.1 is
/// -5.800000000000001, which lies in cell -59), so that index_of(geometry().origin_m) is the map's
/// lower-left cell.
double cell_corner(std::int64_t cell, double resolution) {
  double corner = static_cast<double>(cell) * resolution;
  for (int ulp = 0; ulp < 16 && std::floor(corner / resolution) < static_cast<double>(cell); ++ulp) {
    corner = std::nextafter(corner, kInf);  // one or two ulps in practice; bounded all the same
  }
  return corner;
}

/// The origin cell of an n x n map centred on `position`: floor(position / resolution) - n / 2 per
/// axis. Throws (naming `what`) unless the position is finite, within 1e12 m and within 2^52 cells
/// of the origin (a finer resolution than that would overflow the cell index).
Eigen::Matrix<std::int64_t, 2, 1> origin_cell_at(const Eigen::Vector2d& position, double resolution, int n,
                                                 const std::string& what) {
  const Eigen::Vector2d cells = position / resolution;
  if (!position.allFinite() || (position.array().abs() > 1e12).any() || (cells.array().abs() > 0x1p52).any()) {
    throw std::invalid_argument(what +
                                " must be finite and within 1e12 m of the origin, and no more than 2^52 cells of " +
                                detail::number_text(resolution) + " m from it");
  }
  return {static_cast<std::int64_t>(std::floor(cells.x())) - n / 2,
          static_cast<std::int64_t>(std::floor(cells.y())) - n / 2};
}

}  // namespace

LocalMap::LocalMap(const LocalMapParams& params) : params_(params) {
  check_local_map_params(params);
  const int n = cells_per_side(params);
  geometry_.resolution_m = params.resolution_m;
  geometry_.size = CellIndex(n, n);
  origin_cell_ = Eigen::Matrix<std::int64_t, 2, 1>::Constant(-(n / 2));
  geometry_.origin_m = {cell_corner(origin_cell_.x(), params.resolution_m),
                        cell_corner(origin_cell_.y(), params.resolution_m)};
  layers_ = ElevationMap(geometry_);
  for (const char* name : kLayerNames) layers_.add(name, name == std::string("count") ? 0.0F : kNaN);
  const std::size_t cells = geometry_.num_cells();
  reference_.assign(cells, 0.0);
  sum_.assign(cells, 0.0);
  sum_squares_.assign(cells, 0.0);
}

std::int64_t LocalMap::storage_of(std::int64_t global, int axis) const {
  const std::int64_t n = geometry_.size[axis];
  return ((global % n) + n) % n;
}

CellIndex LocalMap::start_index() const {
  return CellIndex(static_cast<int>(storage_of(origin_cell_.x(), 0)),
                   static_cast<int>(storage_of(origin_cell_.y(), 1)));
}

std::optional<CellIndex> LocalMap::index_of(const Eigen::Vector2d& position) const {
  const double gx = std::floor(position.x() / params_.resolution_m);
  const double gy = std::floor(position.y() / params_.resolution_m);
  const double ox = static_cast<double>(origin_cell_.x());
  const double oy = static_cast<double>(origin_cell_.y());
  if (!(gx >= ox && gx < ox + geometry_.size.x() && gy >= oy && gy < oy + geometry_.size.y())) return std::nullopt;
  return CellIndex(static_cast<int>(storage_of(static_cast<std::int64_t>(gx), 0)),
                   static_cast<int>(storage_of(static_cast<std::int64_t>(gy), 1)));
}

Eigen::Vector2d LocalMap::position_of(const CellIndex& index) const {
  if ((index.array() < 0).any() || (index.array() >= geometry_.size.array()).any()) {
    throw std::out_of_range("LocalMap.position_of: (" + std::to_string(index.x()) + ", " + std::to_string(index.y()) +
                            ") is not a cell of the " + std::to_string(geometry_.size.x()) + " x " +
                            std::to_string(geometry_.size.y()) + " map");
  }
  const CellIndex start = start_index();
  const std::int64_t gi = (index.x() - start.x() + geometry_.size.x()) % geometry_.size.x();
  const std::int64_t gj = (index.y() - start.y() + geometry_.size.y()) % geometry_.size.y();
  return {(static_cast<double>(origin_cell_.x() + gi) + 0.5) * params_.resolution_m,
          (static_cast<double>(origin_cell_.y() + gj) + 0.5) * params_.resolution_m};
}

const Layer& LocalMap::get(const std::string& name) const { return layers_.get(name); }
std::vector<std::string> LocalMap::layers() const { return layers_.layers(); }

void LocalMap::clear_cells(std::size_t first, std::size_t count, std::size_t stride) {
  const LayerData layer = layer_data(layers_);
  for (std::size_t c = 0; c < count; ++c) clear_cell(layer, {reference_, sum_, sum_squares_}, first + c * stride);
}

void LocalMap::clear() { clear_cells(0, geometry_.num_cells(), 1); }

bool LocalMap::move_to(const Eigen::Vector2d& position) {
  const Eigen::Matrix<std::int64_t, 2, 1> before = origin_cell_;
  const bool reset = shift_to(position);
  // The planner layers near the entering border were computed from cells that have left.
  if (params_.compute_planner_layers && origin_cell_ != before) update_planner_layers();
  return reset;
}

bool LocalMap::shift_to(const Eigen::Vector2d& position) {
  const int n = geometry_.size.x();
  const Eigen::Matrix<std::int64_t, 2, 1> target =
      origin_cell_at(position, params_.resolution_m, n, "LocalMap.move_to: the position");
  const Eigen::Matrix<std::int64_t, 2, 1> shift = target - origin_cell_;
  const bool reset = std::abs(shift.x()) >= n || std::abs(shift.y()) >= n;
  if (reset) {
    clear();
  } else if (shift.x() != 0 || shift.y() != 0) {
    // The global rows (columns) that leave are those of [old, old + shift) for a positive shift
    // and [old + n + shift, old + n) for a negative one; they are stored where the entering ones go.
    for (int axis = 0; axis < 2; ++axis) {
      const std::int64_t s = shift[axis];
      const std::int64_t first = s > 0 ? origin_cell_[axis] : origin_cell_[axis] + n + s;
      for (std::int64_t g = first; g < first + std::abs(s); ++g) {
        const auto line = static_cast<std::size_t>(storage_of(g, axis));
        // A stored row i is cells [i n, i n + n); a stored column j is j, j + n, ...
        if (axis == 0) {
          clear_cells(line * n, n, 1);
        } else {
          clear_cells(line, n, n);
        }
      }
    }
  }
  origin_cell_ = target;
  geometry_.origin_m = {cell_corner(origin_cell_.x(), params_.resolution_m),
                        cell_corner(origin_cell_.y(), params_.resolution_m)};
  return reset;
}

void LocalMap::check_stamp(double stamp_s, double relative_s, double origin_s) const {
  if (std::isinf(stamp_s)) throw std::invalid_argument("LocalMap.update: stamp must be finite (or NaN)");
  if (num_updates_ > 0 && stamped_ != !std::isnan(stamp_s)) {
    throw std::invalid_argument(
        std::string("LocalMap.update: ") +
        (stamped_ ? "no stamp (NaN) after updates with one" : "a stamp after updates without one (NaN: their count)") +
        "; give every update its stamp, or none");
  }
  if (!(std::abs(relative_s) <= 1e30)) {  // "time" is float (3.4e38 at most)
    throw std::invalid_argument("LocalMap.update: stamp " + detail::number_text(stamp_s) + " lies " +
                                detail::number_text(relative_s) + " s from the first update's " +
                                detail::number_text(origin_s) + ": over 1e30 s, beyond the float \"time\" layer");
  }
}

LocalMapUpdate LocalMap::update(const PointsView<float>& points, const Eigen::Matrix4d& pose, double stamp_s,
                                const PointsView<double>& no_return_directions) {
  return update_impl(points, pose, stamp_s, no_return_directions);
}
LocalMapUpdate LocalMap::update(const PointsView<double>& points, const Eigen::Matrix4d& pose, double stamp_s,
                                const PointsView<double>& no_return_directions) {
  return update_impl(points, pose, stamp_s, no_return_directions);
}

template <typename Scalar>
LocalMapUpdate LocalMap::update_impl(const PointsView<Scalar>& points, const Eigen::Matrix4d& pose, double stamp_s,
                                     const PointsView<double>& no_return_directions) {
  detail::check_rigid_transform(pose, "pose");
  check_directions(no_return_directions, "LocalMap.update: no_returns");
  const double absolute_stamp = std::isnan(stamp_s) ? static_cast<double>(num_updates_) : stamp_s;
  // "time" is float: relative to the first update's stamp, ROS stamps (1.7e9 s) keep their ms.
  const double time_origin = time_origin_s_.value_or(absolute_stamp);
  const double stamp = absolute_stamp - time_origin;
  check_stamp(stamp_s, stamp, time_origin);
  const int n = geometry_.size.x();
  const double res = params_.resolution_m;
  const Eigen::Vector3d sensor = pose.block<3, 1>(0, 3);
  const Eigen::Matrix<std::int64_t, 2, 1> target =
      origin_cell_at(sensor.head<2>(), res, n, "LocalMap.update: the pose's position");
  LocalMapUpdate report;
  report.num_points = points.size;

  // Everything that can throw comes before the first change to the map. The scan is leveled
  // once; the map's area with a cell to spare bounds the cloud, so that every point binned into
  // the map took part in the overhang removal.
  Workspace& w = thread_workspace();
  const bool clearing = params_.clear_seen_through && points.size > 0;
  if (clearing) w.visibility.reset(params_.visibility_bin_rad);
  CropBox area;
  area.min =
      Eigen::Vector3d(static_cast<double>(target.x() - 1) * res, static_cast<double>(target.y() - 1) * res, -1e9);
  area.max = Eigen::Vector3d(static_cast<double>(target.x() + n + 1) * res,
                             static_cast<double>(target.y() + n + 1) * res, 1e9);
  struct ReleaseOnExit {
    Workspace& workspace;
    ~ReleaseOnExit() { workspace.release_if_large(); }
  } release_on_exit{w};
  const CollapseResult removed =
      level_and_collapse(points, pose, area, params_, no_return_directions, clearing, w, report);

  time_origin_s_ = time_origin;  // the first change to the map
  stamped_ = !std::isnan(stamp_s);
  report.map_reset = shift_to(sensor.head<2>());  // the planner layers are refreshed at the end
  const LayerData layer = layer_data(layers_);
  if (last_sensor_ && params_.drift_m_per_sqrt_m > 0.0) {
    // Odometry drift: every known height grows less certain with the distance travelled.
    const auto growth =
        static_cast<float>(params_.drift_m_per_sqrt_m * params_.drift_m_per_sqrt_m * (sensor - *last_sensor_).norm());
    for (std::size_t cell = 0; cell < geometry_.num_cells(); ++cell) layer[kVariance][cell] += growth;  // NaN stays
  }
  last_sensor_ = sensor;
  const std::size_t cells = geometry_.num_cells();
  // The stored index of each geometric row (times n) and column.
  w.row_offset.resize(static_cast<std::size_t>(n));
  w.column.resize(static_cast<std::size_t>(n));
  for (int g = 0; g < n; ++g) {
    w.row_offset[g] = static_cast<std::size_t>(storage_of(origin_cell_.x() + g, 0)) * static_cast<std::size_t>(n);
    w.column[g] = static_cast<std::size_t>(storage_of(origin_cell_.y() + g, 1));
  }
  const double ox = static_cast<double>(origin_cell_.x()), oy = static_cast<double>(origin_cell_.y());
  const ScanBinning binning{w.row_offset.data(),
                            w.column.data(),
                            ox,
                            oy,
                            res,
                            n,
                            sensor,
                            params_.range_sigma_m * params_.range_sigma_m,
                            params_.angle_sigma_rad * params_.angle_sigma_rad};
  report.num_in_map = bin_points(removed.overhang, binning, cells, w);

  // Clearing: a stored height that this scan's rays passed under by the margin is gone.
  if (clearing) {
    const Eigen::Vector2d origin(ox * res, oy * res);
    const Clearing distances{params_.clearing_margin_m, params_.clearing_depth_m,
                             std::max(params_.clearing_beyond_m, res), sensor.z()};
    for_each_seen_through(w, layer[kElevation], layer[kMin], n, res, origin, sensor, distances, [&](std::size_t cell) {
      clear_cell(layer, {reference_, sum_, sum_squares_}, cell);
      ++report.num_cleared_cells;
    });
  }

  // The 1-D Kalman update of each measured cell, or its replacement outside the gate.
  const double gate_squared = params_.gate_sigmas * params_.gate_sigmas;
  const double cell_variance = params_.cell_sigma_m * params_.cell_sigma_m;
  for (std::size_t cell = 0; cell < cells; ++cell) {
    const KeptPoint* begin = w.kept.data() + w.start[cell];
    const KeptPoint* end = w.kept.data() + w.start[cell + 1];
    const ScanCell c = measure_cell(begin, end, params_.discontinuity_m, w.gap_scratch, w.overhang_min[cell]);
    if (w.overhang_min[cell] < kInf) layer[kOverhangMin][cell] = static_cast<float>(w.overhang_min[cell]);
    if (c.count == 0) continue;
    ++report.num_fused_cells;
    report.num_replaced_cells +=
        fuse_cell(c, cell, layer, {reference_, sum_, sum_squares_}, cell_variance, gate_squared, stamp);
  }
  refresh_clearance(layer, cells);
  if (params_.compute_planner_layers) update_planner_layers();
  ++num_updates_;
  return report;
}

void LocalMap::update_planner_layers() {
  add_traversability_layers(layers_, params_.traversability, "elevation", start_index(), params_.num_threads);
}

ElevationMap LocalMap::to_elevation_map() const {
  ElevationMap out(geometry_);
  const int n = geometry_.size.x();
  const CellIndex start = start_index();
  for (const std::string& name : layers_.layers()) {
    const Layer& in = layers_.get(name);
    Layer ordered(n, n);
    for (int gi = 0; gi < n; ++gi) {
      const int si = (gi + start.x()) % n;
      for (int gj = 0; gj < n; ++gj) ordered(gi, gj) = in(si, (gj + start.y()) % n);
    }
    out.add(name, std::move(ordered));
  }
  return out;
}

}  // namespace terracube
