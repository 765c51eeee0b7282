#include "quantize_kernels.hpp"

#include <cstdlib>
#include <limits>
#include <type_traits>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#endif

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

bool has_avx2() {
  // TERRACUBE_DISABLE_AVX2 (any value) forces the baseline x86-64 kernels: the tests run once
  // with it, so both builds of every kernel are checked on an AVX2 machine.
  static const bool supported = __builtin_cpu_supports("avx2") && std::getenv("TERRACUBE_DISABLE_AVX2") == nullptr;
  return supported;
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

/// level_rows with AVX2: x, y and z of four rows gathered into doubles, leveled and tested in
/// the same IEEE operations as LeveledCloud::map (no FMA: the target is AVX2 alone), then each
/// lane packed or counted.
template <typename Scalar, bool kTransform, bool kCrop>
__attribute__((target("avx2"))) std::size_t level_avx2(const Scalar* data, std::size_t rows, std::ptrdiff_t row_stride,
                                                       std::ptrdiff_t column_stride, const LevelConstants& k,
                                                       const std::uint8_t* use, double* xyz, std::uint32_t* out_rows,
                                                       LevelCounts& counts) {
  const auto rs = static_cast<int>(row_stride);
  const __m128i index = _mm_setr_epi32(0, rs, 2 * rs, 3 * rs);
  __m256d r[9], t[3], lo[3], hi[3];
  for (int i = 0; i < 9; ++i) r[i] = _mm256_set1_pd(k.rotation[i]);
  for (int i = 0; i < 3; ++i) {
    t[i] = _mm256_set1_pd(k.translation[i]);
    lo[i] = _mm256_set1_pd(k.crop_min[i]);
    hi[i] = _mm256_set1_pd(k.crop_max[i]);
  }
  const __m256d zero = _mm256_setzero_pd();
  std::size_t size = counts.size;
  const std::size_t blocks = rows / 4 * 4;
  alignas(32) double q[3][4];
  for (std::size_t row = 0; row < blocks; row += 4) {
    const Scalar* base = data + static_cast<std::ptrdiff_t>(row) * row_stride;
    const __m256d x = gather_rows(base, index);
    const __m256d y = gather_rows(base + column_stride, index);
    const __m256d z = gather_rows(base + 2 * column_stride, index);
    // (x - x) + (y - y) + (z - z) == 0: all three finite.
    const __m256d finite = _mm256_cmp_pd(
        _mm256_add_pd(_mm256_add_pd(_mm256_sub_pd(x, x), _mm256_sub_pd(y, y)), _mm256_sub_pd(z, z)), zero, _CMP_EQ_OQ);
    __m256d out[3] = {x, y, z};
    if constexpr (kTransform) {
      for (int i = 0; i < 3; ++i) {
        out[i] = _mm256_add_pd(_mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(r[3 * i], x), _mm256_mul_pd(r[3 * i + 1], y)),
                                             _mm256_mul_pd(r[3 * i + 2], z)),
                               t[i]);
      }
    }
    int inside_mask = 0xF;
    if constexpr (kCrop) {
      __m256d inside =
          _mm256_and_pd(_mm256_cmp_pd(out[0], lo[0], _CMP_GE_OQ), _mm256_cmp_pd(out[0], hi[0], _CMP_LE_OQ));
      for (int i = 1; i < 3; ++i) {
        inside = _mm256_and_pd(
            inside, _mm256_and_pd(_mm256_cmp_pd(out[i], lo[i], _CMP_GE_OQ), _mm256_cmp_pd(out[i], hi[i], _CMP_LE_OQ)));
      }
      inside_mask = _mm256_movemask_pd(inside);
    }
    const int finite_mask = _mm256_movemask_pd(finite);
    for (int i = 0; i < 3; ++i) _mm256_store_pd(q[i], out[i]);
    for (int lane = 0; lane < 4; ++lane) {
      const std::size_t row_of_lane = row + static_cast<std::size_t>(lane);
      if (use != nullptr && use[row_of_lane] == 0) continue;
      xyz[3 * size] = q[0][lane];
      xyz[3 * size + 1] = q[1][lane];
      xyz[3 * size + 2] = q[2][lane];
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

#endif

template <typename Scalar>
std::size_t level_dispatch(const Scalar* data, std::size_t rows, std::ptrdiff_t row_stride,
                           std::ptrdiff_t column_stride, const LevelConstants& k, const std::uint8_t* use, double* xyz,
                           std::uint32_t* out_rows, LevelCounts& counts) {
#if defined(TERRACUBE_HAVE_AVX2_KERNELS)
  // The gather's offsets (0 to 3 row strides, plus the column offsets) must fit an int32.
  constexpr std::ptrdiff_t kLimit = std::ptrdiff_t{1} << 28;
  if (!has_avx2() || row_stride <= -kLimit || row_stride >= kLimit || column_stride <= -kLimit ||
      column_stride >= kLimit) {
    return 0;
  }
  if (k.transform) {
    return k.crop
               ? level_avx2<Scalar, true, true>(data, rows, row_stride, column_stride, k, use, xyz, out_rows, counts)
               : level_avx2<Scalar, true, false>(data, rows, row_stride, column_stride, k, use, xyz, out_rows, counts);
  }
  return k.crop
             ? level_avx2<Scalar, false, true>(data, rows, row_stride, column_stride, k, use, xyz, out_rows, counts)
             : level_avx2<Scalar, false, false>(data, rows, row_stride, column_stride, k, use, xyz, out_rows, counts);
#else
  (void)data, (void)rows, (void)row_stride, (void)column_stride, (void)k, (void)use, (void)xyz, (void)out_rows,
      (void)counts;
  return 0;
#endif
}

template <typename Scalar>
void dispatch(const Scalar* data, std::size_t rows, int stride, const QuantizeConstants& k, std::uint32_t* out) {
#if defined(TERRACUBE_HAVE_AVX2_KERNELS)
  if (has_avx2()) {
    quantize_avx2(data, rows, stride, k, out);
    return;
  }
#endif
  quantize_default(data, rows, stride, k, out);
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

void quantize_rows(const float* data, std::size_t rows, int stride, const QuantizeConstants& k, std::uint32_t* out) {
  dispatch(data, rows, stride, k, out);
}

void quantize_rows(const double* data, std::size_t rows, int stride, const QuantizeConstants& k, std::uint32_t* out) {
  dispatch(data, rows, stride, k, out);
}

}  // namespace terracube::detail
