// Private: the two passes of the dense CBC path over contiguous rows of 3 or 4 scalars: the
// bounding box (eqs. 1-3 need xmin, ymin, zmin) and eqs. (1)-(3) and (7) (cube counts below 2^31). Compiled twice, for
// baseline x86-64 and for AVX2, and picked at run time: no -march flags are needed and the results are bit-identical
// (the same IEEE operations).
#pragma once

#include <cstddef>
#include <cstdint>

namespace terracube::detail {

struct QuantizeConstants {
  double x0, y0, z0;    ///< grid min corner [m]
  double inverse_edge;  ///< 1 / E
  std::uint32_t ixmax;  ///< cubes along x
  std::uint32_t layer;  ///< ixmax * iymax
  /// > 0: float rows may be quantised eight at a time in float arithmetic with this margin
  /// [cubes] (quantize_float_margin); 0: in doubles.
  float float_margin = 0.0F;
};

/// The margin [units] within which a float estimate of a coordinate's position on a grid must not
/// fall from a whole number for its floor to equal the double formula's, along one axis of
/// `cells` cells of `unit` metres from `origin`; 0 when no margin up to 2^-7 does (then the
/// double kernels run). Two kernels use it:
///   the map's binning: s = fl(fl(fl(x - fl(origin)) * fl(1 / unit)) + 1) against
///   floor(fl(fl(x - origin) / unit)) (MapGeometry::index_of), decided where -1 < s - 1 < cells + 1;
///   CBC's quantisation: s = fl(fl(fl(x - fl(x0)) * fl(1 / E)) + 0.5) against
///   floor(fl(fl(fl(x - x0) * fl(1 / E)) + 0.5)) (eqs. 1-3 as cube_grid.hpp's quantize), where
///   0 <= x - x0 <= (cells - 1) E.
/// For a float coordinate x (exact in double), with u = 2^-24 and Q the exact (x - origin) / unit,
/// |Q| < R = cells + 2 where the kernels decide (up to the error below):
///   rounding the origin to float moves Q by at most O = |fl(origin) - origin| / unit;
///   the subtraction, 1 / unit (float after double) and the product round by at most
///   (R + O) (3 u + 2^-52) together, adding 1 or 0.5 by (R + 1) u;
///   the double formula is within R 2^-51 of Q (plus the 0.5 exactly, up to 2^-54).
/// The margin is the smallest power of two from 2^-12 that is at least twice their sum B: a float
/// estimate whose fraction lies more than the margin from a whole number then floors as the formula
/// does. Outside decisions of the map (s - 1 <= -1 or >= cells + 1) hold as long as B < 1. Rows
/// within the margin of a border (about 4 margins of the rows per axis) take the double formula.
float float_estimate_margin(double origin, double unit, std::int64_t cells);

/// The float margin of CBC's quantisation on `grid` (the least margin that serves all three axes,
/// see float_estimate_margin), or 0 when float arithmetic cannot decide exactly on it.
float quantize_float_margin(double x0, double y0, double z0, double edge, std::int64_t ixmax, std::int64_t iymax,
                            std::int64_t izmax);

/// out[r] = I of row r, for `rows` rows of `stride` (3 or 4) scalars starting at `data`. Returns
/// how many rows the float kernel left to the double formula (within its margin of a border; 0
/// when it did not run).
std::size_t quantize_rows(const float* data, std::size_t rows, int stride, const QuantizeConstants& k,
                          std::uint32_t* out);
std::size_t quantize_rows(const double* data, std::size_t rows, int stride, const QuantizeConstants& k,
                          std::uint32_t* out);

/// The scalar part of both bounding-box kernels: rows [first, rows) of kStride scalars folded
/// into min/max; false at the first NaN/Inf coordinate.
template <typename Scalar, int kStride>
inline bool extent_tail(const Scalar* data, std::size_t first, std::size_t rows, double* min, double* max) {
  for (std::size_t row = first; row < rows; ++row) {
    for (int axis = 0; axis < 3; ++axis) {
      const auto v = static_cast<double>(data[row * kStride + static_cast<std::size_t>(axis)]);
      if (!(v - v == 0.0)) return false;
      min[axis] = v < min[axis] ? v : min[axis];
      max[axis] = v > max[axis] ? v : max[axis];
    }
  }
  return true;
}

/// Bounding box of `rows` rows of `stride` (3 or 4) scalars (the fourth is ignored) with AVX2, when
/// the CPU has it: sets `handled` and returns false when an x, y or z is NaN/Inf. Leaves `handled`
/// false without AVX2 (the caller then takes the SSE2 kernel in packed_extent.hpp).
bool extent_rows(const float* data, std::size_t rows, int stride, double* min, double* max, bool& handled);
bool extent_rows(const double* data, std::size_t rows, int stride, double* min, double* max, bool& handled);

/// Leveling and cropping of rows (see LeveledCloud::map, whose arithmetic it repeats):
/// q_i = ((r_i0 x + r_i1 y) + r_i2 z) + t_i, inside when crop_min <= q <= crop_max.
struct LevelConstants {
  double rotation[9];  ///< row-major
  double translation[3];
  double crop_min[3], crop_max[3];
  bool transform = false;
  bool crop = false;
};

/// What level_rows found so far; `size` rows packed.
struct LevelCounts {
  std::size_t size = 0;
  std::size_t num_non_finite = 0;
  std::size_t first_non_finite_row = 0;
  std::size_t num_cropped = 0;
};

/// With AVX2, four rows at a time: packs the selected (`use` null: all) finite rows of `data`
/// (rows `row_stride` scalars apart, x y z `column_stride` apart) that fall inside the crop into
/// xyz (3 doubles each) and their row numbers into out_rows, updating `counts`. Returns how many
/// rows it handled from the first (a multiple of 4; 0 without AVX2): the caller does the rest
/// with LeveledCloud::map.
std::size_t level_rows(const float* data, std::size_t rows, std::ptrdiff_t row_stride, std::ptrdiff_t column_stride,
                       const LevelConstants& k, const std::uint8_t* use, double* xyz, std::uint32_t* out_rows,
                       LevelCounts& counts);
std::size_t level_rows(const double* data, std::size_t rows, std::ptrdiff_t row_stride, std::ptrdiff_t column_stride,
                       const LevelConstants& k, const std::uint8_t* use, double* xyz, std::uint32_t* out_rows,
                       LevelCounts& counts);
/// The same for float rows that are cropped but not transformed, packed as they are, in floats
/// (`k.transform` must be false: then every packed value is a float).
std::size_t level_rows(const float* data, std::size_t rows, std::ptrdiff_t row_stride, std::ptrdiff_t column_stride,
                       const LevelConstants& k, const std::uint8_t* use, float* xyz, std::uint32_t* out_rows,
                       LevelCounts& counts);

/// The bounding box of the rows that take part once leveled and cropped (finite, inside the crop;
/// see level_rows for the arithmetic), with AVX2 four rows at a time: folds their leveled points
/// into min/max and updates `counts` (size: the rows that take part). Returns how many rows it
/// handled from the first (a multiple of 4; 0 without AVX2): the caller does the rest with
/// LeveledCloud::map. Nothing is written per row.
std::size_t extent_leveled_rows(const float* data, std::size_t rows, std::ptrdiff_t row_stride,
                                std::ptrdiff_t column_stride, const LevelConstants& k, double* min, double* max,
                                LevelCounts& counts);
std::size_t extent_leveled_rows(const double* data, std::size_t rows, std::ptrdiff_t row_stride,
                                std::ptrdiff_t column_stride, const LevelConstants& k, double* min, double* max,
                                LevelCounts& counts);

/// Eqs. (1)-(3) and (7) of leveled rows (dense path: every count and the product below 2^31):
/// out[r] = I of row r's leveled point, `no_cube` for a row that takes no part (NaN/Inf or outside
/// the crop). With AVX2 four rows at a time, in the same IEEE operations as LeveledCloud::map
/// followed by quantize_rows; returns how many rows it handled from the first (a multiple of 4;
/// 0 without AVX2).
std::size_t quantize_leveled_rows(const float* data, std::size_t rows, std::ptrdiff_t row_stride,
                                  std::ptrdiff_t column_stride, const LevelConstants& k, const QuantizeConstants& q,
                                  std::uint32_t no_cube, std::uint32_t* out);
std::size_t quantize_leveled_rows(const double* data, std::size_t rows, std::ptrdiff_t row_stride,
                                  std::ptrdiff_t column_stride, const LevelConstants& k, const QuantizeConstants& q,
                                  std::uint32_t no_cube, std::uint32_t* out);

}  // namespace terracube::detail
