#include "terracube/elevation_map.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

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

template <typename Cloud>
ElevationMap build_map(const Cloud& cloud, const ElevationParams& params, const std::vector<std::uint8_t>* use) {
  if (use && use->size() != cloud.size()) {
    throw std::invalid_argument("the point selection has " + std::to_string(use->size()) + " flags for " +
                                std::to_string(cloud.size()) + " points");
  }
  const auto selected = [&](std::size_t row) { return use == nullptr || (*use)[row] != 0; };
  // Pass 1: extent of the selected points and NaN/Inf check (the check only, for a fixed extent).
  detail::CloudExtent extent;
  Eigen::Vector3d p;
  const bool fixed_extent = params.origin_m.has_value();
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (!selected(row)) continue;
    if (fixed_extent) {
      if (cloud.map(row, p) == 1 && extent.num_non_finite++ == 0) extent.first_non_finite_row = row;
      continue;
    }
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
  if (extent.num_non_finite > 0 && !params.drop_non_finite) {
    throw std::invalid_argument(std::to_string(extent.num_non_finite) + " of " + std::to_string(cloud.size()) +
                                " point rows contain NaN or Inf (first at row " +
                                std::to_string(extent.first_non_finite_row) +
                                "); clean the cloud or set drop_non_finite=True to drop them");
  }
  ElevationMap map(make_geometry(params, extent));
  const MapGeometry& geometry = map.geometry();
  const std::size_t cells = geometry.num_cells();
  const auto nx = static_cast<std::int64_t>(geometry.size.x());
  const auto ny = static_cast<std::int64_t>(geometry.size.y());

  // Pass 2: cell of every point (row-major cell = i * ny + j) and a histogram of the cells.
  constexpr std::uint32_t kOutside = std::numeric_limits<std::uint32_t>::max();
  std::vector<std::uint32_t> cell_of_point(cloud.size(), kOutside);
  std::vector<std::size_t> offset(cells + 1, 0);
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (!selected(row) || cloud.map(row, p) != 0) continue;
    // Divide (not multiply by 1/res) so that binning agrees with MapGeometry::index_of.
    const double fx = std::floor((p.x() - geometry.origin_m.x()) / geometry.resolution_m);
    const double fy = std::floor((p.y() - geometry.origin_m.y()) / geometry.resolution_m);
    if (!(fx >= 0.0 && fy >= 0.0 && fx < static_cast<double>(nx) && fy < static_cast<double>(ny))) continue;
    const auto cell = static_cast<std::size_t>(static_cast<std::int64_t>(fx) * ny + static_cast<std::int64_t>(fy));
    cell_of_point[row] = static_cast<std::uint32_t>(cell);
    ++offset[cell + 1];
  }
  // Pass 3: counting sort of the elevations by cell, so each cell's values are contiguous and the
  // statistics below read memory in order (a small histogram instead of scattered accumulators).
  for (std::size_t cell = 0; cell < cells; ++cell) offset[cell + 1] += offset[cell];
  std::vector<double> heights(offset[cells]);
  {
    std::vector<std::size_t> next(offset.begin(), offset.end() - 1);
    for (std::size_t row = 0; row < cloud.size(); ++row) {
      const std::uint32_t cell = cell_of_point[row];
      if (cell == kOutside) continue;
      cloud.map(row, p);
      heights[next[cell]++] = p.z();
    }
  }

  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  Layer count(nx, ny), min(nx, ny), max(nx, ny), mean(nx, ny), std_dev(nx, ny), discontinuity(nx, ny);
  for (std::size_t cell = 0; cell < cells; ++cell) {
    const std::size_t n = offset[cell + 1] - offset[cell];
    count.data()[cell] = static_cast<float>(n);
    if (n == 0) {
      min.data()[cell] = max.data()[cell] = mean.data()[cell] = std_dev.data()[cell] = discontinuity.data()[cell] =
          kNaN;
      continue;
    }
    double* begin = heights.data() + offset[cell];
    double* end = heights.data() + offset[cell + 1];
    double lowest = *begin, highest = *begin, sum = 0.0;
    for (const double* z = begin; z < end; ++z) {
      lowest = std::min(lowest, *z);
      highest = std::max(highest, *z);
      sum += *z;
    }
    const double average = sum / static_cast<double>(n);
    double squares = 0.0;  // two-pass variance: no cancellation at large absolute heights
    for (const double* z = begin; z < end; ++z) squares += (*z - average) * (*z - average);
    min.data()[cell] = static_cast<float>(lowest);
    max.data()[cell] = static_cast<float>(highest);
    mean.data()[cell] = static_cast<float>(average);
    std_dev.data()[cell] = static_cast<float>(std::sqrt(squares / static_cast<double>(n)));
    // Only a cell spanning more than the threshold can hold a gap: sort just those.
    bool gap = false;
    if (highest - lowest > params.discontinuity_m) {
      std::sort(begin, end);
      for (const double* z = begin + 1; z < end && !gap; ++z) gap = *z - *(z - 1) > params.discontinuity_m;
    }
    discontinuity.data()[cell] = gap ? 1.0F : 0.0F;
  }
  map.add("count", std::move(count));
  map.add("min", std::move(min));
  map.add("max", std::move(max));
  map.add("mean", std::move(mean));
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
