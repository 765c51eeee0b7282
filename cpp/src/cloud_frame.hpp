// Private helpers shared by collapse_overhangs, the elevation map and the baselines: leveling,
// crop, finiteness checks, the rigid-transform check of every pose input and the bounding box
// that defines the CBC grid ([CBC] eqs. (1)-(9)).
// Not installed.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <stdexcept>
#include <string>

#include "terracube/collapse.hpp"
#include "terracube/cube_grid.hpp"

namespace terracube::detail {

/// Largest entry of R^T R - I accepted in a rigid transform's rotation R: poses written with six
/// significant digits (KITTI's, most text files) pass as they are.
constexpr double kRigidTolerance = 1e-5;

/// Throws std::invalid_argument naming `what` and the problem unless `transform` is finite and
/// rigid: last row 0 0 0 1, R^T R within kRigidTolerance of I, det R > 0. Every pose, guess and
/// transform the core takes passes this one check.
void check_rigid_transform(const Eigen::Matrix4d& transform, const std::string& what);

/// Throws std::invalid_argument unless the crop box (if any) is finite with min <= max.
void check_crop(const std::optional<CropBox>& crop);

/// What a row of a cloud is once leveled and cropped.
enum class RowStatus { kUsed = 0, kNonFinite = 1, kCropped = 2 };

/// A row stride that is read from the PointsView at run time (any layout).
constexpr std::ptrdiff_t kAnyRowStride = 0;

/// Maps input rows into the leveled frame and tells whether a row takes part. The transform and
/// the crop are template switches so that the common case (neither) compiles to a bare loop;
/// kRowStride != kAnyRowStride fixes the layout at compile time (see with_fixed_layout).
template <typename Scalar, bool kTransform, bool kCrop, std::ptrdiff_t kRowStride = kAnyRowStride>
class LeveledCloud {
 public:
  LeveledCloud(const PointsView<Scalar>& points, const Eigen::Matrix4d& transform, const std::optional<CropBox>& crop)
      : points_(points), transform_(transform) {
    if (crop) crop_ = *crop;
  }

  /// Calls f(cloud) with this cloud, or, when its rows are (N, 3) or (N, 4) with x, y, z next to
  /// each other (numpy arrays, Eigen vectors, PCL and KITTI points), with the same cloud whose
  /// strides are compile-time constants: a pass over the rows then loads at fixed offsets (the
  /// cube-index pass over a KITTI scan took 0.68 ms instead of 1.2 ms). Same rows, same bits.
  template <typename F>
  void with_fixed_layout(F&& f) const {
    if constexpr (kRowStride == kAnyRowStride) {
      if (points_.column_stride == 1 && points_.row_stride == 3) {
        return f(LeveledCloud<Scalar, kTransform, kCrop, 3>(points_, transform_, crop_));
      }
      if (points_.column_stride == 1 && points_.row_stride == 4) {
        return f(LeveledCloud<Scalar, kTransform, kCrop, 4>(points_, transform_, crop_));
      }
    }
    f(*this);
  }

  std::size_t size() const { return points_.size; }

  /// Whether every row is used as stored: no transform, no crop, (N, 3) or (N, 4) rows with x, y,
  /// z side by side (plain_extent_of_rows reads such rows without leveling them).
  static constexpr bool kPlainRows = !kTransform && !kCrop && kRowStride != kAnyRowStride;
  static constexpr std::ptrdiff_t kStride = kRowStride;  ///< kAnyRowStride: read at run time
  using ScalarType = Scalar;
  /// The stored scalars of `row` (x, y, z at offsets 0, 1, 2 when kPlainRows).
  const Scalar* row_data(std::size_t row) const {
    const std::ptrdiff_t stride = kRowStride == kAnyRowStride ? points_.row_stride : kRowStride;
    return points_.data + static_cast<std::ptrdiff_t>(row) * stride;
  }

  /// The leveled point of `row`, unchecked: NaN/Inf coordinates stay NaN/Inf.
  Eigen::Vector3d level(std::size_t row) const {
    const Scalar* p = row_data(row);
    const auto x = static_cast<double>(p[0]);
    const auto y = static_cast<double>(p[column_stride()]);
    const auto z = static_cast<double>(p[2 * column_stride()]);
    if constexpr (kTransform) {
      // q_i = ((r_i0 x + r_i1 y) + r_i2 z) + t_i: the one definition every path uses.
      Eigen::Vector3d q;
      for (int i = 0; i < 3; ++i)
        q[i] = transform_(i, 0) * x + transform_(i, 1) * y + transform_(i, 2) * z + transform_(i, 3);
      return q;
    } else {
      return {x, y, z};
    }
  }

  /// Whether a leveled point lies in the crop box (always, without one). False for NaN.
  bool in_crop(const Eigen::Vector3d& q) const {
    if constexpr (kCrop) {
      return (q.x() >= crop_.min.x()) & (q.y() >= crop_.min.y()) & (q.z() >= crop_.min.z()) & (q.x() <= crop_.max.x()) &
             (q.y() <= crop_.max.y()) & (q.z() <= crop_.max.z());
    } else {
      return true;
    }
  }

  /// Writes the leveled point of `row` to `out`: 0 when it takes part, 1 when it is NaN/Inf, 2
  /// when it falls outside the crop box (see RowStatus).
  int map(std::size_t row, Eigen::Vector3d& out) const {
    const Scalar* p = row_data(row);
    const auto x = static_cast<double>(p[0]);
    const auto y = static_cast<double>(p[column_stride()]);
    const auto z = static_cast<double>(p[2 * column_stride()]);
    // x - x is 0 for finite x and NaN for NaN/Inf: one test for all three coordinates.
    if (!((x - x) + (y - y) + (z - z) == 0.0)) return 1;
    out = level(row);
    return in_crop(out) ? 0 : 2;
  }

 private:
  LeveledCloud(const PointsView<Scalar>& points, const Eigen::Matrix4d& transform, const CropBox& crop)
      : points_(points), transform_(transform), crop_(crop) {}
  template <typename, bool, bool, std::ptrdiff_t>
  friend class LeveledCloud;

  std::ptrdiff_t column_stride() const { return kRowStride == kAnyRowStride ? points_.column_stride : 1; }

  PointsView<Scalar> points_;
  Eigen::Matrix4d transform_;
  CropBox crop_;
};

/// Calls f(cloud) with the LeveledCloud specialisation that `transform` and `crop` need.
template <typename Scalar, typename F>
decltype(auto) visit_leveled(const PointsView<Scalar>& points, const Eigen::Matrix4d& transform,
                             const std::optional<CropBox>& crop, F&& f) {
  const bool moves = !transform.isIdentity(0.0);
  if (moves && crop) return f(LeveledCloud<Scalar, true, true>(points, transform, crop));
  if (moves) return f(LeveledCloud<Scalar, true, false>(points, transform, crop));
  if (crop) return f(LeveledCloud<Scalar, false, true>(points, transform, crop));
  return f(LeveledCloud<Scalar, false, false>(points, transform, crop));
}

/// The rows NaN/Inf among those looked at: how many, and the first.
struct NonFiniteRows {
  std::size_t count = 0;
  std::size_t first_row = 0;
  void add(std::size_t row) {
    if (count++ == 0) first_row = row;
  }
  /// Adds the rows of a later run of rows.
  void merge(const NonFiniteRows& later) {
    if (count == 0) first_row = later.first_row;
    count += later.count;
  }
};

/// Throws the std::invalid_argument of NaN/Inf rows: how many of how many, and the first.
[[noreturn]] void throw_non_finite_rows(const NonFiniteRows& rows, std::size_t num_rows);

/// Counts of a pass over a cloud and the bounding box of the rows that take part.
struct CloudExtent {
  Eigen::Vector3d min = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d max = Eigen::Vector3d::Constant(-std::numeric_limits<double>::infinity());
  std::size_t num_used = 0;
  NonFiniteRows non_finite;
  std::size_t num_cropped = 0;

  /// Adds the extent of a later run of rows.
  void merge(const CloudExtent& later) {
    min = min.cwiseMin(later.min);
    max = max.cwiseMax(later.max);
    num_used += later.num_used;
    non_finite.merge(later.non_finite);
    num_cropped += later.num_cropped;
  }
};

/// The extent of rows [begin, end) of a cloud of plain rows (LeveledCloud::kPlainRows) when all
/// their x, y, z are finite; nothing otherwise (extent_of_rows then looks at each row). The rows are
/// read as one array, four rows at a time into fixed-size Eigen arrays (a lane per scalar), whose
/// minima, maxima and finiteness test (v - v is 0 for finite v, NaN otherwise) vectorise. The
/// minimum of floats converts exactly to the minimum of their doubles: the same bounds as
/// extent_of_rows.
template <typename Cloud>
std::optional<CloudExtent> plain_extent_of_rows(const Cloud& cloud, std::size_t begin, std::size_t end) {
  using Scalar = typename Cloud::ScalarType;
  constexpr int kStride = static_cast<int>(Cloud::kStride);
  using Lanes = Eigen::Array<Scalar, 4 * kStride, 1>;
  Lanes lo = Lanes::Constant(std::numeric_limits<Scalar>::infinity()), hi = -lo, poison = Lanes::Zero();
  // Four rows of (N, 4) end with the fourth value of the last row, which need not be in memory
  // (a view of x, y, z with a row stride of 4): the last row of the range is left to the tail.
  const std::size_t blocks_end = kStride == 4 && end > begin ? end - 1 : end;
  std::size_t row = begin;
  for (; row + 4 <= blocks_end; row += 4) {
    const Eigen::Map<const Lanes> rows(cloud.row_data(row));
    lo = lo.min(rows);
    hi = hi.max(rows);
    poison += rows - rows;
  }
  for (; row < end; ++row) {  // the last rows, into the first row's lanes
    const Eigen::Map<const Eigen::Array<Scalar, 3, 1>> p(cloud.row_data(row));
    lo.template head<3>() = lo.template head<3>().min(p);
    hi.template head<3>() = hi.template head<3>().max(p);
    poison.template head<3>() += p - p;
  }
  CloudExtent extent;
  for (int j = 0; j < 4 * kStride; ++j) {
    const int axis = j % kStride;
    if (axis > 2) continue;  // the fourth value of (N, 4) rows (intensity) is not a coordinate
    if (poison[j] != 0) return std::nullopt;
    extent.min[axis] = std::min(extent.min[axis], static_cast<double>(lo[j]));
    extent.max[axis] = std::max(extent.max[axis], static_cast<double>(hi[j]));
  }
  extent.num_used = end - begin;
  return extent;
}

/// The extent of rows [begin, end) selected by `use` (null: all). Never throws.
template <typename Cloud>
CloudExtent extent_of_rows(const Cloud& cloud, std::size_t begin, std::size_t end, const std::uint8_t* use = nullptr) {
  if constexpr (Cloud::kPlainRows) {
    if (use == nullptr) {
      if (const std::optional<CloudExtent> plain = plain_extent_of_rows(cloud, begin, end)) return *plain;
    }
  }
  CloudExtent extent;
  // Six running bounds in plain doubles: independent chains the compiler keeps in registers.
  constexpr double kInf = std::numeric_limits<double>::infinity();
  double min_x = kInf, min_y = kInf, min_z = kInf, max_x = -kInf, max_y = -kInf, max_z = -kInf;
  Eigen::Vector3d p;
  for (std::size_t row = begin; row < end; ++row) {
    if (use != nullptr && use[row] == 0) continue;
    const int status = cloud.map(row, p);
    if (status == 0) {
      min_x = p.x() < min_x ? p.x() : min_x;
      min_y = p.y() < min_y ? p.y() : min_y;
      min_z = p.z() < min_z ? p.z() : min_z;
      max_x = p.x() > max_x ? p.x() : max_x;
      max_y = p.y() > max_y ? p.y() : max_y;
      max_z = p.z() > max_z ? p.z() : max_z;
      ++extent.num_used;
    } else if (status == 1) {
      extent.non_finite.add(row);
    } else {
      ++extent.num_cropped;
    }
  }
  extent.min = {min_x, min_y, min_z};
  extent.max = {max_x, max_y, max_z};
  return extent;
}

/// [CBC] eqs. (2)-(6) need the bounding box: that of the rows that take part, and
/// their counts. Throws std::invalid_argument on NaN/Inf rows unless drop_non_finite.
template <typename Cloud>
CloudExtent measure_extent(const Cloud& cloud, bool drop_non_finite) {
  CloudExtent extent = extent_of_rows(cloud, 0, cloud.size());
  if (extent.non_finite.count > 0 && !drop_non_finite) throw_non_finite_rows(extent.non_finite, cloud.size());
  return extent;
}

/// [CBC] eqs. (2)-(3) (and the same for z): the grid over a non-empty extent. Throws std::invalid_argument when the
/// cube count would overflow a 64-bit index.
CubeGrid make_grid(const CloudExtent& extent, double edge_m);

}  // namespace terracube::detail
