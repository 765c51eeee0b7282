// The point-based overhang search that [CBC] compares collapsible cubes with (its refs. [3], [7]).
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "cloud_frame.hpp"
#include "number_text.hpp"
#include "terracube/baselines.hpp"

namespace terracube {

namespace {

/// One used point: its 2D cell, its height and height step on the cube grid, its input row.
struct CellPoint {
  std::int64_t cell;
  double z;
  std::int64_t step;
  std::size_t row;
};

}  // namespace

void check_point_based_params(const PointBasedParams& params) {
  if (!(params.edge_m > 0.0) || !std::isfinite(params.edge_m)) {
    throw std::invalid_argument("edge must be a positive finite length in metres, got " +
                                detail::number_text(params.edge_m));
  }
  if (params.sigma < 1) throw std::invalid_argument("sigma must be >= 1, got " + std::to_string(params.sigma));
  if (!(params.variance_threshold_m2 >= 0.0) || !std::isfinite(params.variance_threshold_m2)) {
    throw std::invalid_argument("variance threshold must be a finite value >= 0 in m^2, got " +
                                detail::number_text(params.variance_threshold_m2));
  }
  detail::check_rigid_transform(params.transform, "transform");
  detail::check_crop(params.crop);
}

namespace {

/// Population variance of the heights of [begin, end).
double height_variance(const std::vector<CellPoint>& points, std::size_t begin, std::size_t end) {
  double mean = 0.0;
  for (std::size_t i = begin; i < end; ++i) mean += points[i].z;
  mean /= static_cast<double>(end - begin);
  double sum = 0.0;
  for (std::size_t i = begin; i < end; ++i) sum += (points[i].z - mean) * (points[i].z - mean);
  return sum / static_cast<double>(end - begin);
}

/// The first point of the cell [begin, end) (sorted by height) above a gap of sigma or more empty
/// steps from the ground below it, the ground rising with each point under the gap; end if none.
std::size_t first_above_gap(const std::vector<CellPoint>& points, std::size_t begin, std::size_t end, int sigma) {
  std::int64_t ground = points[begin].step;
  for (std::size_t i = begin + 1; i < end; ++i) {
    if (points[i].step - ground - 1 >= sigma) return i;
    ground = points[i].step;
  }
  return end;
}

template <typename Cloud>
std::vector<std::uint8_t> point_based_mask(const Cloud& cloud, const PointBasedParams& params) {
  std::vector<std::uint8_t> overhang(cloud.size(), 0);
  const detail::CloudExtent extent = detail::measure_extent(cloud, params.drop_non_finite);
  if (extent.num_used == 0) return overhang;
  const CubeGrid grid = detail::make_grid(extent, params.edge_m);  // the cubes' grid, [CBC] eqs. (1)-(6)
  const double inverse_edge = 1.0 / params.edge_m;
  std::vector<CellPoint> points;
  points.reserve(extent.num_used);
  Eigen::Vector3d p;
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (cloud.map(row, p) != 0) continue;
    const std::int64_t cell = quantize(p.x(), grid.min_corner.x(), inverse_edge) +
                              quantize(p.y(), grid.min_corner.y(), inverse_edge) * grid.ixmax;
    points.push_back({cell, p.z(), quantize(p.z(), grid.min_corner.z(), inverse_edge), row});
  }
  std::sort(points.begin(), points.end(), [](const CellPoint& a, const CellPoint& b) {
    return a.cell != b.cell ? a.cell < b.cell : (a.z != b.z ? a.z < b.z : a.row < b.row);
  });
  for (std::size_t begin = 0; begin < points.size();) {
    std::size_t end = begin + 1;
    while (end < points.size() && points[end].cell == points[begin].cell) ++end;
    // Refs. [3], [7]: only cells whose heights vary enough are searched for a gap.
    if (height_variance(points, begin, end) > params.variance_threshold_m2) {
      for (std::size_t i = first_above_gap(points, begin, end, params.sigma); i < end; ++i) overhang[points[i].row] = 1;
    }
    begin = end;
  }
  return overhang;
}

template <typename Scalar>
std::vector<std::uint8_t> point_based(const PointsView<Scalar>& points, const PointBasedParams& params) {
  check_point_based_params(params);
  return detail::visit_leveled(points, params.transform, params.crop,
                               [&](const auto& cloud) { return point_based_mask(cloud, params); });
}

}  // namespace

std::vector<std::uint8_t> point_based_overhangs(const PointsView<float>& points, const PointBasedParams& params) {
  return point_based(points, params);
}

std::vector<std::uint8_t> point_based_overhangs(const PointsView<double>& points, const PointBasedParams& params) {
  return point_based(points, params);
}

}  // namespace terracube
