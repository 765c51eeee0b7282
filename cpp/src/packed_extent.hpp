// Private: the bounding box of a plain (N, 3) or (N, 4) row-major cloud with packed min/max: AVX2
// (quantize_kernels.cpp) when the CPU has it, else SSE2. Not installed. Returns false where neither applies.
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>
#include <type_traits>

#include "quantize_kernels.hpp"
#include "terracube/cube_grid.hpp"

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace terracube::detail {

#if defined(__SSE2__)
template <typename Scalar>
struct Packed;

template <>
struct Packed<double> {
  using Vector = __m128d;
  static constexpr int kLanes = 2;
  static Vector load(const double* p) { return _mm_loadu_pd(p); }
  static Vector splat(double v) { return _mm_set1_pd(v); }
  static Vector min(Vector v, Vector acc) { return _mm_min_pd(v, acc); }  // NaN v keeps acc
  static Vector max(Vector v, Vector acc) { return _mm_max_pd(v, acc); }
  static Vector poison(Vector v, Vector acc, Vector mask) {
    return _mm_add_pd(acc, _mm_and_pd(_mm_sub_pd(v, v), mask));
  }
  static Vector lane_mask(const bool* keep) {
    const std::int64_t m0 = keep[0] ? -1 : 0;
    const std::int64_t m1 = keep[1] ? -1 : 0;
    return _mm_castsi128_pd(_mm_set_epi64x(m1, m0));
  }
  static void store(double* p, Vector v) { _mm_storeu_pd(p, v); }
};

template <>
struct Packed<float> {
  using Vector = __m128;
  static constexpr int kLanes = 4;
  static Vector load(const float* p) { return _mm_loadu_ps(p); }
  static Vector splat(float v) { return _mm_set1_ps(v); }
  static Vector min(Vector v, Vector acc) { return _mm_min_ps(v, acc); }
  static Vector max(Vector v, Vector acc) { return _mm_max_ps(v, acc); }
  static Vector poison(Vector v, Vector acc, Vector mask) {
    return _mm_add_ps(acc, _mm_and_ps(_mm_sub_ps(v, v), mask));
  }
  static Vector lane_mask(const bool* keep) {
    return _mm_castsi128_ps(_mm_set_epi32(keep[3] ? -1 : 0, keep[2] ? -1 : 0, keep[1] ? -1 : 0, keep[0] ? -1 : 0));
  }
  static void store(float* p, Vector v) { _mm_storeu_ps(p, v); }
};

/// Rows of kStride scalars (x, y, z, and for kStride 4 one more value that is ignored).
/// Returns false when an x, y or z is NaN/Inf.
template <typename Scalar, int kStride>
bool packed_extent_kernel(const Scalar* data, std::size_t rows, double* min, double* max) {
  using P = Packed<Scalar>;
  constexpr int kLanes = P::kLanes;
  constexpr int kPeriod = kStride == 3 ? 3 * kLanes : (kLanes > kStride ? kLanes : kStride);  // lcm
  constexpr int kVectors = kPeriod / kLanes;
  constexpr std::size_t kRowsPerPeriod = kPeriod / kStride;
  constexpr Scalar kInf = std::numeric_limits<Scalar>::infinity();
  typename P::Vector lo[kVectors], hi[kVectors], bad[kVectors], mask[kVectors];
  for (int v = 0; v < kVectors; ++v) {
    bool keep[kLanes];
    for (int lane = 0; lane < kLanes; ++lane) keep[lane] = (v * kLanes + lane) % kStride < 3;
    lo[v] = P::splat(kInf);
    hi[v] = P::splat(-kInf);
    bad[v] = P::splat(Scalar(0));
    mask[v] = P::lane_mask(keep);
  }
  const std::size_t periods = rows / kRowsPerPeriod;
  const Scalar* p = data;
  for (std::size_t period = 0; period < periods; ++period, p += kPeriod) {
    for (int v = 0; v < kVectors; ++v) {
      const auto x = P::load(p + v * kLanes);
      lo[v] = P::min(x, lo[v]);
      hi[v] = P::max(x, hi[v]);
      bad[v] = P::poison(x, bad[v], mask[v]);
    }
  }
  Scalar lo_s[kPeriod], hi_s[kPeriod], bad_s[kPeriod];
  for (int v = 0; v < kVectors; ++v) {
    P::store(lo_s + v * kLanes, lo[v]);
    P::store(hi_s + v * kLanes, hi[v]);
    P::store(bad_s + v * kLanes, bad[v]);
  }
  for (int k = 0; k < kPeriod; ++k) {
    if (!(bad_s[k] == Scalar(0))) return false;
    const int axis = k % kStride;
    if (axis >= 3) continue;
    min[axis] = lo_s[k] < min[axis] ? static_cast<double>(lo_s[k]) : min[axis];
    max[axis] = hi_s[k] > max[axis] ? static_cast<double>(hi_s[k]) : max[axis];
  }
  return extent_tail<Scalar, kStride>(data, periods * kRowsPerPeriod, rows, min, max);
}
#endif

/// Bounding box of a row-major view with 3 or 4 scalars per row, packed (AVX2 when the CPU has it,
/// else SSE2). Returns false when the
/// layout is not one of those (or SSE2 is missing), or when a coordinate is NaN/Inf; `handled`
/// tells the two apart.
template <typename Scalar>
bool packed_extent(const PointsView<Scalar>& view, double* min, double* max, bool& handled) {
  handled = false;
  if (view.column_stride == 1 && (view.row_stride == 3 || view.row_stride == 4)) {
    const bool finite = extent_rows(view.data, view.size, static_cast<int>(view.row_stride), min, max, handled);
    if (handled) return finite;  // the AVX2 kernel ran
  }
#if defined(__SSE2__)
  constexpr double kInf = std::numeric_limits<double>::infinity();
  for (int axis = 0; axis < 3; ++axis) {
    min[axis] = kInf;
    max[axis] = -kInf;
  }
  if (view.column_stride == 1 && view.row_stride == 3) {
    handled = true;
    return packed_extent_kernel<Scalar, 3>(view.data, view.size, min, max);
  }
  if (view.column_stride == 1 && view.row_stride == 4) {
    handled = true;
    return packed_extent_kernel<Scalar, 4>(view.data, view.size, min, max);
  }
#else
  (void)view;
  (void)min;
  (void)max;
#endif
  return false;
}

}  // namespace terracube::detail
