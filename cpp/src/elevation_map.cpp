#include "terracube/elevation_map.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "cloud_frame.hpp"

namespace terracube {

std::optional<CellIndex> MapGeometry::index_of(const Eigen::Vector2d& position) const {
  const Eigen::Vector2d cells = (position - origin_m) / resolution_m;
  if (!(cells.x() >= 0.0 && cells.y() >= 0.0 && cells.x() < size.x() && cells.y() < size.y())) return std::nullopt;
  return CellIndex(static_cast<int>(std::floor(cells.x())), static_cast<int>(std::floor(cells.y())));
}

ElevationMap::ElevationMap(const MapGeometry& geometry) : geometry_(geometry) {
  if (!(geometry.resolution_m > 0.0) || !std::isfinite(geometry.resolution_m)) {
    throw std::invalid_argument("map resolution must be a positive finite length in metres");
  }
  if ((geometry.size < 0).any()) throw std::invalid_argument("map size must not be negative");
}

void ElevationMap::add(const std::string& name, float value) {
  add(name, Layer::Constant(geometry_.size.x(), geometry_.size.y(), value));
}

void ElevationMap::add(const std::string& name, Layer data) {
  if (data.rows() != geometry_.size.x() || data.cols() != geometry_.size.y()) {
    throw std::invalid_argument("layer '" + name + "' is " + std::to_string(data.rows()) + " x " +
                                std::to_string(data.cols()) + " cells, the map is " +
                                std::to_string(geometry_.size.x()) + " x " + std::to_string(geometry_.size.y()));
  }
  for (auto& [existing, layer] : layers_) {
    if (existing == name) {
      layer.array() = data.array();  // in place: views of the old layer stay valid
      return;
    }
  }
  layers_.emplace_back(name, std::move(data));
}

bool ElevationMap::exists(const std::string& name) const {
  return std::any_of(layers_.begin(), layers_.end(), [&](const auto& entry) { return entry.first == name; });
}

const Layer& ElevationMap::get(const std::string& name) const {
  for (const auto& [existing, layer] : layers_) {
    if (existing == name) return layer;
  }
  std::string names;
  for (const auto& entry : layers_) names += (names.empty() ? "" : ", ") + entry.first;
  throw std::out_of_range("elevation map has no layer '" + name + "' (layers: " + names + ")");
}

Layer& ElevationMap::get(const std::string& name) {
  return const_cast<Layer&>(static_cast<const ElevationMap&>(*this).get(name));
}

std::vector<std::string> ElevationMap::layers() const {
  std::vector<std::string> names;
  for (const auto& entry : layers_) names.push_back(entry.first);
  return names;
}

Layer step_layer(const Layer& height) {
  const auto nx = height.rows();
  const auto ny = height.cols();
  Layer step = Layer::Constant(nx, ny, std::numeric_limits<float>::quiet_NaN());
  for (Eigen::Index i = 0; i < nx; ++i) {
    for (Eigen::Index j = 0; j < ny; ++j) {
      const float h = height(i, j);
      if (std::isnan(h)) continue;
      float largest = 0.0F;
      for (Eigen::Index di = -1; di <= 1; ++di) {
        for (Eigen::Index dj = -1; dj <= 1; ++dj) {
          const Eigen::Index a = i + di;
          const Eigen::Index b = j + dj;
          if ((di == 0 && dj == 0) || a < 0 || b < 0 || a >= nx || b >= ny) continue;
          const float other = height(a, b);
          if (!std::isnan(other)) largest = std::max(largest, std::abs(other - h));
        }
      }
      step(i, j) = largest;
    }
  }
  return step;
}

namespace {

void check_elevation_params(const ElevationParams& params) {
  if (!(params.resolution_m > 0.0) || !std::isfinite(params.resolution_m) ||
      !std::isfinite(1.0 / params.resolution_m)) {
    throw std::invalid_argument("resolution must be a positive finite length in metres, got " +
                                std::to_string(params.resolution_m));
  }
  if (!(params.discontinuity_m > 0.0) || !std::isfinite(params.discontinuity_m)) {
    throw std::invalid_argument("discontinuity must be a positive finite length in metres");
  }
  if (params.origin_m.has_value() != params.size.has_value()) {
    throw std::invalid_argument("give both origin and size for a fixed map extent, or neither");
  }
  if (params.origin_m && !params.origin_m->allFinite()) throw std::invalid_argument("map origin must be finite");
  if (params.size && (params.size->x() <= 0 || params.size->y() <= 0)) {
    throw std::invalid_argument("map size must be at least 1 x 1 cells");
  }
  detail::check_rigid_transform(params.transform, "transform");
  detail::check_crop(params.crop);
}

MapGeometry make_geometry(const ElevationParams& params, const detail::CloudExtent& extent) {
  MapGeometry geometry;
  geometry.resolution_m = params.resolution_m;
  double cells_x = 0.0;
  double cells_y = 0.0;
  if (params.origin_m) {
    geometry.origin_m = *params.origin_m;
    cells_x = params.size->x();
    cells_y = params.size->y();
  } else if (extent.num_used > 0) {
    // Snap outwards to whole cells so that every point falls inside.
    for (int axis = 0; axis < 2; ++axis) {
      double origin = std::floor(extent.min[axis] / params.resolution_m) * params.resolution_m;
      // first * res can round above the minimum (1.7 / 0.1 = 17, 17 * 0.1 = 1.7000000000000002).
      while (origin > extent.min[axis]) origin -= params.resolution_m;
      geometry.origin_m[axis] = origin;
    }
    cells_x = std::floor((extent.max.x() - geometry.origin_m.x()) / params.resolution_m) + 1.0;
    cells_y = std::floor((extent.max.y() - geometry.origin_m.y()) / params.resolution_m) + 1.0;
  }
  if (!(cells_x * cells_y <= static_cast<double>(params.max_cells))) {
    throw std::invalid_argument("the map would need " + std::to_string(cells_x) + " x " + std::to_string(cells_y) +
                                " cells, over max_cells = " + std::to_string(params.max_cells) +
                                "; use a coarser resolution, a fixed extent or a crop");
  }
  geometry.size = CellIndex(static_cast<int>(cells_x), static_cast<int>(cells_y));
  return geometry;
}

/// Exact cell coordinate along one axis: floor((coordinate - origin) / resolution), the formula of
/// MapGeometry::index_of. Dividing costs several cycles per point, so the quotient is first
/// estimated by multiplying with 1 / resolution: estimate and quotient differ by at most three
/// roundings (|q| * 3.4e-16 < 1e-6 for the |q| < 2^31 + 1 that matter), so their floors agree
/// unless the estimate lies within 2^-16 of a whole number; only such points (and points on cell
/// borders, the same case) are divided.
class AxisBinning {
 public:
  AxisBinning(double origin_m, double resolution_m, std::int64_t cells)
      : origin_(origin_m),
        resolution_(resolution_m),
        inverse_(1.0 / resolution_m),
        cells_(cells),
        upper_(static_cast<double>(cells) + 1.0) {}

  /// The cell index in [0, cells), or -1 when the coordinate lies outside.
  std::int64_t operator()(double coordinate) const {
    const double offset = coordinate - origin_;
    const double estimate = offset * inverse_;
    if (!(estimate > -1.0 && estimate < upper_)) return -1;  // outside by about a cell or more (or NaN)
    // estimate + 1 lies in (0, cells + 2), where truncation is floor. Its rounding is far below
    // the margin, so it too can only move the floor when the exact path takes over.
    const double shifted = estimate + 1.0;
    const auto whole = static_cast<std::int64_t>(shifted);
    const double fraction = shifted - static_cast<double>(whole);
    constexpr double kMargin = 1.0 / 65536.0;
    if (!(fraction > kMargin && fraction < 1.0 - kMargin)) return exact(offset);
    const std::int64_t index = whole - 1;
    return index < cells_ ? index : -1;  // index >= -1 here
  }

  /// The defining formula, division and floor.
  std::int64_t exact(double offset) const {
    const double cell = std::floor(offset / resolution_);
    return cell >= 0.0 && cell < static_cast<double>(cells_) ? static_cast<std::int64_t>(cell) : -1;
  }

 private:
  double origin_;
  double resolution_;
  double inverse_;
  std::int64_t cells_;
  double upper_;
};

/// Whether the mapped z of every row of a cloud is exactly a float: a float cloud, not transformed.
template <typename Cloud>
struct ExactFloatHeights : std::false_type {};
template <bool kCrop>
struct ExactFloatHeights<detail::LeveledCloud<float, false, kCrop>> : std::true_type {};

/// values[k] = sqrt(values[k]) for values that are >= 0 or NaN. Packed SSE2 square roots where
/// available: std::sqrt's errno handling keeps compilers from vectorising the plain loop.
void square_roots(double* values, std::size_t n) {
  std::size_t k = 0;
#if defined(__SSE2__)
  for (; k + 2 <= n; k += 2) _mm_storeu_pd(values + k, _mm_sqrt_pd(_mm_loadu_pd(values + k)));
#endif
  for (; k < n; ++k) values[k] = std::sqrt(values[k]);
}

/// Per-thread scratch buffers of build_map, kept between calls: a fresh multi-megabyte buffer
/// costs a page fault per 4 kB page on first touch, which on a fresh map would take longer than
/// the whole computation. Buffers over kKeepBytes are released after the call.
struct BuildScratch {
  std::vector<std::uint32_t> cell_of_point, count, wide_cells, slot;
  std::vector<double> sum, squares, heights, lowest, highest;
  std::vector<std::size_t> offset, next;

  static constexpr std::size_t kKeepBytes = std::size_t{32} << 20;

  void release_if_large() {
    const std::size_t bytes =
        4 * (cell_of_point.capacity() + count.capacity() + wide_cells.capacity() + slot.capacity()) +
        8 * (sum.capacity() + squares.capacity() + heights.capacity() + lowest.capacity() + highest.capacity() +
             offset.capacity() + next.capacity());
    if (bytes > kKeepBytes) *this = BuildScratch();
  }
};

BuildScratch& thread_scratch() {
  thread_local BuildScratch scratch;
  return scratch;
}

template <typename Cloud>
ElevationMap build_map(const Cloud& cloud, const ElevationParams& params, const std::vector<std::uint8_t>* use) {
  if (use && use->size() != cloud.size()) {
    throw std::invalid_argument("the point selection has " + std::to_string(use->size()) + " flags for " +
                                std::to_string(cloud.size()) + " points");
  }
  const auto selected = [&](std::size_t row) { return use == nullptr || (*use)[row] != 0; };
  const auto throw_non_finite = [&](const detail::CloudExtent& extent) {
    throw std::invalid_argument(std::to_string(extent.num_non_finite) + " of " + std::to_string(cloud.size()) +
                                " point rows contain NaN or Inf (first at row " +
                                std::to_string(extent.first_non_finite_row) +
                                "); clean the cloud or set drop_non_finite=True to drop them");
  };
  // Pass 1 (auto extent only): extent of the selected points and NaN/Inf check. With a fixed
  // extent the check happens in pass 2.
  detail::CloudExtent extent;
  Eigen::Vector3d p;
  const bool fixed_extent = params.origin_m.has_value();
  if (!fixed_extent) {
    for (std::size_t row = 0; row < cloud.size(); ++row) {
      if (!selected(row)) continue;
      const int status = cloud.map(row, p);
      if (status == 1) {
        if (extent.num_non_finite++ == 0) extent.first_non_finite_row = row;
        continue;
      }
      if (status == 2) continue;
      extent.min = extent.min.cwiseMin(p);
      extent.max = extent.max.cwiseMax(p);
      ++extent.num_used;
    }
    if (extent.num_non_finite > 0 && !params.drop_non_finite) throw_non_finite(extent);
  }
  ElevationMap map(make_geometry(params, extent));
  const MapGeometry& geometry = map.geometry();
  const std::size_t cells = geometry.num_cells();
  const auto nx = static_cast<std::int64_t>(geometry.size.x());
  const auto ny = static_cast<std::int64_t>(geometry.size.y());

  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  constexpr double kInfinity = std::numeric_limits<double>::infinity();
  Layer count_layer(nx, ny), min(nx, ny), max(nx, ny), mean_layer(nx, ny), std_dev(nx, ny), discontinuity(nx, ny);

  // Heights are exact floats when a float cloud is not transformed: then min and max are
  // accumulated in the float layers themselves. Otherwise in doubles, rounded at the end (rounding
  // is monotonic, so float(min z) = min float(z) either way).
  using Height = std::conditional_t<ExactFloatHeights<Cloud>::value, float, double>;
  BuildScratch& scratch = thread_scratch();
  struct ReleaseOnExit {
    BuildScratch& scratch;
    ~ReleaseOnExit() { scratch.release_if_large(); }
  } release_on_exit{scratch};
  std::vector<double>& lowest_store = scratch.lowest;
  std::vector<double>& highest_store = scratch.highest;
  Height* lowest = nullptr;
  Height* highest = nullptr;
  if constexpr (std::is_same_v<Height, float>) {
    lowest = min.data();
    highest = max.data();
  } else {
    lowest_store.resize(cells);
    highest_store.resize(cells);
    lowest = lowest_store.data();
    highest = highest_store.data();
  }
  std::fill(lowest, lowest + cells, static_cast<Height>(kInfinity));
  std::fill(highest, highest + cells, static_cast<Height>(-kInfinity));

  // Pass 2, one sweep over the points: cell of every point (row-major cell = i * ny + j) and the
  // per-cell count, sum, min and max, accumulated in place (structure of arrays, so that the
  // per-cell sweeps below vectorise).
  constexpr std::uint32_t kOutside = std::numeric_limits<std::uint32_t>::max();
  std::vector<std::uint32_t>& cell_of_point = scratch.cell_of_point;
  std::vector<std::uint32_t>& count = scratch.count;
  std::vector<double>& sum = scratch.sum;
  cell_of_point.resize(cloud.size());
  count.assign(cells, 0);
  sum.assign(cells, 0.0);
  const AxisBinning along_x(geometry.origin_m.x(), geometry.resolution_m, nx);
  const AxisBinning along_y(geometry.origin_m.y(), geometry.resolution_m, ny);
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    cell_of_point[row] = kOutside;
    if (!selected(row)) continue;
    const int status = cloud.map(row, p);
    if (status != 0) {
      if (status == 1 && extent.num_non_finite++ == 0) extent.first_non_finite_row = row;
      continue;
    }
    const std::int64_t i = along_x(p.x());
    const std::int64_t j = along_y(p.y());
    if (i < 0 || j < 0) continue;
    const auto cell = static_cast<std::size_t>(i * ny + j);
    cell_of_point[row] = static_cast<std::uint32_t>(cell);
    const auto z = static_cast<Height>(p.z());
    ++count[cell];
    sum[cell] += p.z();
    lowest[cell] = z < lowest[cell] ? z : lowest[cell];
    highest[cell] = z > highest[cell] ? z : highest[cell];
  }
  if (fixed_extent && extent.num_non_finite > 0 && !params.drop_non_finite) throw_non_finite(extent);

  // Discontinuity: only a cell whose elevations span more than the threshold can hold a gap
  // longer than it (rounding is monotonic, so this holds for the computed differences too). Those
  // (few) "wide" cells have their elevations gathered in pass 3 and sorted; the others get 0.
  std::size_t num_wide = 0;  // counted first by a loop that vectorises
  const auto wide = [&](std::size_t cell) {
    return std::isgreater(static_cast<double>(highest[cell]) - static_cast<double>(lowest[cell]),
                          params.discontinuity_m);  // false for empty cells: -inf - inf
  };
  for (std::size_t cell = 0; cell < cells; ++cell) num_wide += wide(cell);
  std::vector<std::uint32_t>& wide_cells = scratch.wide_cells;  // cell of each wide cell
  std::vector<std::uint32_t>& slot = scratch.slot;              // per cell: its place in wide_cells, or kOutside
  std::vector<std::size_t>& offset = scratch.offset;            // the wide cells' elevations, counting-sorted by cell
  std::vector<double>& heights = scratch.heights;
  wide_cells.clear();
  if (num_wide > 0) {
    wide_cells.reserve(num_wide);
    for (std::size_t cell = 0; cell < cells; ++cell) {
      if (wide(cell)) wide_cells.push_back(static_cast<std::uint32_t>(cell));
    }
    slot.assign(cells, kOutside);
    offset.assign(num_wide + 1, 0);
    for (std::size_t k = 0; k < num_wide; ++k) {
      slot[wide_cells[k]] = static_cast<std::uint32_t>(k);
      offset[k + 1] = offset[k] + count[wide_cells[k]];
    }
    heights.resize(offset.back());
  }

  // Means, then pass 3: the two-pass variance (no cancellation at large absolute heights; the sums
  // run in point order, as numpy's bincount does) and the wide cells' elevations.
  std::vector<double>& mean = sum;  // in place
  for (std::size_t cell = 0; cell < cells; ++cell) mean[cell] /= static_cast<double>(count[cell]);
  std::vector<double>& squares = scratch.squares;
  squares.assign(cells, 0.0);
  if (num_wide == 0) {
    for (std::size_t row = 0; row < cloud.size(); ++row) {
      const std::uint32_t cell = cell_of_point[row];
      if (cell == kOutside) continue;
      cloud.map_unchecked(row, p);
      const double deviation = p.z() - mean[cell];
      squares[cell] += deviation * deviation;
    }
  } else {
    std::vector<std::size_t>& next = scratch.next;
    next.assign(offset.begin(), offset.end() - 1);
    for (std::size_t row = 0; row < cloud.size(); ++row) {
      const std::uint32_t cell = cell_of_point[row];
      if (cell == kOutside) continue;
      cloud.map_unchecked(row, p);
      const double deviation = p.z() - mean[cell];
      squares[cell] += deviation * deviation;
      if (slot[cell] != kOutside) heights[next[slot[cell]]++] = p.z();
    }
  }

  // The layers, NaN where a cell is empty; simple loops that vectorise (the conversions happen
  // unconditionally, so the NaN choices are plain selects).
  for (std::size_t cell = 0; cell < cells; ++cell) {
    const bool empty = count[cell] == 0;
    const float lo = static_cast<float>(lowest[cell]);
    const float hi = static_cast<float>(highest[cell]);
    count_layer.data()[cell] = static_cast<float>(count[cell]);
    min.data()[cell] = empty ? kNaN : lo;
    max.data()[cell] = empty ? kNaN : hi;
    discontinuity.data()[cell] = empty ? kNaN : 0.0F;
  }
  for (std::size_t cell = 0; cell < cells; ++cell) {
    mean_layer.data()[cell] = static_cast<float>(mean[cell]);  // 0 / 0 = NaN when empty
    squares[cell] /= static_cast<double>(count[cell]);         // the variance, NaN when empty
  }
  square_roots(squares.data(), cells);
  for (std::size_t cell = 0; cell < cells; ++cell) std_dev.data()[cell] = static_cast<float>(squares[cell]);
  for (std::size_t k = 0; k < num_wide; ++k) {
    double* begin = heights.data() + offset[k];
    double* end = heights.data() + offset[k + 1];
    std::sort(begin, end);
    bool gap = false;
    for (const double* z = begin + 1; z < end && !gap; ++z) gap = *z - *(z - 1) > params.discontinuity_m;
    discontinuity.data()[wide_cells[k]] = gap ? 1.0F : 0.0F;
  }
  map.add("count", std::move(count_layer));
  map.add("min", std::move(min));
  map.add("max", std::move(max));
  map.add("mean", std::move(mean_layer));
  map.add("std_dev", std::move(std_dev));
  map.add("discontinuity", std::move(discontinuity));
  return map;
}

template <typename Scalar>
ElevationMap build_impl(const PointsView<Scalar>& points, const ElevationParams& params,
                        const std::vector<std::uint8_t>* use) {
  check_elevation_params(params);
  if (points.size > 0 && points.data == nullptr) throw std::invalid_argument("points view has no data");
  if (points.size >= std::numeric_limits<std::uint32_t>::max()) {
    throw std::invalid_argument("build_elevation_map handles fewer than 2^32 points per call");
  }
  return detail::visit_leveled(points, params.transform, params.crop,
                               [&](const auto& cloud) { return build_map(cloud, params, use); });
}

template <typename Scalar>
OverhangFreeMap overhang_free_impl(const PointsView<Scalar>& points, const CollapseParams& collapse,
                                   const ElevationParams& elevation) {
  OverhangFreeMap out;
  out.collapse = collapse_overhangs(points, collapse);
  ElevationParams params = elevation;
  params.transform = collapse.transform;
  params.crop = collapse.crop;
  params.drop_non_finite = collapse.drop_non_finite;
  std::vector<std::uint8_t> kept(out.collapse.overhang.size());
  for (std::size_t i = 0; i < kept.size(); ++i) kept[i] = out.collapse.overhang[i] ? 0 : 1;
  // The geometry follows all points (kept and overhang) unless fixed, so both maps align.
  if (!params.origin_m) {
    const ElevationMap all = build_impl(points, params, nullptr);
    if (all.geometry().num_cells() > 0) {  // an empty cloud keeps the auto (empty) extent
      params.origin_m = all.geometry().origin_m;
      params.size = all.geometry().size;
    }
  }
  out.map = build_impl(points, params, &kept);
  const ElevationMap overhangs = build_impl(points, params, &out.collapse.overhang);
  const Layer& lowest_overhang = overhangs.get("min");
  const Layer& top = out.map.get("max");
  // The ground under an overhang: the highest kept point below the cell's lowest overhang point.
  // (A map cell can straddle two cube columns, so a kept wall may rise above an overhang that its
  // neighbouring column collapsed; measuring from it would give a negative clearance.)
  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  Layer under = Layer::Constant(top.rows(), top.cols(), kNaN);
  const MapGeometry& geometry = out.map.geometry();
  detail::visit_leveled(points, params.transform, params.crop, [&](const auto& cloud) {
    Eigen::Vector3d p;
    for (std::size_t row = 0; row < cloud.size(); ++row) {
      if (!kept[row] || cloud.map(row, p) != 0) continue;
      const auto index = geometry.index_of(p.head<2>());
      if (!index) continue;
      const float overhang = lowest_overhang(index->x(), index->y());
      if (std::isnan(overhang) || !(p.z() < overhang)) continue;
      float& highest = under(index->x(), index->y());
      if (std::isnan(highest) || p.z() > highest) highest = static_cast<float>(p.z());
    }
  });
  Layer clearance = Layer::Constant(top.rows(), top.cols(), kNaN);
  for (Eigen::Index k = 0; k < top.size(); ++k) {
    if (std::isnan(top.data()[k])) continue;  // no kept point: unknown
    if (std::isnan(lowest_overhang.data()[k])) {
      clearance.data()[k] = std::numeric_limits<float>::infinity();
    } else if (!std::isnan(under.data()[k])) {
      clearance.data()[k] = lowest_overhang.data()[k] - under.data()[k];
    }
  }
  out.map.add("overhang_min", lowest_overhang);
  out.map.add("clearance", std::move(clearance));
  out.map.add("step", step_layer(top));
  return out;
}

}  // namespace

ElevationMap build_elevation_map(const PointsView<float>& points, const ElevationParams& params,
                                 const std::vector<std::uint8_t>* use) {
  return build_impl(points, params, use);
}
ElevationMap build_elevation_map(const PointsView<double>& points, const ElevationParams& params,
                                 const std::vector<std::uint8_t>* use) {
  return build_impl(points, params, use);
}
OverhangFreeMap build_overhang_free_map(const PointsView<float>& points, const CollapseParams& collapse,
                                        const ElevationParams& elevation) {
  return overhang_free_impl(points, collapse, elevation);
}
OverhangFreeMap build_overhang_free_map(const PointsView<double>& points, const CollapseParams& collapse,
                                        const ElevationParams& elevation) {
  return overhang_free_impl(points, collapse, elevation);
}

}  // namespace terracube
