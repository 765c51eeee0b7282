// Coarse binary cubes (CBC) geometry: [CBC] = Reina et al., "Collapsible cubes", IEEE AIM 2014, eqs. (1)-(9).
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace terracube {

/// A read-only view of N points stored as rows of 3 coordinates (x, y, z), in metres.
/// Strides are in elements, so a numpy (N,3) array of any layout is viewed without a copy.
template <typename Scalar>
struct PointsView {
  const Scalar* data = nullptr;
  std::size_t size = 0;              ///< number of points N
  std::ptrdiff_t row_stride = 3;     ///< elements between consecutive points
  std::ptrdiff_t column_stride = 1;  ///< elements between x, y and z of one point

  PointsView() = default;
  PointsView(const Scalar* data_, std::size_t size_, std::ptrdiff_t row_stride_ = 3, std::ptrdiff_t column_stride_ = 1)
      : data(data_), size(size_), row_stride(row_stride_), column_stride(column_stride_) {}
  /// A view of contiguous Eigen vectors (x, y, z, x, y, z, ...).
  explicit PointsView(const std::vector<Eigen::Matrix<Scalar, 3, 1>>& points)
      : data(points.empty() ? nullptr : points.front().data()), size(points.size()) {}

  Scalar operator()(std::size_t row, int axis) const {
    return data[static_cast<std::ptrdiff_t>(row) * row_stride + axis * column_stride];
  }
  Eigen::Vector3d point(std::size_t row) const {
    return {static_cast<double>((*this)(row, 0)), static_cast<double>((*this)(row, 1)),
            static_cast<double>((*this)(row, 2))};
  }
};

/// Cube coordinates (ix, iy, iz) of one cube of a CubeGrid.
using CubeCoordinates = Eigen::Matrix<std::int64_t, 3, 1>;

/// The CBC grid over a leveled cloud.
///
/// [CBC] eqs. (4)-(6): a point p falls into cube (ix, iy, iz) with ix = round((x - xmin) / E), where
/// round() is round-half-up computed in double as floor((x - xmin) * (1 / E) + 0.5). Cube
/// (ix, iy, iz) is therefore centred on min_corner + E * (ix, iy, iz): the bounding-box minimum
/// is the centre of cube (0, 0, 0), not its corner.
/// [CBC] eqs. (2)-(3): ixmax = round((xmax - xmin) / E) + 1 cubes along x (likewise y, and z).
/// [CBC] eq. (1): the cube index I = ix + iy * ixmax + iz * ixmax * iymax, 64-bit. Sorting by I sweeps
/// layer by layer bottom-up; the column of a cube is I mod (ixmax * iymax).
struct CubeGrid {
  Eigen::Vector3d min_corner = Eigen::Vector3d::Zero();  ///< (xmin, ymin, zmin) [m]
  double edge_m = 0.0;                                   ///< cube edge E [m]
  std::int64_t ixmax = 0;                                ///< cubes along x
  std::int64_t iymax = 0;                                ///< cubes along y
  std::int64_t izmax = 0;                                ///< cubes along z

  std::int64_t num_columns() const { return ixmax * iymax; }
  std::int64_t num_cubes() const { return ixmax * iymax * izmax; }
  /// [CBC] eq. (1).
  std::int64_t index(std::int64_t ix, std::int64_t iy, std::int64_t iz) const {
    return ix + iy * ixmax + iz * ixmax * iymax;
  }
  /// [CBC] eqs. (7)-(9), the inverse of eq. (1).
  CubeCoordinates coordinates(std::int64_t index) const {
    const std::int64_t columns = num_columns();
    const std::int64_t column = index % columns;
    return {column % ixmax, column / ixmax, index / columns};
  }
  /// Centre of cube `index` [m].
  Eigen::Vector3d center(std::int64_t index) const { return min_corner + edge_m * coordinates(index).cast<double>(); }
};

/// [CBC] eqs. (4)-(6): the cube coordinate of one coordinate value along one axis.
inline std::int64_t quantize(double value, double min_value, double inverse_edge) {
  // value >= min_value, so the truncation below is floor(): round-half-up.
  return static_cast<std::int64_t>((value - min_value) * inverse_edge + 0.5);
}

}  // namespace terracube
