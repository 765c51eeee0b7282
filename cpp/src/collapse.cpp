#include "terracube/collapse.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <unordered_map>

#include "cloud_frame.hpp"

namespace terracube {

namespace {

constexpr std::uint32_t kNoCube32 = std::numeric_limits<std::uint32_t>::max();

/// Algorithm 1, lines 5-15: sweep the sorted occupied cubes L. Sorting by I (eq. 7) visits the
/// layers bottom-up, so every column is seen bottom-up too. ground_of(column) is M: the layer iz
/// of the column's current ground cube, -1 for none. An occupied cube separated from the ground
/// by fewer than σ empty cubes becomes the new ground; otherwise it is collapsed into R.
template <typename GroundOf>
void sweep_columns(const std::vector<std::int64_t>& occupied, std::int64_t num_columns, int sigma,
                   GroundOf&& ground_of, std::vector<std::int64_t>& removed) {
  for (const std::int64_t cube : occupied) {
    const std::int64_t column = cube % num_columns;
    const std::int64_t layer = cube / num_columns;
    std::int64_t& ground = ground_of(column);
    const std::int64_t empty_between = layer - ground - 1;
    if (ground < 0 || empty_between < sigma) {
      ground = layer;
    } else {
      removed.push_back(cube);
    }
  }
}

struct GridQuantizer {
  Eigen::Vector3d min_corner;
  double inverse_edge;
  std::int64_t ixmax;
  std::int64_t layer_size;

  explicit GridQuantizer(const CubeGrid& grid)
      : min_corner(grid.min_corner),
        inverse_edge(1.0 / grid.edge_m),
        ixmax(grid.ixmax),
        layer_size(grid.ixmax * grid.iymax) {}

  /// Eqs. (1)-(3) and (7).
  std::int64_t operator()(const Eigen::Vector3d& p) const {
    return quantize(p.x(), min_corner.x(), inverse_edge) + quantize(p.y(), min_corner.y(), inverse_edge) * ixmax +
           quantize(p.z(), min_corner.z(), inverse_edge) * layer_size;
  }
};

std::size_t dense_bytes(const CubeGrid& grid) {
  return static_cast<std::size_t>((grid.num_cubes() + 63) / 64) * 8 +
         static_cast<std::size_t>(grid.num_columns()) * sizeof(std::int64_t);
}

CubeStorage choose_storage(const CubeGrid& grid, const CollapseParams& params, std::size_t num_used) {
  // 2^31 cubes keeps per-point indices in 32 bits on the dense path.
  const bool fits = grid.num_cubes() < (std::int64_t{1} << 31) && dense_bytes(grid) <= params.dense_budget_bytes;
  if (params.storage == CubeStorage::kDense) {
    if (!fits) {
      throw std::invalid_argument("dense cube storage would need " + std::to_string(dense_bytes(grid)) +
                                  " bytes for " + std::to_string(grid.num_cubes()) +
                                  " cubes, over dense_budget_bytes; use storage auto or sparse");
    }
    return CubeStorage::kDense;
  }
  if (params.storage == CubeStorage::kSparse) return CubeStorage::kSparse;
  // Auto: dense only while clearing V and M costs about as much as a pass over the points.
  const std::size_t affordable = (std::size_t{16} << 20) + 16 * num_used;
  return fits && dense_bytes(grid) <= affordable ? CubeStorage::kDense : CubeStorage::kSparse;
}

/// Dense path: V is a bit vector over all cubes, M a vector over all columns.
template <typename Scalar>
void collapse_dense(const detail::LeveledCloud<Scalar>& cloud, const CollapseParams& params, CollapseResult& result) {
  const CubeGrid& grid = result.grid;
  const GridQuantizer quantizer(grid);
  std::vector<std::uint64_t> occupancy(static_cast<std::size_t>((grid.num_cubes() + 63) / 64), 0);  // V
  std::vector<std::uint32_t> cube_of_point(cloud.size());

  // Algorithm 1, lines 1-4: one O(N) pass sets V.
  Eigen::Vector3d p;
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (cloud.map(row, p) != 0) {
      cube_of_point[row] = kNoCube32;
      continue;
    }
    const std::int64_t cube = quantizer(p);
    cube_of_point[row] = static_cast<std::uint32_t>(cube);
    occupancy[static_cast<std::size_t>(cube >> 6)] |= std::uint64_t{1} << (cube & 63);
  }

  // L sorted: reading V in index order is a bucket sort of L, O(|V| / 64 + |L|).
  std::vector<std::int64_t>& occupied = result.occupied_cubes;
  for (std::size_t word = 0; word < occupancy.size(); ++word) {
    for (std::uint64_t bits = occupancy[word]; bits != 0; bits &= bits - 1) {
      occupied.push_back(static_cast<std::int64_t>(word * 64 + static_cast<std::size_t>(__builtin_ctzll(bits))));
    }
  }

  std::vector<std::int64_t> ground(static_cast<std::size_t>(grid.num_columns()), -1);  // M
  sweep_columns(
      occupied, grid.num_columns(), params.sigma,
      [&ground](std::int64_t column) -> std::int64_t& { return ground[static_cast<std::size_t>(column)]; },
      result.removed_cubes);

  // Points in R's cubes are overhang: clear R's bits in V, then a point is overhang when its
  // cube's bit is gone.
  for (const std::int64_t cube : result.removed_cubes) {
    occupancy[static_cast<std::size_t>(cube >> 6)] &= ~(std::uint64_t{1} << (cube & 63));
  }
  std::size_t count = 0;
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    const std::uint32_t cube = cube_of_point[row];
    const bool removed = cube != kNoCube32 && ((occupancy[cube >> 6] >> (cube & 63)) & 1U) == 0;
    result.overhang[row] = removed ? 1 : 0;
    count += removed ? 1 : 0;
  }
  result.num_overhang = count;
}

/// Sparse path: L is the sorted set of the points' cube indices and M a hash map over the
/// columns that hold points, so memory is O(N) whatever the extent.
template <typename Scalar>
void collapse_sparse(const detail::LeveledCloud<Scalar>& cloud, const CollapseParams& params,
                     CollapseResult& result) {
  const CubeGrid& grid = result.grid;
  const GridQuantizer quantizer(grid);
  std::vector<std::int64_t> cube_of_point(cloud.size(), -1);
  std::vector<std::int64_t>& occupied = result.occupied_cubes;
  occupied.reserve(result.num_used);
  Eigen::Vector3d p;
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (cloud.map(row, p) != 0) continue;
    cube_of_point[row] = quantizer(p);
    occupied.push_back(cube_of_point[row]);
  }
  std::sort(occupied.begin(), occupied.end());
  occupied.erase(std::unique(occupied.begin(), occupied.end()), occupied.end());
  occupied.shrink_to_fit();

  std::unordered_map<std::int64_t, std::int64_t> ground;  // M, only for columns that hold points
  ground.reserve(occupied.size());
  sweep_columns(
      occupied, grid.num_columns(), params.sigma,
      [&ground](std::int64_t column) -> std::int64_t& { return ground.try_emplace(column, -1).first->second; },
      result.removed_cubes);

  const std::vector<std::int64_t>& removed_cubes = result.removed_cubes;  // sorted: swept in I order
  std::size_t count = 0;
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    const std::int64_t cube = cube_of_point[row];
    const bool removed = cube >= 0 && std::binary_search(removed_cubes.begin(), removed_cubes.end(), cube);
    result.overhang[row] = removed ? 1 : 0;
    count += removed ? 1 : 0;
  }
  result.num_overhang = count;
}

template <typename Scalar>
CollapseResult collapse_impl(const PointsView<Scalar>& points, const CollapseParams& params) {
  detail::check_collapse_params(params);
  if (points.size > 0 && points.data == nullptr) {
    throw std::invalid_argument("points view has no data but claims " + std::to_string(points.size) + " rows");
  }
  CollapseResult result;
  result.num_points = points.size;
  result.overhang.assign(points.size, 0);
  result.grid.edge_m = params.edge_m;

  const detail::LeveledCloud<Scalar> cloud(points, params.transform, params.crop);
  const detail::CloudExtent extent = detail::measure_extent(cloud, params.drop_non_finite);
  result.num_used = extent.num_used;
  result.num_cropped = extent.num_cropped;
  result.num_dropped_non_finite = extent.num_non_finite;
  if (extent.num_used == 0) return result;  // empty grid, nothing occupied, nothing removed

  result.grid = detail::make_grid(extent, params.edge_m);
  result.storage_used = choose_storage(result.grid, params, extent.num_used);
  if (result.storage_used == CubeStorage::kDense) {
    collapse_dense(cloud, params, result);
  } else {
    collapse_sparse(cloud, params, result);
  }
  return result;
}

}  // namespace

int sigma_from_robot_height(double robot_height_m, double edge_m) {
  if (!(robot_height_m > 0.0) || !std::isfinite(robot_height_m)) {
    throw std::invalid_argument("robot height must be a positive finite length in metres");
  }
  if (!(edge_m > 0.0) || !std::isfinite(edge_m)) {
    throw std::invalid_argument("edge must be a positive finite length in metres");
  }
  const double cubes = std::ceil(robot_height_m / edge_m);
  if (cubes > static_cast<double>(std::numeric_limits<int>::max())) {
    throw std::invalid_argument("robot height / edge is too large for sigma");
  }
  return std::max(1, static_cast<int>(cubes));
}

Eigen::Matrix4d leveling_transform(double roll_rad, double pitch_rad) {
  if (!std::isfinite(roll_rad) || !std::isfinite(pitch_rad)) {
    throw std::invalid_argument("roll and pitch must be finite angles in radians");
  }
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();
  transform.topLeftCorner<3, 3>() = (Eigen::AngleAxisd(pitch_rad, Eigen::Vector3d::UnitY()) *
                                     Eigen::AngleAxisd(roll_rad, Eigen::Vector3d::UnitX()))
                                        .toRotationMatrix();
  return transform;
}

CollapseResult collapse_overhangs(const PointsView<float>& points, const CollapseParams& params) {
  return collapse_impl(points, params);
}

CollapseResult collapse_overhangs(const PointsView<double>& points, const CollapseParams& params) {
  return collapse_impl(points, params);
}

CollapseResult collapse_overhangs(const std::vector<Eigen::Vector3d>& points, const CollapseParams& params) {
  return collapse_impl(PointsView<double>(points), params);
}

}  // namespace terracube
