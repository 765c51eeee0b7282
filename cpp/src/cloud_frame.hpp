// Private helpers shared by collapse_overhangs and its baselines: leveling, crop, finiteness
// checks and the bounding box that defines the CBC grid (eqs. 1-9). Not installed.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

#include "packed_extent.hpp"
#include "quantize_kernels.hpp"
#include "terracube/collapse.hpp"
#include "terracube/cube_grid.hpp"

namespace terracube::detail {

/// Throws std::invalid_argument unless `transform` is finite and rigid (a proper rotation).
void check_rigid_transform(const Eigen::Matrix4d& transform, const char* what);

/// Maps input rows into the leveled frame and tells whether a row takes part. The transform and
/// the crop are template switches so that the common case (neither) compiles to a bare loop.
template <typename Scalar, bool kTransform, bool kCrop>
class LeveledCloud {
 public:
  LeveledCloud(const PointsView<Scalar>& points, const Eigen::Matrix4d& transform, const std::optional<CropBox>& crop)
      : points_(points) {
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) rotation_[3 * i + j] = transform(i, j);
      translation_[i] = transform(i, 3);
      crop_min_[i] = crop ? crop->min[i] : -std::numeric_limits<double>::infinity();
      crop_max_[i] = crop ? crop->max[i] : std::numeric_limits<double>::infinity();
    }
  }

  /// Neither a transform nor a crop: every finite row takes part unchanged.
  static constexpr bool kPlain = !kTransform && !kCrop;

  std::size_t size() const { return points_.size; }

  const PointsView<Scalar>& view() const { return points_; }

  /// The transform and crop as the leveling kernels take them.
  LevelConstants constants() const {
    LevelConstants k;
    std::copy_n(rotation_, 9, k.rotation);
    std::copy_n(translation_, 3, k.translation);
    std::copy_n(crop_min_, 3, k.crop_min);
    std::copy_n(crop_max_, 3, k.crop_max);
    k.transform = kTransform;
    k.crop = kCrop;
    return k;
  }

  /// The raw coordinates of `row`, as doubles.
  double raw(std::size_t row, int axis) const {
    return static_cast<double>(
        points_.data[static_cast<std::ptrdiff_t>(row) * points_.row_stride + axis * points_.column_stride]);
  }

  /// Writes the leveled point of `row` to `out` without any check: for rows known to take part.
  void map_unchecked(std::size_t row, Eigen::Vector3d& out) const {
    const Scalar* p = points_.data + static_cast<std::ptrdiff_t>(row) * points_.row_stride;
    level(static_cast<double>(p[0]), static_cast<double>(p[points_.column_stride]),
          static_cast<double>(p[2 * points_.column_stride]), out.data());
  }

  /// Writes the leveled point of `row` to `out`; returns 0 when it takes part, 1 when it is
  /// NaN/Inf, 2 when it falls outside the crop box.
  int map(std::size_t row, Eigen::Vector3d& out) const {
    const Scalar* p = points_.data + static_cast<std::ptrdiff_t>(row) * points_.row_stride;
    const double x = static_cast<double>(p[0]);
    const double y = static_cast<double>(p[points_.column_stride]);
    const double z = static_cast<double>(p[2 * points_.column_stride]);
    // x - x is 0 for finite x and NaN for NaN/Inf: one test for all three coordinates.
    if (!((x - x) + (y - y) + (z - z) == 0.0)) return 1;
    double* q = out.data();
    level(x, y, z, q);
    if constexpr (kCrop) {
      const bool inside = (q[0] >= crop_min_[0]) & (q[1] >= crop_min_[1]) & (q[2] >= crop_min_[2]) &
                          (q[0] <= crop_max_[0]) & (q[1] <= crop_max_[1]) & (q[2] <= crop_max_[2]);
      if (!inside) return 2;
    }
    return 0;
  }

 private:
  /// The leveled point, in plain doubles: q_i = ((r_i0 x + r_i1 y) + r_i2 z) + t_i, the one
  /// definition every path (collapse, maps, baselines) uses.
  void level(double x, double y, double z, double* q) const {
    if constexpr (kTransform) {
      for (int i = 0; i < 3; ++i) {
        q[i] = rotation_[3 * i] * x + rotation_[3 * i + 1] * y + rotation_[3 * i + 2] * z + translation_[i];
      }
    } else {
      q[0] = x, q[1] = y, q[2] = z;
    }
  }

  PointsView<Scalar> points_;
  double rotation_[9];  // row-major
  double translation_[3];
  double crop_min_[3], crop_max_[3];  // +-inf without a crop box
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

/// Counts of the first pass over a cloud.
struct CloudExtent {
  Eigen::Vector3d min = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d max = Eigen::Vector3d::Constant(-std::numeric_limits<double>::infinity());
  std::size_t num_used = 0;
  std::size_t num_non_finite = 0;
  std::size_t first_non_finite_row = 0;
  std::size_t num_cropped = 0;
};

/// Throws the std::invalid_argument of NaN/Inf rows: how many of how many, and the first.
[[noreturn]] inline void throw_non_finite_rows(std::size_t num_non_finite, std::size_t num_rows,
                                               std::size_t first_row) {
  throw std::invalid_argument(std::to_string(num_non_finite) + " of " + std::to_string(num_rows) +
                              " point rows contain NaN or Inf (first at row " + std::to_string(first_row) +
                              "); clean the cloud or set drop_non_finite=True to drop them");
}

/// The rows of a cloud that take part once leveled and cropped, packed x y z in doubles (or, for
/// a float cloud that is only cropped, in floats: its values unchanged), with the input row of
/// each: the plain (branch-free) paths then run on view() (float_view()), and whatever they find
/// per row goes back to rows[k]. Leveling once costs less than leveling row by row in every pass.
struct PackedRows {
  std::vector<double> xyz;          // 3 per row, the first `size` rows valid
  std::vector<float> xyz_float;     // the same in floats (see pack_rows)
  std::vector<std::uint32_t> rows;  // input row of each
  std::size_t size = 0;
  std::size_t num_non_finite = 0;  // selected rows with NaN/Inf
  std::size_t first_non_finite_row = 0;
  std::size_t num_cropped = 0;  // selected finite rows outside the crop box
  PointsView<double> view() const { return PointsView<double>(xyz.data(), size, 3, 1); }
  PointsView<float> float_view() const { return PointsView<float>(xyz_float.data(), size, 3, 1); }
  template <typename Out>
  std::vector<Out>& buffer() {
    if constexpr (std::is_same_v<Out, float>) {
      return xyz_float;
    } else {
      return xyz;
    }
  }
};

/// The calling thread's PackedRows, kept between calls (fresh buffers cost a page fault per
/// 4 kB); release_packed_rows_if_large() drops them after a call that needed over 64 MB.
PackedRows& packed_rows_scratch();
void release_packed_rows_if_large();

/// Fills `out` with the rows of `points` selected by `use` (all when null) that are finite and,
/// leveled by `transform`, inside `crop`, as `Out` (float only for float rows without a transform:
/// then the packed values are the input's). NaN/Inf rows throw unless `drop_non_finite`.
/// Needs points.size < 2^32.
template <typename Out, typename Scalar>
void pack_rows(const PointsView<Scalar>& points, const Eigen::Matrix4d& transform, const std::optional<CropBox>& crop,
               bool drop_non_finite, const std::vector<std::uint8_t>* use, PackedRows& out) {
  static_assert(std::is_same_v<Out, double> || std::is_same_v<Scalar, float>, "floats pack only float rows");
  std::vector<Out>& buffer = out.buffer<Out>();
  if (buffer.size() < 3 * points.size) buffer.resize(3 * points.size);
  if (out.rows.size() < points.size) out.rows.resize(points.size);
  Out* xyz = buffer.data();
  std::uint32_t* rows = out.rows.data();
  // Four rows at a time with AVX2 where the CPU has it, the rest (or all) row by row: the same
  // arithmetic either way.
  std::size_t size = 0;
  visit_leveled(points, transform, crop, [&](const auto& cloud) {
    LevelCounts counts;
    const std::size_t handled =
        level_rows(points.data, points.size, points.row_stride, points.column_stride, cloud.constants(),
                   use != nullptr ? use->data() : nullptr, xyz, rows, counts);
    size = counts.size;
    out.num_non_finite = counts.num_non_finite;
    out.first_non_finite_row = counts.first_non_finite_row;
    out.num_cropped = counts.num_cropped;
    Eigen::Vector3d p = Eigen::Vector3d::Zero();  // written out even for rows that do not take part
    for (std::size_t row = handled; row < cloud.size(); ++row) {
      if (use != nullptr && (*use)[row] == 0) continue;
      const int status = cloud.map(row, p);
      // Written whatever the status; only a row that takes part advances the count.
      for (int axis = 0; axis < 3; ++axis) xyz[3 * size + axis] = static_cast<Out>(p[axis]);
      rows[size] = static_cast<std::uint32_t>(row);
      size += status == 0 ? 1 : 0;
      if (status == 1) {
        if (out.num_non_finite++ == 0) out.first_non_finite_row = row;
      } else if (status == 2) {
        ++out.num_cropped;
      }
    }
  });
  out.size = size;
  if (out.num_non_finite > 0 && !drop_non_finite) {
    throw_non_finite_rows(out.num_non_finite, points.size, out.first_non_finite_row);
  }
}

/// f(view) of the rows of `points` that take part, packed once: as floats for a float cloud that
/// is only cropped (the plain float paths then run on them, with the same results as on doubles,
/// at half the bytes), else leveled in doubles. Returns what f returns.
template <typename Scalar, typename F>
decltype(auto) with_packed_rows(const PointsView<Scalar>& points, const Eigen::Matrix4d& transform,
                                const std::optional<CropBox>& crop, bool drop_non_finite,
                                const std::vector<std::uint8_t>* use, PackedRows& packed, F&& f) {
  if constexpr (std::is_same_v<Scalar, float>) {
    if (transform.isIdentity(0.0)) {
      pack_rows<float>(points, transform, crop, drop_non_finite, use, packed);
      return f(packed.float_view());
    }
  }
  pack_rows<double>(points, transform, crop, drop_non_finite, use, packed);
  return f(packed.view());
}

/// The result of collapse_overhangs on packed.view() as the result for the input rows: `result`
/// (num_points and an all-zero overhang mask of the input's size) receives the rest.
inline void unpack_collapse(CollapseResult packed, const PackedRows& rows, CollapseResult& result) {
  for (std::size_t k = 0; k < rows.size; ++k) result.overhang[rows.rows[k]] = packed.overhang[k];
  result.grid = packed.grid;
  result.occupied_cubes = std::move(packed.occupied_cubes);
  result.removed_cubes = std::move(packed.removed_cubes);
  result.num_used = packed.num_used;
  result.num_cropped = rows.num_cropped;
  result.num_dropped_non_finite = rows.num_non_finite;
  result.num_overhang = packed.num_overhang;
  result.storage_used = packed.storage_used;
}

/// First pass: bounding box of the used points (eqs. 1-3 need xmin, ymin, zmin) and counts.
/// Throws std::invalid_argument on NaN/Inf rows unless drop_non_finite.
/// Bounding box of a plain cloud without per-row branches: two interleaved accumulator sets
/// break the min/max dependency chains. Returns false when a row is NaN/Inf (then the caller
/// takes the checking path).
template <typename Cloud>
bool try_fast_extent(const Cloud& cloud, CloudExtent& extent) {
  bool handled = false;
  double packed_min[3], packed_max[3];
  const bool finite = packed_extent(cloud.view(), packed_min, packed_max, handled);
  if (handled) {
    if (!finite) return false;
    extent.min = {packed_min[0], packed_min[1], packed_min[2]};
    extent.max = {packed_max[0], packed_max[1], packed_max[2]};
    extent.num_used = cloud.size();
    return true;
  }
  // Six running minima/maxima over x y z x y z: two rows per step, independent chains that the
  // compiler turns into packed min/max.
  constexpr double kInf = std::numeric_limits<double>::infinity();
  double lo[6] = {kInf, kInf, kInf, kInf, kInf, kInf};
  double hi[6] = {-kInf, -kInf, -kInf, -kInf, -kInf, -kInf};
  double poison[6] = {0, 0, 0, 0, 0, 0};  // stay 0 while every coordinate is finite, NaN otherwise
  const std::size_t n = cloud.size();
  const std::size_t pairs = n / 2;
  for (std::size_t pair = 0; pair < pairs; ++pair) {
    double v[6];
    for (int k = 0; k < 6; ++k) v[k] = cloud.raw(2 * pair + static_cast<std::size_t>(k / 3), k % 3);
    for (int k = 0; k < 6; ++k) {
      poison[k] += v[k] - v[k];
      lo[k] = v[k] < lo[k] ? v[k] : lo[k];
      hi[k] = v[k] > hi[k] ? v[k] : hi[k];
    }
  }
  if (n % 2 == 1) {
    for (int axis = 0; axis < 3; ++axis) {
      const double v = cloud.raw(n - 1, axis);
      poison[axis] += v - v;
      lo[axis] = v < lo[axis] ? v : lo[axis];
      hi[axis] = v > hi[axis] ? v : hi[axis];
    }
  }
  for (int k = 0; k < 6; ++k) {
    if (!(poison[k] == 0.0)) return false;
  }
  for (int axis = 0; axis < 3; ++axis) {
    extent.min[axis] = std::min(lo[axis], lo[axis + 3]);
    extent.max[axis] = std::max(hi[axis], hi[axis + 3]);
  }
  extent.num_used = n;
  return true;
}

template <typename Cloud>
CloudExtent measure_extent(const Cloud& cloud, bool drop_non_finite) {
  CloudExtent extent;
  if constexpr (Cloud::kPlain) {
    if (try_fast_extent(cloud, extent)) return extent;
  }
  constexpr double kInf = std::numeric_limits<double>::infinity();
  double min_x = kInf, min_y = kInf, min_z = kInf, max_x = -kInf, max_y = -kInf, max_z = -kInf;
  std::size_t first = 0;  // rows before it went through the leveling kernel (AVX2 CPUs)
  if constexpr (!Cloud::kPlain) {
    const auto& view = cloud.view();
    double lo[3] = {kInf, kInf, kInf}, hi[3] = {-kInf, -kInf, -kInf};
    LevelCounts counts;
    first = extent_leveled_rows(view.data, view.size, view.row_stride, view.column_stride, cloud.constants(), lo, hi,
                                counts);
    min_x = lo[0], min_y = lo[1], min_z = lo[2], max_x = hi[0], max_y = hi[1], max_z = hi[2];
    extent.num_used = counts.size;
    extent.num_non_finite = counts.num_non_finite;
    extent.first_non_finite_row = counts.first_non_finite_row;
    extent.num_cropped = counts.num_cropped;
  }
  Eigen::Vector3d p;
  for (std::size_t row = first; row < cloud.size(); ++row) {
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
      if (extent.num_non_finite == 0) extent.first_non_finite_row = row;
      ++extent.num_non_finite;
    } else {
      ++extent.num_cropped;
    }
  }
  extent.min = {min_x, min_y, min_z};
  extent.max = {max_x, max_y, max_z};
  if (extent.num_non_finite > 0 && !drop_non_finite) {
    throw_non_finite_rows(extent.num_non_finite, cloud.size(), extent.first_non_finite_row);
  }
  return extent;
}

/// Eqs. (4)-(6): the grid over a non-empty extent. Throws std::invalid_argument when the cube
/// count would overflow a 64-bit index.
CubeGrid make_grid(const CloudExtent& extent, double edge_m);

/// Throws std::invalid_argument unless the crop box (if any) is finite with min <= max.
void check_crop(const std::optional<CropBox>& crop);

/// Throws std::invalid_argument unless edge > 0 and finite, and sigma >= 1.
void check_collapse_params(const CollapseParams& params);

}  // namespace terracube::detail
