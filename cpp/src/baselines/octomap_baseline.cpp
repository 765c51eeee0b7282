// [CBC] Algorithm 1's column rule evaluated on OctoMap's OcTree: an independent storage and sweep that
// collapse_overhangs must agree with point for point.
#include <octomap/OcTree.h>

#include <algorithm>
#include <array>
#include <limits>
#include <stdexcept>
#include <string>

#include "cloud_frame.hpp"
#include "number_text.hpp"
#include "terracube/baselines.hpp"

namespace terracube {

namespace {

constexpr std::int64_t kOctomapKeys = 65536;  // 16-bit keys per axis
constexpr std::int64_t kOctomapKeyOffset = 32768;

template <typename Cloud>
std::vector<std::uint8_t> octomap_mask(const Cloud& cloud, const CollapseParams& params);

template <typename Scalar>
std::vector<std::uint8_t> octomap_impl(const PointsView<Scalar>& points, const CollapseParams& params) {
  check_collapse_params(params);
  return detail::visit_leveled(points, params.transform, params.crop,
                               [&](const auto& cloud) { return octomap_mask(cloud, params); });
}

template <typename Cloud>
std::vector<std::uint8_t> octomap_mask(const Cloud& cloud, const CollapseParams& params) {
  std::vector<std::uint8_t> overhang(cloud.size(), 0);
  const detail::CloudExtent extent = detail::measure_extent(cloud, params.drop_non_finite);
  if (extent.num_used == 0) return overhang;
  const CubeGrid grid = detail::make_grid(extent, params.edge_m);
  if (grid.ixmax > kOctomapKeys || grid.iymax > kOctomapKeys || grid.izmax > kOctomapKeys) {
    throw std::invalid_argument("the OctoMap baseline holds at most 65536 cubes per axis; this cloud needs " +
                                std::to_string(grid.ixmax) + " x " + std::to_string(grid.iymax) + " x " +
                                std::to_string(grid.izmax));
  }
  // OctoMap keeps float coordinates: its 65536 keys per axis must span a finite float extent.
  if (!(static_cast<double>(kOctomapKeys) * grid.edge_m < static_cast<double>(std::numeric_limits<float>::max()))) {
    throw std::invalid_argument("the OctoMap baseline stores float coordinates: an edge of " +
                                detail::number_text(grid.edge_m) + " m times its 65536 keys overflows float");
  }
  const double inverse_edge = 1.0 / grid.edge_m;
  // The tree's voxel with key k spans [(k - 32768) E, (k - 32768 + 1) E): the centre of CBC cube
  // (ix, iy, iz), [CBC] eqs. (4)-(6), is placed at the centre of the voxel with key (ix, iy, iz).
  octomap::OcTree occupied_tree(grid.edge_m);
  const auto cube_centre_in_tree = [&](const Eigen::Vector3d& p) {
    octomap::point3d centre;
    for (int axis = 0; axis < 3; ++axis) {
      const std::int64_t cube = quantize(p[axis], grid.min_corner[axis], inverse_edge);
      centre(axis) = static_cast<float>((static_cast<double>(cube - kOctomapKeyOffset) + 0.5) * grid.edge_m);
    }
    return centre;
  };
  const auto key_of = [&](const octomap::OcTree& tree, const Eigen::Vector3d& p) {
    octomap::OcTreeKey key;
    if (!tree.coordToKeyChecked(cube_centre_in_tree(p), key)) {
      throw std::logic_error("OctoMap baseline: a cube centre fell outside the tree");
    }
    return key;
  };

  Eigen::Vector3d p;
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (cloud.map(row, p) != 0) continue;
    occupied_tree.updateNode(key_of(occupied_tree, p), true, /*lazy_eval=*/true);
  }
  occupied_tree.updateInnerOccupancy();
  occupied_tree.expand();  // undo any pruning so that every occupied cube is one leaf

  std::vector<std::array<int, 3>> keys;
  for (auto it = occupied_tree.begin_leafs(), end = occupied_tree.end_leafs(); it != end; ++it) {
    if (it.getDepth() != occupied_tree.getTreeDepth()) {
      throw std::logic_error("OctoMap baseline: a leaf above the finest depth after expand()");
    }
    if (!occupied_tree.isNodeOccupied(*it)) continue;
    const octomap::OcTreeKey key = it.getKey();
    keys.push_back({key[0], key[1], key[2]});
  }
  // Columns are runs of equal (x, y) keys; within a run z ascends: sweep bottom-up.
  std::sort(keys.begin(), keys.end());
  octomap::OcTree removed_tree(grid.edge_m);
  for (std::size_t begin = 0; begin < keys.size();) {
    std::size_t end = begin;
    int ground = -1;
    for (; end < keys.size() && keys[end][0] == keys[begin][0] && keys[end][1] == keys[begin][1]; ++end) {
      const int layer = keys[end][2];
      if (ground < 0 || layer - ground - 1 < params.sigma) {
        ground = layer;
      } else {
        removed_tree.updateNode(
            octomap::OcTreeKey(static_cast<octomap::key_type>(keys[end][0]),
                               static_cast<octomap::key_type>(keys[end][1]), static_cast<octomap::key_type>(layer)),
            true, /*lazy_eval=*/true);
      }
    }
    begin = end;
  }
  removed_tree.updateInnerOccupancy();

  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (cloud.map(row, p) != 0) continue;
    const octomap::OcTreeNode* node = removed_tree.search(key_of(removed_tree, p));
    overhang[row] = node != nullptr && removed_tree.isNodeOccupied(node) ? 1 : 0;
  }
  return overhang;
}

}  // namespace

std::vector<std::uint8_t> octomap_column_overhangs(const PointsView<float>& points, const CollapseParams& params) {
  return octomap_impl(points, params);
}

std::vector<std::uint8_t> octomap_column_overhangs(const PointsView<double>& points, const CollapseParams& params) {
  return octomap_impl(points, params);
}

}  // namespace terracube
