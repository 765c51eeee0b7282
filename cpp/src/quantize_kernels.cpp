#include "quantize_kernels.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <type_traits>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#endif

#include "cpu_features.hpp"

// No FMA target and ISO C++ (-ffp-contract=off): (x - x0) * (1/E) + 0.5 must round twice, exactly
// as the definition in cube_grid.hpp and every reference implementation computes it.

namespace terracube::detail {

namespace {

template <typename Scalar, int kStride>
inline __attribute__((always_inline)) void quantize_body(const Scalar* data, std::size_t rows,
                                                         const QuantizeConstants& k, std::uint32_t* out) {
  const double x0 = k.x0, y0 = k.y0, z0 = k.z0, inverse = k.inverse_edge;
  const std::uint32_t ixmax = k.ixmax, layer = k.layer;
  for (std::size_t r = 0; r < rows; ++r) {
    const Scalar* p = data + r * kStride;
    const auto ix =
        static_cast<std::uint32_t>(static_cast<std::int32_t>((static_cast<double>(p[0]) - x0) * inverse + 0.5));
    const auto iy =
        static_cast<std::uint32_t>(static_cast<std::int32_t>((static_cast<double>(p[1]) - y0) * inverse + 0.5));
    const auto iz =
        static_cast<std::uint32_t>(static_cast<std::int32_t>((static_cast<double>(p[2]) - z0) * inverse + 0.5));
    out[r] = ix + iy * ixmax + iz * layer;  // eq. (7)
  }
}

template <typename Scalar>
void quantize_default(const Scalar* data, std::size_t rows, int stride, const QuantizeConstants& k,
                      std::uint32_t* out) {
  if (stride == 3) {
    quantize_body<Scalar, 3>(data, rows, k, out);
  } else {
    quantize_body<Scalar, 4>(data, rows, k, out);
  }
}

#if defined(__x86_64__) && defined(__GNUC__)
#define TERRACUBE_HAVE_AVX2_KERNELS 1
template <typename Scalar>
__attribute__((target("avx2"))) void quantize_avx2(const Scalar* data, std::size_t rows, int stride,
                                                   const QuantizeConstants& k, std::uint32_t* out) {
  if (stride == 3) {
    quantize_body<Scalar, 3>(data, rows, k, out);
  } else {
    quantize_body<Scalar, 4>(data, rows, k, out);
  }
}

/// Lanes whose estimate's fraction (estimate - whole, exact) lies clear of the margin: there the
/// truncation `whole` is the double formula's.
__attribute__((target("avx2"))) inline __m256 clear_of_margin(__m256 estimate, __m256i whole, __m256 margin,
                                                              __m256 one_minus_margin) {
  const __m256 fraction = _mm256_sub_ps(estimate, _mm256_cvtepi32_ps(whole));
  return _mm256_and_ps(_mm256_cmp_ps(fraction, margin, _CMP_GT_OQ),
                       _mm256_cmp_ps(fraction, one_minus_margin, _CMP_LT_OQ));
}

/// quantize_body for float rows, eight at a time in float arithmetic, where
/// QuantizeConstants::float_margin > 0 (see float_estimate_margin): a lane whose estimate
/// s = (x - x0) * (1 / E) + 0.5 lies within the margin of a whole number on any axis is quantised
/// again by quantize_body's double formula, so every index is the formula's. The rows a full
/// vector does not cover go through quantize_body.
template <int kStride>
__attribute__((target("avx2"))) std::size_t quantize_float_avx2_8(const float* data, std::size_t rows,
                                                                  const QuantizeConstants& k, std::uint32_t* out) {
  const __m256 x0 = _mm256_set1_ps(static_cast<float>(k.x0));
  const __m256 y0 = _mm256_set1_ps(static_cast<float>(k.y0));
  const __m256 z0 = _mm256_set1_ps(static_cast<float>(k.z0));
  const __m256 inverse = _mm256_set1_ps(static_cast<float>(k.inverse_edge));
  const __m256 half = _mm256_set1_ps(0.5F);
  const __m256 margin = _mm256_set1_ps(k.float_margin), one_minus_margin = _mm256_set1_ps(1.0F - k.float_margin);
  const __m256i ixmax = _mm256_set1_epi32(static_cast<std::int32_t>(k.ixmax));
  const __m256i layer = _mm256_set1_epi32(static_cast<std::int32_t>(k.layer));
  // A 16-byte load at row r reads up to data[r * kStride + 3]: with 3 scalars a row, the last
  // row is left to the scalar tail.
  const std::size_t vector_rows = kStride == 4 ? rows : (rows > 0 ? rows - 1 : 0);
  std::size_t r = 0;
  std::size_t num_undecided = 0;
  for (; r + 8 <= vector_rows; r += 8) {
    const float* p = data + r * kStride;
    // Rows r..r+3 in the low halves, r+4..r+7 in the high halves; a 4x4 transpose per half then
    // gives the x, y and z of the eight rows in order.
    const __m256 a = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(p)), _mm_loadu_ps(p + 4 * kStride), 1);
    const __m256 b =
        _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(p + kStride)), _mm_loadu_ps(p + 5 * kStride), 1);
    const __m256 c =
        _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(p + 2 * kStride)), _mm_loadu_ps(p + 6 * kStride), 1);
    const __m256 d =
        _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(p + 3 * kStride)), _mm_loadu_ps(p + 7 * kStride), 1);
    const __m256 ab_low = _mm256_unpacklo_ps(a, b), ab_high = _mm256_unpackhi_ps(a, b);
    const __m256 cd_low = _mm256_unpacklo_ps(c, d), cd_high = _mm256_unpackhi_ps(c, d);
    const __m256 x = _mm256_shuffle_ps(ab_low, cd_low, _MM_SHUFFLE(1, 0, 1, 0));
    const __m256 y = _mm256_shuffle_ps(ab_low, cd_low, _MM_SHUFFLE(3, 2, 3, 2));
    const __m256 z = _mm256_shuffle_ps(ab_high, cd_high, _MM_SHUFFLE(1, 0, 1, 0));
    // Eqs. (1)-(3): x >= x0 on the dense path, so truncation is the floor.
    const __m256 sx = _mm256_add_ps(_mm256_mul_ps(_mm256_sub_ps(x, x0), inverse), half);
    const __m256 sy = _mm256_add_ps(_mm256_mul_ps(_mm256_sub_ps(y, y0), inverse), half);
    const __m256 sz = _mm256_add_ps(_mm256_mul_ps(_mm256_sub_ps(z, z0), inverse), half);
    const __m256i ix = _mm256_cvttps_epi32(sx), iy = _mm256_cvttps_epi32(sy), iz = _mm256_cvttps_epi32(sz);
    const __m256 decided = _mm256_and_ps(_mm256_and_ps(clear_of_margin(sx, ix, margin, one_minus_margin),
                                                       clear_of_margin(sy, iy, margin, one_minus_margin)),
                                         clear_of_margin(sz, iz, margin, one_minus_margin));
    // Eq. (7), in uint32 arithmetic (the dense path's cube count is below 2^31).
    const __m256i cube =
        _mm256_add_epi32(_mm256_add_epi32(ix, _mm256_mullo_epi32(iy, ixmax)), _mm256_mullo_epi32(iz, layer));
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(out + r), cube);
    const int undecided = ~_mm256_movemask_ps(decided) & 0xFF;
    if (undecided != 0) {  // rare (but for lattice data): a row within the margin of a cube border
      num_undecided += static_cast<std::size_t>(__builtin_popcount(static_cast<unsigned>(undecided)));
      for (int lane = 0; lane < 8; ++lane) {
        if ((undecided >> lane) & 1) {
          const auto row = static_cast<std::size_t>(lane);
          quantize_body<float, kStride>(p + row * kStride, 1, k, out + r + row);
        }
      }
    }
  }
  quantize_body<float, kStride>(data + r * kStride, rows - r, k, out + r);
  return num_undecided;
}

// The AVX2 vector of a scalar type.
template <typename Scalar>
struct Avx2Vector;
template <>
struct Avx2Vector<double> {
  using type = __m256d;
};
template <>
struct Avx2Vector<float> {
  using type = __m256;
};

/// The bounding box with AVX2: the rows repeat a lane pattern every kPeriod scalars (x y z x | y z
/// x y | z x y z for three doubles per row), so each accumulator sees fixed axes and no shuffles
/// are needed. kAcc independent accumulators hide the latency of min/max. NaN is caught by an
/// unordered compare per lane, Inf afterwards by a bound at +-inf.
template <typename Scalar, int kStride>
__attribute__((target("avx2"))) bool extent_avx2(const Scalar* data, std::size_t rows, double* min, double* max) {
  constexpr bool kDouble = std::is_same_v<Scalar, double>;
  using Vector = typename Avx2Vector<Scalar>::type;
  constexpr int kLanes = 32 / static_cast<int>(sizeof(Scalar));
  constexpr int kPeriod = kStride == 3 ? 3 * kLanes : kLanes;  // lcm(kLanes, kStride)
  constexpr int kVectors = kPeriod / kLanes;
  constexpr int kUnroll = kVectors == 3 ? 2 : 4;
  constexpr int kAcc = kVectors * kUnroll;
  constexpr std::size_t kRowsPerStep = static_cast<std::size_t>(kPeriod * kUnroll / kStride);
  constexpr Scalar kInf = std::numeric_limits<Scalar>::infinity();
  Vector lo[kAcc], hi[kAcc], bad[kAcc];
  for (int a = 0; a < kAcc; ++a) {
    if constexpr (kDouble) {
      lo[a] = _mm256_set1_pd(kInf);
      hi[a] = _mm256_set1_pd(-kInf);
      bad[a] = _mm256_setzero_pd();
    } else {
      lo[a] = _mm256_set1_ps(kInf);
      hi[a] = _mm256_set1_ps(-kInf);
      bad[a] = _mm256_setzero_ps();
    }
  }
  const std::size_t steps = rows / kRowsPerStep;
  const Scalar* p = data;
  for (std::size_t step = 0; step < steps; ++step, p += kPeriod * kUnroll) {
    for (int a = 0; a < kAcc; ++a) {
      if constexpr (kDouble) {
        const __m256d x = _mm256_loadu_pd(p + a * kLanes);
        lo[a] = _mm256_min_pd(x, lo[a]);  // a NaN x keeps lo: NaN is caught by `bad`
        hi[a] = _mm256_max_pd(x, hi[a]);
        bad[a] = _mm256_or_pd(bad[a], _mm256_cmp_pd(x, x, _CMP_UNORD_Q));
      } else {
        const __m256 x = _mm256_loadu_ps(p + a * kLanes);
        lo[a] = _mm256_min_ps(x, lo[a]);
        hi[a] = _mm256_max_ps(x, hi[a]);
        bad[a] = _mm256_or_ps(bad[a], _mm256_cmp_ps(x, x, _CMP_UNORD_Q));
      }
    }
  }
  Scalar lo_s[kAcc * kLanes], hi_s[kAcc * kLanes], bad_s[kAcc * kLanes];
  for (int a = 0; a < kAcc; ++a) {
    if constexpr (kDouble) {
      _mm256_storeu_pd(lo_s + a * kLanes, lo[a]);
      _mm256_storeu_pd(hi_s + a * kLanes, hi[a]);
      _mm256_storeu_pd(bad_s + a * kLanes, bad[a]);
    } else {
      _mm256_storeu_ps(lo_s + a * kLanes, lo[a]);
      _mm256_storeu_ps(hi_s + a * kLanes, hi[a]);
      _mm256_storeu_ps(bad_s + a * kLanes, bad[a]);
    }
  }
  for (int k = 0; k < kAcc * kLanes; ++k) {
    const int axis = (k % kPeriod) % kStride;    // accumulator a holds period positions (a % kVectors) * kLanes + lane
    if (axis >= 3) continue;                     // the fourth value of a row (intensity) is not a coordinate
    if (!(bad_s[k] == Scalar(0))) return false;  // an all-ones lane: a NaN went through it
    min[axis] = lo_s[k] < min[axis] ? static_cast<double>(lo_s[k]) : min[axis];
    max[axis] = hi_s[k] > max[axis] ? static_cast<double>(hi_s[k]) : max[axis];
  }
  if (!extent_tail<Scalar, kStride>(data, steps * kRowsPerStep, rows, min, max)) return false;
  constexpr double kInfinity = std::numeric_limits<double>::infinity();
  for (int axis = 0; axis < 3; ++axis) {
    if (min[axis] == -kInfinity || max[axis] == kInfinity) return false;
  }
  return true;
}

/// One coordinate of four rows (`index`: their offsets) as doubles.
__attribute__((target("avx2"), always_inline)) inline __m256d gather_rows(const float* base, __m128i index) {
  // The masked gathers, all lanes on: the plain ones leave GCC 12 warning of an uninitialised source.
  const __m128 all = _mm_castsi128_ps(_mm_set1_epi32(-1));
  return _mm256_cvtps_pd(_mm_mask_i32gather_ps(_mm_setzero_ps(), base, index, all, 4));
}
__attribute__((target("avx2"), always_inline)) inline __m256d gather_rows(const double* base, __m128i index) {
  const __m256d all = _mm256_castsi256_pd(_mm256_set1_epi64x(-1));
  return _mm256_mask_i32gather_pd(_mm256_setzero_pd(), base, index, all, 8);
}

/// x, y and z of four rows whose coordinates are adjacent (column stride 1), rows `row_stride`
/// scalars apart: one load of four scalars per row (the fourth is not used; see
/// kernel_rows), transposed in registers. Cheaper than three gathers.
__attribute__((target("avx2"), always_inline)) inline void load_rows(const float* base, std::ptrdiff_t row_stride,
                                                                     __m256d& x, __m256d& y, __m256d& z) {
  const __m128 r0 = _mm_loadu_ps(base), r1 = _mm_loadu_ps(base + row_stride);
  const __m128 r2 = _mm_loadu_ps(base + 2 * row_stride), r3 = _mm_loadu_ps(base + 3 * row_stride);
  const __m128 xy01 = _mm_unpacklo_ps(r0, r1), xy23 = _mm_unpacklo_ps(r2, r3);  // x0 x1 y0 y1 | x2 x3 y2 y3
  const __m128 zw01 = _mm_unpackhi_ps(r0, r1), zw23 = _mm_unpackhi_ps(r2, r3);  // z0 z1 w0 w1 | z2 z3 w2 w3
  x = _mm256_cvtps_pd(_mm_movelh_ps(xy01, xy23));
  y = _mm256_cvtps_pd(_mm_movehl_ps(xy23, xy01));
  z = _mm256_cvtps_pd(_mm_movelh_ps(zw01, zw23));
}
__attribute__((target("avx2"), always_inline)) inline void load_rows(const double* base, std::ptrdiff_t row_stride,
                                                                     __m256d& x, __m256d& y, __m256d& z) {
  const __m256d r0 = _mm256_loadu_pd(base), r1 = _mm256_loadu_pd(base + row_stride);
  const __m256d r2 = _mm256_loadu_pd(base + 2 * row_stride), r3 = _mm256_loadu_pd(base + 3 * row_stride);
  const __m256d xz01 = _mm256_unpacklo_pd(r0, r1), xz23 = _mm256_unpacklo_pd(r2, r3);  // x0 x1 z0 z1 | x2 x3 z2 z3
  const __m256d yw01 = _mm256_unpackhi_pd(r0, r1), yw23 = _mm256_unpackhi_pd(r2, r3);  // y0 y1 w0 w1 | y2 y3 w2 w3
  x = _mm256_permute2f128_pd(xz01, xz23, 0x20);
  y = _mm256_permute2f128_pd(yw01, yw23, 0x20);
  z = _mm256_permute2f128_pd(xz01, xz23, 0x31);
}

/// How many rows (a multiple of 4) a leveling kernel takes. With row loads a row of three
/// adjacent scalars is read with the scalar after it, which the last row does not have: that
/// row's block is left to the caller.
inline std::size_t kernel_rows(std::size_t rows, std::ptrdiff_t row_stride, bool row_loads) {
  if (row_loads && row_stride < 4) return rows == 0 ? 0 : (rows - 1) / 4 * 4;
  return rows / 4 * 4;
}

/// The leveling constants as vectors.
struct LevelVectors {
  __m256d r[9], t[3], lo[3], hi[3];
};

__attribute__((target("avx2"), always_inline)) inline void broadcast(const LevelConstants& k, LevelVectors& v) {
  for (int i = 0; i < 9; ++i) v.r[i] = _mm256_set1_pd(k.rotation[i]);
  for (int i = 0; i < 3; ++i) {
    v.t[i] = _mm256_set1_pd(k.translation[i]);
    v.lo[i] = _mm256_set1_pd(k.crop_min[i]);
    v.hi[i] = _mm256_set1_pd(k.crop_max[i]);
  }
}

/// Four rows (`index`: their offsets from `base`) leveled into q, in the same IEEE operations as
/// LeveledCloud::map (no FMA: the target is AVX2 alone), with the lanes whose x, y and z are all
/// finite (`finite`) and those whose leveled point lies inside the crop box (`inside`).
template <typename Scalar, bool kTransform, bool kCrop, bool kRows>
__attribute__((target("avx2"), always_inline)) inline void level4(const Scalar* base, std::ptrdiff_t row_stride,
                                                                  __m128i index, std::ptrdiff_t column_stride,
                                                                  const LevelVectors& v, __m256d* q, __m256d& finite,
                                                                  __m256d& inside) {
  __m256d x, y, z;
  if constexpr (kRows) {
    load_rows(base, row_stride, x, y, z);
  } else {
    x = gather_rows(base, index);
    y = gather_rows(base + column_stride, index);
    z = gather_rows(base + 2 * column_stride, index);
  }
  // (x - x) + (y - y) + (z - z) == 0: all three finite.
  finite = _mm256_cmp_pd(_mm256_add_pd(_mm256_add_pd(_mm256_sub_pd(x, x), _mm256_sub_pd(y, y)), _mm256_sub_pd(z, z)),
                         _mm256_setzero_pd(), _CMP_EQ_OQ);
  q[0] = x, q[1] = y, q[2] = z;
  if constexpr (kTransform) {
    for (int i = 0; i < 3; ++i) {
      q[i] = _mm256_add_pd(_mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(v.r[3 * i], x), _mm256_mul_pd(v.r[3 * i + 1], y)),
                                         _mm256_mul_pd(v.r[3 * i + 2], z)),
                           v.t[i]);
    }
  }
  if constexpr (kCrop) {
    inside = _mm256_and_pd(_mm256_cmp_pd(q[0], v.lo[0], _CMP_GE_OQ), _mm256_cmp_pd(q[0], v.hi[0], _CMP_LE_OQ));
    for (int i = 1; i < 3; ++i) {
      inside = _mm256_and_pd(
          inside, _mm256_and_pd(_mm256_cmp_pd(q[i], v.lo[i], _CMP_GE_OQ), _mm256_cmp_pd(q[i], v.hi[i], _CMP_LE_OQ)));
    }
  } else {
    inside = _mm256_castsi256_pd(_mm256_set1_epi64x(-1));
  }
}

/// The number of set bits of a 4-bit lane mask (the baseline target has no popcnt instruction).
constexpr std::uint8_t kLaneCount[16] = {0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4};

/// level_rows with AVX2: four rows leveled and tested at a time, then each lane packed (as `Out`)
/// or counted.
template <typename Scalar, bool kTransform, bool kCrop, bool kRows, typename Out>
__attribute__((target("avx2"))) std::size_t level_avx2(const Scalar* data, std::size_t rows, std::ptrdiff_t row_stride,
                                                       std::ptrdiff_t column_stride, const LevelConstants& k,
                                                       const std::uint8_t* use, Out* xyz, std::uint32_t* out_rows,
                                                       LevelCounts& counts) {
  const auto rs = static_cast<int>(row_stride);
  const __m128i index = _mm_setr_epi32(0, rs, 2 * rs, 3 * rs);
  LevelVectors v;
  broadcast(k, v);
  std::size_t size = counts.size;
  const std::size_t blocks = kernel_rows(rows, row_stride, kRows);
  alignas(32) double q[3][4];
  for (std::size_t row = 0; row < blocks; row += 4) {
    __m256d out[3], finite, inside;
    level4<Scalar, kTransform, kCrop, kRows>(data + static_cast<std::ptrdiff_t>(row) * row_stride, row_stride, index,
                                             column_stride, v, out, finite, inside);
    const int inside_mask = _mm256_movemask_pd(inside);
    const int finite_mask = _mm256_movemask_pd(finite);
    for (int i = 0; i < 3; ++i) _mm256_store_pd(q[i], out[i]);
    for (int lane = 0; lane < 4; ++lane) {
      const std::size_t row_of_lane = row + static_cast<std::size_t>(lane);
      if (use != nullptr && use[row_of_lane] == 0) continue;
      xyz[3 * size] = static_cast<Out>(q[0][lane]);
      xyz[3 * size + 1] = static_cast<Out>(q[1][lane]);
      xyz[3 * size + 2] = static_cast<Out>(q[2][lane]);
      out_rows[size] = static_cast<std::uint32_t>(row_of_lane);
      const int is_finite = (finite_mask >> lane) & 1;
      const int is_inside = (inside_mask >> lane) & 1;
      size += static_cast<std::size_t>(is_finite & is_inside);
      if (is_finite == 0) {
        if (counts.num_non_finite++ == 0) counts.first_non_finite_row = row_of_lane;
      } else {
        counts.num_cropped += static_cast<std::size_t>(1 - is_inside);
      }
    }
  }
  counts.size = size;
  return blocks;
}

/// extent_leveled_rows with AVX2: per axis four running minima and maxima over the lanes that
/// take part (the others fold +-inf). min(q, lo) and max(q, hi) are the scalar path's
/// q < lo ? q : lo and q > hi ? q : hi, lane by lane.
template <typename Scalar, bool kTransform, bool kCrop, bool kRows>
__attribute__((target("avx2"))) std::size_t extent_leveled_avx2(const Scalar* data, std::size_t rows,
                                                                std::ptrdiff_t row_stride, std::ptrdiff_t column_stride,
                                                                const LevelConstants& k, double* min, double* max,
                                                                LevelCounts& counts) {
  const auto rs = static_cast<int>(row_stride);
  const __m128i index = _mm_setr_epi32(0, rs, 2 * rs, 3 * rs);
  LevelVectors v;
  broadcast(k, v);
  constexpr double kInf = std::numeric_limits<double>::infinity();
  const __m256d plus_inf = _mm256_set1_pd(kInf), minus_inf = _mm256_set1_pd(-kInf);
  __m256d lo[3] = {plus_inf, plus_inf, plus_inf}, hi[3] = {minus_inf, minus_inf, minus_inf};
  std::size_t used = 0, cropped = 0;
  const std::size_t blocks = kernel_rows(rows, row_stride, kRows);
  for (std::size_t row = 0; row < blocks; row += 4) {
    __m256d q[3], finite, inside;
    level4<Scalar, kTransform, kCrop, kRows>(data + static_cast<std::ptrdiff_t>(row) * row_stride, row_stride, index,
                                             column_stride, v, q, finite, inside);
    const __m256d take = _mm256_and_pd(finite, inside);
    for (int i = 0; i < 3; ++i) {
      lo[i] = _mm256_min_pd(_mm256_blendv_pd(plus_inf, q[i], take), lo[i]);
      hi[i] = _mm256_max_pd(_mm256_blendv_pd(minus_inf, q[i], take), hi[i]);
    }
    const int finite_mask = _mm256_movemask_pd(finite);
    const int take_mask = _mm256_movemask_pd(take);
    used += kLaneCount[take_mask];
    cropped += kLaneCount[finite_mask & ~take_mask];
    if (finite_mask != 0xF) {
      const int bad = ~finite_mask & 0xF;
      if (counts.num_non_finite == 0) counts.first_non_finite_row = row + static_cast<std::size_t>(__builtin_ctz(bad));
      counts.num_non_finite += kLaneCount[bad];
    }
  }
  alignas(32) double lo_s[3][4], hi_s[3][4];
  for (int i = 0; i < 3; ++i) {
    _mm256_store_pd(lo_s[i], lo[i]);
    _mm256_store_pd(hi_s[i], hi[i]);
    for (int lane = 0; lane < 4; ++lane) {
      min[i] = lo_s[i][lane] < min[i] ? lo_s[i][lane] : min[i];
      max[i] = hi_s[i][lane] > max[i] ? hi_s[i][lane] : max[i];
    }
  }
  counts.size += used;
  counts.num_cropped += cropped;
  return blocks;
}

/// quantize_leveled_rows with AVX2: the leveled points of four rows into cube indices as
/// quantize_body does (double (q - x0) / E + 0.5 truncated to int32, then eq. (7) in uint32
/// arithmetic), `no_cube` for the lanes that take no part.
template <typename Scalar, bool kTransform, bool kCrop, bool kRows>
__attribute__((target("avx2"))) std::size_t quantize_leveled_avx2(const Scalar* data, std::size_t rows,
                                                                  std::ptrdiff_t row_stride,
                                                                  std::ptrdiff_t column_stride, const LevelConstants& k,
                                                                  const QuantizeConstants& c, std::uint32_t no_cube,
                                                                  std::uint32_t* out) {
  const auto rs = static_cast<int>(row_stride);
  const __m128i index = _mm_setr_epi32(0, rs, 2 * rs, 3 * rs);
  LevelVectors v;
  broadcast(k, v);
  const __m256d origin[3] = {_mm256_set1_pd(c.x0), _mm256_set1_pd(c.y0), _mm256_set1_pd(c.z0)};
  const __m256d inverse = _mm256_set1_pd(c.inverse_edge), half = _mm256_set1_pd(0.5);
  const __m128i ixmax = _mm_set1_epi32(static_cast<int>(c.ixmax)), layer = _mm_set1_epi32(static_cast<int>(c.layer));
  const __m128i none = _mm_set1_epi32(static_cast<int>(no_cube));
  const __m256i low_halves = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);  // a 64-bit mask's lanes as 32-bit lanes
  const std::size_t blocks = kernel_rows(rows, row_stride, kRows);
  for (std::size_t row = 0; row < blocks; row += 4) {
    __m256d q[3], finite, inside;
    level4<Scalar, kTransform, kCrop, kRows>(data + static_cast<std::ptrdiff_t>(row) * row_stride, row_stride, index,
                                             column_stride, v, q, finite, inside);
    __m128i i[3];
    for (int a = 0; a < 3; ++a) {
      i[a] = _mm256_cvttpd_epi32(_mm256_add_pd(_mm256_mul_pd(_mm256_sub_pd(q[a], origin[a]), inverse), half));
    }
    const __m128i cube = _mm_add_epi32(_mm_add_epi32(i[0], _mm_mullo_epi32(i[1], ixmax)), _mm_mullo_epi32(i[2], layer));
    const __m128i take = _mm256_castsi256_si128(
        _mm256_permutevar8x32_epi32(_mm256_castpd_si256(_mm256_and_pd(finite, inside)), low_halves));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(out + row), _mm_blendv_epi8(none, cube, take));
  }
  return blocks;
}

/// Whether the gathers' offsets (0 to 3 row strides, plus the column offsets) fit an int32.
bool gather_strides_fit(std::ptrdiff_t row_stride, std::ptrdiff_t column_stride) {
  constexpr std::ptrdiff_t kLimit = std::ptrdiff_t{1} << 28;
  return row_stride > -kLimit && row_stride < kLimit && column_stride > -kLimit && column_stride < kLimit;
}

/// Calls kernel(transform, crop, row_loads) with the std::bool_constant switches that `k` and the
/// layout need: row loads for adjacent coordinates (column stride 1) in rows of at least three
/// scalars going forward, gathers otherwise.
template <typename Kernel>
std::size_t with_level_switches(const LevelConstants& k, std::ptrdiff_t row_stride, std::ptrdiff_t column_stride,
                                Kernel&& kernel) {
  using Yes = std::true_type;
  using No = std::false_type;
  const auto with_rows = [&](auto transform, auto crop) {
    return column_stride == 1 && row_stride >= 3 ? kernel(transform, crop, Yes{}) : kernel(transform, crop, No{});
  };
  if (k.transform) return k.crop ? with_rows(Yes{}, Yes{}) : with_rows(Yes{}, No{});
  return k.crop ? with_rows(No{}, Yes{}) : with_rows(No{}, No{});
}

#endif

template <typename Scalar, typename Out>
std::size_t level_dispatch(const Scalar* data, std::size_t rows, std::ptrdiff_t row_stride,
                           std::ptrdiff_t column_stride, const LevelConstants& k, const std::uint8_t* use, Out* xyz,
                           std::uint32_t* out_rows, LevelCounts& counts) {
#if defined(TERRACUBE_HAVE_AVX2_KERNELS)
  if (!has_avx2() || !gather_strides_fit(row_stride, column_stride)) return 0;
  return with_level_switches(k, row_stride, column_stride, [&](auto transform, auto crop, auto row_loads) {
    return level_avx2<Scalar, decltype(transform)::value, decltype(crop)::value, decltype(row_loads)::value, Out>(
        data, rows, row_stride, column_stride, k, use, xyz, out_rows, counts);
  });
#else
  (void)data, (void)rows, (void)row_stride, (void)column_stride, (void)k, (void)use, (void)xyz, (void)out_rows,
      (void)counts;
  return 0;
#endif
}

template <typename Scalar>
std::size_t extent_leveled_dispatch(const Scalar* data, std::size_t rows, std::ptrdiff_t row_stride,
                                    std::ptrdiff_t column_stride, const LevelConstants& k, double* min, double* max,
                                    LevelCounts& counts) {
#if defined(TERRACUBE_HAVE_AVX2_KERNELS)
  if (!has_avx2() || !gather_strides_fit(row_stride, column_stride)) return 0;
  return with_level_switches(k, row_stride, column_stride, [&](auto transform, auto crop, auto row_loads) {
    return extent_leveled_avx2<Scalar, decltype(transform)::value, decltype(crop)::value, decltype(row_loads)::value>(
        data, rows, row_stride, column_stride, k, min, max, counts);
  });
#else
  (void)data, (void)rows, (void)row_stride, (void)column_stride, (void)k, (void)min, (void)max, (void)counts;
  return 0;
#endif
}

template <typename Scalar>
std::size_t quantize_leveled_dispatch(const Scalar* data, std::size_t rows, std::ptrdiff_t row_stride,
                                      std::ptrdiff_t column_stride, const LevelConstants& k, const QuantizeConstants& q,
                                      std::uint32_t no_cube, std::uint32_t* out) {
#if defined(TERRACUBE_HAVE_AVX2_KERNELS)
  if (!has_avx2() || !gather_strides_fit(row_stride, column_stride)) return 0;
  return with_level_switches(k, row_stride, column_stride, [&](auto transform, auto crop, auto row_loads) {
    return quantize_leveled_avx2<Scalar, decltype(transform)::value, decltype(crop)::value, decltype(row_loads)::value>(
        data, rows, row_stride, column_stride, k, q, no_cube, out);
  });
#else
  (void)data, (void)rows, (void)row_stride, (void)column_stride, (void)k, (void)q, (void)no_cube, (void)out;
  return 0;
#endif
}

template <typename Scalar>
std::size_t dispatch(const Scalar* data, std::size_t rows, int stride, const QuantizeConstants& k, std::uint32_t* out) {
#if defined(TERRACUBE_HAVE_AVX2_KERNELS)
  if (has_avx2()) {
    if constexpr (std::is_same_v<Scalar, float>) {
      if (k.float_margin > 0.0F) {
        return stride == 3 ? quantize_float_avx2_8<3>(data, rows, k, out)
                           : quantize_float_avx2_8<4>(data, rows, k, out);
      }
    }
    quantize_avx2(data, rows, stride, k, out);
    return 0;
  }
#endif
  quantize_default(data, rows, stride, k, out);
  return 0;
}

template <typename Scalar>
bool extent_dispatch(const Scalar* data, std::size_t rows, int stride, double* min, double* max, bool& handled) {
  handled = false;
  constexpr double kInf = std::numeric_limits<double>::infinity();
  for (int axis = 0; axis < 3; ++axis) {
    min[axis] = kInf;
    max[axis] = -kInf;
  }
#if defined(TERRACUBE_HAVE_AVX2_KERNELS)
  if (has_avx2() && (stride == 3 || stride == 4)) {
    handled = true;
    return stride == 3 ? extent_avx2<Scalar, 3>(data, rows, min, max) : extent_avx2<Scalar, 4>(data, rows, min, max);
  }
#else
  (void)data;
  (void)rows;
  (void)stride;
#endif
  return false;
}

}  // namespace

float float_estimate_margin(double origin, double unit, std::int64_t cells) {
  constexpr double kUnit = 0x1p-24;
  const auto inverse = static_cast<float>(1.0 / unit);
  if (!(std::isfinite(inverse) && inverse >= std::numeric_limits<float>::min())) return 0.0F;
  const double rounded_origin = std::abs(static_cast<double>(static_cast<float>(origin)) - origin) / unit;
  const double reach = static_cast<double>(cells) + 2.0;
  const double bound =
      rounded_origin + (reach + rounded_origin) * (3.0 * kUnit + 0x1p-52) + (reach + 1.0) * kUnit + reach * 0x1p-51;
  if (!std::isfinite(bound)) return 0.0F;
  for (float margin = 0x1p-12F; margin <= 0x1p-7F; margin *= 2.0F) {
    if (2.0 * bound <= static_cast<double>(margin)) return margin;
  }
  return 0.0F;
}

float quantize_float_margin(double x0, double y0, double z0, double edge, std::int64_t ixmax, std::int64_t iymax,
                            std::int64_t izmax) {
  const float margin_x = float_estimate_margin(x0, edge, ixmax);
  const float margin_y = float_estimate_margin(y0, edge, iymax);
  const float margin_z = float_estimate_margin(z0, edge, izmax);
  if (margin_x == 0.0F || margin_y == 0.0F || margin_z == 0.0F) return 0.0F;
  return std::max({margin_x, margin_y, margin_z});
}

bool extent_rows(const float* data, std::size_t rows, int stride, double* min, double* max, bool& handled) {
  return extent_dispatch(data, rows, stride, min, max, handled);
}

bool extent_rows(const double* data, std::size_t rows, int stride, double* min, double* max, bool& handled) {
  return extent_dispatch(data, rows, stride, min, max, handled);
}

std::size_t level_rows(const float* data, std::size_t rows, std::ptrdiff_t row_stride, std::ptrdiff_t column_stride,
                       const LevelConstants& k, const std::uint8_t* use, double* xyz, std::uint32_t* out_rows,
                       LevelCounts& counts) {
  return level_dispatch(data, rows, row_stride, column_stride, k, use, xyz, out_rows, counts);
}

std::size_t level_rows(const double* data, std::size_t rows, std::ptrdiff_t row_stride, std::ptrdiff_t column_stride,
                       const LevelConstants& k, const std::uint8_t* use, double* xyz, std::uint32_t* out_rows,
                       LevelCounts& counts) {
  return level_dispatch(data, rows, row_stride, column_stride, k, use, xyz, out_rows, counts);
}

std::size_t level_rows(const float* data, std::size_t rows, std::ptrdiff_t row_stride, std::ptrdiff_t column_stride,
                       const LevelConstants& k, const std::uint8_t* use, float* xyz, std::uint32_t* out_rows,
                       LevelCounts& counts) {
  if (k.transform) throw std::logic_error("level_rows packs floats only for rows that are not transformed");
  return level_dispatch(data, rows, row_stride, column_stride, k, use, xyz, out_rows, counts);
}

std::size_t extent_leveled_rows(const float* data, std::size_t rows, std::ptrdiff_t row_stride,
                                std::ptrdiff_t column_stride, const LevelConstants& k, double* min, double* max,
                                LevelCounts& counts) {
  return extent_leveled_dispatch(data, rows, row_stride, column_stride, k, min, max, counts);
}

std::size_t extent_leveled_rows(const double* data, std::size_t rows, std::ptrdiff_t row_stride,
                                std::ptrdiff_t column_stride, const LevelConstants& k, double* min, double* max,
                                LevelCounts& counts) {
  return extent_leveled_dispatch(data, rows, row_stride, column_stride, k, min, max, counts);
}

std::size_t quantize_leveled_rows(const float* data, std::size_t rows, std::ptrdiff_t row_stride,
                                  std::ptrdiff_t column_stride, const LevelConstants& k, const QuantizeConstants& q,
                                  std::uint32_t no_cube, std::uint32_t* out) {
  return quantize_leveled_dispatch(data, rows, row_stride, column_stride, k, q, no_cube, out);
}

std::size_t quantize_leveled_rows(const double* data, std::size_t rows, std::ptrdiff_t row_stride,
                                  std::ptrdiff_t column_stride, const LevelConstants& k, const QuantizeConstants& q,
                                  std::uint32_t no_cube, std::uint32_t* out) {
  return quantize_leveled_dispatch(data, rows, row_stride, column_stride, k, q, no_cube, out);
}

std::size_t quantize_rows(const float* data, std::size_t rows, int stride, const QuantizeConstants& k,
                          std::uint32_t* out) {
  return dispatch(data, rows, stride, k, out);
}

std::size_t quantize_rows(const double* data, std::size_t rows, int stride, const QuantizeConstants& k,
                          std::uint32_t* out) {
  return dispatch(data, rows, stride, k, out);
}

}  // namespace terracube::detail
