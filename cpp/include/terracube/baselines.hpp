// Reference methods that collapse_overhangs is compared against (tests and bench/).
#pragma once

#include <cstdint>
#include <vector>

#include "terracube/collapse.hpp"
#include "terracube/cube_grid.hpp"

namespace terracube {

/// Parameters of the point-based per-cell gap search.
struct PointGapParams {
  /// Edge of the square 2D cells [m], > 0. Cells are aligned like CBC columns: cell (ix, iy)
  /// is centred on (xmin + ix * cell, ymin + iy * cell).
  double cell_m = 0.5;
  /// A vertical gap strictly larger than this separates ground from overhang [m], > 0.
  double min_gap_m = 1.0;
  /// Same meaning as in CollapseParams.
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();
  std::optional<CropBox> crop;
  bool drop_non_finite = false;
};

/// The point-based method the paper compares against: the heights in each 2D cell are sorted and
/// the points above the first gap larger than min_gap_m are overhang. O(N log N), memory O(N).
/// Returns one flag per input point, in input order.
std::vector<std::uint8_t> point_gap_overhangs(const PointsView<float>& points, const PointGapParams& params);
std::vector<std::uint8_t> point_gap_overhangs(const PointsView<double>& points, const PointGapParams& params);

/// Algorithm 1's rule on an OctoMap OcTree: each used point's cube centre (same quantisation as
/// CubeGrid, [CBC] eqs. (4)-(6)) is inserted into an octomap::OcTree of resolution E aligned to the CBC
/// grid, each column of occupied leaves is swept bottom-up with the same σ rule, collapsed keys
/// go into a second OcTree, and each point is looked up there. Must agree with
/// collapse_overhangs point for point. OctoMap keys are 16-bit: at most 65536 cubes per axis.
std::vector<std::uint8_t> octomap_column_overhangs(const PointsView<float>& points, const CollapseParams& params);
std::vector<std::uint8_t> octomap_column_overhangs(const PointsView<double>& points, const CollapseParams& params);

}  // namespace terracube
