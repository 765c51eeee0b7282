#include "quantize_kernels.hpp"

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

bool has_avx2() {
  static const bool supported = __builtin_cpu_supports("avx2");
  return supported;
}
#endif

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

}  // namespace

void quantize_rows(const float* data, std::size_t rows, int stride, const QuantizeConstants& k, std::uint32_t* out) {
  dispatch(data, rows, stride, k, out);
}

void quantize_rows(const double* data, std::size_t rows, int stride, const QuantizeConstants& k, std::uint32_t* out) {
  dispatch(data, rows, stride, k, out);
}

}  // namespace terracube::detail
