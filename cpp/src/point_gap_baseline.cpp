// The point-based per-cell gap search that Reina et al. (2014) compare collapsible cubes with.
#include <algorithm>
#include <stdexcept>
#include <string>

#include "cloud_frame.hpp"
#include "number_text.hpp"
#include "terracube/baselines.hpp"

namespace terracube {

namespace {

template <typename Cloud>
std::vector<std::uint8_t> point_gap_mask(const Cloud& cloud, const PointGapParams& params);

struct CellPoint {
  std::int64_t cell;
  double z;
  std::size_t row;
};

template <typename Scalar>
std::vector<std::uint8_t> point_gap_impl(const PointsView<Scalar>& points, const PointGapParams& params) {
  if (!(params.cell_m > 0.0) || !std::isfinite(params.cell_m)) {
    throw std::invalid_argument("cell must be a positive finite length in metres, got " +
                                detail::number_text(params.cell_m));
  }
  if (!(params.min_gap_m > 0.0) || !std::isfinite(params.min_gap_m)) {
    throw std::invalid_argument("min_gap must be a positive finite length in metres, got " +
                                detail::number_text(params.min_gap_m));
  }
  detail::check_rigid_transform(params.transform, "transform");
  return detail::visit_leveled(points, params.transform, params.crop,
                               [&](const auto& cloud) { return point_gap_mask(cloud, params); });
}

template <typename Cloud>
std::vector<std::uint8_t> point_gap_mask(const Cloud& cloud, const PointGapParams& params) {
  std::vector<std::uint8_t> overhang(cloud.size(), 0);
  detail::CloudExtent extent = detail::measure_extent(cloud, params.drop_non_finite);
  if (extent.num_used == 0) return overhang;
  extent.min.z() = extent.max.z() = 0.0;  // 2D cells: only x and y count
  const CubeGrid cells = detail::make_grid(extent, params.cell_m);
  const double inverse_cell = 1.0 / params.cell_m;

  std::vector<CellPoint> sorted;
  sorted.reserve(extent.num_used);
  Eigen::Vector3d p;
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (cloud.map(row, p) != 0) continue;
    const std::int64_t cell = quantize(p.x(), cells.min_corner.x(), inverse_cell) +
                              quantize(p.y(), cells.min_corner.y(), inverse_cell) * cells.ixmax;
    sorted.push_back({cell, p.z(), row});
  }
  std::sort(sorted.begin(), sorted.end(), [](const CellPoint& a, const CellPoint& b) {
    return a.cell != b.cell ? a.cell < b.cell : (a.z != b.z ? a.z < b.z : a.row < b.row);
  });
  // In each cell, everything above the first gap larger than min_gap is overhang.
  for (std::size_t begin = 0; begin < sorted.size();) {
    std::size_t end = begin + 1;
    while (end < sorted.size() && sorted[end].cell == sorted[begin].cell) ++end;
    for (std::size_t i = begin + 1; i < end; ++i) {
      if (sorted[i].z - sorted[i - 1].z > params.min_gap_m) {
        for (std::size_t j = i; j < end; ++j) overhang[sorted[j].row] = 1;
        break;
      }
    }
    begin = end;
  }
  return overhang;
}

}  // namespace

std::vector<std::uint8_t> point_gap_overhangs(const PointsView<float>& points, const PointGapParams& params) {
  return point_gap_impl(points, params);
}

std::vector<std::uint8_t> point_gap_overhangs(const PointsView<double>& points, const PointGapParams& params) {
  return point_gap_impl(points, params);
}

}  // namespace terracube
