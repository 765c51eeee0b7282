// Private helpers shared by collapse_overhangs and its baselines: leveling, crop, finiteness
// checks and the bounding box that defines the CBC grid (eqs. 1-9). Not installed.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <string>

#include "terracube/collapse.hpp"
#include "terracube/cube_grid.hpp"

namespace terracube::detail {

/// Throws std::invalid_argument unless `transform` is finite and rigid (a proper rotation).
void check_rigid_transform(const Eigen::Matrix4d& transform, const char* what);

/// Maps input rows into the leveled frame and tells whether a row takes part.
template <typename Scalar>
class LeveledCloud {
 public:
  LeveledCloud(const PointsView<Scalar>& points, const Eigen::Matrix4d& transform,
               const std::optional<CropBox>& crop)
      : points_(points),
        rotation_(transform.topLeftCorner<3, 3>()),
        translation_(transform.topRightCorner<3, 1>()),
        identity_(transform.isIdentity(0.0)),
        crop_(crop) {}

  std::size_t size() const { return points_.size; }

  /// Writes the leveled point of `row` to `out`; returns 0 when it takes part, 1 when it is
  /// NaN/Inf, 2 when it falls outside the crop box.
  int map(std::size_t row, Eigen::Vector3d& out) const {
    const double x = static_cast<double>(points_(row, 0));
    const double y = static_cast<double>(points_(row, 1));
    const double z = static_cast<double>(points_(row, 2));
    // x - x is 0 for finite x and NaN for NaN/Inf: one test for all three coordinates.
    if (!((x - x) + (y - y) + (z - z) == 0.0)) return 1;
    if (identity_) {
      out = {x, y, z};
    } else {
      out = rotation_ * Eigen::Vector3d(x, y, z) + translation_;
    }
    if (crop_ && ((out.array() < crop_->min.array()).any() || (out.array() > crop_->max.array()).any())) {
      return 2;
    }
    return 0;
  }

 private:
  PointsView<Scalar> points_;
  Eigen::Matrix3d rotation_;
  Eigen::Vector3d translation_;
  bool identity_;
  std::optional<CropBox> crop_;
};

/// Counts of the first pass over a cloud.
struct CloudExtent {
  Eigen::Vector3d min = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d max = Eigen::Vector3d::Constant(-std::numeric_limits<double>::infinity());
  std::size_t num_used = 0;
  std::size_t num_non_finite = 0;
  std::size_t first_non_finite_row = 0;
  std::size_t num_cropped = 0;
};

/// First pass: bounding box of the used points (eqs. 1-3 need xmin, ymin, zmin) and counts.
/// Throws std::invalid_argument on NaN/Inf rows unless drop_non_finite.
template <typename Scalar>
CloudExtent measure_extent(const LeveledCloud<Scalar>& cloud, bool drop_non_finite) {
  CloudExtent extent;
  Eigen::Vector3d p;
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    const int status = cloud.map(row, p);
    if (status == 0) {
      extent.min = extent.min.cwiseMin(p);
      extent.max = extent.max.cwiseMax(p);
      ++extent.num_used;
    } else if (status == 1) {
      if (extent.num_non_finite == 0) extent.first_non_finite_row = row;
      ++extent.num_non_finite;
    } else {
      ++extent.num_cropped;
    }
  }
  if (extent.num_non_finite > 0 && !drop_non_finite) {
    throw std::invalid_argument(
        std::to_string(extent.num_non_finite) + " of " + std::to_string(cloud.size()) +
        " point rows contain NaN or Inf (first at row " + std::to_string(extent.first_non_finite_row) +
        "); clean the cloud or set drop_non_finite=True to drop them");
  }
  return extent;
}

/// Eqs. (4)-(6): the grid over a non-empty extent. Throws std::invalid_argument when the cube
/// count would overflow a 64-bit index.
CubeGrid make_grid(const CloudExtent& extent, double edge_m);

/// Throws std::invalid_argument unless edge > 0 and finite, and sigma >= 1.
void check_collapse_params(const CollapseParams& params);

}  // namespace terracube::detail
