// Planner layers: a least-squares plane's moments summed over every cell's window (sliding down
// the rows), the window's extremes, and the traversability formula (traversability.hpp).
#include "terracube/traversability.hpp"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <vector>

#include "number_text.hpp"
#include "parallel.hpp"

namespace terracube {

namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr float kInfF = std::numeric_limits<float>::infinity();

/// The moments a least-squares plane needs, summed over a set of known cells: their number n and
/// the sums of y, y^2, z, y z, z^2, x, x^2, x y, x z, with x, y the geometric cell indices and z the
/// height relative to a reference (sums of x and y are whole numbers, exact in double). Within a
/// geometric row x is constant: a row's windows need only the first kRowMoments.
enum Moment { kN, kY, kYY, kZ, kYZ, kZZ, kX, kXX, kXY, kXZ };
constexpr int kRowMoments = 6, kMoments = 10;

/// One array per moment, over the columns of a row (structure of arrays: the loops vectorise).
using MomentArrays = std::vector<std::vector<double>>;

/// The windows [j - r, j + r] of one geometric row, per column j: their first kRowMoments and
/// their lowest and highest height (+inf and -inf when all unknown).
struct RowWindows {
  MomentArrays moments;
  std::vector<float> lowest, highest;

  explicit RowWindows(std::size_t n) : moments(kRowMoments, std::vector<double>(n)), lowest(n), highest(n) {}
};

/// The windows of one row (`out`) from `padded`: the row's n heights in map order (NaN unknown;
/// the moments take them relative to `reference`) between r NaNs on each side, so that every
/// window reads 2 r + 1 of them. The moments are differences of prefix sums (`prefix`: n + 2 r + 1
/// per moment, the first 0); the other loops run without bounds to clip, and vectorise.
void row_windows(const std::vector<float>& padded, double reference, int r, MomentArrays& prefix, RowWindows& out) {
  double sum[kRowMoments] = {};                      // of the cells before p, in registers rather than read back
  for (std::size_t p = 0; p < padded.size(); ++p) {  // padded position p is column p - r
    const bool known = !std::isnan(padded[p]);
    const double y = known ? static_cast<double>(p) - r : 0.0, z = known ? padded[p] - reference : 0.0;
    const double cell[kRowMoments] = {known ? 1.0 : 0.0, y, y * y, z, y * z, z * z};
    for (int k = 0; k < kRowMoments; ++k) prefix[k][p + 1] = sum[k] += cell[k];
  }
  const std::size_t n = out.lowest.size(), width = 2 * static_cast<std::size_t>(r) + 1;
  for (int k = 0; k < kRowMoments; ++k) {
    for (std::size_t j = 0; j < n; ++j) out.moments[k][j] = prefix[k][j + width] - prefix[k][j];
  }
  float *lowest = out.lowest.data(), *highest = out.highest.data();
  std::fill(lowest, lowest + n, kInfF);
  std::fill(highest, highest + n, -kInfF);
  for (std::size_t d = 0; d < width; ++d) {
    for (std::size_t j = 0; j < n; ++j) {  // std::min/max keep the first argument against NaN
      lowest[j] = std::min(lowest[j], padded[j + d]);
      highest[j] = std::max(highest[j], padded[j + d]);
    }
  }
}

/// Adds (sign 1) or takes away (sign -1) the moments of the windows of geometric row `x` to the
/// column sums `sums`, the x ones formed here from the row's: x n, x^2 n, x y and x z.
void add_row(const RowWindows& row, double x, double sign, MomentArrays& sums) {
  const auto add = [&](Moment to, Moment from, double factor) {
    double* s = sums[to].data();
    const double* v = row.moments[from].data();
    for (std::size_t j = 0; j < row.lowest.size(); ++j) s[j] += factor * v[j];
  };
  for (int k = 0; k < kRowMoments; ++k) add(static_cast<Moment>(k), static_cast<Moment>(k), sign);
  add(kX, kN, sign * x);
  add(kXX, kN, sign * x * x);
  add(kXY, kY, sign * x);
  add(kXZ, kZ, sign * x);
}

/// Per column j, the least-squares plane z = a x + b y + c of the cells with moments `m` (x, y in
/// cells, `resolution` m apart): its squared slope tangent (a^2 + b^2) / resolution^2 into tan2[j]
/// and the mean squared vertical residual into residual2[j], both NaN with fewer than min_cells
/// known cells (or only collinear ones). Branch-free, and the outputs overlap no moment
/// (restrict): the loop vectorises.
void fit_planes(const MomentArrays& m, double min_cells, double resolution, double* __restrict tan2,
                double* __restrict residual2) {
  for (std::size_t j = 0; j < m[kN].size(); ++j) {
    const double w = 1.0 / m[kN][j];  // the means and covariances of the window's cells
    const double mx = m[kX][j] * w, my = m[kY][j] * w, mz = m[kZ][j] * w;
    const double cxx = m[kXX][j] * w - mx * mx, cxy = m[kXY][j] * w - mx * my, cyy = m[kYY][j] * w - my * my;
    const double cxz = m[kXZ][j] * w - mx * mz, cyz = m[kYZ][j] * w - my * mz, czz = m[kZZ][j] * w - mz * mz;
    const double det = cxx * cyy - cxy * cxy;
    const double divisor = (m[kN][j] >= min_cells) & (det > 1e-9) ? det : kNaN;  // NaN: no plane, no branch
    const double a = (cyy * cxz - cxy * cyz) / divisor, b = (cxx * cyz - cxy * cxz) / divisor;
    const double a_m = a / resolution, b_m = b / resolution;  // per metre (no 1 / resolution^2 to overflow)
    tan2[j] = a_m * a_m + b_m * b_m;
    residual2[j] = czz - a * cxz - b * cyz;
  }
}

/// TraversabilityParams' formula (traversability.hpp), its weights divided by their thresholds
/// and their sum once per call.
class TraversabilityCost {
 public:
  explicit TraversabilityCost(const TraversabilityParams& tp) : tp_(tp) {
    const double weights = tp.slope_weight + tp.step_weight + tp.roughness_weight;
    slope_ = tp.slope_weight / (tp.max_slope_rad * weights);
    step_ = tp.step_weight / (tp.max_step_m * weights);
    roughness_ = tp.roughness_weight / (tp.max_roughness_m * weights);
  }
  float operator()(double slope, double step, double roughness, float clearance) const {
    // In [0, 1] as the formula is; the clamp holds it there when weights near the smallest double
    // (1e-320) lose the precision that keeps the normalised terms' sum at most 1.
    const double value = std::clamp(1.0 - (slope_ * slope + step_ * step + roughness_ * roughness), 0.0, 1.0);
    // | rather than ||: fewer hard-to-predict branches (the blocked cells are scattered)
    const bool blocked = (slope > tp_.max_slope_rad) | (step > tp_.max_step_m) | (roughness > tp_.max_roughness_m) |
                         (clearance < tp_.min_clearance_m);
    return blocked ? 0.0F : static_cast<float>(value);
  }

 private:
  const TraversabilityParams& tp_;
  double slope_, step_, roughness_;  // w / (max * (w_s + w_t + w_r))
};

/// Where the cells of a (possibly circular) map are stored: per geometric row its stored row
/// times the row length, per geometric column its stored column. No wrap-around arithmetic in
/// the loops, and windows are clipped at the map's border (they never wrap).
struct StorageOrder {
  std::vector<std::size_t> row, column;

  StorageOrder(const CellIndex& size, const CellIndex& start)
      : row(static_cast<std::size_t>(size.x())), column(static_cast<std::size_t>(size.y())) {
    for (int g = 0; g < size.x(); ++g) {
      row[g] = static_cast<std::size_t>((g + start.x()) % size.x()) * static_cast<std::size_t>(size.y());
    }
    for (int g = 0; g < size.y(); ++g) column[g] = static_cast<std::size_t>((g + start.y()) % size.y());
  }
};

/// The layers add_traversability_layers reads and writes, in storage order.
struct PlannerData {
  const float* height;
  const float* clearance;  // null: nothing overhangs
  float *step, *slope, *roughness, *traversability;
};

/// The windows of the cells of one geometric row, per column: their lowest and highest height
/// and their plane (fit_planes).
struct RowFits {
  const std::vector<float>& lowest;
  const std::vector<float>& highest;
  const std::vector<double>& tan2;
  const std::vector<double>& residual2;
};

/// Each cell of geometric row `gi`: its window's step, plane fit and traversability when it is
/// known (finite), else NaN.
void write_row(const PlannerData& d, const StorageOrder& order, const RowFits& w, std::size_t gi,
               const TraversabilityCost& cost) {
  const std::size_t n = order.column.size();
  for (std::size_t gj = 0; gj < n; ++gj) {
    const std::size_t cell = order.row[gi] + order.column[gj];
    const bool known = std::isfinite(d.height[cell]);
    const float step = known ? w.highest[gj] - w.lowest[gj] : kNaN;
    float slope = kNaN, roughness = kNaN, traversability = kNaN;
    if (known && !std::isnan(w.tan2[gj])) {
      slope = std::atan(static_cast<float>(std::sqrt(w.tan2[gj])));  // float: the layer's type
      const double rms = std::sqrt(std::max(w.residual2[gj], 0.0));
      roughness = static_cast<float>(rms);
      traversability = cost(slope, step, rms, d.clearance != nullptr ? d.clearance[cell] : kInfF);
    }
    d.step[cell] = step;
    d.slope[cell] = slope;
    d.roughness[cell] = roughness;
    d.traversability[cell] = traversability;
  }
}

/// The planner layers of the cells of geometric rows [begin, end). The windows slide down the
/// rows: each row's windows along y (row_windows) enter a ring of the window's rows (row a in
/// slot a mod slots) and their moments running sums per column as the window reaches them, and
/// leave as it passes them, so a window's moments cost the same whatever its size and the memory
/// is that of the window's rows, not the map's. A part starts its sums afresh: the same bits
/// whatever the number of threads.
void planner_rows(const PlannerData& d, const StorageOrder& order, double reference, int r, double resolution,
                  const TraversabilityParams& tp, std::size_t begin, std::size_t end) {
  if (begin == end) return;  // more parts than rows (a map of a few long rows)
  const int rows = static_cast<int>(order.row.size());
  const std::size_t n = order.column.size();
  const int slots = static_cast<int>(std::min<std::int64_t>(2 * std::int64_t{r} + 1, rows));
  std::vector<RowWindows> ring(static_cast<std::size_t>(slots), RowWindows(n));
  std::vector<float> padded(n + 2 * static_cast<std::size_t>(r), kNaN), lowest(n), highest(n);
  MomentArrays prefix(kRowMoments, std::vector<double>(padded.size() + 1)), sums(kMoments, std::vector<double>(n));
  std::vector<double> tan2(n), residual2(n);
  const auto enter = [&](int a) {
    for (std::size_t gj = 0; gj < n; ++gj) {
      const float h = d.height[order.row[static_cast<std::size_t>(a)] + order.column[gj]];
      padded[r + gj] = std::isfinite(h) ? h : kNaN;  // +-inf heights are unknown too
    }
    row_windows(padded, reference, r, prefix, ring[a % slots]);
    add_row(ring[a % slots], a, 1.0, sums);
  };
  const TraversabilityCost cost(tp);
  const int first = static_cast<int>(begin);
  for (int a = std::max(first - r, 0); a <= std::min(first + r, rows - 1); ++a) enter(a);
  for (int gi = first; gi < static_cast<int>(end); ++gi) {
    if (gi > first) {
      if (gi - r - 1 >= 0) add_row(ring[(gi - r - 1) % slots], gi - r - 1, -1.0, sums);  // before its slot is reused
      if (gi + r <= rows - 1) enter(gi + r);
    }
    std::fill(lowest.begin(), lowest.end(), kInfF);
    std::fill(highest.begin(), highest.end(), -kInfF);
    for (int a = std::max(gi - r, 0); a <= std::min(gi + r, rows - 1); ++a) {
      const RowWindows& row = ring[a % slots];
      for (std::size_t gj = 0; gj < n; ++gj) {
        lowest[gj] = std::min(lowest[gj], row.lowest[gj]);
        highest[gj] = std::max(highest[gj], row.highest[gj]);
      }
    }
    fit_planes(sums, tp.min_window_cells, resolution, tan2.data(), residual2.data());
    write_row(d, order, {lowest, highest, tan2, residual2}, static_cast<std::size_t>(gi), cost);
  }
}

}  // namespace

void check_traversability_params(const TraversabilityParams& p) {
  detail::check_non_negative(p.footprint_radius_m, "TraversabilityParams.footprint_radius_m");
  detail::check_positive(p.max_slope_rad, "TraversabilityParams.max_slope_rad");
  detail::check_positive(p.max_step_m, "TraversabilityParams.max_step_m");
  detail::check_positive(p.max_roughness_m, "TraversabilityParams.max_roughness_m");
  detail::check_non_negative(p.min_clearance_m, "TraversabilityParams.min_clearance_m");
  detail::check_non_negative(p.slope_weight, "TraversabilityParams.slope_weight");
  detail::check_non_negative(p.step_weight, "TraversabilityParams.step_weight");
  detail::check_non_negative(p.roughness_weight, "TraversabilityParams.roughness_weight");
  if (p.slope_weight + p.step_weight + p.roughness_weight <= 0.0) {
    throw std::invalid_argument("TraversabilityParams: the slope, step and roughness weights must not all be 0");
  }
  if (p.min_window_cells < 3) throw std::invalid_argument("TraversabilityParams.min_window_cells must be >= 3");
}

int traversability_window_radius(const TraversabilityParams& tp, double resolution_m, const CellIndex& size) {
  detail::check_positive(resolution_m, "add_traversability_layers: the map's resolution");
  const double radius =
      std::min(std::max(1.0, std::round(tp.footprint_radius_m / resolution_m)), static_cast<double>(size.maxCoeff()));
  if (!(radius <= kMaxWindowRadius)) {
    throw std::invalid_argument(
        "TraversabilityParams.footprint_radius_m " + detail::number_text(tp.footprint_radius_m) + " m at " +
        detail::number_text(resolution_m) + " m cells is a window of " + detail::number_text(2.0 * radius + 1.0) +
        " cells a side, over " + std::to_string(2 * kMaxWindowRadius + 1) +
        "; use a coarser resolution or a smaller footprint");
  }
  return static_cast<int>(radius);
}

void add_traversability_layers(ElevationMap& map, const TraversabilityParams& tp, const std::string& height_layer,
                               const CellIndex& start, int num_threads) {
  check_traversability_params(tp);
  detail::check_num_threads(num_threads, "add_traversability_layers");
  const CellIndex size = map.geometry().size;
  if ((start < 0).any() || (start >= size.max(1)).any()) {
    throw std::invalid_argument("add_traversability_layers: start must be a cell index of the map");
  }
  const double resolution = map.geometry().resolution_m;
  const int r = traversability_window_radius(tp, resolution, size);
  const auto window_rows = static_cast<double>(std::min(2 * r + 1, std::max(size.x(), 1)));
  // planner_rows' memory per part and column: the ring's rows of moments and extremes, and one
  // row's column sums, prefix sums, fits and extremes.
  const double ring_bytes = window_rows * (kRowMoments * sizeof(double) + 2 * sizeof(float));
  const double row_bytes = (kMoments + kRowMoments + 2) * sizeof(double) + 3 * sizeof(float);
  if ((ring_bytes + row_bytes) * size.y() > 1e9) {
    throw std::invalid_argument("add_traversability_layers: the sums of a window's " +
                                detail::number_text(window_rows) + " rows of " + std::to_string(size.y()) +
                                " cells would need over 1 GB; use a coarser resolution or a smaller footprint");
  }
  for (const char* name : {"step", "slope", "roughness", "traversability"}) {
    if (!map.exists(name)) map.add(name);
  }
  const PlannerData d{map.get(height_layer).data(), map.exists("clearance") ? map.get("clearance").data() : nullptr,
                      map.get("step").data(),       map.get("slope").data(),
                      map.get("roughness").data(),  map.get("traversability").data()};
  const std::size_t cells = map.geometry().num_cells();
  if (cells == 0) return;
  const StorageOrder order(size, start);
  const auto rows = static_cast<std::size_t>(size.x()), n = static_cast<std::size_t>(size.y());
  // Heights relative to the first known one in map order keep the sums of squares small (and
  // the layers the same bits whatever the storage order).
  double reference = std::numeric_limits<double>::quiet_NaN();
  for (std::size_t gi = 0; gi < rows && std::isnan(reference); ++gi) {
    for (std::size_t gj = 0; gj < n && std::isnan(reference); ++gj) {
      const float h = d.height[order.row[gi] + order.column[gj]];
      if (std::isfinite(h)) reference = h;
    }
  }
  const int parts = detail::fixed_parts(cells, 16384);
  detail::for_each_part(num_threads, parts, [&](int part) {
    const auto [begin, end] = detail::part_range(rows, part, parts);
    planner_rows(d, order, reference, r, resolution, tp, begin, end);
  });
}

}  // namespace terracube
