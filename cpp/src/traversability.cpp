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

/// The sums over a set of known cells that a least-squares plane needs: x, y the geometric cell
/// indices, z the height relative to a reference. x and y sums are whole numbers, exact in double.
struct Moments {
  double n = 0, x = 0, y = 0, z = 0, xx = 0, xy = 0, yy = 0, xz = 0, yz = 0, zz = 0;

  void add(double cx, double cy, double cz) {
    n += 1.0;
    x += cx;
    y += cy;
    z += cz;
    xx += cx * cx;
    xy += cx * cy;
    yy += cy * cy;
    xz += cx * cz;
    yz += cy * cz;
    zz += cz * cz;
  }
  Moments& operator+=(const Moments& o) {
    n += o.n, x += o.x, y += o.y, z += o.z, xx += o.xx, xy += o.xy, yy += o.yy, xz += o.xz, yz += o.yz, zz += o.zz;
    return *this;
  }
  Moments& operator-=(const Moments& o) {
    n -= o.n, x -= o.x, y -= o.y, z -= o.z, xx -= o.xx, xy -= o.xy, yy -= o.yy, xz -= o.xz, yz -= o.yz, zz -= o.zz;
    return *this;
  }
  Moments operator-(const Moments& o) const {
    return {n - o.n, x - o.x, y - o.y, z - o.z, xx - o.xx, xy - o.xy, yy - o.yy, xz - o.xz, yz - o.yz, zz - o.zz};
  }
};

/// The moments of geometric row `x` summed over the windows [j - r, j + r] clipped to the row, from
/// differences of prefix sums, into sums[0, n), and each window's lowest and highest height into
/// lowest[0, n) and highest[0, n) (+inf and -inf when all unknown). `padded` holds the row's n
/// heights in map order (NaN unknown; the moments take them relative to `reference`) between r
/// NaNs on each side, so that every window reads 2 r + 1 of them: loops without bounds to clip,
/// which the compiler vectorises.
void row_windows(const std::vector<float>& padded, double x, double reference, int r, std::vector<Moments>& prefix,
                 Moments* sums, float* lowest, float* highest) {
  const int n = static_cast<int>(padded.size()) - 2 * r;
  const float* z = padded.data() + r;
  prefix[0] = Moments();
  for (int j = 0; j < n; ++j) {
    prefix[j + 1] = prefix[j];
    if (!std::isnan(z[j])) prefix[j + 1].add(x, j, z[j] - reference);
  }
  for (int j = 0; j < n; ++j) sums[j] = prefix[std::min(j + r, n - 1) + 1] - prefix[std::max(j - r, 0)];
  std::fill(lowest, lowest + n, kInfF);
  std::fill(highest, highest + n, -kInfF);
  for (int d = -r; d <= r; ++d) {
    for (int j = 0; j < n; ++j) {  // std::min/max keep the first argument against NaN
      lowest[j] = std::min(lowest[j], z[j + d]);
      highest[j] = std::max(highest[j], z[j + d]);
    }
  }
}

/// The least-squares plane z = a x + b y + c of a window from its moments (x, y in cells): the
/// gradient |(a, b)| per cell and the RMS vertical residual; invalid for collinear cells.
struct PlaneFit {
  bool valid = false;
  double gradient = 0.0, roughness = 0.0;
};
PlaneFit fit_plane(const Moments& m) {
  const double w = 1.0 / m.n;  // the means and covariances of the window's cells
  const double mx = m.x * w, my = m.y * w, mz = m.z * w;
  const double cxx = m.xx * w - mx * mx, cxy = m.xy * w - mx * my, cyy = m.yy * w - my * my;
  const double cxz = m.xz * w - mx * mz, cyz = m.yz * w - my * mz, czz = m.zz * w - mz * mz;
  const double det = cxx * cyy - cxy * cxy;
  PlaneFit fit;
  if (!(det > 1e-9)) return fit;
  const double a = (cyy * cxz - cxy * cyz) / det, b = (cxx * cyz - cxy * cxz) / det;
  fit.valid = true;
  fit.gradient = std::sqrt(a * a + b * b);
  fit.roughness = std::sqrt(std::max(czz - a * cxz - b * cyz, 0.0));
  return fit;
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
    if (slope > tp_.max_slope_rad || step > tp_.max_step_m || roughness > tp_.max_roughness_m ||
        clearance < tp_.min_clearance_m) {
      return 0.0F;
    }
    // In [0, 1] as the formula is; the clamp holds it there when weights near the smallest double
    // (1e-320) lose the precision that keeps the normalised terms' sum at most 1.
    return static_cast<float>(std::clamp(1.0 - (slope_ * slope + step_ * step + roughness_ * roughness), 0.0, 1.0));
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

/// The windows of the cells of one geometric row, per column: the moments summed over the window
/// and its lowest and highest height.
struct RowWindows {
  const std::vector<Moments>& sums;
  const std::vector<float>& lowest;
  const std::vector<float>& highest;
};

/// Each known (finite) cell of geometric row `gi`: its window's step, plane fit and traversability.
void fit_row(const PlannerData& d, const StorageOrder& order, const RowWindows& w, std::size_t gi, double resolution,
             int min_window_cells, const TraversabilityCost& cost) {
  const std::size_t n = order.column.size();
  for (std::size_t gj = 0; gj < n; ++gj) {
    const std::size_t cell = order.row[gi] + order.column[gj];
    float* out[] = {d.step + cell, d.slope + cell, d.roughness + cell, d.traversability + cell};
    for (float* value : out) *value = kNaN;
    if (!std::isfinite(d.height[cell])) continue;
    *out[0] = w.highest[gj] - w.lowest[gj];
    const Moments& window = w.sums[gj];
    if (window.n < min_window_cells) continue;
    const PlaneFit fit = fit_plane(window);
    if (!fit.valid) continue;
    const float slope = std::atan(static_cast<float>(fit.gradient / resolution));  // float: the layer's type
    *out[1] = slope;
    *out[2] = static_cast<float>(fit.roughness);
    const float clearance = d.clearance != nullptr ? d.clearance[cell] : kInfF;
    *out[3] = cost(slope, *out[0], fit.roughness, clearance);
  }
}

/// The planner layers of the cells of geometric rows [begin, end). The windows slide down the
/// rows: each row's window sums and extremes along y (row_windows) enter a ring of the window's
/// rows (row a in slot a mod slots) and the moments a running sum per column as the window
/// reaches them, and leave it as it passes them, so a window's moments cost the same whatever its
/// size and the memory is that of the window's rows, not the map's. A part starts its sums
/// afresh: the same bits whatever the number of threads.
void planner_rows(const PlannerData& d, const StorageOrder& order, double reference, int r, double resolution,
                  const TraversabilityParams& tp, std::size_t begin, std::size_t end) {
  if (begin == end) return;  // more parts than rows (a map of a few long rows)
  const int rows = static_cast<int>(order.row.size());
  const std::size_t n = order.column.size();
  const int slots = static_cast<int>(std::min<std::int64_t>(2 * std::int64_t{r} + 1, rows));
  std::vector<Moments> ring(static_cast<std::size_t>(slots) * n), sums(n), row_prefix(n + 1);
  std::vector<float> lowest_ring(static_cast<std::size_t>(slots) * n), highest_ring(lowest_ring.size());
  std::vector<float> lowest(n), highest(n);
  std::vector<float> padded(n + 2 * static_cast<std::size_t>(r), kNaN);
  const auto slot = [&](int a) { return static_cast<std::size_t>(a % slots) * n; };
  const auto enter = [&](int a) {
    for (std::size_t gj = 0; gj < n; ++gj) {
      const float h = d.height[order.row[static_cast<std::size_t>(a)] + order.column[gj]];
      padded[r + gj] = std::isfinite(h) ? h : kNaN;  // +-inf heights are unknown too
    }
    const std::size_t s = slot(a);
    row_windows(padded, a, reference, r, row_prefix, ring.data() + s, lowest_ring.data() + s, highest_ring.data() + s);
    for (std::size_t gj = 0; gj < n; ++gj) sums[gj] += ring[s + gj];
  };
  const auto leave = [&](int a) {
    for (std::size_t gj = 0; gj < n; ++gj) sums[gj] -= ring[slot(a) + gj];
  };
  const TraversabilityCost cost(tp);
  const int first = static_cast<int>(begin);
  for (int a = std::max(first - r, 0); a <= std::min(first + r, rows - 1); ++a) enter(a);
  for (int gi = first; gi < static_cast<int>(end); ++gi) {
    if (gi > first) {
      if (gi - r - 1 >= 0) leave(gi - r - 1);  // before its slot is reused
      if (gi + r <= rows - 1) enter(gi + r);
    }
    std::fill(lowest.begin(), lowest.end(), kInfF);
    std::fill(highest.begin(), highest.end(), -kInfF);
    for (int a = std::max(gi - r, 0); a <= std::min(gi + r, rows - 1); ++a) {
      const float* row_lowest = lowest_ring.data() + slot(a);
      const float* row_highest = highest_ring.data() + slot(a);
      for (std::size_t gj = 0; gj < n; ++gj) {
        lowest[gj] = std::min(lowest[gj], row_lowest[gj]);
        highest[gj] = std::max(highest[gj], row_highest[gj]);
      }
    }
    fit_row(d, order, {sums, lowest, highest}, static_cast<std::size_t>(gi), resolution, tp.min_window_cells, cost);
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
  if (window_rows * size.y() * sizeof(Moments) > 1e9) {  // the ring of planner_rows, per part
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
