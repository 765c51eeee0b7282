// Reference methods that collapse_overhangs is compared against (tests and bench/).
#pragma once

#include <cstdint>
#include <vector>

#include "terracube/collapse.hpp"
#include "terracube/cube_grid.hpp"

namespace terracube {

/// Parameters of point_based_overhangs: the grid and σ of CollapseParams, plus the variance test.
struct PointBasedParams {
  /// Cell edge and height step E [m], > 0: the same grid as the CBC cubes ([CBC] eqs. (1)-(6)).
  double edge_m = 0.5;
  /// The gap [steps of E], >= 1: σ or more empty steps between two consecutive points of a cell.
  int sigma = 2;
  /// Cells whose height variance is at most this are not searched for a gap [m^2], >= 0. The
  /// method of [CBC] refs. [3], [7] searches only cells with a large variance; its value is not
  /// given there: 0.01 m^2 is a standard deviation of 10 cm, [TC]'s "small" spread.
  double variance_threshold_m2 = 0.01;
  /// Same meaning as in CollapseParams.
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();
  std::optional<CropBox> crop;
  bool drop_non_finite = false;
};

/// Throws std::invalid_argument naming the first field out of range; point_based_overhangs calls it first, and a
/// configuration can call it before the first scan.
void check_point_based_params(const PointBasedParams& params);

/// The point-based method [CBC] compares collapsible cubes with (section I and Table I, its refs.
/// [3], [7]): per 2D cell, the height variance of the cell's points is tested first; in the cells
/// that exceed it, the points are sorted by height and searched bottom-up for a vertical gap of σ
/// or more empty steps of E between consecutive points (heights quantised on the cubes' z grid,
/// so the gap is measured as [CBC] Algorithm 1 measures it: "the same results are obtained in
/// both cases"). Everything above the first such gap is overhang. It agrees with
/// collapse_overhangs except in cells that hold a gap but pass the variance test.
/// O(N log N), memory O(N). Returns one flag per input point, in input order.
std::vector<std::uint8_t> point_based_overhangs(const PointsView<float>& points, const PointBasedParams& params);
std::vector<std::uint8_t> point_based_overhangs(const PointsView<double>& points, const PointBasedParams& params);

/// [CBC] Algorithm 1's rule on an OctoMap OcTree: each used point's cube centre (same quantisation as
/// CubeGrid, [CBC] eqs. (4)-(6)) is inserted into an octomap::OcTree of resolution E aligned to the CBC
/// grid, each column of occupied leaves is swept bottom-up with the same σ rule, collapsed keys
/// go into a second OcTree, and each point is looked up there. Must agree with
/// collapse_overhangs point for point. OctoMap keys are 16-bit: at most 65536 cubes per axis.
std::vector<std::uint8_t> octomap_column_overhangs(const PointsView<float>& points, const CollapseParams& params);
std::vector<std::uint8_t> octomap_column_overhangs(const PointsView<double>& points, const CollapseParams& params);

}  // namespace terracube
