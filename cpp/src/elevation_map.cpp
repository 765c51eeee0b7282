#include "terracube/elevation_map.hpp"

#if defined(__linux__)
#include <sys/mman.h>
#endif

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <iomanip>
#include <iterator>
#include <limits>
#include <new>
#include <sstream>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#endif

#include "cloud_frame.hpp"
#include "cpu_features.hpp"
#include "layer_memory.hpp"
#include "number_text.hpp"
#include "threads.hpp"

namespace terracube {

namespace detail {

void advise_huge_pages(void* data, std::size_t bytes) {
#if defined(__linux__) && defined(MADV_HUGEPAGE)
  constexpr std::uintptr_t kHugePage = std::uintptr_t{2} << 20;
  if (bytes < 2 * kHugePage) return;
  const auto first = reinterpret_cast<std::uintptr_t>(data);
  const std::uintptr_t begin = (first + kHugePage - 1) & ~(kHugePage - 1);
  const std::uintptr_t end = (first + bytes) & ~(kHugePage - 1);
  if (end > begin) (void)madvise(reinterpret_cast<void*>(begin), end - begin, MADV_HUGEPAGE);
#else
  (void)data, (void)bytes;
#endif
}

namespace {

/// The buffers of the layers of maps that were dropped, kept per thread for the layers of the next
/// maps (see recycle_layer). Most recently dropped last; the oldest go first when over kKeepBytes.
class LayerPool {
 public:
  static constexpr std::size_t kKeepBytes = std::size_t{64} << 20;

  LayerPool() = default;
  LayerPool(const LayerPool&) = delete;
  LayerPool& operator=(const LayerPool&) = delete;
  ~LayerPool() { open() = false; }

  /// False once this thread's pool is gone (maps dropped later, at thread or program exit, then
  /// free their layers as usual). A trivially destructible flag, valid all along.
  static bool& open() {
    thread_local bool flag = true;
    return flag;
  }

  void put(Layer&& layer) {
    const std::size_t bytes = sizeof(float) * static_cast<std::size_t>(layer.size());
    if (bytes == 0 || bytes > kKeepBytes) return;
    while (bytes_ + bytes > kKeepBytes) {
      bytes_ -= sizeof(float) * static_cast<std::size_t>(layers_.front().size());
      layers_.erase(layers_.begin());
    }
    layers_.push_back(std::move(layer));
    bytes_ += bytes;
  }

  /// A kept buffer of rows * cols floats, reshaped (no reallocation), when there is one.
  bool take(Eigen::Index rows, Eigen::Index cols, Layer& out) {
    for (auto it = layers_.rbegin(); it != layers_.rend(); ++it) {
      if (it->size() != rows * cols) continue;
      out = std::move(*it);
      layers_.erase(std::next(it).base());
      bytes_ -= sizeof(float) * static_cast<std::size_t>(out.size());
      out.resize(rows, cols);
      return true;
    }
    return false;
  }

 private:
  std::vector<Layer> layers_;
  std::size_t bytes_ = 0;
};

LayerPool* layer_pool() {
  if (!LayerPool::open()) return nullptr;
  thread_local LayerPool pool;
  return &pool;
}

}  // namespace

void recycle_layer(Layer&& layer) {
  LayerPool* pool = layer_pool();
  if (pool == nullptr) return;
  try {
    pool->put(std::move(layer));
  } catch (const std::bad_alloc&) {  // called from ~ElevationMap: the layer is then freed as usual
  }
}

Layer uninitialised_layer(Eigen::Index rows, Eigen::Index cols) {
  Layer layer;
  if (LayerPool* pool = layer_pool(); pool != nullptr && pool->take(rows, cols, layer)) return layer;
  layer.resize(rows, cols);
  advise_huge_pages(layer.data(), sizeof(float) * static_cast<std::size_t>(layer.size()));
  return layer;
}

Layer filled_layer(Eigen::Index rows, Eigen::Index cols, float value) {
  Layer layer = uninitialised_layer(rows, cols);
  layer.setConstant(value);
  return layer;
}

}  // namespace detail

std::optional<CellIndex> MapGeometry::index_of(const Eigen::Vector2d& position) const {
  const Eigen::Vector2d cells = (position - origin_m) / resolution_m;
  if (!(cells.x() >= 0.0 && cells.y() >= 0.0 && cells.x() < size.x() && cells.y() < size.y())) return std::nullopt;
  return CellIndex(static_cast<int>(std::floor(cells.x())), static_cast<int>(std::floor(cells.y())));
}

ElevationMap::~ElevationMap() {
  for (auto& entry : layers_) detail::recycle_layer(std::move(entry.second));
}

ElevationMap::ElevationMap(const MapGeometry& geometry) : geometry_(geometry) {
  if (!(geometry.resolution_m > 0.0) || !std::isfinite(geometry.resolution_m)) {
    throw std::invalid_argument("map resolution must be a positive finite length in metres");
  }
  if ((geometry.size < 0).any()) throw std::invalid_argument("map size must not be negative");
}

void ElevationMap::set_geometry(const MapGeometry& geometry) {
  if (!(geometry.resolution_m > 0.0) || !std::isfinite(geometry.resolution_m)) {
    throw std::invalid_argument("map resolution must be a positive finite length in metres");
  }
  if (!geometry.origin_m.allFinite()) throw std::invalid_argument("map origin must be finite");
  if ((geometry.size < 0).any()) throw std::invalid_argument("map size must not be negative");
  if (!layers_.empty() && (geometry.size != geometry_.size).any()) {
    throw std::invalid_argument("the map's layers are " + std::to_string(geometry_.size.x()) + " x " +
                                std::to_string(geometry_.size.y()) + " cells; a geometry of " +
                                std::to_string(geometry.size.x()) + " x " + std::to_string(geometry.size.y()) +
                                " cells would need new layers");
  }
  geometry_ = geometry;
}

void ElevationMap::add(const std::string& name, float value) {
  add(name, detail::filled_layer(geometry_.size.x(), geometry_.size.y(), value));
}

void ElevationMap::add(const std::string& name, Layer data) {
  if (data.rows() != geometry_.size.x() || data.cols() != geometry_.size.y()) {
    throw std::invalid_argument("layer '" + name + "' is " + std::to_string(data.rows()) + " x " +
                                std::to_string(data.cols()) + " cells, the map is " +
                                std::to_string(geometry_.size.x()) + " x " + std::to_string(geometry_.size.y()));
  }
  for (auto& [existing, layer] : layers_) {
    if (existing == name) {
      layer.array() = data.array();  // in place: views of the old layer stay valid
      detail::recycle_layer(std::move(data));
      return;
    }
  }
  layers_.emplace_back(name, std::move(data));
}

bool ElevationMap::exists(const std::string& name) const {
  return std::any_of(layers_.begin(), layers_.end(), [&](const auto& entry) { return entry.first == name; });
}

const Layer& ElevationMap::get(const std::string& name) const {
  for (const auto& [existing, layer] : layers_) {
    if (existing == name) return layer;
  }
  std::string names;
  for (const auto& entry : layers_) names += (names.empty() ? "" : ", ") + entry.first;
  throw std::out_of_range("elevation map has no layer '" + name + "' (layers: " + names + ")");
}

Layer& ElevationMap::get(const std::string& name) {
  return const_cast<Layer&>(static_cast<const ElevationMap&>(*this).get(name));
}

std::vector<std::string> ElevationMap::layers() const {
  std::vector<std::string> names;
  for (const auto& entry : layers_) names.push_back(entry.first);
  return names;
}

Layer step_layer(const Layer& height) {
  const auto nx = height.rows();
  const auto ny = height.cols();
  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  Layer step = detail::uninitialised_layer(nx, ny);
  // std::max(largest, d) keeps `largest` when d is NaN (a neighbour without data), so no test is
  // needed per neighbour; a cell without data gets NaN at the end.
  const auto cell_step = [&](Eigen::Index i, Eigen::Index j) {
    const float h = height(i, j);
    float largest = 0.0F;
    for (Eigen::Index a = std::max<Eigen::Index>(i - 1, 0); a <= std::min(i + 1, nx - 1); ++a) {
      for (Eigen::Index b = std::max<Eigen::Index>(j - 1, 0); b <= std::min(j + 1, ny - 1); ++b) {
        largest = std::max(largest, std::abs(height(a, b) - h));  // the cell itself adds 0
      }
    }
    return std::isnan(h) ? kNaN : largest;
  };
  for (Eigen::Index i = 0; i < nx; ++i) {
    if (i == 0 || i == nx - 1 || ny < 3) {
      for (Eigen::Index j = 0; j < ny; ++j) step(i, j) = cell_step(i, j);
      continue;
    }
    // Interior rows: the first and last cells take the bounds-checked form, the others a
    // branch-free loop over the three rows (row-major, so each is contiguous) that vectorises.
    step(i, 0) = cell_step(i, 0);
    step(i, ny - 1) = cell_step(i, ny - 1);
    const float* up = &height(i - 1, 0);
    const float* mid = &height(i, 0);
    const float* down = &height(i + 1, 0);
    float* out = &step(i, 0);
    for (Eigen::Index j = 1; j + 1 < ny; ++j) {
      const float h = mid[j];
      float largest = 0.0F;
      largest = std::max(largest, std::abs(up[j - 1] - h));
      largest = std::max(largest, std::abs(up[j] - h));
      largest = std::max(largest, std::abs(up[j + 1] - h));
      largest = std::max(largest, std::abs(mid[j - 1] - h));
      largest = std::max(largest, std::abs(mid[j + 1] - h));
      largest = std::max(largest, std::abs(down[j - 1] - h));
      largest = std::max(largest, std::abs(down[j] - h));
      largest = std::max(largest, std::abs(down[j + 1] - h));
      out[j] = h == h ? largest : kNaN;
    }
  }
  return step;
}

namespace {

void check_elevation_params(const ElevationParams& params) {
  if (!(params.resolution_m > 0.0) || !std::isfinite(params.resolution_m) ||
      !std::isfinite(1.0 / params.resolution_m)) {
    throw std::invalid_argument("resolution must be a positive finite length in metres, got " +
                                detail::number_text(params.resolution_m));
  }
  detail::check_num_threads(params.num_threads, "ElevationParams");
  if (!(params.discontinuity_m > 0.0) || !std::isfinite(params.discontinuity_m)) {
    throw std::invalid_argument("discontinuity must be a positive finite length in metres");
  }
  if (params.origin_m.has_value() != params.size.has_value()) {
    throw std::invalid_argument("give both origin and size for a fixed map extent, or neither");
  }
  if (params.origin_m && !params.origin_m->allFinite()) throw std::invalid_argument("map origin must be finite");
  if (params.size && (params.size->x() <= 0 || params.size->y() <= 0)) {
    throw std::invalid_argument("map size must be at least 1 x 1 cells");
  }
  detail::check_rigid_transform(params.transform, "transform");
  detail::check_crop(params.crop);
}

MapGeometry make_geometry(const ElevationParams& params, const detail::CloudExtent& extent) {
  MapGeometry geometry;
  geometry.resolution_m = params.resolution_m;
  double cells_x = 0.0;
  double cells_y = 0.0;
  if (params.origin_m) {
    geometry.origin_m = *params.origin_m;
    cells_x = params.size->x();
    cells_y = params.size->y();
  } else if (extent.num_used > 0) {
    // Snap outwards to whole cells so that every point falls inside.
    for (int axis = 0; axis < 2; ++axis) {
      double origin = std::floor(extent.min[axis] / params.resolution_m) * params.resolution_m;
      // first * res can round above the minimum (1.7 / 0.1 = 17, 17 * 0.1 = 1.7000000000000002).
      while (origin > extent.min[axis]) origin -= params.resolution_m;
      geometry.origin_m[axis] = origin;
    }
    cells_x = std::floor((extent.max.x() - geometry.origin_m.x()) / params.resolution_m) + 1.0;
    cells_y = std::floor((extent.max.y() - geometry.origin_m.y()) / params.resolution_m) + 1.0;
  }
  if (!(cells_x * cells_y <= static_cast<double>(params.max_cells))) {
    const auto whole = [](double cells) {  // a cell count as a whole number, however large
      std::ostringstream text;
      text << std::fixed << std::setprecision(0) << cells;
      return text.str();
    };
    throw std::invalid_argument("the map would need " + whole(cells_x) + " x " + whole(cells_y) +
                                " cells, over max_cells = " + std::to_string(params.max_cells) +
                                "; use a coarser resolution, a fixed extent or a crop");
  }
  geometry.size = CellIndex(static_cast<int>(cells_x), static_cast<int>(cells_y));
  return geometry;
}

/// Exact cell coordinate along one axis: floor((coordinate - origin) / resolution), the formula of
/// MapGeometry::index_of. Dividing costs several cycles per point, so the quotient is first
/// estimated by multiplying with 1 / resolution: estimate and quotient differ by at most three
/// roundings (|q| * 3.4e-16 < 1e-6 for the |q| < 2^31 + 1 that matter), so their floors agree
/// unless the estimate lies within 2^-16 of a whole number; only such points (and points on cell
/// borders, the same case) are divided.
class AxisBinning {
 public:
  AxisBinning(double origin_m, double resolution_m, std::int64_t cells)
      : origin_(origin_m),
        resolution_(resolution_m),
        inverse_(1.0 / resolution_m),
        cells_(cells),
        upper_(static_cast<double>(cells) + 1.0) {}

  /// The cell index in [0, cells), or -1 when the coordinate lies outside.
  std::int64_t operator()(double coordinate) const {
    const double offset = coordinate - origin_;
    const double estimate = offset * inverse_;
    if (!(estimate > -1.0 && estimate < upper_)) return -1;  // outside by about a cell or more (or NaN)
    // estimate + 1 lies in (0, cells + 2), where truncation is floor. Its rounding is far below
    // the margin, so it too can only move the floor when the exact path takes over.
    const double shifted = estimate + 1.0;
    const auto whole = static_cast<std::int64_t>(shifted);
    const double fraction = shifted - static_cast<double>(whole);
    constexpr double kMargin = 1.0 / 65536.0;
    if (!(fraction > kMargin && fraction < 1.0 - kMargin)) return exact(offset);
    const std::int64_t index = whole - 1;
    return index < cells_ ? index : -1;  // index >= -1 here
  }

  /// The defining formula, division and floor.
  std::int64_t exact(double offset) const {
    const double cell = std::floor(offset / resolution_);
    return cell >= 0.0 && cell < static_cast<double>(cells_) ? static_cast<std::int64_t>(cell) : -1;
  }

 private:
  double origin_;
  double resolution_;
  double inverse_;
  std::int64_t cells_;
  double upper_;
};

/// Whether the mapped z of every row of a cloud is exactly a float: a float cloud, not transformed.
template <typename Cloud>
struct ExactFloatHeights : std::false_type {};
template <bool kCrop>
struct ExactFloatHeights<detail::LeveledCloud<float, false, kCrop>> : std::true_type {};

/// Cell codes of the first pass over the points (cells themselves are below kSlow).
constexpr std::uint32_t kOutside = std::numeric_limits<std::uint32_t>::max();
/// The row needs the checking path: NaN/Inf, or a coordinate within rounding of a cell border.
constexpr std::uint32_t kSlow = kOutside - 1;

/// Constants of the binning kernel: AxisBinning's estimate for both axes at once.
struct BinningConstants {
  double origin_x, origin_y, inverse;  // inverse = 1 / resolution
  double upper_x, upper_y;             // cells + 1 along x and y
  std::int32_t nx, ny;
  /// > 0: float rows may be binned in float arithmetic with this margin [cells] (see
  /// detail::float_estimate_margin); 0: they are binned in doubles.
  float float_margin = 0.0F;
  double resolution = 0.0;  ///< for the exact formula of the rows the estimate leaves (kSlow)
};

/// The cell code of each row of a plain (untransformed, uncropped) cloud with rows `kStride`
/// scalars apart: the cell when AxisBinning's estimate decides it on both axes (the same
/// arithmetic, without branches so that it vectorises), kOutside when an axis puts the row
/// outside, else kSlow (NaN/Inf, or an estimate within the margin of a border; the caller
/// re-bins those rows with the exact formula).
template <typename Scalar, int kStride>
inline __attribute__((always_inline)) bool bin_rows_body(const Scalar* data, std::size_t rows,
                                                         const BinningConstants& k, std::uint32_t* out) {
  bool any_slow = false;
  constexpr double kMargin = 1.0 / 65536.0;
  const double origin_x = k.origin_x, origin_y = k.origin_y, inverse = k.inverse;
  const double upper_x = k.upper_x, upper_y = k.upper_y;
  const std::int32_t nx = k.nx, ny = k.ny;
  for (std::size_t r = 0; r < rows; ++r) {
    const Scalar* p = data + r * kStride;
    const double x = static_cast<double>(p[0]);
    const double y = static_cast<double>(p[1]);
    const double z = static_cast<double>(p[2]);
    // Comparisons combine with & and |, not && and ||: no branches, so the loop vectorises.
    const bool finite = (x - x) + (y - y) + (z - z) == 0.0;
    const double ex = (x - origin_x) * inverse;
    const double ey = (y - origin_y) * inverse;
    const bool near_x = (ex > -1.0) & (ex < upper_x);  // else outside by about a cell or more (or NaN)
    const bool near_y = (ey > -1.0) & (ey < upper_y);
    // estimate + 1 lies in (0, cells + 2) where near: truncation is floor there (0.5 elsewhere,
    // a defined conversion whose result is not used).
    const double sx = near_x ? ex + 1.0 : 0.5;
    const double sy = near_y ? ey + 1.0 : 0.5;
    const auto wx = static_cast<std::int32_t>(sx);
    const auto wy = static_cast<std::int32_t>(sy);
    const double fx = sx - static_cast<double>(wx);
    const double fy = sy - static_cast<double>(wy);
    const bool clear_x = (fx > kMargin) & (fx < 1.0 - kMargin);
    const bool clear_y = (fy > kMargin) & (fy < 1.0 - kMargin);
    const std::int32_t i = wx - 1;  // >= -1
    const std::int32_t j = wy - 1;
    const bool in_x = (i >= 0) & (i < nx);
    const bool in_y = (j >= 0) & (j < ny);
    const bool outside = !near_x | !near_y | (clear_x & !in_x) | (clear_y & !in_y);
    const bool decided = clear_x & clear_y & in_x & in_y & finite;
    const auto cell = static_cast<std::uint32_t>(i) * static_cast<std::uint32_t>(ny) + static_cast<std::uint32_t>(j);
    out[r] = decided ? cell : (outside & finite ? kOutside : kSlow);
    any_slow |= out[r] == kSlow;
  }
  return any_slow;
}

template <typename Scalar>
bool bin_rows_default(const Scalar* data, std::size_t rows, int stride, const BinningConstants& k, std::uint32_t* out) {
  return stride == 3 ? bin_rows_body<Scalar, 3>(data, rows, k, out) : bin_rows_body<Scalar, 4>(data, rows, k, out);
}

#if defined(__x86_64__) && defined(__GNUC__)
#define TERRACUBE_HAVE_AVX2_BINNING 1
/// bin_rows_body's decision for four rows whose x, y and z are in AVX2 doubles: the same estimate
/// (no FMA target, so every product and sum rounds as in the scalar code), hence the same codes, with
/// fewer operations: the estimate + 1 is clamped to [0.5, cells + 1.5] instead of tested against
/// both ends (a row clamped at either end lands half a cell outside the map, clear of the margin,
/// and is outside: its quotient is below -0.5 or above cells + 0.5 within the margin; bin_rows_body
/// may send some of these rows to the exact formula instead, which puts them outside too), the
/// margin is a distance to the nearest whole number, and 0 <= i < cells one unsigned compare.
/// Writes the four codes to `out` and returns the mask of rows that got kSlow.
struct Avx2Binning {
  __m256d origin_x, origin_y, inverse, top_x, top_y, one, half, zero, margin, magnitude;
  __m128i minus_one_i, last_i, last_j, ny;

  __attribute__((target("avx2"))) explicit Avx2Binning(const BinningConstants& k)
      : origin_x(_mm256_set1_pd(k.origin_x)),
        origin_y(_mm256_set1_pd(k.origin_y)),
        inverse(_mm256_set1_pd(k.inverse)),
        top_x(_mm256_set1_pd(static_cast<double>(k.nx) + 1.5)),
        top_y(_mm256_set1_pd(static_cast<double>(k.ny) + 1.5)),
        one(_mm256_set1_pd(1.0)),
        half(_mm256_set1_pd(0.5)),
        zero(_mm256_setzero_pd()),
        margin(_mm256_set1_pd(1.0 / 65536.0)),
        magnitude(_mm256_castsi256_pd(_mm256_set1_epi64x(0x7FFFFFFFFFFFFFFF))),
        minus_one_i(_mm_set1_epi32(-1)),
        last_i(_mm_set1_epi32(k.nx - 1)),
        last_j(_mm_set1_epi32(k.ny - 1)),
        ny(_mm_set1_epi32(k.ny)) {}

  __attribute__((target("avx2"), always_inline)) inline int decide(__m256d x, __m256d y, __m256d z,
                                                                   std::uint32_t* out) const {
    // x + y + z is finite when all three are; a finite row whose sum overflows goes to the exact
    // formula, which bins it.
    const __m256d sum = _mm256_add_pd(_mm256_add_pd(x, y), z);
    const int finite = _mm256_movemask_pd(_mm256_cmp_pd(_mm256_sub_pd(sum, sum), zero, _CMP_EQ_OQ));
    const __m256d ex = _mm256_mul_pd(_mm256_sub_pd(x, origin_x), inverse);
    const __m256d ey = _mm256_mul_pd(_mm256_sub_pd(y, origin_y), inverse);
    // max gives its second operand (0.5) for NaN; the finite mask then decides.
    const __m256d sx = _mm256_min_pd(_mm256_max_pd(_mm256_add_pd(ex, one), half), top_x);
    const __m256d sy = _mm256_min_pd(_mm256_max_pd(_mm256_add_pd(ey, one), half), top_y);
    const __m128i wx = _mm256_cvttpd_epi32(sx);
    const __m128i wy = _mm256_cvttpd_epi32(sy);
    // sx - trunc(sx) in (margin, 1 - margin) is: more than the margin from the nearest whole number
    // (both differences exact).
    const __m256d round_x = _mm256_round_pd(sx, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    const __m256d round_y = _mm256_round_pd(sy, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    const int clear_x =
        _mm256_movemask_pd(_mm256_cmp_pd(_mm256_and_pd(_mm256_sub_pd(sx, round_x), magnitude), margin, _CMP_GT_OQ));
    const int clear_y =
        _mm256_movemask_pd(_mm256_cmp_pd(_mm256_and_pd(_mm256_sub_pd(sy, round_y), magnitude), margin, _CMP_GT_OQ));
    const __m128i i = _mm_add_epi32(wx, minus_one_i);
    const __m128i j = _mm_add_epi32(wy, minus_one_i);
    // 0 <= i < nx: i (-1 wraps to 2^32 - 1) is at most nx - 1, unsigned.
    const int in_x = _mm_movemask_ps(_mm_castsi128_ps(_mm_cmpeq_epi32(_mm_min_epu32(i, last_i), i)));
    const int in_y = _mm_movemask_ps(_mm_castsi128_ps(_mm_cmpeq_epi32(_mm_min_epu32(j, last_j), j)));
    const int decided = clear_x & clear_y & in_x & in_y & finite;
    const int outside = ((clear_x & ~in_x) | (clear_y & ~in_y)) & finite & 0xF;
    const __m128i cell = _mm_add_epi32(_mm_mullo_epi32(i, ny), j);
    if (decided == 0xF) {
      _mm_storeu_si128(reinterpret_cast<__m128i*>(out), cell);
    } else if (outside == 0xF) {
      _mm_storeu_si128(reinterpret_cast<__m128i*>(out), _mm_set1_epi32(-1));  // kOutside
    } else {
      alignas(16) std::uint32_t cells[4];
      _mm_store_si128(reinterpret_cast<__m128i*>(cells), cell);
      for (int lane = 0; lane < 4; ++lane) {
        out[lane] = (decided >> lane) & 1 ? cells[lane] : ((outside >> lane) & 1 ? kOutside : kSlow);
      }
    }
    return ~(decided | outside) & 0xF;
  }
};

/// bin_rows_body for float rows, four at a time in AVX2 doubles (Avx2Binning).
template <int kStride>
__attribute__((target("avx2"))) bool bin_float_rows_avx2(const float* data, std::size_t rows, const BinningConstants& k,
                                                         std::uint32_t* out) {
  const Avx2Binning binning(k);
  // A 16-byte load at row r reads up to data[r * kStride + 3]: with 3 scalars a row, the last
  // row is left to the scalar tail.
  const std::size_t vector_rows = kStride == 4 ? rows : (rows > 0 ? rows - 1 : 0);
  std::size_t r = 0;
  int slow = 0;
  for (; r + 4 <= vector_rows; r += 4) {
    const float* p = data + r * kStride;
    __m128 x4 = _mm_loadu_ps(p);
    __m128 y4 = _mm_loadu_ps(p + kStride);
    __m128 z4 = _mm_loadu_ps(p + 2 * kStride);
    __m128 w4 = _mm_loadu_ps(p + 3 * kStride);
    _MM_TRANSPOSE4_PS(x4, y4, z4, w4);  // now the x, y, z (and 4th) values of the 4 rows
    slow |= binning.decide(_mm256_cvtps_pd(x4), _mm256_cvtps_pd(y4), _mm256_cvtps_pd(z4), out + r);
  }
  return bin_rows_body<float, kStride>(data + r * kStride, rows - r, k, out + r) || slow != 0;
}

/// bin_rows_body for double rows, four at a time (Avx2Binning), the rows' x, y and z gathered
/// from three (3 scalars a row) or four (4 a row) 32-byte loads.
template <int kStride>
__attribute__((target("avx2"))) bool bin_double_rows_avx2(const double* data, std::size_t rows,
                                                          const BinningConstants& k, std::uint32_t* out) {
  const Avx2Binning binning(k);
  std::size_t r = 0;
  int slow = 0;
  for (; r + 4 <= rows; r += 4) {
    const double* p = data + r * kStride;
    __m256d x, y, z;
    if constexpr (kStride == 3) {
      const __m256d a = _mm256_loadu_pd(p);                   // x0 y0 z0 x1
      const __m256d b = _mm256_loadu_pd(p + 4);               // y1 z1 x2 y2
      const __m256d c = _mm256_loadu_pd(p + 8);               // z2 x3 y3 z3
      const __m256d xy = _mm256_blend_pd(a, b, 0b1100);       // x0 y0 x2 y2
      const __m256d zx = _mm256_permute2f128_pd(a, c, 0x21);  // z0 x1 z2 x3
      const __m256d yz = _mm256_blend_pd(b, c, 0b1100);       // y1 z1 y3 z3
      x = _mm256_blend_pd(xy, zx, 0b1010);
      y = _mm256_shuffle_pd(xy, yz, 0b0101);
      z = _mm256_blend_pd(zx, yz, 0b1010);
    } else {
      const __m256d a = _mm256_loadu_pd(p), b = _mm256_loadu_pd(p + 4);
      const __m256d c = _mm256_loadu_pd(p + 8), d = _mm256_loadu_pd(p + 12);
      const __m256d ab_low = _mm256_unpacklo_pd(a, b), ab_high = _mm256_unpackhi_pd(a, b);  // x0 x1 z0 z1, y0 y1 w0 w1
      const __m256d cd_low = _mm256_unpacklo_pd(c, d), cd_high = _mm256_unpackhi_pd(c, d);
      x = _mm256_permute2f128_pd(ab_low, cd_low, 0x20);
      y = _mm256_permute2f128_pd(ab_high, cd_high, 0x20);
      z = _mm256_permute2f128_pd(ab_low, cd_low, 0x31);
    }
    slow |= binning.decide(x, y, z, out + r);
  }
  return bin_rows_body<double, kStride>(data + r * kStride, rows - r, k, out + r) || slow != 0;
}

/// The cell codes of bin_rows_body for float rows, eight at a time in float arithmetic: the
/// estimate has a float's precision, so it runs only where detail::float_estimate_margin gives a margin,
/// and rows within that margin of a border get kSlow. The rows
/// a full vector does not cover go through bin_rows_body.
template <int kStride>
__attribute__((target("avx2"))) bool bin_float_rows_avx2_8(const float* data, std::size_t rows,
                                                           const BinningConstants& k, std::uint32_t* out) {
  const __m256 origin_x = _mm256_set1_ps(static_cast<float>(k.origin_x));
  const __m256 origin_y = _mm256_set1_ps(static_cast<float>(k.origin_y));
  const __m256 inverse = _mm256_set1_ps(static_cast<float>(k.inverse));
  // Estimates + 1 are clamped to [0.5, cells + 1.5] (exact: there is a float margin only for
  // fewer than 2^16 cells). A row clamped at either end lands half a cell outside the map, clear
  // of the margin, and is outside: its quotient is below -0.5 or above cells + 0.5 within the
  // margin. (Without the clamp, cvtt would overflow past 2^31.)
  const __m256 top_x = _mm256_set1_ps(static_cast<float>(k.nx) + 1.5F);
  const __m256 top_y = _mm256_set1_ps(static_cast<float>(k.ny) + 1.5F);
  const __m256 one = _mm256_set1_ps(1.0F), half = _mm256_set1_ps(0.5F);
  const __m256 zero = _mm256_setzero_ps();
  const __m256 margin = _mm256_set1_ps(k.float_margin);
  const __m256 magnitude = _mm256_castsi256_ps(_mm256_set1_epi32(0x7FFFFFFF));
  const __m256i minus_one_i = _mm256_set1_epi32(-1), ny = _mm256_set1_epi32(k.ny);
  const __m256i last_i = _mm256_set1_epi32(k.nx - 1), last_j = _mm256_set1_epi32(k.ny - 1);
  const __m256i outside_code = _mm256_set1_epi32(static_cast<std::int32_t>(kOutside));
  const __m256i slow_code = _mm256_set1_epi32(static_cast<std::int32_t>(kSlow));
  // A 16-byte load at row r reads up to data[r * kStride + 3]: with 3 scalars a row, the last
  // row is left to the scalar tail.
  const std::size_t vector_rows = kStride == 4 ? rows : (rows > 0 ? rows - 1 : 0);
  std::size_t r = 0;
  int slow = 0;
  for (; r + 8 <= vector_rows; r += 8) {
    const float* p = data + r * kStride;
    // Rows r..r+3 in the low halves, r+4..r+7 in the high halves; a 4x4 transpose per half then
    // gives the x, y and z of the eight rows in order.
    __m256 a = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(p)), _mm_loadu_ps(p + 4 * kStride), 1);
    __m256 b =
        _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(p + kStride)), _mm_loadu_ps(p + 5 * kStride), 1);
    __m256 c =
        _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(p + 2 * kStride)), _mm_loadu_ps(p + 6 * kStride), 1);
    __m256 d =
        _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(p + 3 * kStride)), _mm_loadu_ps(p + 7 * kStride), 1);
    const __m256 ab_low = _mm256_unpacklo_ps(a, b), ab_high = _mm256_unpackhi_ps(a, b);
    const __m256 cd_low = _mm256_unpacklo_ps(c, d), cd_high = _mm256_unpackhi_ps(c, d);
    const __m256 x = _mm256_shuffle_ps(ab_low, cd_low, _MM_SHUFFLE(1, 0, 1, 0));
    const __m256 y = _mm256_shuffle_ps(ab_low, cd_low, _MM_SHUFFLE(3, 2, 3, 2));
    const __m256 z = _mm256_shuffle_ps(ab_high, cd_high, _MM_SHUFFLE(1, 0, 1, 0));
    // x + y + z is finite when all three are (NaN or an infinity makes it NaN or infinite); a
    // finite row whose sum overflows is sent to the exact formula, which bins it.
    const __m256 sum = _mm256_add_ps(_mm256_add_ps(x, y), z);
    const __m256i finite = _mm256_castps_si256(_mm256_cmp_ps(_mm256_sub_ps(sum, sum), zero, _CMP_EQ_OQ));
    // Estimate + 1, clamped (max gives its second operand for NaN, then the finite mask decides).
    const __m256 ex = _mm256_mul_ps(_mm256_sub_ps(x, origin_x), inverse);
    const __m256 ey = _mm256_mul_ps(_mm256_sub_ps(y, origin_y), inverse);
    const __m256 sx = _mm256_min_ps(_mm256_max_ps(_mm256_add_ps(ex, one), half), top_x);
    const __m256 sy = _mm256_min_ps(_mm256_max_ps(_mm256_add_ps(ey, one), half), top_y);
    const __m256i wx = _mm256_cvttps_epi32(sx);
    const __m256i wy = _mm256_cvttps_epi32(sy);
    // Clear of a border: more than the margin from the nearest whole number (the difference is
    // exact). The same rows as sx - trunc(sx) in (margin, 1 - margin).
    const __m256 round_x = _mm256_round_ps(sx, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    const __m256 round_y = _mm256_round_ps(sy, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    const __m256i clear_x =
        _mm256_castps_si256(_mm256_cmp_ps(_mm256_and_ps(_mm256_sub_ps(sx, round_x), magnitude), margin, _CMP_GT_OQ));
    const __m256i clear_y =
        _mm256_castps_si256(_mm256_cmp_ps(_mm256_and_ps(_mm256_sub_ps(sy, round_y), magnitude), margin, _CMP_GT_OQ));
    const __m256i i = _mm256_add_epi32(wx, minus_one_i);
    const __m256i j = _mm256_add_epi32(wy, minus_one_i);
    // 0 <= i < nx: i (-1 wraps to 2^32 - 1) is at most nx - 1, unsigned.
    const __m256i in_x = _mm256_cmpeq_epi32(_mm256_min_epu32(i, last_i), i);
    const __m256i in_y = _mm256_cmpeq_epi32(_mm256_min_epu32(j, last_j), j);
    const __m256i decided =
        _mm256_and_si256(_mm256_and_si256(_mm256_and_si256(clear_x, clear_y), _mm256_and_si256(in_x, in_y)), finite);
    const __m256i outside = _mm256_and_si256(
        _mm256_or_si256(_mm256_andnot_si256(in_x, clear_x), _mm256_andnot_si256(in_y, clear_y)), finite);
    const __m256i cell = _mm256_add_epi32(_mm256_mullo_epi32(i, ny), j);
    const __m256i code = _mm256_blendv_epi8(_mm256_blendv_epi8(slow_code, outside_code, outside), cell, decided);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(out + r), code);
    slow |= _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(code, slow_code)));
  }
  return bin_rows_body<float, kStride>(data + r * kStride, rows - r, k, out + r) || slow != 0;
}

template <typename Scalar>
bool bin_rows_avx2(const Scalar* data, std::size_t rows, int stride, const BinningConstants& k, std::uint32_t* out) {
  if constexpr (std::is_same_v<Scalar, float>) {
    if (k.float_margin > 0.0F) {
      return stride == 3 ? bin_float_rows_avx2_8<3>(data, rows, k, out) : bin_float_rows_avx2_8<4>(data, rows, k, out);
    }
    return stride == 3 ? bin_float_rows_avx2<3>(data, rows, k, out) : bin_float_rows_avx2<4>(data, rows, k, out);
  } else {
    return stride == 3 ? bin_double_rows_avx2<3>(data, rows, k, out) : bin_double_rows_avx2<4>(data, rows, k, out);
  }
}

/// The rows of `codes[0, rows)` that got kSlow, listed into `slow_rows` from slow_rows[num_slow],
/// eight codes at a time (a block on a fine map holds a few such rows among a thousand). Returns
/// the rows gone through (a multiple of 8).
__attribute__((target("avx2"))) std::size_t list_slow_rows_avx2(const std::uint32_t* codes, std::size_t rows,
                                                                std::uint32_t* slow_rows, std::size_t& num_slow) {
  const __m256i slow_code = _mm256_set1_epi32(static_cast<std::int32_t>(kSlow));
  std::size_t k = 0;
  for (; k + 8 <= rows; k += 8) {
    const __m256i code = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(codes + k));
    auto mask = static_cast<unsigned>(_mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(code, slow_code))));
    for (; mask != 0; mask &= mask - 1) slow_rows[num_slow++] = static_cast<std::uint32_t>(k + __builtin_ctz(mask));
  }
  return k;
}

/// The defining formula (MapGeometry::index_of, AxisBinning::exact: floor((coordinate - origin) /
/// resolution) on each axis) for the listed rows `rows[0, count)` of rows `kStride` scalars apart,
/// four at a time: IEEE division and floor round as the scalar code does. Writes the cell or
/// kOutside to codes[row]; a row with a NaN/Inf coordinate keeps its code (kSlow) for the checking
/// path. Returns how many listed rows it went through from the first (a multiple of 4).
template <typename Scalar, int kStride>
__attribute__((target("avx2"))) std::size_t bin_exact_rows_avx2(const Scalar* data, const std::uint32_t* rows,
                                                                std::size_t count, const BinningConstants& k,
                                                                std::uint32_t* codes) {
  const __m256d origin_x = _mm256_set1_pd(k.origin_x), origin_y = _mm256_set1_pd(k.origin_y);
  const __m256d resolution = _mm256_set1_pd(k.resolution), zero = _mm256_setzero_pd();
  const __m256d cells_x = _mm256_set1_pd(k.nx), cells_y = _mm256_set1_pd(k.ny);
  std::size_t n = 0;
  for (; n + 4 <= count; n += 4) {
    const auto at = [&](int lane, int axis) {
      return static_cast<double>(
          data[std::size_t{rows[n + static_cast<std::size_t>(lane)]} * kStride + static_cast<std::size_t>(axis)]);
    };
    const __m256d x = _mm256_set_pd(at(3, 0), at(2, 0), at(1, 0), at(0, 0));
    const __m256d y = _mm256_set_pd(at(3, 1), at(2, 1), at(1, 1), at(0, 1));
    const __m256d z = _mm256_set_pd(at(3, 2), at(2, 2), at(1, 2), at(0, 2));
    const __m256d residue = _mm256_add_pd(_mm256_add_pd(_mm256_sub_pd(x, x), _mm256_sub_pd(y, y)), _mm256_sub_pd(z, z));
    const int finite = _mm256_movemask_pd(_mm256_cmp_pd(residue, zero, _CMP_EQ_OQ));
    const __m256d i = _mm256_floor_pd(_mm256_div_pd(_mm256_sub_pd(x, origin_x), resolution));
    const __m256d j = _mm256_floor_pd(_mm256_div_pd(_mm256_sub_pd(y, origin_y), resolution));
    const int inside = _mm256_movemask_pd(
        _mm256_and_pd(_mm256_and_pd(_mm256_cmp_pd(i, zero, _CMP_GE_OQ), _mm256_cmp_pd(i, cells_x, _CMP_LT_OQ)),
                      _mm256_and_pd(_mm256_cmp_pd(j, zero, _CMP_GE_OQ), _mm256_cmp_pd(j, cells_y, _CMP_LT_OQ))));
    alignas(32) double i_lanes[4], j_lanes[4];
    _mm256_store_pd(i_lanes, i);
    _mm256_store_pd(j_lanes, j);
    for (int lane = 0; lane < 4; ++lane) {
      if (((finite >> lane) & 1) == 0) continue;  // NaN/Inf: the checking path counts it
      const std::uint32_t row = rows[n + static_cast<std::size_t>(lane)];
      // Inside, i and j are whole numbers below nx and ny: the cell fits 32 bits.
      const auto cell = static_cast<std::uint32_t>(static_cast<std::int64_t>(i_lanes[lane]) * k.ny +
                                                   static_cast<std::int64_t>(j_lanes[lane]));
      codes[row] = ((inside >> lane) & 1) != 0 ? cell : kOutside;
    }
  }
  return n;
}

#endif

/// The exact formula for the listed rows `rows[0, count)` of a plain cloud (rows 3 or 4 scalars
/// apart) with AVX2 when the CPU has it (see bin_exact_rows_avx2). Returns how many listed rows
/// it went through from the first; the caller bins the rest, and the rows still kSlow, by the
/// checking path.
template <typename Scalar>
std::size_t bin_exact_rows(const Scalar* data, int stride, const std::uint32_t* rows, std::size_t count,
                           const BinningConstants& k, std::uint32_t* codes) {
#if defined(TERRACUBE_HAVE_AVX2_BINNING)
  if (detail::has_avx2()) {
    return stride == 3 ? bin_exact_rows_avx2<Scalar, 3>(data, rows, count, k, codes)
                       : bin_exact_rows_avx2<Scalar, 4>(data, rows, count, k, codes);
  }
#endif
  (void)data, (void)stride, (void)rows, (void)count, (void)k, (void)codes;
  return 0;
}

/// bin_rows_body for rows 3 or 4 scalars apart (x y z, or x y z intensity), AVX2 when the CPU has it.
template <typename Scalar>
/// Returns whether any row got kSlow.
bool bin_rows(const Scalar* data, std::size_t rows, int stride, const BinningConstants& k, std::uint32_t* out) {
#if defined(TERRACUBE_HAVE_AVX2_BINNING)
  if (detail::has_avx2()) return bin_rows_avx2(data, rows, stride, k, out);
#endif
  return bin_rows_default(data, rows, stride, k, out);
}

/// What a cell's layers are made of: count, least and greatest elevation, and the sums of the
/// elevations and of their squares relative to the cell's first elevation (a shifted one-pass
/// variance: with `first` one of the samples, (first - mean)^2 <= n var, so sum(d^2) - sum(d)^2 / n
/// loses at most about n ulps of the variance to cancellation, where the plain sums of z and z^2
/// lose everything at large absolute heights).
template <typename Height>
struct CellSums {
  Height lowest;
  Height highest;
  double sum;      ///< sum of (z - first)
  double squares;  ///< sum of (z - first)^2
};

/// The sums of a cell's elevations z[0, n) (n >= 1, z[0] its first). The additions follow one fixed
/// order, that of eight lanes: chunk i adds d[8i + j] + d[8i + j + 4] to lane j (j < 4), and the
/// lanes end as (lane 0 + lane 2) + (lane 1 + lane 3); past n, d is 0 (adding 0 changes nothing).
/// cell_sums_avx2 computes the same operations in vector registers, so both give the same sums, bit
/// for bit (the least and greatest elevation are the same values; a cell holding both +0 and -0 may
/// get either sign).
template <typename Height>
CellSums<Height> cell_sums_scalar(const Height* z, std::uint32_t n) {
  const double shift = static_cast<double>(z[0]);
  CellSums<Height> out{z[0], z[0], 0.0, 0.0};
  double sum[4] = {0.0, 0.0, 0.0, 0.0};
  double squares[4] = {0.0, 0.0, 0.0, 0.0};
  for (std::uint32_t chunk = 0; chunk < n; chunk += 8) {
    for (std::uint32_t j = 0; j < 4; ++j) {
      const std::uint32_t first = chunk + j;
      const std::uint32_t second = chunk + j + 4;
      const double a = first < n ? static_cast<double>(z[first]) - shift : 0.0;
      const double b = second < n ? static_cast<double>(z[second]) - shift : 0.0;
      if (first < n) {
        out.lowest = std::min(out.lowest, z[first]);
        out.highest = std::max(out.highest, z[first]);
      }
      if (second < n) {
        out.lowest = std::min(out.lowest, z[second]);
        out.highest = std::max(out.highest, z[second]);
      }
      sum[j] += a + b;
      const double a2 = a * a;
      const double b2 = b * b;
      squares[j] += a2 + b2;
    }
  }
  out.sum = (sum[0] + sum[2]) + (sum[1] + sum[3]);
  out.squares = (squares[0] + squares[2]) + (squares[1] + squares[3]);
  return out;
}

#if defined(__x86_64__) && defined(__GNUC__)
/// Horizontal reductions of cell_sums_avx2: (lane 0 + lane 2) + (lane 1 + lane 3), least, greatest.
__attribute__((target("avx2"))) inline double lane_sum(__m256d v) {
  const __m128d pairs = _mm_add_pd(_mm256_castpd256_pd128(v), _mm256_extractf128_pd(v, 1));
  return _mm_cvtsd_f64(_mm_add_sd(pairs, _mm_unpackhi_pd(pairs, pairs)));
}
__attribute__((target("avx2"))) inline double lane_min(__m256d v) {
  const __m128d pairs = _mm_min_pd(_mm256_castpd256_pd128(v), _mm256_extractf128_pd(v, 1));
  return _mm_cvtsd_f64(_mm_min_sd(pairs, _mm_unpackhi_pd(pairs, pairs)));
}
__attribute__((target("avx2"))) inline double lane_max(__m256d v) {
  const __m128d pairs = _mm_max_pd(_mm256_castpd256_pd128(v), _mm256_extractf128_pd(v, 1));
  return _mm_cvtsd_f64(_mm_max_sd(pairs, _mm_unpackhi_pd(pairs, pairs)));
}
__attribute__((target("avx2"))) inline float lane_min(__m256 v) {
  __m128 x = _mm_min_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
  x = _mm_min_ps(x, _mm_movehl_ps(x, x));
  return _mm_cvtss_f32(_mm_min_ss(x, _mm_shuffle_ps(x, x, 1)));
}
__attribute__((target("avx2"))) inline float lane_max(__m256 v) {
  __m128 x = _mm_max_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
  x = _mm_max_ps(x, _mm_movehl_ps(x, x));
  return _mm_cvtss_f32(_mm_max_ss(x, _mm_shuffle_ps(x, x, 1)));
}

/// cell_sums_scalar in AVX2 (no FMA: the products are rounded as there). Reads up to 7 heights past
/// z + n (the sorted heights are padded); those lanes are masked out.
__attribute__((target("avx2"))) inline CellSums<float> cell_sums_avx2(const float* z, std::uint32_t n) {
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const __m256 first = _mm256_set1_ps(z[0]);
  const __m256d shift = _mm256_set1_pd(static_cast<double>(z[0]));
  __m256 lowest = first;
  __m256 highest = first;
  __m256d sum = _mm256_setzero_pd();
  __m256d squares = _mm256_setzero_pd();
  for (std::uint32_t chunk = 0; chunk < n; chunk += 8) {
    const int left = static_cast<int>(std::min<std::uint32_t>(n - chunk, 8));
    const __m256 inside = _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_set1_epi32(left), lane));
    const __m256 heights = _mm256_blendv_ps(first, _mm256_loadu_ps(z + chunk), inside);  // first: d = 0
    lowest = _mm256_min_ps(lowest, heights);
    highest = _mm256_max_ps(highest, heights);
    const __m256d a = _mm256_sub_pd(_mm256_cvtps_pd(_mm256_castps256_ps128(heights)), shift);
    const __m256d b = _mm256_sub_pd(_mm256_cvtps_pd(_mm256_extractf128_ps(heights, 1)), shift);
    sum = _mm256_add_pd(sum, _mm256_add_pd(a, b));
    squares = _mm256_add_pd(squares, _mm256_add_pd(_mm256_mul_pd(a, a), _mm256_mul_pd(b, b)));
  }
  return {lane_min(lowest), lane_max(highest), lane_sum(sum), lane_sum(squares)};
}

/// The same for double heights, four to a register.
__attribute__((target("avx2"))) inline CellSums<double> cell_sums_avx2(const double* z, std::uint32_t n) {
  const __m256i lane_low = _mm256_setr_epi64x(0, 1, 2, 3);
  const __m256i lane_high = _mm256_setr_epi64x(4, 5, 6, 7);
  const __m256d first = _mm256_set1_pd(z[0]);
  __m256d lowest = first;
  __m256d highest = first;
  __m256d sum = _mm256_setzero_pd();
  __m256d squares = _mm256_setzero_pd();
  for (std::uint32_t chunk = 0; chunk < n; chunk += 8) {
    const __m256i left = _mm256_set1_epi64x(static_cast<long long>(n - chunk));
    const __m256d in_a = _mm256_castsi256_pd(_mm256_cmpgt_epi64(left, lane_low));
    const __m256d in_b = _mm256_castsi256_pd(_mm256_cmpgt_epi64(left, lane_high));
    const __m256d za = _mm256_blendv_pd(first, _mm256_loadu_pd(z + chunk), in_a);
    const __m256d zb = _mm256_blendv_pd(first, _mm256_loadu_pd(z + chunk + 4), in_b);
    lowest = _mm256_min_pd(lowest, _mm256_min_pd(za, zb));
    highest = _mm256_max_pd(highest, _mm256_max_pd(za, zb));
    const __m256d a = _mm256_sub_pd(za, first);
    const __m256d b = _mm256_sub_pd(zb, first);
    sum = _mm256_add_pd(sum, _mm256_add_pd(a, b));
    squares = _mm256_add_pd(squares, _mm256_add_pd(_mm256_mul_pd(a, a), _mm256_mul_pd(b, b)));
  }
  return {lane_min(lowest), lane_max(highest), lane_sum(sum), lane_sum(squares)};
}
#endif

/// Mean and std-dev of cells [begin, end) from their first elevation, sums and count (see
/// CellSums): the population variance from the shifted sums, where rounding can leave it just
/// below 0.
inline void finish_cells(const double* firsts, const double* sums, const double* squares, const double* counts,
                         int begin, int end, float* means, float* std_devs) {
  for (int k = begin; k < end; ++k) {
    const double offset_of_mean = sums[k] / counts[k];
    const double variance = std::max((squares[k] - sums[k] * offset_of_mean) / counts[k], 0.0);
    means[k] = static_cast<float>(firsts[k] + offset_of_mean);
    std_devs[k] = static_cast<float>(std::sqrt(variance));
  }
}

#if defined(__x86_64__) && defined(__GNUC__)
/// finish_cells four cells at a time (the same correctly rounded operations: the same bits). The
/// arrays are 32-byte aligned; the last incomplete group is left to finish_cells.
__attribute__((target("avx2"))) void finish_cells_avx2(const double* firsts, const double* sums, const double* squares,
                                                       const double* counts, int end, float* means, float* std_devs) {
  const __m256d zero = _mm256_setzero_pd();
  int k = 0;
  for (; k + 4 <= end; k += 4) {
    const __m256d n = _mm256_load_pd(counts + k);
    const __m256d sum = _mm256_load_pd(sums + k);
    const __m256d offset_of_mean = _mm256_div_pd(sum, n);
    const __m256d spread = _mm256_sub_pd(_mm256_load_pd(squares + k), _mm256_mul_pd(sum, offset_of_mean));
    // max(0, v) returns v for v = -0, as std::max(v, 0.0) does.
    const __m256d variance = _mm256_max_pd(zero, _mm256_div_pd(spread, n));
    _mm_store_ps(means + k, _mm256_cvtpd_ps(_mm256_add_pd(_mm256_load_pd(firsts + k), offset_of_mean)));
    _mm_store_ps(std_devs + k, _mm256_cvtpd_ps(_mm256_sqrt_pd(variance)));
  }
  finish_cells(firsts, sums, squares, counts, k, end, means, std_devs);
}
#endif

/// The sums (CellSums) of the occupied cells of one bitmap word (`bits`, cells base + bit), from
/// their heights grouped by cell (`start`: where each cell begins): the cells in bit order, their
/// first elevation and count, and the sums, in the arrays of the word (WordSums). kAvx2: with
/// cell_sums_avx2, for CellRange::write_words_avx2, which inlines it all (flatten). The arrays have
/// room for the word's 64 cells and the three more that word_sums_small_avx2 may write past the last.
template <typename Height>
struct WordSums {
  static constexpr int kRoom = 68;
  std::uint32_t cells[kRoom];
  alignas(32) double firsts[kRoom], sums[kRoom], squares[kRoom], counts[kRoom];
  Height lowest[kRoom], highest[kRoom];

  /// Appends a cell at `listed` (and advances it): its first elevation, count and sums.
  void add(int& listed, std::size_t cell, Height first, std::uint32_t count, const CellSums<Height>& s) {
    cells[listed] = static_cast<std::uint32_t>(cell);
    firsts[listed] = static_cast<double>(first);
    sums[listed] = s.sum;
    squares[listed] = s.squares;
    counts[listed] = static_cast<double>(count);
    lowest[listed] = s.lowest;
    highest[listed++] = s.highest;
  }
};

template <bool kAvx2, typename Height>
int word_sums(const Height* heights, const std::uint32_t* start, std::uint64_t bits, std::size_t base,
              WordSums<Height>& out) {
  int listed = 0;
  for (; bits != 0; bits &= bits - 1) {
    const std::size_t cell = base + static_cast<std::size_t>(__builtin_ctzll(bits));
    const std::uint32_t first = start[cell];
    const std::uint32_t count = start[cell + 1] - first;
    CellSums<Height> s;
#if defined(__x86_64__) && defined(__GNUC__)
    if constexpr (kAvx2) {
      s = cell_sums_avx2(heights + first, count);
    } else {
      s = cell_sums_scalar(heights + first, count);
    }
#else
    s = cell_sums_scalar(heights + first, count);
#endif
    out.add(listed, cell, heights[first], count, s);
  }
  return listed;
}

#if defined(__x86_64__) && defined(__GNUC__)
/// word_sums<true> for float heights: the cells of at most eight heights (95 % of the occupied cells
/// of a KITTI scan on a 10 cm map; 69 % hold at most four) four at a time, one cell per lane, the
/// others by cell_sums_avx2. Lane j of a cell (cell_sums_scalar's order) ends as 0 + (d[j] + d[j + 4])
/// for such a cell, so the sums are (T0 + T2) + (T1 + T3) with T_j = 0 + (D_j + D_(j+4)), D_j the
/// vector of the four cells' d[j] (0 past a cell's count): the same operations on the same values,
/// so the same bits. Each cell's first eight heights are loaded (the heights are padded) and the
/// four cells' transposed; positions past every count of the four are skipped.
__attribute__((target("avx2"))) inline int word_sums_small_avx2(const float* heights, const std::uint32_t* start,
                                                                std::uint64_t bits, std::size_t base,
                                                                WordSums<float>& out) {
  alignas(16) std::uint32_t small_cell[64 + 3], small_first[64 + 3], small_count[64 + 3];
  int num_small = 0;
  int listed = 0;
  for (; bits != 0; bits &= bits - 1) {
    const std::size_t cell = base + static_cast<std::size_t>(__builtin_ctzll(bits));
    const std::uint32_t first = start[cell];
    const std::uint32_t count = start[cell + 1] - first;
    if (count <= 8) {
      small_cell[num_small] = static_cast<std::uint32_t>(cell);
      small_first[num_small] = first;
      small_count[num_small++] = count;
      continue;
    }
    const CellSums<float> s = cell_sums_avx2(heights + first, count);
    out.add(listed, cell, heights[first], count, s);
  }
  if (num_small == 0) return listed;
  for (int k = num_small; k < (num_small + 3) / 4 * 4; ++k) {  // lanes past the last: a copy of it
    small_cell[k] = small_cell[num_small - 1];
    small_first[k] = small_first[num_small - 1];
    small_count[k] = small_count[num_small - 1];
  }
  const float* z = heights;
  const __m256d zero = _mm256_setzero_pd();
  for (int g = 0; g < num_small; g += 4) {
    const __m128i count = _mm_load_si128(reinterpret_cast<const __m128i*>(small_count + g));
    // The four cells' first eight heights (the heights are padded: reading past the last is safe),
    // transposed: h[j] holds the j-th height of each cell.
    const __m256 r0 = _mm256_loadu_ps(z + small_first[g]);
    const __m256 r1 = _mm256_loadu_ps(z + small_first[g + 1]);
    const __m256 r2 = _mm256_loadu_ps(z + small_first[g + 2]);
    const __m256 r3 = _mm256_loadu_ps(z + small_first[g + 3]);
    const __m256 u0 = _mm256_unpacklo_ps(r0, r1);  // a0 b0 a1 b1 | a4 b4 a5 b5
    const __m256 u1 = _mm256_unpackhi_ps(r0, r1);  // a2 b2 a3 b3 | a6 b6 a7 b7
    const __m256 u2 = _mm256_unpacklo_ps(r2, r3);
    const __m256 u3 = _mm256_unpackhi_ps(r2, r3);
    const __m256 c0 = _mm256_shuffle_ps(u0, u2, 0x44);  // a0 b0 c0 d0 | a4 b4 c4 d4
    const __m256 c1 = _mm256_shuffle_ps(u0, u2, 0xEE);  // a1 b1 c1 d1 | a5 ...
    const __m256 c2 = _mm256_shuffle_ps(u1, u3, 0x44);
    const __m256 c3 = _mm256_shuffle_ps(u1, u3, 0xEE);
    const __m128 h[8] = {_mm256_castps256_ps128(c0),   _mm256_castps256_ps128(c1),   _mm256_castps256_ps128(c2),
                         _mm256_castps256_ps128(c3),   _mm256_extractf128_ps(c0, 1), _mm256_extractf128_ps(c1, 1),
                         _mm256_extractf128_ps(c2, 1), _mm256_extractf128_ps(c3, 1)};
    const __m128 z0 = h[0];
    const __m256d shift = _mm256_cvtps_pd(z0);
    __m128 lowest = z0;
    __m128 highest = z0;
    __m256d d[8] = {zero, zero, zero, zero, zero, zero, zero, zero};  // d[0] = z0 - shift = +0
    for (int j = 1; j < 8; ++j) {
      const __m128i left = _mm_cmpgt_epi32(count, _mm_set1_epi32(j));
      if (_mm_movemask_epi8(left) == 0) break;  // counts are at most j in all four cells
      const __m128 zj = _mm_blendv_ps(z0, h[j], _mm_castsi128_ps(left));
      lowest = _mm_min_ps(lowest, zj);
      highest = _mm_max_ps(highest, zj);
      d[j] = _mm256_sub_pd(_mm256_cvtps_pd(zj), shift);  // 0 where the cell has no j-th height
    }
    __m256d t[4], q[4];
    for (int j = 0; j < 4; ++j) {
      t[j] = _mm256_add_pd(zero, _mm256_add_pd(d[j], d[j + 4]));
      q[j] = _mm256_add_pd(zero, _mm256_add_pd(_mm256_mul_pd(d[j], d[j]), _mm256_mul_pd(d[j + 4], d[j + 4])));
    }
    _mm_storeu_si128(reinterpret_cast<__m128i*>(out.cells + listed),
                     _mm_load_si128(reinterpret_cast<const __m128i*>(small_cell + g)));
    _mm256_storeu_pd(out.firsts + listed, shift);
    _mm256_storeu_pd(out.sums + listed, _mm256_add_pd(_mm256_add_pd(t[0], t[2]), _mm256_add_pd(t[1], t[3])));
    _mm256_storeu_pd(out.squares + listed, _mm256_add_pd(_mm256_add_pd(q[0], q[2]), _mm256_add_pd(q[1], q[3])));
    _mm256_storeu_pd(out.counts + listed, _mm256_cvtepi32_pd(count));
    _mm_storeu_ps(out.lowest + listed, lowest);
    _mm_storeu_ps(out.highest + listed, highest);
    listed += std::min(4, num_small - g);
  }
  return listed;
}

/// CellRange::place_heights' first loop over the first `words` whole bitmap words, eight counts at a
/// time: each becomes the running total up to and including it (slot[cell + 1], `slot` as given),
/// and its bit is set when it is not 0. Returns the words done; `total` carries the running total on.
__attribute__((target("avx2"))) std::size_t count_to_starts_avx2(std::uint32_t* slot, std::size_t words,
                                                                 std::uint64_t* occupied, std::uint32_t& total) {
  const __m256i zero = _mm256_setzero_si256();
  const __m256i last = _mm256_set1_epi32(7);
  const __m256i fourth = _mm256_set1_epi32(3);
  __m256i carry = _mm256_set1_epi32(static_cast<int>(total));
  for (std::size_t w = 0; w < words; ++w) {
    std::uint64_t bits = 0;
    for (int k = 0; k < 8; ++k) {
      __m256i* at = reinterpret_cast<__m256i*>(slot + w * 64 + 8 * k + 1);
      const __m256i counts = _mm256_loadu_si256(at);
      const auto empty =
          static_cast<std::uint32_t>(_mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(counts, zero))));
      bits |= static_cast<std::uint64_t>(~empty & 0xFFU) << (8 * k);
      __m256i sums = _mm256_add_epi32(counts, _mm256_slli_si256(counts, 4));  // prefix sums in each half
      sums = _mm256_add_epi32(sums, _mm256_slli_si256(sums, 8));
      const __m256i low_total = _mm256_permutevar8x32_epi32(sums, fourth);  // the low half's total
      sums = _mm256_add_epi32(sums, _mm256_blend_epi32(zero, low_total, 0xF0));
      sums = _mm256_add_epi32(sums, carry);
      _mm256_storeu_si256(at, sums);
      carry = _mm256_permutevar8x32_epi32(sums, last);
    }
    occupied[w] = bits;
  }
  total = static_cast<std::uint32_t>(_mm256_cvtsi256_si32(carry));
  return words;
}
#endif

/// Whether the elevations [begin, end) of a cell, once sorted, hold two neighbours more than
/// `threshold` apart, found without sorting them (the classic linear-time maximum gap): the range
/// [lowest, highest] (the cell's least and greatest elevation, known from its sums) is cut
/// into buckets of about threshold / 2 and each bucket keeps its least and greatest elevation. A
/// bucket is floor((z - lowest) * (2 / threshold)): rounding is monotonic, so the bucket of z never
/// decreases as z grows, and two elevations in one bucket lie at most threshold / 2 and a few ulps
/// apart. Two neighbours in sorted order either share a bucket, and then are no gap, or lie in
/// consecutive non-empty buckets as the greater elevation of the first and the least of the second.
/// So the answer is whether any two consecutive non-empty buckets are more than `threshold` apart,
/// each difference computed as the sorted scan would compute it. A cell whose range would need more
/// buckets than four per elevation (an outlier far above the rest) is sorted instead, keeping
/// memory O(points). Up to kStackBuckets buckets live on the stack (most wide cells: 64 m of range).
bool has_gap(std::pair<double*, double*> elevations, double lowest, double highest, double threshold,
             std::vector<double>& buckets) {
  const auto [begin, end] = elevations;
  const auto count = static_cast<std::size_t>(end - begin);
  if (count < 2) return false;
  const double per_metre = 2.0 / threshold;
  const double spread = (highest - lowest) * per_metre;  // the largest bucket, by monotonic rounding
  if (!(spread < static_cast<double>(4 * count + 64))) {
    std::sort(begin, end);
    for (const double* z = begin + 1; z < end; ++z) {
      if (*z - *(z - 1) > threshold) return true;
    }
    return false;
  }
  const auto num_buckets = static_cast<std::size_t>(spread) + 1;
  constexpr std::size_t kStackBuckets = 128;
  double on_stack[2 * kStackBuckets];
  double* least = on_stack;
  if (num_buckets > kStackBuckets) {
    buckets.resize(2 * num_buckets);
    least = buckets.data();
  }
  double* greatest = least + num_buckets;
  std::fill_n(least, num_buckets, std::numeric_limits<double>::infinity());
  std::fill_n(greatest, num_buckets, -std::numeric_limits<double>::infinity());
  for (const double* z = begin; z < end; ++z) {
    const auto bucket = static_cast<std::size_t>((*z - lowest) * per_metre);  // <= spread
    least[bucket] = std::min(least[bucket], *z);
    greatest[bucket] = std::max(greatest[bucket], *z);
  }
  double previous = greatest[0];  // bucket 0 holds the lowest elevation
  for (std::size_t bucket = 1; bucket < num_buckets; ++bucket) {
    if (least[bucket] > greatest[bucket]) continue;  // empty
    if (least[bucket] - previous > threshold) return true;
    previous = greatest[bucket];
  }
  return false;
}

/// Per-thread scratch buffers of build_map, kept between calls: a fresh multi-megabyte buffer
/// costs a page fault per 4 kB page on first touch, which on a fresh map would take longer than
/// the whole computation. `slot` and the bitmap (per cell) are left clean after every call, so a
/// call costs O(points + cells), the cells' part being no more than writing the layers. Buffers
/// over kKeepBytes are released after the call.
struct BuildScratch {
  std::vector<std::uint32_t> cell_of_point;
  std::vector<std::uint32_t> slot;       // per cell + 2: counts, then where each cell's heights start
  std::vector<std::uint64_t> occupied;   // one bit per cell
  std::vector<std::uint32_t> row_cell;   // per row of the range, in row order: its cell (from lo)
  std::vector<float> row_heights_float;  // ... and its height
  std::vector<double> row_heights_double;
  std::vector<float> by_cell_float;  // the heights grouped by cell (row order within a cell), padded
  std::vector<double> by_cell_double;
  std::vector<double> heights, buckets;

  static constexpr std::size_t kKeepBytes = std::size_t{32} << 20;

  template <typename Height>
  std::vector<Height>& row_heights() {
    if constexpr (std::is_same_v<Height, float>) {
      return row_heights_float;
    } else {
      return row_heights_double;
    }
  }

  template <typename Height>
  std::vector<Height>& by_cell() {
    if constexpr (std::is_same_v<Height, float>) {
      return by_cell_float;
    } else {
      return by_cell_double;
    }
  }

  void release_if_large() {
    const std::size_t bytes = 4 * (cell_of_point.capacity() + slot.capacity() + row_cell.capacity() +
                                   row_heights_float.capacity() + by_cell_float.capacity()) +
                              8 * (occupied.capacity() + row_heights_double.capacity() + by_cell_double.capacity() +
                                   heights.capacity() + buckets.capacity());
    if (bytes > kKeepBytes) *this = BuildScratch();
  }
};

BuildScratch& thread_scratch() {
  thread_local BuildScratch scratch;
  return scratch;
}

/// The 64 cells of a bitmap word set to `value`.
inline void fill_word(float* __restrict cells, float value) {
  for (int k = 0; k < 64; ++k) cells[k] = value;
}

/// The layers build_map writes, in the order a fresh map gets them.
constexpr std::array<const char*, 6> kBuiltLayers = {"count", "min", "max", "mean", "std_dev", "discontinuity"};

/// The height of a row as the map bins it (the mapped z).
template <typename Cloud>
double row_height(const Cloud& cloud, std::size_t row) {
  if constexpr (Cloud::kPlain) {
    return cloud.raw(row, 2);
  } else {
    Eigen::Vector3d p;
    cloud.map_unchecked(row, p);
    return p.z();
  }
}

/// row_height for a loop over rows, as a value the loop keeps in registers: a plain view's z column
/// and row stride (read through the cloud, they would be reloaded from memory after every store).
template <typename Cloud, bool kPlain = Cloud::kPlain>
struct RowHeights {
  const Cloud* cloud;
  explicit RowHeights(const Cloud& c) : cloud(&c) {}
  double operator()(std::size_t row) const { return row_height(*cloud, row); }
};
template <typename Cloud>
struct RowHeights<Cloud, true> {
  const std::remove_const_t<std::remove_pointer_t<decltype(std::declval<const Cloud&>().view().data)>>* z;
  std::ptrdiff_t stride;
  explicit RowHeights(const Cloud& c)
      : z(c.view().data + 2 * c.view().column_stride), stride(static_cast<std::ptrdiff_t>(c.view().row_stride)) {}
  double operator()(std::size_t row) const { return static_cast<double>(z[static_cast<std::ptrdiff_t>(row) * stride]); }
};

/// NaN/Inf rows met while binning: how many, and the first.
struct NonFiniteRows {
  std::size_t count = 0;
  std::size_t first_row = 0;
  void add(std::size_t row) {
    if (count++ == 0 || row < first_row) first_row = row;
  }
  void merge(const NonFiniteRows& other) {
    if (other.count == 0) return;
    first_row = count == 0 ? other.first_row : std::min(first_row, other.first_row);
    count += other.count;
  }
};

/// Asks for the cache lines of [data, data + bytes) ahead of scattered reads and writes: one
/// prefetch per 64-byte line, which the processor streams in at memory bandwidth, where the
/// scattered accesses themselves would each wait for memory in turn when the caches are cold (after
/// other work: the common case in a program that does more than build maps). Where the lines are
/// cached already, this costs a few thousand prefetch instructions.
inline void prefetch_lines(const void* data, std::size_t bytes) {
  const char* begin = static_cast<const char*>(data);
  for (std::size_t offset = 0; offset < bytes; offset += 64) __builtin_prefetch(begin + offset, 1, 3);
}

/// Rows binned and listed at a time (their rows still in L1).
constexpr std::size_t kListBlock = 1024;

#if defined(__x86_64__) && defined(__GNUC__)
/// CellRange::list_block's loop, eight rows at a time: a range's rows come in long runs (a scan
/// sweeps in azimuth, and rows outside the map or in another thread's cells come in runs too), so
/// eight rows of which none is the range's cost one compare, and eight that all are take no branch
/// per row. Returns the first row not listed (the rest go through the scalar loop); `listed` is
/// advanced by the rows listed.
template <typename HeightOf, typename Height>
__attribute__((target("avx2"))) std::size_t list_rows_avx2(const std::uint32_t* codes, std::size_t begin,
                                                           std::size_t end, std::uint32_t lo, std::uint32_t span,
                                                           const HeightOf& height_of, std::uint32_t* __restrict counts,
                                                           std::uint32_t* __restrict row_cell,
                                                           Height* __restrict row_heights, std::size_t& listed) {
  const __m256i first = _mm256_set1_epi32(static_cast<int>(lo));
  const __m256i last = _mm256_set1_epi32(static_cast<int>(span - 1));
  std::size_t at = listed;
  std::size_t row = begin;
  for (; row + 8 <= end; row += 8) {
    // cell - lo wraps for cells below the range: in the range iff min(cell, span - 1) == cell.
    const __m256i cell =
        _mm256_sub_epi32(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(codes + (row - begin))), first);
    const __m256i inside = _mm256_cmpeq_epi32(_mm256_min_epu32(cell, last), cell);
    auto mask = static_cast<unsigned>(_mm256_movemask_ps(_mm256_castsi256_ps(inside)));
    if (mask == 0) continue;
    alignas(32) std::uint32_t cells[8];
    _mm256_store_si256(reinterpret_cast<__m256i*>(cells), cell);
    if (mask == 0xFFU) {
      for (int k = 0; k < 8; ++k) {
        row_cell[at + k] = cells[k];
        ++counts[cells[k]];
        row_heights[at + k] = static_cast<Height>(height_of(row + k));
      }
      at += 8;
      continue;
    }
    for (; mask != 0; mask &= mask - 1) {
      const int k = __builtin_ctz(mask);
      row_cell[at] = cells[k];
      ++counts[cells[k]];
      row_heights[at] = static_cast<Height>(height_of(row + k));
      ++at;
    }
  }
  listed = at;
  return row;
}
#endif

/// The cells [lo, hi) of a map (lo a multiple of 64) as one thread builds them, by a counting sort
/// of the range's heights by cell. list_rows() goes over the cell codes of all rows and lists the
/// range's rows in row order (cell and height), counting the rows of each cell; write() turns the
/// counts into where each cell's heights start, places every height there in list order (a cell's
/// heights stay in row order, its first one first) and then writes the range's layers, each cell
/// from its contiguous heights (cell_sums). No branch depends on where a cell's rows begin or end
/// (on a scan they alternate between cells every few rows, and such a branch was mispredicted once
/// per run), and each cell's sums come from its heights alone, in one fixed order, so the map is the
/// same bit for bit however the cells are split between threads. Several threads build disjoint
/// ranges with their own scratch. The scratch's per-cell buffers are indexed from lo, and left clean
/// when the range is destroyed, whatever happens.
template <typename Cloud>
class CellRange {
 public:
  // Heights are exact floats when a float cloud is not transformed: then they are kept as floats.
  // Otherwise in doubles, rounded at the end (rounding is monotonic, so float(min z) = min float(z)
  // either way) -- the wide-cell test needs the double range.
  using Height = std::conditional_t<ExactFloatHeights<Cloud>::value, float, double>;

  CellRange(const Cloud& cloud, std::size_t lo, std::size_t hi, BuildScratch& scratch)
      : cloud_(cloud), lo_(lo), span_(hi - lo), words_((span_ + 63) / 64), scratch_(scratch) {
    if (scratch.slot.size() < span_ + 2) scratch.slot.resize(span_ + 2, 0);  // old entries were left at 0
    if (scratch.occupied.size() < words_) scratch.occupied.resize(words_, 0);
  }
  CellRange(const CellRange&) = delete;
  CellRange& operator=(const CellRange&) = delete;

  /// Leaves the per-cell buffers clean (write() leaves them so already, unless it did not run). The
  /// scratch's owner releases oversized buffers (release_if_large) once no range uses them.
  ~CellRange() {
    if (clean_) return;
    std::fill_n(scratch_.slot.begin(), span_ + 2, 0U);
    std::fill_n(scratch_.occupied.begin(), words_, std::uint64_t{0});
  }

  /// Lists and counts the range's rows, in blocks of kListBlock; bin_block(begin, end) gives the
  /// block's cell codes, indexed from begin (binning them first, or where they are already).
  template <typename BinBlock>
  void list_rows(const BinBlock& bin_block) {
    const std::size_t rows = cloud_.size();
    clean_ = false;
    prefetch_lines(scratch_.slot.data(), 4 * (span_ + 2));  // the counts, scattered below
    for (std::size_t begin = 0; begin < rows; begin += kListBlock) {
      const std::size_t end = std::min(rows, begin + kListBlock);
      const std::uint32_t* codes = bin_block(begin, end);
      // A block adds at most one entry per row: room for them is made here, not per row.
      const std::size_t least = num_rows_ + (end - begin);
      std::vector<Height>& row_heights = scratch_.row_heights<Height>();
      if (scratch_.row_cell.size() < least || row_heights.size() < least) {
        const std::size_t size = std::min(rows, std::max(least, 2 * row_heights.size()));
        if (scratch_.row_cell.size() < size) scratch_.row_cell.resize(size);
        row_heights.resize(size);
      }
      list_block(begin, end, codes);
    }
  }

  /// The range's cells of the six layers (`layers` in kBuiltLayers' order, indexed by map cell),
  /// 64 cells at a time: empty, then the occupied cells from their heights. Discontinuity: only a
  /// cell whose elevations span more than the threshold can hold a gap longer than it (rounding is
  /// monotonic, so this holds for the computed differences too); those (few) "wide" cells are
  /// tested by has_gap, the others get 0. The range's cells of the `stale` layers are set to NaN.
  void write(const std::array<float*, kBuiltLayers.size()>& layers, const std::vector<float*>& stale,
             double discontinuity_m) {
    for (float* layer : stale) std::fill_n(layer + lo_, span_, std::numeric_limits<float>::quiet_NaN());
    place_heights();
#if defined(__x86_64__) && defined(__GNUC__)
    if (detail::has_avx2()) {
      write_words_avx2(layers, discontinuity_m);
    } else {
      write_words<false>(layers, discontinuity_m);
    }
#else
    write_words<false>(layers, discontinuity_m);
#endif
    std::fill_n(scratch_.slot.begin(), span_ + 2, 0U);
    clean_ = true;
  }

 private:
#if defined(__x86_64__) && defined(__GNUC__)
  /// write_words compiled for AVX2 with everything it calls inlined (flatten), the AVX2 kernels too.
  __attribute__((target("avx2"), flatten, noinline)) void write_words_avx2(
      const std::array<float*, kBuiltLayers.size()>& layers, double discontinuity_m) {
    write_words<true>(layers, discontinuity_m);
  }
#endif

  /// write()'s cells, a bitmap word at a time (kAvx2: with the AVX2 kernels).
  template <bool kAvx2>
  void write_words(const std::array<float*, kBuiltLayers.size()>& layers, double discontinuity_m) {
    constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
    const std::uint32_t* start = scratch_.slot.data();
    const Height* heights = scratch_.by_cell<Height>().data();
    std::uint64_t* occupied = scratch_.occupied.data();
    float* count_layer = layers[0] + lo_;
    float* min = layers[1] + lo_;
    float* max = layers[2] + lo_;
    float* mean = layers[3] + lo_;
    float* std_dev = layers[4] + lo_;
    float* discontinuity = layers[5] + lo_;
    WordSums<Height> word;
    for (std::size_t w = 0; w < words_; ++w) {
      const std::size_t base = w * 64;
      if (base + 64 <= span_) {  // a whole word: fills of a constant length, unrolled (no loop exit to mispredict)
        fill_word(count_layer + base, 0.0F);
        for (float* layer : {min, max, mean, std_dev, discontinuity}) fill_word(layer + base, kNaN);
      } else {
        const std::size_t length = span_ - base;
        std::fill_n(count_layer + base, length, 0.0F);
        for (float* layer : {min, max, mean, std_dev, discontinuity}) std::fill_n(layer + base, length, kNaN);
      }
      // The word's occupied cells: sums (word_sums), then count, min, max and the gap test, then mean
      // and std-dev in a loop of their own, whose divisions and square roots (long latencies) overlap.
      alignas(32) float means[64], std_devs[64];
#if defined(__x86_64__) && defined(__GNUC__)
      int listed = 0;
      if constexpr (kAvx2 && std::is_same_v<Height, float>) {
        listed = word_sums_small_avx2(heights, start, occupied[w], base, word);
      } else {
        listed = word_sums<kAvx2>(heights, start, occupied[w], base, word);
      }
#else
      const int listed = word_sums<false>(heights, start, occupied[w], base, word);
#endif
      const std::uint32_t* cells = word.cells;
      for (int k = 0; k < listed; ++k) {
        const std::uint32_t cell = cells[k];
        const auto lowest = static_cast<double>(word.lowest[k]);
        const auto highest = static_cast<double>(word.highest[k]);
        count_layer[cell] = static_cast<float>(word.counts[k]);
        min[cell] = static_cast<float>(word.lowest[k]);
        max[cell] = static_cast<float>(word.highest[k]);
        const bool wide = std::isgreater(highest - lowest, discontinuity_m);
        discontinuity[cell] =
            wide && has_gap(as_doubles(heights + start[cell], static_cast<std::uint32_t>(word.counts[k])), lowest,
                            highest, discontinuity_m, scratch_.buckets)
                ? 1.0F
                : 0.0F;
      }
#if defined(__x86_64__) && defined(__GNUC__)
      if constexpr (kAvx2) {
        finish_cells_avx2(word.firsts, word.sums, word.squares, word.counts, listed, means, std_devs);
      } else {
        finish_cells(word.firsts, word.sums, word.squares, word.counts, 0, listed, means, std_devs);
      }
#else
      finish_cells(word.firsts, word.sums, word.squares, word.counts, 0, listed, means, std_devs);
#endif
      for (int k = 0; k < listed; ++k) {
        mean[cells[k]] = means[k];
        std_dev[cells[k]] = std_devs[k];
      }
      occupied[w] = 0;
    }
  }

  static constexpr std::size_t kPadding = 8;  ///< heights read past a cell's last by cell_sums_avx2

  /// The heights [z, z + n) as doubles, in the scratch (has_gap may reorder them).
  std::pair<double*, double*> as_doubles(const Height* z, std::uint32_t n) {
    std::vector<double>& heights = scratch_.heights;
    if (heights.size() < n) heights.resize(n);
    std::copy_n(z, n, heights.data());
    return {heights.data(), heights.data() + n};
  }

  /// The rows [begin, end) of list_rows(): each row of the range is listed, and counted in
  /// slot[cell + 2] (slot[0] and slot[1] stay 0 for the starts, see place_heights).
  __attribute__((noinline)) void list_block(std::size_t begin, std::size_t end, const std::uint32_t* __restrict codes) {
    std::uint32_t* __restrict counts = scratch_.slot.data() + 2;
    std::uint32_t* __restrict row_cell = scratch_.row_cell.data();
    Height* __restrict row_heights = scratch_.row_heights<Height>().data();
    std::size_t listed = num_rows_;
    const auto lo = static_cast<std::uint32_t>(lo_);
    const auto span = static_cast<std::uint32_t>(span_);
    const RowHeights<Cloud> height_of(cloud_);
    std::size_t row = begin;
#if defined(__x86_64__) && defined(__GNUC__)
    if (detail::has_avx2() && span > 0) {
      row = list_rows_avx2(codes, begin, end, lo, span, height_of, counts, row_cell, row_heights, listed);
    }
#endif
    for (; row < end; ++row) {
      const std::uint32_t cell = codes[row - begin] - lo;  // wraps for cells below the range (and kOutside)
      if (cell >= span) continue;
      row_cell[listed] = cell;
      ++counts[cell];
      row_heights[listed] = static_cast<Height>(height_of(row));
      ++listed;
    }
    num_rows_ = listed;
  }

  /// Counts to starts, then every listed height to its place. The counts are in slot[cell + 2]; they
  /// become the starts shifted by one (slot[cell + 1] = where the cell's heights start; the bitmap
  /// marks the cells with any), and each height placed advances its cell's entry, which so ends as
  /// the start of the next cell: slot[cell] = where the cell's heights start, slot[span] = all of
  /// them. (A rank per listed row, computed while counting, avoided the advancing entries' chain of
  /// loads and stores, but writing and reading it back cost more: bench/ab_builds.sh, 0.96-0.97
  /// without it on KITTI frame 0, one and two threads.)
  void place_heights() {
    std::uint32_t* const slot = scratch_.slot.data();
    std::uint32_t* const counted = slot + 1;  // counted[cell + 1]: the cell's count, then its start
    std::uint64_t* occupied = scratch_.occupied.data();
    std::uint32_t total = 0;
    std::size_t w = 0;
#if defined(__x86_64__) && defined(__GNUC__)
    if (detail::has_avx2()) w = count_to_starts_avx2(counted, span_ / 64, occupied, total);
#endif
    for (; w < words_; ++w) {
      const std::size_t base = w * 64;
      const std::size_t length = std::min<std::size_t>(64, span_ - base);
      std::uint64_t bits = 0;
      for (std::size_t k = 0; k < length; ++k) {
        const std::uint32_t count = counted[base + k + 1];
        bits |= static_cast<std::uint64_t>(count != 0) << k;
        total += count;
        counted[base + k + 1] = total;
      }
      occupied[w] = bits;
    }
    std::vector<Height>& by_cell = scratch_.by_cell<Height>();
    if (by_cell.size() < num_rows_ + kPadding) by_cell.resize(num_rows_ + kPadding, Height{0});
    Height* __restrict placed = by_cell.data();
    prefetch_lines(placed, sizeof(Height) * num_rows_);
    std::uint32_t* __restrict next = slot + 1;  // next[cell]: where the cell's next height goes
    const std::uint32_t* __restrict row_cell = scratch_.row_cell.data();
    const Height* __restrict row_heights = scratch_.row_heights<Height>().data();
    for (std::size_t k = 0; k < num_rows_; ++k) placed[next[row_cell[k]]++] = row_heights[k];
  }

  const Cloud& cloud_;
  std::size_t lo_, span_, words_;
  BuildScratch& scratch_;
  std::size_t num_rows_ = 0;  ///< rows of the range listed
  bool clean_ = true;         ///< the per-cell buffers are clean
};

/// Builds into `*into` (see build_elevation_map_into) when given, else into the returned map. With
/// `cells_out`, hands over the cell of every row (row-major i * ny + j; kOutside for rows outside the
/// map, unselected or NaN/Inf) by swapping buffers with it.
///
/// On one thread the rows are binned and listed a block at a time (the block's rows still in L1).
/// On several: the threads bin disjoint blocks of rows, then each builds a range of cells
/// (CellRange) holding about as many rows (from a sample of the codes) and cells as the others.
template <typename Cloud>
ElevationMap build_map(const Cloud& cloud, const ElevationParams& params, const std::vector<std::uint8_t>* use,
                       ElevationMap* into, std::vector<std::uint32_t>* cells_out = nullptr) {
  if (use && use->size() != cloud.size()) {
    throw std::invalid_argument("the point selection has " + std::to_string(use->size()) + " flags for " +
                                std::to_string(cloud.size()) + " points");
  }
  const auto selected = [&](std::size_t row) { return use == nullptr || (*use)[row] != 0; };
  const auto throw_non_finite = [&](std::size_t count, std::size_t first_row) {
    throw std::invalid_argument(std::to_string(count) + " of " + std::to_string(cloud.size()) +
                                " point rows contain NaN or Inf (first at row " + std::to_string(first_row) +
                                "); clean the cloud or set drop_non_finite=True to drop them");
  };
  // Pass 1 (auto extent only): extent of the selected points and NaN/Inf check. With a fixed
  // extent the check happens in pass 2.
  detail::CloudExtent extent;
  const bool fixed_extent = params.origin_m.has_value();
  if (!fixed_extent) {
    Eigen::Vector3d p;
    for (std::size_t row = 0; row < cloud.size(); ++row) {
      if (!selected(row)) continue;
      const int status = cloud.map(row, p);
      if (status == 1) {
        if (extent.num_non_finite++ == 0) extent.first_non_finite_row = row;
        continue;
      }
      if (status == 2) continue;
      extent.min = extent.min.cwiseMin(p);
      extent.max = extent.max.cwiseMax(p);
      ++extent.num_used;
    }
    if (extent.num_non_finite > 0 && !params.drop_non_finite) {
      throw_non_finite(extent.num_non_finite, extent.first_non_finite_row);
    }
  }
  const MapGeometry geometry = make_geometry(params, extent);
  if (into != nullptr && !into->layers().empty() && (into->geometry().size != geometry.size).any()) {
    throw std::invalid_argument("cannot refill a map of " + std::to_string(into->geometry().size.x()) + " x " +
                                std::to_string(into->geometry().size.y()) + " cells with a build of " +
                                std::to_string(geometry.size.x()) + " x " + std::to_string(geometry.size.y()) +
                                " cells: give a fixed extent (origin and size) of the map's size");
  }
  const std::size_t cells = geometry.num_cells();
  const auto nx = static_cast<std::int64_t>(geometry.size.x());
  const auto ny = static_cast<std::int64_t>(geometry.size.y());
  if (cells >= kSlow) throw std::invalid_argument("build_elevation_map handles maps of fewer than 2^32 - 2 cells");

  // Pass 2, in blocks of rows that stay in the L1 cache: the cell code of every row (row-major
  // cell = i * ny + j), then the block's rows listed and counted by cell (CellRange).
  BuildScratch& scratch = thread_scratch();
  struct ReleaseOnExit {  // after the cells have been handed over (or on an exception)
    BuildScratch& scratch;
    ~ReleaseOnExit() { scratch.release_if_large(); }
  } release_on_exit{scratch};
  constexpr std::size_t kRowsPerThread = 32768;
  int parts = detail::thread_count(params.num_threads, cloud.size(), kRowsPerThread);
  if (cells < 64 * static_cast<std::size_t>(parts)) parts = 1;
  // The cell of every row is kept when several threads share the rows, or for cells_out; else only
  // a block's at a time (in L1: a scan's worth would be written and read back from memory).
  std::vector<std::uint32_t>& cell_of_point = scratch.cell_of_point;
  const bool all_codes = parts > 1 || cells_out != nullptr;
  cell_of_point.resize(all_codes ? cloud.size() : 0);
  std::uint32_t* codes = cell_of_point.data();
  const AxisBinning along_x(geometry.origin_m.x(), geometry.resolution_m, nx);
  const AxisBinning along_y(geometry.origin_m.y(), geometry.resolution_m, ny);
  const auto bin_row = [&](std::size_t row, std::uint32_t& code, NonFiniteRows& non_finite) {  // the checking path
    code = kOutside;
    if (!selected(row)) return;
    Eigen::Vector3d p;
    const int status = cloud.map(row, p);
    if (status != 0) {
      if (status == 1) non_finite.add(row);
      return;
    }
    const std::int64_t i = along_x(p.x());
    const std::int64_t j = along_y(p.y());
    if (i >= 0 && j >= 0) code = static_cast<std::uint32_t>(i * ny + j);
  };
  const auto& view = cloud.view();
  bool kernel = false;  // plain rows of 3 or 4 scalars: the branch-free (vectorised) binning
  BinningConstants constants{};
  if constexpr (Cloud::kPlain) {
    constexpr std::int64_t kLargest = std::int64_t{1} << 30;  // cells + 2 must fit the kernel's int32
    // With a selection the kernel bins every row and the unselected ones are dropped after: worth
    // it with the AVX2 kernels, not with the scalar one (no faster than the per-row path).
    kernel = (use == nullptr || detail::has_avx2()) && view.column_stride == 1 &&
             (view.row_stride == 3 || view.row_stride == 4) && nx < kLargest && ny < kLargest;
    constants = {geometry.origin_m.x(),         geometry.origin_m.y(),         1.0 / geometry.resolution_m,
                 static_cast<double>(nx) + 1.0, static_cast<double>(ny) + 1.0, static_cast<std::int32_t>(nx),
                 static_cast<std::int32_t>(ny)};
    constants.resolution = geometry.resolution_m;
    const float margin_x = detail::float_estimate_margin(geometry.origin_m.x(), geometry.resolution_m, nx);
    const float margin_y = detail::float_estimate_margin(geometry.origin_m.y(), geometry.resolution_m, ny);
    if (margin_x > 0.0F && margin_y > 0.0F) constants.float_margin = std::max(margin_x, margin_y);
  }
  // The cell codes of the rows [begin, end) (at most kListBlock) into out[0, end - begin).
  const auto bin_block = [&](std::size_t begin, std::size_t end, std::uint32_t* out, NonFiniteRows& non_finite) {
    if (!kernel) {
      for (std::size_t row = begin; row < end; ++row) bin_row(row, out[row - begin], non_finite);
      return;
    }
    const auto* data = view.data + static_cast<std::ptrdiff_t>(begin) * view.row_stride;
    const auto stride = static_cast<int>(view.row_stride);
    const bool any_slow = bin_rows(data, end - begin, stride, constants, out);
    if (use != nullptr) {  // rows not selected take no part (nor count as NaN/Inf)
      const std::uint8_t* flags = use->data() + begin;
      for (std::size_t k = 0; k < end - begin; ++k) out[k] = flags[k] != 0 ? out[k] : kOutside;
    }
    if (any_slow) {  // NaN/Inf rows and rows on cell borders: rare, but for lattice data
      // The rows are listed first without a branch per row (on a 1 cm lattice a fifth of the
      // rows sit on 0.1 m cell borders, at random), then binned by the checking path.
      std::uint32_t slow_rows[kListBlock];  // from begin
      std::size_t num_slow = 0;
      std::size_t k = 0;
#if defined(__x86_64__) && defined(__GNUC__)
      if (detail::has_avx2()) k = list_slow_rows_avx2(out, end - begin, slow_rows, num_slow);
#endif
      for (; k < end - begin; ++k) {
        slow_rows[num_slow] = static_cast<std::uint32_t>(k);
        num_slow += out[k] == kSlow ? 1 : 0;
      }
      // The exact formula, four rows at a time; NaN/Inf rows (still kSlow) and the rest of the
      // list go through the checking path.
      const std::size_t done = bin_exact_rows(data, stride, slow_rows, num_slow, constants, out);
      for (std::size_t k = 0; k < num_slow; ++k) {
        std::uint32_t& code = out[slow_rows[k]];
        if (k >= done || code == kSlow) bin_row(begin + slow_rows[k], code, non_finite);
      }
    }
  };

  // The layers: the map's own buffers when refilling (in place, so that references to them stay
  // valid and no page is touched for the first time), else fresh ones. Every cell is written.
  // Added only once the rows have passed the NaN/Inf check: a map that throws is left unchanged.
  // A refilled map's other layers (of an earlier use: no data yet) are set to NaN by the ranges.
  ElevationMap fresh;
  std::array<float*, kBuiltLayers.size()> layers{};
  std::vector<float*> stale;
  const auto make_layers = [&] {
    if (into != nullptr) {
      into->set_geometry(geometry);
    } else {
      fresh = ElevationMap(geometry);
    }
    ElevationMap& map = into != nullptr ? *into : fresh;
    for (std::size_t k = 0; k < kBuiltLayers.size(); ++k) {
      if (!map.exists(kBuiltLayers[k])) map.add(kBuiltLayers[k], detail::uninitialised_layer(nx, ny));
      layers[k] = map.get(kBuiltLayers[k]).data();
    }
    for (const std::string& name : map.layers()) {
      if (std::find(kBuiltLayers.begin(), kBuiltLayers.end(), name) == kBuiltLayers.end()) {
        stale.push_back(map.get(name).data());
      }
    }
  };
  const auto check_non_finite = [&](const NonFiniteRows& non_finite) {
    if (fixed_extent && non_finite.count > 0 && !params.drop_non_finite) {
      throw_non_finite(non_finite.count, non_finite.first_row);
    }
  };

  const std::size_t block = kListBlock;
  const std::size_t num_blocks = (cloud.size() + block - 1) / block;
  if (parts == 1) {
    NonFiniteRows non_finite;
    CellRange<Cloud> range(cloud, 0, cells, scratch);
    std::uint32_t block_codes[kListBlock];
    range.list_rows([&](std::size_t begin, std::size_t end) {
      std::uint32_t* out = all_codes ? codes + begin : block_codes;
      bin_block(begin, end, out, non_finite);
      return out;
    });
    check_non_finite(non_finite);
    make_layers();
    range.write(layers, stale, params.discontinuity_m);
  } else {
    // Bin: each part takes a run of blocks, and counts the codes of every sample-th row in
    // buckets of 2^shift cells (at least 64, at most 4096 buckets) for the split below: about
    // 1024 sampled rows per part, every row to every 64th (a split within a few per cent of even
    // work; counting more rows costs more than it balances: KITTI frame 0 on two threads,
    // bench/ab_builds.sh, every 4th row against every 64th took 2-3 % longer).
    const std::size_t sample =
        std::clamp<std::size_t>(cloud.size() / (std::size_t{1024} * static_cast<std::size_t>(parts)), 1, 64);
    int shift = 6;
    while ((cells >> shift) >= 4096) ++shift;
    const std::size_t num_buckets = (cells >> shift) + 1;
    std::vector<NonFiniteRows> non_finite(static_cast<std::size_t>(parts));
    std::vector<std::uint64_t> sampled(static_cast<std::size_t>(parts) * num_buckets, 0);
    detail::for_each_part(parts, [&](int part) {
      const auto k = static_cast<std::size_t>(part);
      std::uint64_t* histogram = sampled.data() + k * num_buckets;
      for (std::size_t b = num_blocks * k / parts; b < num_blocks * (k + 1) / parts; ++b) {
        const std::size_t begin = b * block;
        const std::size_t end = std::min(cloud.size(), begin + block);
        bin_block(begin, end, codes + begin, non_finite[k]);
        for (std::size_t row = (begin + sample - 1) / sample * sample; row < end; row += sample) {
          const std::uint32_t code = codes[row];
          if (code != kOutside) ++histogram[code >> shift];
        }
      }
    });
    NonFiniteRows all;
    for (const NonFiniteRows& counted : non_finite) all.merge(counted);
    check_non_finite(all);
    make_layers();
    // Split the cells at bucket borders into parts of about equal work: `sample` rows per sampled
    // code, plus a quarter of a row per cell for the layers.
    // In quarter rows, in integers: the calling thread does this alone between the two steps (on
    // KITTI frame 0 about 4 us, against 6 us in doubles).
    std::uint64_t* work = sampled.data();  // part 0's counts become the buckets' work
    for (int part = 1; part < parts; ++part) {
      const std::uint64_t* counted = sampled.data() + static_cast<std::size_t>(part) * num_buckets;
      for (std::size_t b = 0; b < num_buckets; ++b) work[b] += counted[b];
    }
    const std::uint64_t per_code = 4 * static_cast<std::uint64_t>(sample);
    for (std::size_t b = 0; b < num_buckets; ++b) work[b] *= per_code;
    for (std::size_t b = 0; (b << shift) < cells; ++b)
      work[b] += std::min(cells - (b << shift), std::size_t{1} << shift);
    std::uint64_t total = 0;
    for (std::size_t b = 0; b < num_buckets; ++b) total += work[b];
    std::vector<std::size_t> cut(static_cast<std::size_t>(parts) + 1, cells);
    cut[0] = 0;
    std::uint64_t done = 0;
    std::size_t next_cut = 1;
    for (std::size_t b = 0; b < num_buckets && next_cut < static_cast<std::size_t>(parts); ++b) {
      done += work[b];
      while (next_cut < static_cast<std::size_t>(parts) &&
             done * static_cast<std::uint64_t>(parts) >= total * next_cut) {
        cut[next_cut++] = std::min(cells, (b + 1) << shift);
      }
    }
    detail::for_each_part(parts, [&](int part) {
      const auto k = static_cast<std::size_t>(part);
      if (cut[k] >= cut[k + 1]) return;
      BuildScratch& own = thread_scratch();  // the calling thread's is `scratch`, which holds the codes
      {
        CellRange<Cloud> range(cloud, cut[k], cut[k + 1], own);
        range.list_rows([&](std::size_t begin, std::size_t) { return codes + begin; });
        range.write(layers, stale, params.discontinuity_m);
      }
      if (&own != &scratch) own.release_if_large();
    });
  }
  if (cells_out != nullptr) cells_out->swap(cell_of_point);
  return fresh;
}

/// build_map on any view; `cells_out` (see build_map) is left empty when a transform or crop packs
/// the rows first (its cells would index the packed rows).
template <typename Scalar>
ElevationMap build_impl(const PointsView<Scalar>& points, const ElevationParams& params,
                        const std::vector<std::uint8_t>* use, ElevationMap* into = nullptr,
                        std::vector<std::uint32_t>* cells_out = nullptr) {
  check_elevation_params(params);
  if (points.size > 0 && points.data == nullptr) throw std::invalid_argument("points view has no data");
  if (points.size >= std::numeric_limits<std::uint32_t>::max()) {
    throw std::invalid_argument("build_elevation_map handles fewer than 2^32 points per call");
  }
  if (!params.transform.isIdentity(0.0) || params.crop.has_value()) {
    // A transform or a crop: level the selected rows that take part into a packed buffer once,
    // then build from it on the plain path (branch-free binning; the per-row path would level
    // every row in scalar code, and twice where it reads heights).
    if (use && use->size() != points.size) {
      throw std::invalid_argument("the point selection has " + std::to_string(use->size()) + " flags for " +
                                  std::to_string(points.size) + " points");
    }
    ElevationParams plain = params;
    plain.transform = Eigen::Matrix4d::Identity();
    plain.crop.reset();
    ElevationMap map = detail::with_packed_rows(
        points, params.transform, params.crop, params.drop_non_finite, use, detail::packed_rows_scratch(),
        [&](const auto& packed) {
          using Packed = std::remove_cv_t<std::remove_pointer_t<decltype(packed.data)>>;
          return build_map(detail::LeveledCloud<Packed, false, false>(packed, plain.transform, std::nullopt), plain,
                           nullptr, into);
        });
    detail::release_packed_rows_if_large();
    return map;
  }
  return detail::visit_leveled(points, params.transform, params.crop,
                               [&](const auto& cloud) { return build_map(cloud, params, use, into, cells_out); });
}

template <typename Scalar>
OverhangFreeMap overhang_free_impl(const PointsView<Scalar>& points, const CollapseParams& collapse,
                                   const ElevationParams& elevation) {
  if (!collapse.transform.isIdentity(0.0) || collapse.crop.has_value()) {
    // Level the rows that take part once; collapse, the maps and the clearance pass then all run
    // on the packed points (the plain paths), and the overhang mask goes back to the input rows.
    detail::check_collapse_params(collapse);
    if (points.size > 0 && points.data == nullptr) throw std::invalid_argument("points view has no data");
    if (points.size >= std::numeric_limits<std::uint32_t>::max()) {
      throw std::invalid_argument("build_overhang_free_map handles fewer than 2^32 points per call");
    }
    detail::PackedRows& packed = detail::packed_rows_scratch();
    CollapseParams plain = collapse;
    plain.transform = Eigen::Matrix4d::Identity();
    plain.crop.reset();
    OverhangFreeMap inner =
        detail::with_packed_rows(points, collapse.transform, collapse.crop, collapse.drop_non_finite, nullptr, packed,
                                 [&](const auto& rows) { return overhang_free_impl(rows, plain, elevation); });
    OverhangFreeMap out;
    out.map = std::move(inner.map);
    out.collapse.num_points = points.size;
    out.collapse.overhang.assign(points.size, 0);
    detail::unpack_collapse(std::move(inner.collapse), packed, out.collapse);
    detail::release_packed_rows_if_large();
    return out;
  }
  OverhangFreeMap out;
  out.collapse = collapse_overhangs(points, collapse);
  ElevationParams params = elevation;
  params.transform = collapse.transform;
  params.crop = collapse.crop;
  params.drop_non_finite = collapse.drop_non_finite;
  std::vector<std::uint8_t> kept(out.collapse.overhang.size());
  for (std::size_t i = 0; i < kept.size(); ++i) kept[i] = out.collapse.overhang[i] ? 0 : 1;
  // The geometry follows all points (kept and overhang) unless fixed, so that the raw DEM of the
  // same parameters aligns: their bounding box, as build_elevation_map's first pass finds it.
  if (!params.origin_m) {
    const detail::CloudExtent extent =
        detail::visit_leveled(points, params.transform, params.crop,
                              [&](const auto& cloud) { return detail::measure_extent(cloud, params.drop_non_finite); });
    if (extent.num_used > 0) {  // an empty cloud keeps the auto (empty) extent
      const MapGeometry geometry = make_geometry(params, extent);
      params.origin_m = geometry.origin_m;
      params.size = geometry.size;
    }
  }
  // The kept rows' cells come back from the map's binning (a buffer swapped with the thread's
  // scratch, and given back to it at the end).
  std::vector<std::uint32_t> cells;
  out.map = build_impl(points, params, &kept, nullptr, &cells);
  const Layer& top = out.map.get("max");
  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  const MapGeometry& geometry = out.map.geometry();
  // The lowest overhang point of each cell (the "min" layer of the overhang points' map: rounding
  // is monotonic, so the least rounded height is the rounded least height), then the ground under
  // it: the highest kept point below it. (A map cell can straddle two cube columns, so a kept
  // wall may rise above an overhang that its neighbouring column collapsed; measuring from it
  // would give a negative clearance.) The kept points' cells are those of the map's binning
  // (kOutside for overhang rows); the few overhang points are binned here by the same formula
  // (MapGeometry::index_of, as AxisBinning computes it).
  const AxisBinning along_x(geometry.origin_m.x(), geometry.resolution_m, geometry.size.x());
  const AxisBinning along_y(geometry.origin_m.y(), geometry.resolution_m, geometry.size.y());
  const auto ny = static_cast<std::int64_t>(geometry.size.y());
  Layer lowest_overhang = detail::filled_layer(top.rows(), top.cols(), kNaN);
  Layer under = detail::filled_layer(top.rows(), top.cols(), kNaN);
  float* lowest = lowest_overhang.data();
  float* highest_under = under.data();
  const std::vector<std::uint8_t>& overhang = out.collapse.overhang;
  detail::visit_leveled(points, params.transform, params.crop, [&](const auto& cloud) {
    Eigen::Vector3d p;
    for (std::size_t row = 0; row < cloud.size(); ++row) {
      if (!overhang[row] || cloud.map(row, p) != 0) continue;
      const std::int64_t i = along_x(p.x());
      const std::int64_t j = along_y(p.y());
      if (i < 0 || j < 0) continue;
      float& least = lowest[i * ny + j];
      const auto z = static_cast<float>(p.z());
      if (std::isnan(least) || z < least) least = z;
    }
    if (cells.size() != cloud.size()) {  // not handed over (build_impl packed the rows): bin them here
      cells.assign(cloud.size(), kOutside);
      for (std::size_t row = 0; row < cloud.size(); ++row) {
        if (!kept[row] || cloud.map(row, p) != 0) continue;
        const std::int64_t i = along_x(p.x());
        const std::int64_t j = along_y(p.y());
        if (i >= 0 && j >= 0) cells[row] = static_cast<std::uint32_t>(i * ny + j);
      }
    }
    for (std::size_t row = 0; row < cloud.size(); ++row) {
      const std::uint32_t cell = cells[row];
      if (cell == kOutside) continue;
      const float above = lowest[cell];
      if (std::isnan(above)) continue;  // no overhang over the cell (most cells)
      cloud.map_unchecked(row, p);
      if (!(p.z() < above)) continue;
      float& highest = highest_under[cell];
      if (std::isnan(highest) || p.z() > highest) highest = static_cast<float>(p.z());
    }
  });
  // Clearance: NaN without a kept point (unknown), +inf without an overhang, else the overhang's
  // height over the ground under it (NaN when no kept point lies below it). Selects, no branches.
  Layer clearance = detail::uninitialised_layer(top.rows(), top.cols());
  {
    const float* kept_top = top.data();
    const float* overhang_low = lowest_overhang.data();
    const float* ground = under.data();
    float* out_clearance = clearance.data();
    constexpr float kInfinity = std::numeric_limits<float>::infinity();
    for (Eigen::Index k = 0; k < top.size(); ++k) {
      const float gap = overhang_low[k] - ground[k];
      const float value = std::isnan(overhang_low[k]) ? kInfinity : gap;
      out_clearance[k] = std::isnan(kept_top[k]) ? kNaN : value;
    }
  }
  thread_scratch().cell_of_point.swap(cells);  // kept warm for the next map of this thread
  out.map.add("overhang_min", std::move(lowest_overhang));
  out.map.add("clearance", std::move(clearance));
  out.map.add("step", step_layer(top));
  return out;
}

}  // namespace

ElevationMap build_elevation_map(const PointsView<float>& points, const ElevationParams& params,
                                 const std::vector<std::uint8_t>* use) {
  return build_impl(points, params, use);
}
ElevationMap build_elevation_map(const PointsView<double>& points, const ElevationParams& params,
                                 const std::vector<std::uint8_t>* use) {
  return build_impl(points, params, use);
}
void build_elevation_map_into(ElevationMap& map, const PointsView<float>& points, const ElevationParams& params,
                              const std::vector<std::uint8_t>* use) {
  build_impl(points, params, use, &map);
}
void build_elevation_map_into(ElevationMap& map, const PointsView<double>& points, const ElevationParams& params,
                              const std::vector<std::uint8_t>* use) {
  build_impl(points, params, use, &map);
}
OverhangFreeMap build_overhang_free_map(const PointsView<float>& points, const CollapseParams& collapse,
                                        const ElevationParams& elevation) {
  return overhang_free_impl(points, collapse, elevation);
}
OverhangFreeMap build_overhang_free_map(const PointsView<double>& points, const CollapseParams& collapse,
                                        const ElevationParams& elevation) {
  return overhang_free_impl(points, collapse, elevation);
}

}  // namespace terracube
