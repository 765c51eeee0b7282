// 2.5D elevation maps: the cells' statistics by a counting sort of the points by cell.
#include "terracube/elevation_map.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <iomanip>
#include <iterator>
#include <limits>
#include <new>
#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "cloud_frame.hpp"
#include "number_text.hpp"
#include "parallel.hpp"

namespace terracube {

namespace {

/// The layers of the maps this thread dropped, kept for the layers of its next maps: a new layer is
/// fresh memory otherwise, and first touching it (about 2.5 us per 4 kB page on the VMs measured:
/// 1.2 ms for a KITTI map and its classes) costs more than building the map (docs/performance.md).
/// At most kKeptBytes; the most recently dropped go first to a new map, the oldest go when full.
class DroppedLayers {
 public:
  static constexpr std::size_t kKeptBytes = std::size_t{32} << 20;

  DroppedLayers() = default;
  DroppedLayers(const DroppedLayers&) = delete;
  DroppedLayers& operator=(const DroppedLayers&) = delete;
  ~DroppedLayers() { alive() = false; }

  /// This thread's, or null once it is gone (a map dropped later, at thread exit, frees its layers).
  static DroppedLayers* of_this_thread() {
    if (!alive()) return nullptr;
    thread_local DroppedLayers layers;
    return &layers;
  }

  void keep(Layer&& layer) {
    const std::size_t bytes = sizeof(float) * static_cast<std::size_t>(layer.size());
    if (bytes == 0 || bytes > kKeptBytes) return;
    for (; bytes_ + bytes > kKeptBytes; layers_.erase(layers_.begin())) {
      bytes_ -= sizeof(float) * static_cast<std::size_t>(layers_.front().size());
    }
    layers_.push_back(std::move(layer));
    bytes_ += bytes;
  }

  /// A kept layer of rows x cols cells (its values unspecified), or a new one.
  Layer take(Eigen::Index rows, Eigen::Index cols) {
    for (auto kept = layers_.rbegin(); kept != layers_.rend(); ++kept) {
      if (kept->size() != rows * cols) continue;
      Layer layer = std::move(*kept);
      layers_.erase(std::next(kept).base());
      bytes_ -= sizeof(float) * static_cast<std::size_t>(layer.size());
      layer.resize(rows, cols);  // the same number of cells: no new memory
      return layer;
    }
    return Layer(rows, cols);
  }

 private:
  /// False once this thread's DroppedLayers is destroyed: trivially destructible, valid all along.
  static bool& alive() {
    thread_local bool flag = true;
    return flag;
  }

  std::vector<Layer> layers_;
  std::size_t bytes_ = 0;
};

/// A layer of the map's size (values unspecified), from a dropped map's when this thread kept one.
Layer new_layer(const MapGeometry& geometry) {
  DroppedLayers* dropped = DroppedLayers::of_this_thread();
  return dropped != nullptr ? dropped->take(geometry.size.x(), geometry.size.y())
                            : Layer(geometry.size.x(), geometry.size.y());
}

}  // namespace

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

void ElevationMap::set_geometry(const MapGeometry& geometry) {
  if (!(geometry.resolution_m > 0.0) || !std::isfinite(geometry.resolution_m)) {
    throw std::invalid_argument("map resolution must be a positive finite length in metres");
  }
  if (!geometry.origin_m.allFinite()) throw std::invalid_argument("map origin must be finite");
  if ((geometry.size < 0).any()) throw std::invalid_argument("map size must not be negative");
  if (!layers_.empty() && (geometry.size != geometry_.size).any()) {
    throw std::invalid_argument("the map's layers are " + std::to_string(geometry_.size.x()) + " x " +
                                std::to_string(geometry_.size.y()) + " cells; a geometry of " +
                                std::to_string(geometry.size.x()) + " x " + std::to_string(geometry.size.y()) +
                                " cells would need new layers");
  }
  geometry_ = geometry;
}

ElevationMap::~ElevationMap() {
  DroppedLayers* dropped = DroppedLayers::of_this_thread();
  if (dropped == nullptr) return;
  try {
    for (auto& entry : layers_) dropped->keep(std::move(entry.second));
  } catch (const std::bad_alloc&) {  // no room to keep them: they are freed as usual
  }
}

void ElevationMap::add(const std::string& name, float value) {
  for (auto& [existing, layer] : layers_) {
    if (existing == name) {
      layer.setConstant(value);  // in place: views of the layer stay valid
      return;
    }
  }
  Layer layer = new_layer(geometry_);
  layer.setConstant(value);
  layers_.emplace_back(name, std::move(layer));
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
  const Eigen::Index nx = height.rows();
  const Eigen::Index ny = height.cols();
  Layer step(nx, ny);
  for (Eigen::Index i = 0; i < nx; ++i) {
    for (Eigen::Index j = 0; j < ny; ++j) {
      const float h = height(i, j);
      // std::max(largest, d) keeps `largest` when d is NaN (a neighbour without data).
      float largest = 0.0F;
      for (Eigen::Index a = std::max<Eigen::Index>(i - 1, 0); a <= std::min(i + 1, nx - 1); ++a) {
        for (Eigen::Index b = std::max<Eigen::Index>(j - 1, 0); b <= std::min(j + 1, ny - 1); ++b) {
          largest = std::max(largest, std::abs(height(a, b) - h));  // the cell itself adds 0
        }
      }
      step(i, j) = std::isnan(h) ? std::numeric_limits<float>::quiet_NaN() : largest;
    }
  }
  return step;
}

namespace {

/// Rows per part of the binning pass and cells per part of the statistics pass: a fixed
/// partition, so the map never depends on the number of threads (see parallel.hpp).
constexpr std::size_t kRowsPerPart = 32768;
constexpr std::size_t kCellsPerPart = 16384;
/// The cell of a row that takes no part (outside the map, not selected, NaN/Inf or cropped).
constexpr std::uint32_t kOutside = std::numeric_limits<std::uint32_t>::max();

}  // namespace

void check_elevation_params(const ElevationParams& params) {
  if (!(params.resolution_m > 0.0) || !std::isfinite(params.resolution_m) ||
      !std::isfinite(1.0 / params.resolution_m)) {
    throw std::invalid_argument("resolution must be a positive finite length in metres, got " +
                                detail::number_text(params.resolution_m));
  }
  detail::check_num_threads(params.num_threads, "ElevationParams");
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

namespace {

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
      // Closed form, no loop: first * res can round above the minimum (1.7 / 0.1 = 17, but
      // 17 * 0.1 = 1.7000000000000002), so one cell lower then. A resolution below the spacing of
      // doubles near the minimum cannot snap at all; the cell count check below refuses it.
      const double first = std::floor(extent.min[axis] / params.resolution_m);
      double origin = first * params.resolution_m;
      if (origin > extent.min[axis]) origin = (first - 1.0) * params.resolution_m;
      if (origin > extent.min[axis]) origin = extent.min[axis];
      geometry.origin_m[axis] = origin;
    }
    cells_x = std::floor((extent.max.x() - geometry.origin_m.x()) / params.resolution_m) + 1.0;
    cells_y = std::floor((extent.max.y() - geometry.origin_m.y()) / params.resolution_m) + 1.0;
  }
  if (!(cells_x * cells_y <= static_cast<double>(params.max_cells))) {
    const auto whole = [](double cells) {  // a cell count as a whole number, however large
      std::ostringstream text;
      text << std::fixed << std::setprecision(0) << cells;
      return text.str();
    };
    throw std::invalid_argument("the map would need " + whole(cells_x) + " x " + whole(cells_y) +
                                " cells, over max_cells = " + std::to_string(params.max_cells) +
                                "; use a coarser resolution, a fixed extent or a crop");
  }
  geometry.size = CellIndex(static_cast<int>(cells_x), static_cast<int>(cells_y));
  return geometry;
}

/// The row-major cell i * ny + j of a point by the formula of MapGeometry::index_of,
/// floor((coordinate - origin) / resolution) on each axis, or kOutside.
struct CellBinning {
  explicit CellBinning(const MapGeometry& geometry)
      : origin_x(geometry.origin_m.x()),
        origin_y(geometry.origin_m.y()),
        resolution(geometry.resolution_m),
        nx(geometry.size.x()),
        ny(geometry.size.y()) {}

  std::uint32_t operator()(const Eigen::Vector3d& p) const {
    const double i = (p.x() - origin_x) / resolution;
    const double j = (p.y() - origin_y) / resolution;
    // Inside the map both are >= 0, where truncation is floor (and cheaper: without SSE4.1,
    // std::floor is a call).
    const bool inside = (i >= 0.0) & (j >= 0.0) & (i < nx) & (j < ny);
    return inside ? static_cast<std::uint32_t>(i) * static_cast<std::uint32_t>(ny) + static_cast<std::uint32_t>(j)
                  : kOutside;
  }

  double origin_x, origin_y, resolution, nx, ny;
};

/// The buffers of one build, kept by the calling thread for its next build: on the VMs this
/// project is measured on, first touching fresh memory costs about 2.5 us per 4 kB page, which for
/// a scan's worth of buffers is more than the whole computation. Released after a build that
/// needed over 64 MB.
struct Workspace {
  std::vector<std::uint32_t> cell;  ///< per row: its cell, or kOutside
  std::vector<double> height;       ///< per row: its height (when it has a cell)
  /// Counting sort by cell: cell c holds heights[start[c], start[c + 1]), rows in row order.
  std::vector<std::uint32_t> start;
  std::vector<double> heights;

  void release_if_large() {
    const std::size_t bytes = 4 * (cell.capacity() + start.capacity()) + 8 * (height.capacity() + heights.capacity());
    if (bytes > (std::size_t{64} << 20)) *this = Workspace();
  }
};

Workspace& thread_workspace() {
  thread_local Workspace workspace;
  return workspace;
}

/// Bins the rows selected by `use` (null: all) in parts into `out.cell` and `out.height`; returns
/// the NaN/Inf rows among them.
template <typename Cloud>
detail::NonFiniteRows bin_rows(const Cloud& cloud, const MapGeometry& geometry, const std::uint8_t* use,
                               int num_threads, Workspace& out) {
  const CellBinning cell_of(geometry);
  out.cell.resize(cloud.size());
  out.height.resize(cloud.size());
  const int parts = detail::fixed_parts(cloud.size(), kRowsPerPart);
  std::vector<detail::NonFiniteRows> non_finite(static_cast<std::size_t>(parts));
  detail::for_each_part(num_threads, parts, [&](int part) {
    const auto [begin, end] = detail::part_range(cloud.size(), part, parts);
    std::uint32_t* cell = out.cell.data();
    double* height = out.height.data();
    cloud.with_fixed_layout([&, begin = begin, end = end](const auto& rows) {
      Eigen::Vector3d p;
      for (std::size_t row = begin; row < end; ++row) {
        cell[row] = kOutside;
        if (use != nullptr && use[row] == 0) continue;
        const int status = rows.map(row, p);
        if (status == 1) non_finite[static_cast<std::size_t>(part)].add(row);
        if (status != 0) continue;
        cell[row] = cell_of(p);
        height[row] = p.z();
      }
    });
  });
  detail::NonFiniteRows all;
  for (const detail::NonFiniteRows& rows : non_finite) all.merge(rows);
  return all;
}

/// The counting sort of the binned heights by cell (row order within a cell) into `w.start` and
/// `w.heights`.
void group_by_cell(std::size_t cells, Workspace& w) {
  // Counts go to start[c + 2]; their prefix sums make start[c + 1] the first slot of cell c, which
  // advances as its heights are placed and so ends as the first slot of cell c + 1.
  w.start.assign(cells + 2, 0);
  std::uint32_t* start = w.start.data();
  const std::uint32_t* cell = w.cell.data();
  const std::size_t rows = w.cell.size();
  for (std::size_t row = 0; row < rows; ++row) {
    if (cell[row] != kOutside) ++start[cell[row] + 2];
  }
  for (std::size_t c = 2; c < cells + 2; ++c) start[c] += start[c - 1];
  w.heights.resize(start[cells + 1]);
  double* heights = w.heights.data();
  const double* height = w.height.data();
  for (std::size_t row = 0; row < rows; ++row) {
    if (cell[row] != kOutside) heights[start[cell[row] + 1]++] = height[row];
  }
}

/// The layers build_map writes, in the order a fresh map gets them.
constexpr std::array<const char*, 6> kBuiltLayers = {"count", "min", "max", "mean", "std_dev", "discontinuity"};
using BuiltLayers = std::array<float*, kBuiltLayers.size()>;

/// The six layers of cells [begin, end). Mean and population std-dev come from the sums of the
/// elevations relative to the cell's first one, added in row order (a shifted one-pass variance:
/// with `first` one of the samples, it stays accurate at large absolute heights). Only a cell whose
/// elevations span more than the threshold can hold a longer gap: only those are looked into.
void write_cells(const Workspace& cells, std::size_t begin, std::size_t end, double discontinuity_m,
                 const BuiltLayers& layers) {
  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  const auto [count, min, max, mean, std_dev, discontinuity] = layers;
  std::vector<double> buffer;  // lowest_height_gap's
  for (std::size_t cell = begin; cell < end; ++cell) {
    const double* z = cells.heights.data() + cells.start[cell];
    const std::uint32_t n = cells.start[cell + 1] - cells.start[cell];
    count[cell] = static_cast<float>(n);
    if (n == 0) {
      min[cell] = max[cell] = mean[cell] = std_dev[cell] = discontinuity[cell] = kNaN;
      continue;
    }
    const double first = z[0];
    double lowest = first, highest = first, sum = 0.0, squares = 0.0;
    for (std::uint32_t k = 0; k < n; ++k) {
      lowest = std::min(lowest, z[k]);
      highest = std::max(highest, z[k]);
      const double d = z[k] - first;
      sum += d;
      squares += d * d;
    }
    const double offset_of_mean = sum / n;
    const double variance = std::max((squares - sum * offset_of_mean) / n, 0.0);
    // Rounding to float is monotonic: float(min z) is the least of the rounded elevations.
    min[cell] = static_cast<float>(lowest);
    max[cell] = static_cast<float>(highest);
    mean[cell] = static_cast<float>(first + offset_of_mean);
    std_dev[cell] = static_cast<float>(std::sqrt(variance));
    bool gap = false;
    if (std::isgreater(highest - lowest, discontinuity_m)) {
      gap = lowest_height_gap(z, n, discontinuity_m, buffer).has_value();
    }
    discontinuity[cell] = gap ? 1.0F : 0.0F;
  }
}

/// The map's six layers (added when missing; reused in place when refilling, so that references
/// to them stay valid), and its other layers (of an earlier use) reset to NaN.
BuiltLayers prepare_layers(ElevationMap& map) {
  BuiltLayers layers{};
  for (std::size_t k = 0; k < kBuiltLayers.size(); ++k) {
    if (!map.exists(kBuiltLayers[k])) map.add(kBuiltLayers[k], new_layer(map.geometry()));
  }
  for (const std::string& name : map.layers()) {
    const auto built = std::find(kBuiltLayers.begin(), kBuiltLayers.end(), name);
    if (built == kBuiltLayers.end()) {
      map.get(name).setConstant(std::numeric_limits<float>::quiet_NaN());
    } else {
      layers[static_cast<std::size_t>(built - kBuiltLayers.begin())] = map.get(name).data();
    }
  }
  return layers;
}

/// Builds into `*into` (see build_elevation_map_into) when given, else into the returned map: bins
/// the rows, groups their heights by cell and writes every cell's statistics.
template <typename Cloud>
ElevationMap build_map(const Cloud& cloud, const ElevationParams& params, const std::vector<std::uint8_t>* use,
                       ElevationMap* into) {
  const std::uint8_t* selected = use != nullptr ? use->data() : nullptr;
  detail::CloudExtent extent;
  if (!params.origin_m) {  // auto extent: the selected points' bounding box
    extent = detail::extent_of_rows(cloud, 0, cloud.size(), selected);
    if (extent.non_finite.count > 0 && !params.drop_non_finite) {
      detail::throw_non_finite_rows(extent.non_finite, cloud.size());
    }
  }
  const MapGeometry geometry = make_geometry(params, extent);
  if (into != nullptr && !into->layers().empty() && (into->geometry().size != geometry.size).any()) {
    throw std::invalid_argument("cannot refill a map of " + std::to_string(into->geometry().size.x()) + " x " +
                                std::to_string(into->geometry().size.y()) + " cells with a build of " +
                                std::to_string(geometry.size.x()) + " x " + std::to_string(geometry.size.y()) +
                                " cells: give a fixed extent (origin and size) of the map's size");
  }
  const std::size_t cells = geometry.num_cells();
  if (cells >= kOutside) throw std::invalid_argument("build_elevation_map handles maps of fewer than 2^32 - 1 cells");

  Workspace& workspace = thread_workspace();
  struct ReleaseOnExit {
    Workspace& workspace;
    ~ReleaseOnExit() { workspace.release_if_large(); }
  } release_on_exit{workspace};
  const detail::NonFiniteRows non_finite = bin_rows(cloud, geometry, selected, params.num_threads, workspace);
  if (non_finite.count > 0 && !params.drop_non_finite) detail::throw_non_finite_rows(non_finite, cloud.size());
  group_by_cell(cells, workspace);

  // Only now, past every check, is the map touched: a call that throws leaves it unchanged.
  ElevationMap fresh;
  if (into != nullptr) {
    into->set_geometry(geometry);
  } else {
    fresh = ElevationMap(geometry);
  }
  const BuiltLayers layers = prepare_layers(into != nullptr ? *into : fresh);
  const int parts = detail::fixed_parts(cells, kCellsPerPart);
  detail::for_each_part(params.num_threads, parts, [&](int part) {
    const auto [begin, end] = detail::part_range(cells, part, parts);
    write_cells(workspace, begin, end, params.discontinuity_m, layers);
  });
  return fresh;
}

template <typename Scalar>
ElevationMap build_impl(const PointsView<Scalar>& points, const ElevationParams& params,
                        const std::vector<std::uint8_t>* use, ElevationMap* into = nullptr) {
  check_elevation_params(params);
  if (points.size > 0 && points.data == nullptr) throw std::invalid_argument("points view has no data");
  if (points.size >= std::numeric_limits<std::uint32_t>::max()) {
    throw std::invalid_argument("build_elevation_map handles fewer than 2^32 points per call");
  }
  if (use && use->size() != points.size) {
    throw std::invalid_argument("the point selection has " + std::to_string(use->size()) + " flags for " +
                                std::to_string(points.size) + " points");
  }
  return detail::visit_leveled(points, params.transform, params.crop,
                               [&](const auto& cloud) { return build_map(cloud, params, use, into); });
}

/// The "overhang_min" and "clearance" layers of a map of the kept points: the lowest overhang
/// point of each cell, then the ground under it (the highest kept point below it; a map cell can
/// straddle two cube columns, so a kept wall may rise above an overhang that its neighbouring
/// column collapsed, and measuring from it would give a negative clearance).
template <typename Cloud>
void add_clearance(const Cloud& cloud, const std::vector<std::uint8_t>& overhang, ElevationMap& map) {
  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  const MapGeometry& geometry = map.geometry();
  const CellBinning cell_of(geometry);
  Layer lowest_overhang = Layer::Constant(geometry.size.x(), geometry.size.y(), kNaN);
  Layer under = Layer::Constant(geometry.size.x(), geometry.size.y(), kNaN);
  float* lowest = lowest_overhang.data();
  float* highest_under = under.data();
  Eigen::Vector3d p;
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (!overhang[row] || cloud.map(row, p) != 0) continue;
    const std::uint32_t cell = cell_of(p);
    if (cell == kOutside) continue;
    const auto z = static_cast<float>(p.z());
    if (std::isnan(lowest[cell]) || z < lowest[cell]) lowest[cell] = z;
  }
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (overhang[row] || cloud.map(row, p) != 0) continue;
    const std::uint32_t cell = cell_of(p);
    if (cell == kOutside || !(p.z() < lowest[cell])) continue;  // also skips cells without overhang
    if (std::isnan(highest_under[cell]) || p.z() > highest_under[cell]) highest_under[cell] = static_cast<float>(p.z());
  }
  // NaN without a kept point (unknown), +inf without an overhang, else the overhang's height over
  // the ground under it (NaN when no kept point lies below it).
  const Layer& top = map.get("max");
  Layer clearance(top.rows(), top.cols());
  for (Eigen::Index k = 0; k < top.size(); ++k) {
    const float gap = lowest[k] - highest_under[k];
    const float value = std::isnan(lowest[k]) ? std::numeric_limits<float>::infinity() : gap;
    clearance.data()[k] = std::isnan(top.data()[k]) ? kNaN : value;
  }
  map.add("overhang_min", std::move(lowest_overhang));
  map.add("clearance", std::move(clearance));
}

template <typename Scalar>
OverhangFreeMap overhang_free_impl(const PointsView<Scalar>& points, const CollapseParams& collapse,
                                   const ElevationParams& elevation, const PointsView<double>& no_returns) {
  check_elevation_params(elevation);  // before any geometry is derived from it
  OverhangFreeMap out;
  out.collapse = collapse_overhangs(points, collapse, no_returns);
  ElevationParams params = elevation;
  params.transform = collapse.transform;
  params.crop = collapse.crop;
  params.drop_non_finite = collapse.drop_non_finite;
  // The geometry follows all points (kept and overhang) unless fixed, so that the raw DEM of the
  // same parameters aligns.
  if (!params.origin_m) {
    const detail::CloudExtent extent =
        detail::visit_leveled(points, params.transform, params.crop,
                              [&](const auto& cloud) { return detail::measure_extent(cloud, params.drop_non_finite); });
    if (extent.num_used > 0) {  // an empty cloud keeps the auto (empty) extent
      const MapGeometry geometry = make_geometry(params, extent);
      params.origin_m = geometry.origin_m;
      params.size = geometry.size;
    }
  }
  std::vector<std::uint8_t> kept(out.collapse.overhang.size());
  for (std::size_t i = 0; i < kept.size(); ++i) kept[i] = out.collapse.overhang[i] ? 0 : 1;
  out.map = build_impl(points, params, &kept);
  detail::visit_leveled(points, params.transform, params.crop,
                        [&](const auto& cloud) { add_clearance(cloud, out.collapse.overhang, out.map); });
  out.map.add("step", step_layer(out.map.get("max")));
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
void build_elevation_map_into(ElevationMap& map, const PointsView<float>& points, const ElevationParams& params,
                              const std::vector<std::uint8_t>* use) {
  build_impl(points, params, use, &map);
}
void build_elevation_map_into(ElevationMap& map, const PointsView<double>& points, const ElevationParams& params,
                              const std::vector<std::uint8_t>* use) {
  build_impl(points, params, use, &map);
}
OverhangFreeMap build_overhang_free_map(const PointsView<float>& points, const CollapseParams& collapse,
                                        const ElevationParams& elevation, const PointsView<double>& no_returns) {
  return overhang_free_impl(points, collapse, elevation, no_returns);
}
OverhangFreeMap build_overhang_free_map(const PointsView<double>& points, const CollapseParams& collapse,
                                        const ElevationParams& elevation, const PointsView<double>& no_returns) {
  return overhang_free_impl(points, collapse, elevation, no_returns);
}

std::optional<HeightGap> lowest_height_gap(const double* heights, std::size_t n, double threshold,
                                           std::vector<double>& buffer) {
  detail::check_positive(threshold, "lowest_height_gap: threshold_m");
  if (n == 0) return std::nullopt;
  double lowest = heights[0], highest = heights[0];
  for (std::size_t k = 0; k < n; ++k) {
    if (!std::isfinite(heights[k])) throw std::invalid_argument("lowest_height_gap: the heights must be finite");
    lowest = std::min(lowest, heights[k]);
    highest = std::max(highest, heights[k]);
  }
  const double per_metre = 2.0 / threshold;
  const double last = (highest - lowest) * per_metre;  // the highest bucket (NaN or inf: sort)
  if (!(last < 2.0 * static_cast<double>(n))) {
    buffer.resize(n);
    for (std::size_t k = 0; k < n; ++k) buffer[k] = heights[k];
    std::sort(buffer.begin(), buffer.end());
    for (std::size_t k = 1; k < n; ++k) {
      if (buffer[k] - buffer[k - 1] > threshold) return HeightGap{buffer[k - 1], buffer[k]};
    }
    return std::nullopt;
  }
  const auto buckets = static_cast<std::size_t>(last) + 1;
  buffer.assign(2 * buckets, std::numeric_limits<double>::quiet_NaN());  // lowest, highest per bucket
  for (std::size_t k = 0; k < n; ++k) {
    const double z = heights[k];
    double* bucket = &buffer[2 * static_cast<std::size_t>((z - lowest) * per_metre)];
    bucket[0] = std::isnan(bucket[0]) ? z : std::min(bucket[0], z);
    bucket[1] = std::isnan(bucket[1]) ? z : std::max(bucket[1], z);
  }
  double below = buffer[1];  // the highest height of the last non-empty bucket (bucket 0 holds `lowest`)
  for (std::size_t b = 1; b < buckets; ++b) {
    if (std::isnan(buffer[2 * b])) continue;
    if (buffer[2 * b] - below > threshold) return HeightGap{below, buffer[2 * b]};
    below = buffer[2 * b + 1];
  }
  return std::nullopt;
}

}  // namespace terracube
