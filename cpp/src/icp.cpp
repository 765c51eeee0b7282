#include "terracube/icp.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>
#include <stdexcept>
#include <string>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define TERRACUBE_HAVE_AVX2_ICP 1
#endif

#include "cloud_frame.hpp"
#include "cpu_features.hpp"

namespace terracube {

namespace {

constexpr std::uint32_t kLeafSize = 8;
// Rounding allowance of the nearest-neighbour certificates [m]: far above the error of the
// distances (about 1e-15 m at map scale), far below any distance that matters.
constexpr double kCertificateSlack = 1e-9;
// A search that finds nothing within the certificate reach looks this many times the distance
// limit far (see Registration::search).
constexpr double kEmptyReach = 1.5;
// The number of set bits of a 4-bit lane mask.
constexpr std::uint8_t kLaneCount[16] = {0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4};

using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Vector6d = Eigen::Matrix<double, 6, 1>;

void check_registration_params(const RegistrationParams& p) {
  const auto positive = [](double v) { return v > 0.0 && std::isfinite(v); };
  const auto non_negative = [](double v) { return v >= 0.0 && std::isfinite(v); };
  if (!positive(p.max_correspondence_distance_m) || !positive(p.min_correspondence_distance_m)) {
    throw std::invalid_argument("correspondence distances must be positive and finite [m]");
  }
  if (p.min_correspondence_distance_m > p.max_correspondence_distance_m) {
    throw std::invalid_argument("min correspondence distance must not exceed the max correspondence distance");
  }
  if (!(p.correspondence_distance_decay > 0.0 && p.correspondence_distance_decay <= 1.0)) {
    throw std::invalid_argument("correspondence distance decay must lie in (0, 1]");
  }
  if (p.max_iterations < 1) throw std::invalid_argument("max iterations must be at least 1");
  if (!non_negative(p.rotation_tolerance_rad) || !non_negative(p.translation_tolerance_m) ||
      !non_negative(p.error_threshold_m)) {
    throw std::invalid_argument("tolerances and the error threshold must be finite and >= 0");
  }
  if (p.coarse_subsample < 1) throw std::invalid_argument("coarse subsample must be at least 1");
  if (!non_negative(p.coarse_until_motion_m)) {
    throw std::invalid_argument("coarse-until motion must be finite and >= 0 [m]");
  }
  if (p.min_correspondences < 3) throw std::invalid_argument("min correspondences must be at least 3");
  if (!non_negative(p.structure_radius_m)) {
    throw std::invalid_argument("structure_radius_m must be finite and >= 0 [m]");
  }
  if (!(p.degeneracy_threshold >= 0.0 && p.degeneracy_threshold < 1.0)) {
    throw std::invalid_argument("degeneracy threshold must lie in [0, 1)");
  }
  for (const double w : p.class_weights) {
    if (!non_negative(w)) throw std::invalid_argument("class weights must be finite and >= 0");
  }
  if (!non_negative(p.ground_weight)) throw std::invalid_argument("ground weight must be finite and >= 0");
  if (!positive(p.ground_cell_m)) throw std::invalid_argument("ground cell must be positive and finite [m]");
}

void check_points(const ClassifiedPoints& set, const char* what) {
  if (set.classes.size() != set.points.size()) {
    throw std::invalid_argument(std::string(what) + " has " + std::to_string(set.points.size()) + " points but " +
                                std::to_string(set.classes.size()) + " classes");
  }
  // One sweep without branches (x - x is 0 for a finite x and NaN for NaN and Inf, and NaN
  // propagates); the offending point is looked up only when there is one.
  double poison = 0.0;
  std::uint8_t largest = 0;
  for (std::size_t k = 0; k < set.size(); ++k) {
    const Eigen::Vector3d& p = set.points[k];
    poison += (p.x() - p.x()) + (p.y() - p.y()) + (p.z() - p.z());
    largest = std::max(largest, set.classes[k]);
  }
  if (poison == 0.0 && largest < kNumTerrainClasses) return;
  for (std::size_t k = 0; k < set.size(); ++k) {
    if (!set.points[k].allFinite()) {
      throw std::invalid_argument(std::string(what) + " point " + std::to_string(k) + " is NaN or Inf");
    }
    if (set.classes[k] >= kNumTerrainClasses) {
      throw std::invalid_argument(std::string(what) + " class " + std::to_string(set.classes[k]) + " at point " +
                                  std::to_string(k) + " is not a TerrainClass");
    }
  }
}

Eigen::Matrix3d skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0.0, -v.z(), v.y(), v.z(), 0.0, -v.x(), -v.y(), v.x(), 0.0;
  return m;
}

/// One correspondence pass: the weighted normal equations about the correspondences' weighted
/// source centroid.
struct Pass {
  Matrix6d normal = Matrix6d::Zero();
  Vector6d gradient = Vector6d::Zero();
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  double weight_sum = 0.0;
  double weighted_squared_error = 0.0;
  /// rms distance of the class correspondences from their centroid (ground planes not counted)
  double class_radius = 0.0;
  double class_weight_sum = 0.0, class_squared_error = 0.0;  // the class correspondences' part
  std::size_t count = 0;
  std::array<std::size_t, kNumTerrainClasses> per_class{};
};

/// Unweighted sums over the correspondences of one class (p, q: the moved source point and its
/// partner, both relative to the pass's origin o); a class's weight multiplies them afterwards.
struct ClassMoments {
  std::size_t count = 0;
  double squared = 0.0;  // sum |p - q|^2
  double p[3] = {0, 0, 0}, q[3] = {0, 0, 0}, pxq[3] = {0, 0, 0};
  double pp[6] = {0, 0, 0, 0, 0, 0};  // xx xy xz yy yz zz

  void add(const Eigen::Vector3d& a, const Eigen::Vector3d& b, double d2) {
    ++count;
    squared += d2;
    for (int i = 0; i < 3; ++i) p[i] += a[i], q[i] += b[i];
    pp[0] += a.x() * a.x(), pp[1] += a.x() * a.y(), pp[2] += a.x() * a.z();
    pp[3] += a.y() * a.y(), pp[4] += a.y() * a.z(), pp[5] += a.z() * a.z();
    pxq[0] += a.y() * b.z() - a.z() * b.y();
    pxq[1] += a.z() * b.x() - a.x() * b.z();
    pxq[2] += a.x() * b.y() - a.y() * b.x();
  }
};

/// A pass's motion: rotation r (row-major), translation t and the moments' origin o.
struct Motion {
  double r[9], t[3], o[3];
};

#if defined(TERRACUBE_HAVE_AVX2_ICP)
/// a^2 + b^2 + c^2 lane by lane, in that order.
__attribute__((target("avx2"), always_inline)) inline __m256d squared_norm4(__m256d a, __m256d b, __m256d c) {
  return _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(a, a), _mm256_mul_pd(b, b)), _mm256_mul_pd(c, c));
}

/// The sum of the four lanes, (0 + 1) + (2 + 3).
__attribute__((target("avx2"), always_inline)) inline double lane_total(__m256d v) {
  alignas(32) double lanes[4];
  _mm256_store_pd(lanes, v);
  return (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
}
#endif

/// Square cells of side `cell` over (x, y), cell (kx, ky) = (floor(x / cell), floor(y / cell)),
/// numbered in the order their first point comes. Dense (an entry per cell of the points'
/// bounding box) when the box has at most 8 n + 65536 cells, else sorted keys and a binary search,
/// so that memory stays O(n) for any extent.
class GroundCells {
 public:
  GroundCells() = default;

  /// `id_of_point` receives each point's cell number. Throws std::invalid_argument when a point
  /// lies 2^31 or more cells from the origin.
  GroundCells(const std::vector<Eigen::Vector3d>& points, double cell, std::vector<std::uint32_t>& id_of_point)
      : cell_(cell) {
    const std::size_t n = points.size();
    std::vector<std::int64_t> kx(n), ky(n);
    for (std::size_t k = 0; k < n; ++k) {
      const double fx = std::floor(points[k].x() / cell), fy = std::floor(points[k].y() / cell);
      if (!(std::abs(fx) < kLimit && std::abs(fy) < kLimit)) {
        throw std::invalid_argument(
            "ground cell is too small for the extent of the ground points (2^31 cells or "
            "more from the origin)");
      }
      kx[k] = static_cast<std::int64_t>(fx), ky[k] = static_cast<std::int64_t>(fy);
      kx0_ = std::min(kx0_, kx[k]), kx1_ = std::max(kx1_, kx[k]);
      ky0_ = std::min(ky0_, ky[k]), ky1_ = std::max(ky1_, ky[k]);
    }
    id_of_point.resize(n);
    if (n == 0) return;
    columns_ = kx1_ - kx0_ + 1;
    const double cells = static_cast<double>(columns_) * static_cast<double>(ky1_ - ky0_ + 1);
    if (cells <= 8.0 * static_cast<double>(n) + 65536.0) {
      dense_.assign(static_cast<std::size_t>(cells), -1);
      for (std::size_t k = 0; k < n; ++k) {
        std::int32_t& id = dense_[static_cast<std::size_t>((kx[k] - kx0_) + (ky[k] - ky0_) * columns_)];
        if (id < 0) id = static_cast<std::int32_t>(size_++);
        id_of_point[k] = static_cast<std::uint32_t>(id);
      }
      return;
    }
    keys_.resize(n);
    for (std::size_t k = 0; k < n; ++k) keys_[k] = key(kx[k], ky[k]);
    std::sort(keys_.begin(), keys_.end());
    keys_.erase(std::unique(keys_.begin(), keys_.end()), keys_.end());
    size_ = keys_.size();
    for (std::size_t k = 0; k < n; ++k) {
      id_of_point[k] =
          static_cast<std::uint32_t>(std::lower_bound(keys_.begin(), keys_.end(), key(kx[k], ky[k])) - keys_.begin());
    }
  }

  std::size_t size() const { return size_; }

  /// The number of the cell holding (x, y), or -1 where no point fell (NaN included).
  std::int64_t find(double x, double y) const {
    const double fx = std::floor(x / cell_), fy = std::floor(y / cell_);
    if (!(fx >= static_cast<double>(kx0_) && fx <= static_cast<double>(kx1_) && fy >= static_cast<double>(ky0_) &&
          fy <= static_cast<double>(ky1_))) {
      return -1;
    }
    const auto ix = static_cast<std::int64_t>(fx), iy = static_cast<std::int64_t>(fy);
    if (!dense_.empty()) return dense_[static_cast<std::size_t>((ix - kx0_) + (iy - ky0_) * columns_)];
    const std::uint64_t wanted = key(ix, iy);
    const auto it = std::lower_bound(keys_.begin(), keys_.end(), wanted);
    return it != keys_.end() && *it == wanted ? it - keys_.begin() : -1;
  }

 private:
  static constexpr double kLimit = 2147483648.0;  // 2^31
  static std::uint64_t key(std::int64_t kx, std::int64_t ky) {
    return (static_cast<std::uint64_t>(kx + (std::int64_t{1} << 31)) << 32) |
           static_cast<std::uint64_t>(ky + (std::int64_t{1} << 31));
  }

  double cell_ = 1.0;
  std::int64_t kx0_ = std::numeric_limits<std::int64_t>::max(), ky0_ = std::numeric_limits<std::int64_t>::max();
  std::int64_t kx1_ = std::numeric_limits<std::int64_t>::min(), ky1_ = std::numeric_limits<std::int64_t>::min();
  std::int64_t columns_ = 0;
  std::vector<std::int32_t> dense_;
  std::vector<std::uint64_t> keys_;
  std::size_t size_ = 0;
};

/// A target ground cell's plane (RegistrationParams::ground_weight): a point on it (the mean of
/// the cell's points) and its unit normal.
struct GroundPlane {
  Eigen::Vector3d point, normal;
};

/// Per cell of `index`, the least-squares plane z = a + b x + c y of its points (`id_of_point`);
/// horizontal through the mean below three points or when the points nearly lie on a line.
std::vector<GroundPlane> fit_ground_planes(const std::vector<Eigen::Vector3d>& points,
                                           const std::vector<std::uint32_t>& id_of_point, std::size_t cells) {
  // Sums relative to each cell's first point, so that they stay well conditioned far from zero:
  // n, x, y, z, xx, xy, yy, xz, yz.
  std::vector<std::array<double, 9>> sums(cells, std::array<double, 9>{});
  std::vector<Eigen::Vector3d> first(cells);
  for (std::size_t k = 0; k < points.size(); ++k) {
    auto& m = sums[id_of_point[k]];
    if (m[0] == 0.0) first[id_of_point[k]] = points[k];
    const Eigen::Vector3d d = points[k] - first[id_of_point[k]];
    m[0] += 1.0, m[1] += d.x(), m[2] += d.y(), m[3] += d.z();
    m[4] += d.x() * d.x(), m[5] += d.x() * d.y(), m[6] += d.y() * d.y(), m[7] += d.x() * d.z(), m[8] += d.y() * d.z();
  }
  std::vector<GroundPlane> planes(cells);
  for (std::size_t c = 0; c < cells; ++c) {
    const auto& m = sums[c];
    const double n = m[0];
    const Eigen::Vector3d mean(m[1] / n, m[2] / n, m[3] / n);
    // Centred moments.
    const double xx = m[4] - m[1] * mean.x(), xy = m[5] - m[1] * mean.y(), yy = m[6] - m[2] * mean.y();
    const double xz = m[7] - m[1] * mean.z(), yz = m[8] - m[2] * mean.z();
    const double det = xx * yy - xy * xy;
    double b = 0.0, slope_y = 0.0;
    if (n >= 3.0 && det > 1e-6 * (xx + yy) * (xx + yy)) {
      b = (yy * xz - xy * yz) / det;
      slope_y = (xx * yz - xy * xz) / det;
    }
    planes[c].point = first[c] + mean;
    planes[c].normal = Eigen::Vector3d(-b, -slope_y, 1.0).normalized();
  }
  return planes;
}

class Registration {
 public:
  Registration(const ClassifiedPoints& source, const ClassifiedPoints& target, const RegistrationParams& params) {
    // One grid per class (or one for all): buckets of target points.
    std::array<std::vector<Eigen::Vector3d>, kNumTerrainClasses> buckets;
    for (std::size_t k = 0; k < target.size(); ++k) {
      const std::size_t c = params.use_classes ? target.classes[k] : 0;
      if (!params.use_classes || params.class_weights[c] > 0.0) buckets[c].push_back(target.points[k]);
    }
    for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
      if (!buckets[c].empty()) grids_[c] = NearestNeighborGrid(std::move(buckets[c]));
    }
    // The source points that can take part, grouped by class (in their order within a class):
    // a class has one weight and one grid, and its points are checked four at a time.
    std::array<std::size_t, kNumTerrainClasses> count{};
    for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
      class_grid_[c] = static_cast<std::uint8_t>(params.use_classes ? c : 0);
      const double w = params.use_classes ? params.class_weights[c] : 1.0;
      class_weight_[c] = w > 0.0 && grids_[class_grid_[c]].size() > 0 ? w : 0.0;
    }
    for (std::size_t k = 0; k < source.size(); ++k) count[source.classes[k]] += class_weight_[source.classes[k]] > 0.0;
    class_begin_[0] = 0;
    for (std::size_t c = 0; c < kNumTerrainClasses; ++c) class_begin_[c + 1] = class_begin_[c] + count[c];
    const std::size_t n = class_begin_[kNumTerrainClasses];
    if (n >= std::numeric_limits<std::uint32_t>::max()) {
      throw std::invalid_argument("register_points handles fewer than 2^32 - 1 source points that take part");
    }
    for (auto* v : {&x_, &y_, &z_}) v->resize(n);
    ordinal_.resize(n);
    std::array<std::size_t, kNumTerrainClasses> next{};
    std::copy(class_begin_.begin(), class_begin_.end() - 1, next.begin());
    for (std::size_t k = 0, ordinal = 0; k < source.size(); ++k) {
      const std::uint8_t c = source.classes[k];
      if (!(class_weight_[c] > 0.0)) continue;
      const std::size_t slot = next[c]++;
      ordinal_[slot] = static_cast<std::uint32_t>(ordinal++);
      const Eigen::Vector3d& p = source.points[k];
      x_[slot] = p.x(), y_[slot] = p.y(), z_[slot] = p.z();
      total_weight_ += class_weight_[c];
      reference_ += p;
    }
    if (n > 0) reference_ /= static_cast<double>(n);
    // No certificate yet: no candidate, a clearance that proves nothing.
    for (auto* v :
         {&anchor_x_, &anchor_y_, &anchor_z_, &first_x_, &first_y_, &first_z_, &second_x_, &second_y_, &second_z_}) {
      v->assign(n, 0.0);
    }
    clearance_.assign(n, -1.0);
    first_.assign(n, -1);
    second_.assign(n, -1);
    deferred_.resize(n + 4);
    certificate_reach_ = params.min_correspondence_distance_m;
    if (params.use_classes && params.ground_weight > 0.0) set_up_ground(source, target, params);
  }

  bool has_common_class() const { return class_begin_[kNumTerrainClasses] > 0; }
  std::size_t active_size() const { return class_begin_[kNumTerrainClasses]; }

  /// The eq. (4) error of a pass truncated at `max_distance`: sum over the active source points of
  /// w min(d^2, max_distance^2), d the distance to the nearest target point of the class. A proper
  /// objective to compare poses with (unlike the RMSE, it does not fall when pairs drop out).
  double truncated_error(const Pass& pass, double max_distance) const {
    return pass.class_squared_error + (total_weight_ - pass.class_weight_sum) * max_distance * max_distance;
  }

  /// Correspondences of the source moved by `transform`, each source point paired with its nearest
  /// target point (of its class) within `max_distance`; one sweep accumulates the moments. With
  /// `stride` > 1 only every stride-th active point takes part (the coarse iterations).
  Pass pass(const Eigen::Matrix4d& transform, double max_distance, std::size_t stride = 1) {
    if (stride > 1 && stride != coarse_stride_) select_coarse(stride);
    Motion motion{};
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) motion.r[3 * i + j] = transform(i, j);
      motion.t[i] = transform(i, 3);
    }
    // Moments are taken about o, the moved centroid of the active source points, so that they
    // stay well conditioned far from the origin.
    const Eigen::Vector3d o = transform.topLeftCorner<3, 3>() * reference_ + transform.topRightCorner<3, 1>();
    for (int i = 0; i < 3; ++i) motion.o[i] = o[i];
    const double max_squared = max_distance * max_distance;
    Pass result;
    double w_sum = 0.0, error = 0.0;
    double sp[3] = {0, 0, 0}, sq[3] = {0, 0, 0}, spxq[3] = {0, 0, 0};
    double spp[6] = {0, 0, 0, 0, 0, 0};  // xx xy xz yy yz zz
    for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
      const std::size_t begin = class_begin_[c], end = class_begin_[c + 1];
      if (begin == end) continue;
      ClassMoments m;
      std::size_t num_deferred = 0;
      if (stride == 1) {
        std::size_t slot = begin;
#if defined(TERRACUBE_HAVE_AVX2_ICP)
        if (detail::has_avx2()) slot = check_avx2(begin, end, motion, max_distance, m, num_deferred);
#endif
        for (; slot < end; ++slot) check_one(slot, motion, max_distance, m, num_deferred);
      } else {
        for (std::size_t k = coarse_begin_[c]; k < coarse_begin_[c + 1]; ++k) {
          check_one(coarse_[k], motion, max_distance, m, num_deferred);
        }
      }
      // The points whose certificate did not hold: searched again.
      for (std::size_t k = 0; k < num_deferred; ++k) {
        const std::uint32_t s = deferred_[k];
        const Eigen::Vector3d moved = move(motion, s);
        double squared = 0.0;
        search(class_grid_[c], moved, max_squared, s, squared);
        if (first_[s] >= 0 && squared <= max_squared) {
          m.add(moved - o, Eigen::Vector3d(first_x_[s], first_y_[s], first_z_[s]) - o, squared);
        }
      }
      // Eq. (4): the class's weight on each of its correspondences.
      const double w = class_weight_[c];
      result.count += m.count;
      result.per_class[c] += m.count;
      w_sum += w * static_cast<double>(m.count);
      error += w * m.squared;
      for (int i = 0; i < 3; ++i) sp[i] += w * m.p[i], sq[i] += w * m.q[i], spxq[i] += w * m.pxq[i];
      for (int i = 0; i < 6; ++i) spp[i] += w * m.pp[i];
    }
    // Ground as planes (RegistrationParams::ground_weight): each source sample with the plane of
    // the target cell under it, residual along the plane's normal n. About o, v = (a x n, n) with a
    // the moved sample; about the centroid c below, J = M v with M = [I, -[c]x; 0, I].
    Matrix6d ground_normal = Matrix6d::Zero();
    Vector6d ground_gradient = Vector6d::Zero();
    std::size_t ground_count = 0;
    double ground_error = 0.0;
    for (std::size_t k = 0; k < ground_x_.size(); k += stride) {
      const double x = ground_x_[k], y = ground_y_[k], z = ground_z_[k];
      const Eigen::Vector3d moved(motion.r[0] * x + motion.r[1] * y + motion.r[2] * z + motion.t[0],
                                  motion.r[3] * x + motion.r[4] * y + motion.r[5] * z + motion.t[1],
                                  motion.r[6] * x + motion.r[7] * y + motion.r[8] * z + motion.t[2]);
      const std::int64_t cell = ground_cells_.find(moved.x(), moved.y());
      if (cell < 0) continue;
      const GroundPlane& plane = ground_planes_[static_cast<std::size_t>(cell)];
      const double d = plane.normal.dot(moved - plane.point);
      if (!(d * d <= max_squared)) continue;
      Vector6d v;
      v << (moved - o).cross(plane.normal), plane.normal;
      ground_normal.noalias() += v * v.transpose();
      ground_gradient -= d * v;
      ground_error += d * d;
      ++ground_count;
    }
    const double class_w_sum = w_sum;
    result.class_weight_sum = w_sum;
    result.class_squared_error = error;
    if (ground_count > 0) {
      result.count += ground_count;
      result.per_class[static_cast<std::size_t>(TerrainClass::kGround)] += ground_count;
      w_sum += ground_weight_ * static_cast<double>(ground_count);
      error += ground_weight_ * ground_error;
    }
    result.weight_sum = w_sum;
    result.weighted_squared_error = error;
    if (result.count == 0) return result;
    // Eq. (A6) with per-class weights (eq. 4). Unknowns x = (omega, t) about the weighted centroid
    // c of the moved source points; residual r_i = p_i + omega x (p_i - c) + t - q_i, so
    // J_i = [-[p_i - c]x, I], H = sum w J^T J and g = sum w J^T (q_i - p_i). From the moments
    // (p, q relative to o, c = sum w p / W):
    //   sum w [p - c]x^T [p - c]x = tr(C) I - C with C = sum w p p^T - W c c^T,
    //   the rotation-translation block is [sum w (p - c)]x = 0,
    //   g_rot = sum w (p - c) x (q - p) = sum w p x q - c x sum w q,  g_trans = sum w q - W c.
    // c: the centroid of the class correspondences (o itself when there are only ground pairs).
    const Eigen::Vector3d c = class_w_sum > 0.0 ? Eigen::Vector3d(Eigen::Vector3d(sp[0], sp[1], sp[2]) / class_w_sum)
                                                : Eigen::Vector3d::Zero();
    Eigen::Matrix3d scatter;
    scatter << spp[0], spp[1], spp[2], spp[1], spp[3], spp[4], spp[2], spp[4], spp[5];
    scatter -= class_w_sum * c * c.transpose();
    const Eigen::Vector3d weighted_q(sq[0], sq[1], sq[2]);
    result.normal.setZero();
    result.normal.topLeftCorner<3, 3>() = scatter.trace() * Eigen::Matrix3d::Identity() - scatter;
    result.normal.bottomRightCorner<3, 3>() = class_w_sum * Eigen::Matrix3d::Identity();
    result.gradient << Eigen::Vector3d(spxq[0], spxq[1], spxq[2]) - c.cross(weighted_q), weighted_q - class_w_sum * c;
    // The trace of the rotation block is 2 sum w |p - c|^2.
    result.class_radius =
        class_w_sum > 0.0
            ? std::sqrt(std::max(result.normal.topLeftCorner<3, 3>().trace() / (2.0 * class_w_sum), 1e-12))
            : 1e-6;
    if (ground_count > 0) {
      Matrix6d shift = Matrix6d::Identity();
      shift.topRightCorner<3, 3>() = -skew(c);
      result.normal += ground_weight_ * (shift * ground_normal * shift.transpose());
      result.gradient += ground_weight_ * (shift * ground_gradient);
    }
    result.centroid = c + o;
    return result;
  }

  /// RegistrationResult::constraint_matrix at `transform`: each active source point paired with
  /// its nearest target point of its class within `max_distance` (from its certificate where that
  /// still holds, else searched), the row
  /// [((p - c) x e)^T, e^T] of every direction e in which the partner's neighbourhood within
  /// `radius` does not extend, weighted; plus the ground planes' rows along their normals.
  Matrix6d constraints(const Eigen::Matrix4d& transform, double max_distance, double radius,
                       const Eigen::Vector3d& c) const {
    const Eigen::Matrix3d rotation = transform.topLeftCorner<3, 3>();
    const Eigen::Vector3d translation = transform.topRightCorner<3, 1>();
    const double max_squared = max_distance * max_distance;
    const double extent = 0.25 * radius;  // standard deviation along a direction the structure extends in
    Matrix6d information = Matrix6d::Zero();
    const auto add_row = [&](const Eigen::Vector3d& p, const Eigen::Vector3d& e, double w) {
      Vector6d row;
      row << (p - c).cross(e), e;
      information.noalias() += w * row * row.transpose();
    };
    std::vector<std::uint32_t> neighbours;
    for (std::size_t cls = 0; cls < kNumTerrainClasses; ++cls) {
      const NearestNeighborGrid& grid = grids_[class_grid_[cls]];
      for (std::size_t slot = class_begin_[cls]; slot < class_begin_[cls + 1]; ++slot) {
        const Eigen::Vector3d p = rotation * Eigen::Vector3d(x_[slot], y_[slot], z_[slot]) + translation;
        // The partner from the slot's certificate where it holds (as in check_one), else searched.
        std::ptrdiff_t partner = -1;
        const double margin = clearance_[slot] -
                              (p - Eigen::Vector3d(anchor_x_[slot], anchor_y_[slot], anchor_z_[slot])).norm() -
                              kCertificateSlack;
        const double d0 = (p - Eigen::Vector3d(first_x_[slot], first_y_[slot], first_z_[slot])).squaredNorm();
        const double d1 = (p - Eigen::Vector3d(second_x_[slot], second_y_[slot], second_z_[slot])).squaredNorm();
        const bool nearer_second = second_[slot] >= 0 && d1 < d0;
        const double squared = nearer_second ? d1 : d0;
        if (first_[slot] >= 0 ? margin >= 0.0 && squared <= margin * margin : margin > max_distance) {
          if (first_[slot] >= 0 && squared <= max_squared) partner = nearer_second ? second_[slot] : first_[slot];
        } else {
          double found = max_squared;
          partner = grid.nearest(p, max_squared, found);
        }
        if (partner < 0) continue;
        const Eigen::Vector3d& q = grid.point(static_cast<std::size_t>(partner));
        neighbours.clear();
        grid.within(q, radius, neighbours);
        // The neighbourhood's covariance (about q, which is among the neighbours).
        Eigen::Vector3d mean = Eigen::Vector3d::Zero();
        Eigen::Matrix3d moments = Eigen::Matrix3d::Zero();
        for (const std::uint32_t k : neighbours) {
          const Eigen::Vector3d d = grid.point(k) - q;
          mean += d;
          moments.noalias() += d * d.transpose();
        }
        const double n = static_cast<double>(std::max<std::size_t>(neighbours.size(), 1));
        mean /= n;
        const Eigen::Matrix3d covariance = moments / n - mean * mean.transpose();
        Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver;
        solver.computeDirect(covariance);
        for (int k = 0; k < 3; ++k) {
          if (!(std::sqrt(std::max(solver.eigenvalues()(k), 0.0)) > extent)) {
            add_row(p, solver.eigenvectors().col(k), class_weight_[cls]);
          }
        }
      }
    }
    for (std::size_t k = 0; k < ground_x_.size(); ++k) {
      const Eigen::Vector3d p = rotation * Eigen::Vector3d(ground_x_[k], ground_y_[k], ground_z_[k]) + translation;
      const std::int64_t cell = ground_cells_.find(p.x(), p.y());
      if (cell < 0) continue;
      const GroundPlane& plane = ground_planes_[static_cast<std::size_t>(cell)];
      const double d = plane.normal.dot(p - plane.point);
      if (d * d <= max_squared) add_row(p, plane.normal, ground_weight_);
    }
    // (w r) r^T is symmetric only up to rounding; make it exactly so.
    return 0.5 * (information + information.transpose());
  }

 private:
  /// The ground planes of the target and the ground samples of the source (one per occupied
  /// source cell: the mean of its ground points).
  void set_up_ground(const ClassifiedPoints& source, const ClassifiedPoints& target, const RegistrationParams& params) {
    constexpr auto kGround = static_cast<std::uint8_t>(TerrainClass::kGround);
    std::vector<Eigen::Vector3d> target_ground, source_ground;
    for (std::size_t k = 0; k < target.size(); ++k) {
      if (target.classes[k] == kGround) target_ground.push_back(target.points[k]);
    }
    for (std::size_t k = 0; k < source.size(); ++k) {
      if (source.classes[k] == kGround) source_ground.push_back(source.points[k]);
    }
    if (target_ground.empty() || source_ground.empty()) return;
    std::vector<std::uint32_t> ids;
    ground_cells_ = GroundCells(target_ground, params.ground_cell_m, ids);
    ground_planes_ = fit_ground_planes(target_ground, ids, ground_cells_.size());
    const GroundCells source_cells(source_ground, params.ground_cell_m, ids);
    // Sums relative to each cell's first point (well conditioned far from zero).
    std::vector<Eigen::Vector3d> first(source_cells.size()), sums(source_cells.size(), Eigen::Vector3d::Zero());
    std::vector<double> counts(source_cells.size(), 0.0);
    for (std::size_t k = 0; k < source_ground.size(); ++k) {
      if (counts[ids[k]] == 0.0) first[ids[k]] = source_ground[k];
      sums[ids[k]] += source_ground[k] - first[ids[k]];
      counts[ids[k]] += 1.0;
    }
    for (std::size_t c = 0; c < sums.size(); ++c) {
      const Eigen::Vector3d mean = first[c] + sums[c] / counts[c];
      ground_x_.push_back(mean.x()), ground_y_.push_back(mean.y()), ground_z_.push_back(mean.z());
    }
    ground_weight_ = params.ground_weight;
  }

  /// The points of the coarse passes: every stride-th active point in the source's order (their
  /// slots, by class).
  void select_coarse(std::size_t stride) {
    coarse_.clear();
    for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
      coarse_begin_[c] = coarse_.size();
      for (std::size_t slot = class_begin_[c]; slot < class_begin_[c + 1]; ++slot) {
        if (ordinal_[slot] % stride == 0) coarse_.push_back(static_cast<std::uint32_t>(slot));
      }
    }
    coarse_begin_[kNumTerrainClasses] = coarse_.size();
    coarse_stride_ = stride;
  }

  /// Source point `slot` moved, in the operations of check_avx2.
  Eigen::Vector3d move(const Motion& m, std::size_t slot) const {
    const double x = x_[slot], y = y_[slot], z = z_[slot];
    return {m.r[0] * x + m.r[1] * y + m.r[2] * z + m.t[0], m.r[3] * x + m.r[4] * y + m.r[5] * z + m.t[1],
            m.r[6] * x + m.r[7] * y + m.r[8] * z + m.t[2]};
  }

  /// One source point: its correspondence from its certificate, or the slot deferred to a search.
  /// The last search from `anchor` found the candidates (its two nearest target points) and
  /// nothing else nearer than `clearance`. The moved query is `shift` from the anchor, so by the
  /// triangle inequality the nearer candidate is still the nearest point while its distance is at
  /// most clearance - shift; likewise nothing lies within the limit while the limit is below
  /// clearance - shift (no candidate). Otherwise the point is searched again.
  void check_one(std::size_t s, const Motion& motion, double max_distance, ClassMoments& m, std::size_t& num_deferred) {
    const Eigen::Vector3d moved = move(motion, s);
    const double ax = moved.x() - anchor_x_[s], ay = moved.y() - anchor_y_[s], az = moved.z() - anchor_z_[s];
    const double margin = clearance_[s] - std::sqrt(ax * ax + ay * ay + az * az) - kCertificateSlack;
    const Eigen::Vector3d first(first_x_[s], first_y_[s], first_z_[s]);
    const Eigen::Vector3d second(second_x_[s], second_y_[s], second_z_[s]);
    const auto squared_to = [&](const Eigen::Vector3d& q) {
      const double dx = moved.x() - q.x(), dy = moved.y() - q.y(), dz = moved.z() - q.z();
      return dx * dx + dy * dy + dz * dz;
    };
    const double d0 = squared_to(first), d1 = squared_to(second);
    const bool nearer_second = second_[s] >= 0 && d1 < d0;
    const double squared = nearer_second ? d1 : d0;
    const bool holds = first_[s] >= 0 ? margin >= 0.0 && squared <= margin * margin : margin > max_distance;
    if (!holds) {
      deferred_[num_deferred++] = static_cast<std::uint32_t>(s);
      return;
    }
    if (first_[s] >= 0 && squared <= max_distance * max_distance) {
      const Eigen::Vector3d o(motion.o[0], motion.o[1], motion.o[2]);
      m.add(moved - o, (nearer_second ? second : first) - o, squared);
    }
  }

#if defined(TERRACUBE_HAVE_AVX2_ICP)
  /// check_one four points at a time, from `begin` while four remain before `end`; returns the
  /// first slot not checked. The same IEEE operations lane by lane; only the order in which the
  /// moments are summed differs (four running sums, added up at the end).
  __attribute__((target("avx2"))) std::size_t check_avx2(std::size_t begin, std::size_t end, const Motion& motion,
                                                         double max_distance, ClassMoments& m,
                                                         std::size_t& num_deferred) {
    __m256d r[9], t[3], o[3];
    for (int i = 0; i < 9; ++i) r[i] = _mm256_set1_pd(motion.r[i]);
    for (int i = 0; i < 3; ++i) t[i] = _mm256_set1_pd(motion.t[i]), o[i] = _mm256_set1_pd(motion.o[i]);
    const __m256d zero = _mm256_setzero_pd(), slack = _mm256_set1_pd(kCertificateSlack);
    const __m256d limit = _mm256_set1_pd(max_distance), limit_squared = _mm256_set1_pd(max_distance * max_distance);
    const __m256i none = _mm256_set1_epi64x(-1);
    __m256d sum_squared = zero, sum_p[3] = {zero, zero, zero}, sum_q[3] = {zero, zero, zero};
    __m256d sum_pxq[3] = {zero, zero, zero}, sum_pp[6] = {zero, zero, zero, zero, zero, zero};
    std::size_t count = 0;
    std::size_t s = begin;
    for (; s + 4 <= end; s += 4) {
      const __m256d x = _mm256_loadu_pd(&x_[s]), y = _mm256_loadu_pd(&y_[s]), z = _mm256_loadu_pd(&z_[s]);
      __m256d moved[3];
      for (int i = 0; i < 3; ++i) {
        moved[i] =
            _mm256_add_pd(_mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(r[3 * i], x), _mm256_mul_pd(r[3 * i + 1], y)),
                                        _mm256_mul_pd(r[3 * i + 2], z)),
                          t[i]);
      }
      const __m256d shift = _mm256_sqrt_pd(squared_norm4(_mm256_sub_pd(moved[0], _mm256_loadu_pd(&anchor_x_[s])),
                                                         _mm256_sub_pd(moved[1], _mm256_loadu_pd(&anchor_y_[s])),
                                                         _mm256_sub_pd(moved[2], _mm256_loadu_pd(&anchor_z_[s]))));
      const __m256d margin = _mm256_sub_pd(_mm256_sub_pd(_mm256_loadu_pd(&clearance_[s]), shift), slack);
      const __m256d first[3] = {_mm256_loadu_pd(&first_x_[s]), _mm256_loadu_pd(&first_y_[s]),
                                _mm256_loadu_pd(&first_z_[s])};
      const __m256d second[3] = {_mm256_loadu_pd(&second_x_[s]), _mm256_loadu_pd(&second_y_[s]),
                                 _mm256_loadu_pd(&second_z_[s])};
      const __m256d d0 = squared_norm4(_mm256_sub_pd(moved[0], first[0]), _mm256_sub_pd(moved[1], first[1]),
                                       _mm256_sub_pd(moved[2], first[2]));
      const __m256d d1 = squared_norm4(_mm256_sub_pd(moved[0], second[0]), _mm256_sub_pd(moved[1], second[1]),
                                       _mm256_sub_pd(moved[2], second[2]));
      const __m256d has_first = _mm256_castsi256_pd(
          _mm256_cmpgt_epi64(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(&first_[s])), none));
      const __m256d has_second = _mm256_castsi256_pd(
          _mm256_cmpgt_epi64(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(&second_[s])), none));
      const __m256d nearer_second = _mm256_and_pd(has_second, _mm256_cmp_pd(d1, d0, _CMP_LT_OQ));
      const __m256d squared = _mm256_blendv_pd(d0, d1, nearer_second);
      const __m256d holds_with = _mm256_and_pd(_mm256_cmp_pd(margin, zero, _CMP_GE_OQ),
                                               _mm256_cmp_pd(squared, _mm256_mul_pd(margin, margin), _CMP_LE_OQ));
      const __m256d holds = _mm256_blendv_pd(_mm256_cmp_pd(margin, limit, _CMP_GT_OQ), holds_with, has_first);
      const int search = ~_mm256_movemask_pd(holds) & 0xF;
      for (int lane = 0; lane < 4; ++lane) {  // branch-free append of the lanes to search
        deferred_[num_deferred] = static_cast<std::uint32_t>(s + static_cast<std::size_t>(lane));
        num_deferred += static_cast<std::size_t>((search >> lane) & 1);
      }
      const __m256d take =
          _mm256_and_pd(_mm256_and_pd(holds, has_first), _mm256_cmp_pd(squared, limit_squared, _CMP_LE_OQ));
      count += kLaneCount[_mm256_movemask_pd(take)];
      __m256d p[3], q[3];
      for (int i = 0; i < 3; ++i) {
        p[i] = _mm256_and_pd(_mm256_sub_pd(moved[i], o[i]), take);
        q[i] = _mm256_and_pd(_mm256_sub_pd(_mm256_blendv_pd(first[i], second[i], nearer_second), o[i]), take);
        sum_p[i] = _mm256_add_pd(sum_p[i], p[i]);
        sum_q[i] = _mm256_add_pd(sum_q[i], q[i]);
      }
      sum_squared = _mm256_add_pd(sum_squared, _mm256_and_pd(squared, take));
      sum_pp[0] = _mm256_add_pd(sum_pp[0], _mm256_mul_pd(p[0], p[0]));
      sum_pp[1] = _mm256_add_pd(sum_pp[1], _mm256_mul_pd(p[0], p[1]));
      sum_pp[2] = _mm256_add_pd(sum_pp[2], _mm256_mul_pd(p[0], p[2]));
      sum_pp[3] = _mm256_add_pd(sum_pp[3], _mm256_mul_pd(p[1], p[1]));
      sum_pp[4] = _mm256_add_pd(sum_pp[4], _mm256_mul_pd(p[1], p[2]));
      sum_pp[5] = _mm256_add_pd(sum_pp[5], _mm256_mul_pd(p[2], p[2]));
      sum_pxq[0] = _mm256_add_pd(sum_pxq[0], _mm256_sub_pd(_mm256_mul_pd(p[1], q[2]), _mm256_mul_pd(p[2], q[1])));
      sum_pxq[1] = _mm256_add_pd(sum_pxq[1], _mm256_sub_pd(_mm256_mul_pd(p[2], q[0]), _mm256_mul_pd(p[0], q[2])));
      sum_pxq[2] = _mm256_add_pd(sum_pxq[2], _mm256_sub_pd(_mm256_mul_pd(p[0], q[1]), _mm256_mul_pd(p[1], q[0])));
    }
    m.count += count;
    m.squared += lane_total(sum_squared);
    for (int i = 0; i < 3; ++i) {
      m.p[i] += lane_total(sum_p[i]), m.q[i] += lane_total(sum_q[i]), m.pxq[i] += lane_total(sum_pxq[i]);
    }
    for (int i = 0; i < 6; ++i) m.pp[i] += lane_total(sum_pp[i]);
    return s;
  }
#endif

  /// A fresh search from `moved` within the limit; records the certificate of `slot` and returns
  /// the squared distance to its nearest candidate in `squared`.
  void search(std::uint8_t grid_index, const Eigen::Vector3d& moved, double max_squared, std::size_t slot,
              double& squared) {
    const NearestNeighborGrid& grid = grids_[grid_index];
    // The two nearest within a reach of at most certificate_reach_ (a wider search costs more and
    // a wider certificate is rarely needed); nothing there: the plain nearest within
    // kEmptyReach times the limit. A partner found so (beyond the reach, within the limit) has a
    // certificate that holds for no motion (clearance = its own distance).
    std::array<std::ptrdiff_t, 2> index = {-1, -1};
    std::array<double, 2> distances{};
    const double reach_squared = std::min(max_squared, certificate_reach_ * certificate_reach_);
    double others = reach_squared;
    grid.nearest_two(moved, reach_squared, index, distances, others);
    if (index[0] < 0) {
      // Nothing within the reach: the nearest within kEmptyReach times the limit. Beyond the
      // limit it is no partner, but its distance still certifies "nothing within the limit"
      // for a motion of up to its distance minus the limit (without it a point with no partner
      // would search again on every pass once the limit has shrunk to the reach).
      const double wide_squared = max_squared * (kEmptyReach * kEmptyReach);
      double nearest_squared = wide_squared;
      const std::ptrdiff_t nearest = grid.nearest(moved, wide_squared, nearest_squared);
      if (nearest >= 0 && nearest_squared <= max_squared) {
        index[0] = nearest;
        distances[0] = nearest_squared;
      }
      others = nearest_squared;
    }
    anchor_x_[slot] = moved.x(), anchor_y_[slot] = moved.y(), anchor_z_[slot] = moved.z();
    clearance_[slot] = std::sqrt(others);
    first_[slot] = index[0];
    second_[slot] = index[1];
    if (index[0] >= 0) {
      const Eigen::Vector3d& q = grid.point(static_cast<std::size_t>(index[0]));
      first_x_[slot] = q.x(), first_y_[slot] = q.y(), first_z_[slot] = q.z();
    }
    if (index[1] >= 0) {
      const Eigen::Vector3d& q = grid.point(static_cast<std::size_t>(index[1]));
      second_x_[slot] = q.x(), second_y_[slot] = q.y(), second_z_[slot] = q.z();
    }
    squared = distances[0];
  }

  std::array<NearestNeighborGrid, kNumTerrainClasses> grids_;
  // The active source points (those that can take part), grouped by class: class c's are
  // [class_begin_[c], class_begin_[c + 1]), with its weight (eq. 4; 0: none take part) and grid.
  std::array<std::size_t, kNumTerrainClasses + 1> class_begin_{};
  std::array<double, kNumTerrainClasses> class_weight_{};
  std::array<std::uint8_t, kNumTerrainClasses> class_grid_{};
  std::vector<double> x_, y_, z_;
  std::vector<std::uint32_t> ordinal_;  // of each slot among the active points in the source's order
  std::size_t coarse_stride_ = 0;       // of coarse_ (0: not selected yet)
  std::vector<std::uint32_t> coarse_;   // see select_coarse
  std::array<std::size_t, kNumTerrainClasses + 1> coarse_begin_{};
  Eigen::Vector3d reference_ = Eigen::Vector3d::Zero();
  double total_weight_ = 0.0;       // of the active source points
  double certificate_reach_ = 0.0;  // widest search for a certificate [m]
  // Per active source point, what its last search proved (see check_one): the query (anchor),
  // its two nearest target points (first, second; index -1: none) and a bound below which no
  // other target point lies (clearance; -1 before any search).
  std::vector<double> anchor_x_, anchor_y_, anchor_z_, first_x_, first_y_, first_z_, second_x_, second_y_, second_z_;
  std::vector<double> clearance_;
  std::vector<std::ptrdiff_t> first_, second_;
  std::vector<std::uint32_t> deferred_;  // the slots of a class to search again in a pass
  // Ground as planes (empty unless RegistrationParams::ground_weight > 0 and both sets have ground).
  GroundCells ground_cells_;                            // the target's ground cells
  std::vector<GroundPlane> ground_planes_;              // one per target ground cell
  std::vector<double> ground_x_, ground_y_, ground_z_;  // the source's ground samples
  double ground_weight_ = 0.0;
};

/// Rodrigues: the exact rotation exp([omega]x).
Eigen::Matrix3d rotation_of(const Eigen::Vector3d& omega) {
  const double angle = omega.norm();
  if (angle < 1e-12) return Eigen::Matrix3d::Identity() + skew(omega);
  return Eigen::AngleAxisd(angle, omega / angle).toRotationMatrix();
}

/// Re-orthonormalises a rotation that has accumulated rounding (nearest rotation via SVD-free
/// quaternion normalisation).
Eigen::Matrix3d orthonormalised(const Eigen::Matrix3d& rotation) {
  return Eigen::Quaterniond(rotation).normalized().toRotationMatrix();
}

/// The rigid motion p -> R (p - c) + c + f t with R = exp(f [omega]x), for x = (omega, t).
Eigen::Matrix4d update_about(const Eigen::Vector3d& c, const Vector6d& x, double f) {
  const Eigen::Matrix3d rotation = rotation_of(f * x.head<3>());
  Eigen::Matrix4d update = Eigen::Matrix4d::Identity();
  update.topLeftCorner<3, 3>() = rotation;
  update.topRightCorner<3, 1>() = c + f * x.tail<3>() - rotation * c;
  return update;
}

constexpr double kCosExtrapolation = 0.98480775301220802;  // cos(10 degrees)
constexpr double kMaxExtrapolation = 10.0;
// Coarse iterations only when the subsample keeps at least this many source points.
constexpr std::size_t kMinCoarsePoints = 500;

void fill(RegistrationResult& result, const Pass& pass, double distance) {
  result.num_correspondences = pass.count;
  result.correspondences_per_class = pass.per_class;
  result.correspondence_distance_m = distance;
  result.rmse_m = pass.count > 0 ? std::sqrt(pass.weighted_squared_error / pass.weight_sum)
                                 : std::numeric_limits<double>::quiet_NaN();
  result.normal_matrix = pass.normal;
  if (pass.count > 0) {
    Eigen::SelfAdjointEigenSolver<Matrix6d> solver(pass.normal, Eigen::EigenvaluesOnly);
    result.eigenvalues = solver.eigenvalues();
  } else {
    result.eigenvalues.setZero();
  }
}

}  // namespace

const char* to_string(StopReason reason) {
  switch (reason) {
    case StopReason::kConverged:
      return "converged";
    case StopReason::kErrorBelowThreshold:
      return "error_below_threshold";
    case StopReason::kMaxIterations:
      return "max_iterations";
    case StopReason::kTooFewCorrespondences:
      return "too_few_correspondences";
    case StopReason::kNoCommonClass:
      return "no_common_class";
    case StopReason::kDegenerate:
      return "degenerate";
  }
  return "unknown";
}

namespace {

/// The class code of a "class" value, branch-free: NaN or out of range is unknown (0). On the
/// bits: the non-negative floats below 6 are exactly the bit patterns below 6.0F's (negative
/// values, -0, Inf and NaN are above it as unsigned integers).
static_assert(kNumTerrainClasses == 6, "0x40C00000 is 6.0F");
constexpr std::uint32_t kSixBits = 0x40C00000U;

inline std::uint32_t class_code(const float* value) {
  std::uint32_t bits;
  std::memcpy(&bits, value, sizeof bits);
  bits &= 0U - static_cast<std::uint32_t>(bits < kSixBits);  // out of range: +0, unknown
  float c;
  std::memcpy(&c, &bits, sizeof c);
  return static_cast<std::uint32_t>(static_cast<std::int32_t>(c));  // 0 <= c < 6
}

/// Of `length` (at most 64) cells from `z` and `classes` (null: all unknown), bit k of `finite`:
/// z[k] is finite; bit k of the result: also its class is in `keep` (bit c for class c).
std::uint64_t take_bits_scalar(const float* z, const float* classes, std::size_t length, std::uint32_t keep,
                               std::uint64_t& finite) {
  constexpr float kLargest = std::numeric_limits<float>::max();
  std::uint64_t finite_bits = 0, bits = 0;
  for (std::size_t k = 0; k < length; ++k) {
    const std::uint64_t is_finite = std::fabs(z[k]) <= kLargest ? 1 : 0;  // 0 for NaN and Inf
    const std::uint32_t code = classes != nullptr ? class_code(classes + k) : 0;
    finite_bits |= is_finite << k;
    bits |= (is_finite & ((keep >> code) & 1U)) << k;
  }
  finite = finite_bits;
  return bits;
}

#if defined(TERRACUBE_HAVE_AVX2_ICP)
/// take_bits_scalar eight cells at a time.
__attribute__((target("avx2"))) std::uint64_t take_bits_avx2(const float* z, const float* classes, std::size_t length,
                                                             std::uint32_t keep, std::uint64_t& finite) {
  const __m256 magnitude = _mm256_castsi256_ps(_mm256_set1_epi32(0x7FFFFFFF));
  const __m256 largest = _mm256_set1_ps(std::numeric_limits<float>::max());
  const __m256i six = _mm256_set1_epi32(static_cast<int>(kSixBits)), minus_one = _mm256_set1_epi32(-1);
  const __m256i keep_vector = _mm256_set1_epi32(static_cast<int>(keep)), one = _mm256_set1_epi32(1);
  const int keep_unknown = (keep & 1U) != 0 ? 0xFF : 0;
  std::uint64_t finite_bits = 0, bits = 0;
  std::size_t k = 0;
  for (; k + 8 <= length; k += 8) {
    const __m256 height = _mm256_and_ps(_mm256_loadu_ps(z + k), magnitude);
    const auto is_finite = static_cast<std::uint64_t>(_mm256_movemask_ps(_mm256_cmp_ps(height, largest, _CMP_LE_OQ)));
    std::uint64_t kept = static_cast<std::uint64_t>(keep_unknown);
    if (classes != nullptr) {
      // As signed integers the class values' bits are in [0, 6.0F's) exactly when in range.
      const __m256i value = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(classes + k));
      const __m256i in_range = _mm256_and_si256(_mm256_cmpgt_epi32(six, value), _mm256_cmpgt_epi32(value, minus_one));
      const __m256i code = _mm256_cvttps_epi32(_mm256_castsi256_ps(_mm256_and_si256(value, in_range)));
      const __m256i take = _mm256_and_si256(_mm256_srlv_epi32(keep_vector, code), one);
      kept = static_cast<std::uint64_t>(_mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(take, one))));
    }
    finite_bits |= is_finite << k;
    bits |= (is_finite & kept) << k;
  }
  finite = finite_bits;
  if (k == length) return bits;
  std::uint64_t tail_finite = 0;  // k < 64 from here
  const std::uint64_t tail =
      take_bits_scalar(z + k, classes != nullptr ? classes + k : nullptr, length - k, keep, tail_finite);
  finite |= tail_finite << k;
  return bits | (tail << k);
}
#endif

std::uint64_t take_bits(const float* z, const float* classes, std::size_t length, std::uint32_t keep,
                        std::uint64_t& finite) {
#if defined(TERRACUBE_HAVE_AVX2_ICP)
  if (detail::has_avx2()) return take_bits_avx2(z, classes, length, keep, finite);
#endif
  return take_bits_scalar(z, classes, length, keep, finite);
}

/// The cells of points_of_map, only those of classes with a positive weight when `weights` is
/// given; `cells_with_data` receives the number of all cells with data.
ClassifiedPoints cells_of_map(const ElevationMap& map, const ClassWeights* weights, std::size_t& cells_with_data) {
  const Layer& highest = map.get("max");
  const float* classes = map.exists("class") ? map.get("class").data() : nullptr;
  const MapGeometry& geometry = map.geometry();
  const auto rows = static_cast<std::size_t>(highest.rows()), cols = static_cast<std::size_t>(highest.cols());
  const float* z = highest.data();  // row-major: cell (i, j) at i * cols + j
  std::uint32_t keep = 0;           // bit c: class c takes part
  for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
    if (weights == nullptr || (*weights)[c] > 0.0) keep |= std::uint32_t{1} << c;
  }
  // Pass 1: a bit per cell that takes part (finite "max", a kept class), 64 cells of a row per
  // word, and the exact number of points, so that they are allocated once.
  const std::size_t words_per_row = (cols + 63) / 64;
  std::vector<std::uint64_t> takes_part(rows * words_per_row);
  std::size_t total = 0, with_data = 0;
  for (std::size_t i = 0; i < rows; ++i) {
    for (std::size_t w = 0; w < words_per_row; ++w) {
      const std::size_t first = i * cols + w * 64;
      std::uint64_t finite = 0;
      const std::uint64_t bits = take_bits(z + first, classes != nullptr ? classes + first : nullptr,
                                           std::min<std::size_t>(64, cols - w * 64), keep, finite);
      takes_part[i * words_per_row + w] = bits;
      with_data += static_cast<std::size_t>(__builtin_popcountll(finite));
      total += static_cast<std::size_t>(__builtin_popcountll(bits));
    }
  }
  cells_with_data = with_data;
  // Pass 2: the cell centres of MapGeometry::position_of, one coordinate at a time.
  std::vector<double> ys(cols);
  for (std::size_t j = 0; j < cols; ++j) {
    ys[j] = geometry.origin_m.y() + (static_cast<double>(j) + 0.5) * geometry.resolution_m;
  }
  ClassifiedPoints set;
  set.points.resize(total);
  set.classes.resize(total);
  std::size_t next = 0;
  for (std::size_t i = 0; i < rows; ++i) {
    const double x = geometry.origin_m.x() + (static_cast<double>(i) + 0.5) * geometry.resolution_m;
    for (std::size_t w = 0; w < words_per_row; ++w) {
      for (std::uint64_t bits = takes_part[i * words_per_row + w]; bits != 0; bits &= bits - 1) {
        const std::size_t j = w * 64 + static_cast<std::size_t>(__builtin_ctzll(bits));
        const std::size_t cell = i * cols + j;
        set.points[next] = Eigen::Vector3d(x, ys[j], static_cast<double>(z[cell]));
        set.classes[next] = static_cast<std::uint8_t>(classes != nullptr ? class_code(classes + cell) : 0);
        ++next;
      }
    }
  }
  return set;
}

/// register_points after the checks; `*_empty`: whether the source (target) has no point at all.
RegistrationResult register_checked(const ClassifiedPoints& source, const ClassifiedPoints& target,
                                    const Eigen::Matrix4d& initial, const RegistrationParams& params, bool source_empty,
                                    bool target_empty);

}  // namespace

ClassifiedPoints points_of_map(const ElevationMap& map) {
  std::size_t cells_with_data = 0;
  return cells_of_map(map, nullptr, cells_with_data);
}

RegistrationResult register_points(const ClassifiedPoints& source, const ClassifiedPoints& target,
                                   const Eigen::Matrix4d& initial, const RegistrationParams& params) {
  check_registration_params(params);
  detail::check_rigid_transform(initial, "initial transform");
  check_points(source, "source");
  check_points(target, "target");
  return register_checked(source, target, initial, params, source.size() == 0, target.size() == 0);
}

namespace {

RegistrationResult register_checked(const ClassifiedPoints& source, const ClassifiedPoints& target,
                                    const Eigen::Matrix4d& initial, const RegistrationParams& params, bool source_empty,
                                    bool target_empty) {
  RegistrationResult result;
  result.transform = initial;
  Registration registration(source, target, params);
  if (!registration.has_common_class()) {
    result.reason = source_empty || target_empty ? StopReason::kTooFewCorrespondences : StopReason::kNoCommonClass;
    result.rmse_m = std::numeric_limits<double>::quiet_NaN();
    return result;
  }

  // The distance limit of iteration k (from 0).
  const auto limit_of = [&](int iteration) {
    return std::max(params.min_correspondence_distance_m,
                    params.max_correspondence_distance_m * std::pow(params.correspondence_distance_decay, iteration));
  };
  Eigen::Matrix4d transform = initial;
  double distance = limit_of(0);
  // Coarse to fine: the first iterations use every coarse_subsample-th source point, until an
  // update moves the points less than coarse_until_motion_m (or registration would stop).
  auto stride = static_cast<std::size_t>(params.coarse_subsample);
  if (registration.active_size() / stride < kMinCoarsePoints) stride = 1;
  Pass pass = registration.pass(transform, distance, stride);
  int passes = 1;
  int extrapolations = 0;
  // Extrapolation state: the last update as a 6-vector, the pivot and the length scale.
  Vector6d previous_step = Vector6d::Zero();
  bool has_previous_step = false;
  Eigen::Vector3d pivot = Eigen::Vector3d::Zero();
  double radius = 1.0;
  const auto finish = [&](StopReason reason) {
    if (params.structure_radius_m > 0.0 && pass.count > 0 && result.num_correspondences > 0) {
      result.constraint_matrix = registration.constraints(result.transform, result.correspondence_distance_m,
                                                          params.structure_radius_m, pass.centroid);
      Eigen::SelfAdjointEigenSolver<Matrix6d> solver(result.constraint_matrix);
      result.constraint_eigenvalues = solver.eigenvalues();
      result.constraint_eigenvectors = solver.eigenvectors();
    }
    result.reason = reason;
    result.converged = reason == StopReason::kConverged || reason == StopReason::kErrorBelowThreshold;
    result.passes = passes;
    result.extrapolations = extrapolations;
    return result;
  };
  for (int iteration = 0;; ++iteration) {
    // `pass` holds the correspondences at `transform` within `distance`.
    result.transform = transform;
    result.iterations = iteration;
    fill(result, pass, distance);
    StopReason stop = StopReason::kConverged;  // kConverged: go on
    if (pass.count < params.min_correspondences) {
      stop = StopReason::kTooFewCorrespondences;
    } else if (result.rmse_m < params.error_threshold_m) {
      stop = StopReason::kErrorBelowThreshold;
    } else if (result.eigenvalues(0) <= params.degeneracy_threshold * result.eigenvalues(5)) {
      stop = StopReason::kDegenerate;
    } else if (iteration == params.max_iterations) {
      stop = StopReason::kMaxIterations;
    }
    if (stop != StopReason::kConverged) {
      if (stride == 1) return finish(stop);
      // Decide on all the points: redo this pass in full.
      stride = 1;
      pass = registration.pass(transform, distance);
      ++passes;
      --iteration;
      continue;
    }
    if (iteration == 0) {
      pivot = pass.centroid;
      // rms distance of the class correspondences from their centroid (Pass::class_radius)
      radius = pass.class_radius;
    }
    // Eq. (A6): H x = g, solved by LDLT.
    const Vector6d x = pass.normal.ldlt().solve(pass.gradient);
    if (!x.allFinite()) return finish(StopReason::kDegenerate);
    // The update about the centroid c: p -> R (p - c) + c + t, composed exactly (no small-angle matrix).
    Eigen::Matrix4d plain = update_about(pass.centroid, x, 1.0) * transform;
    plain.topLeftCorner<3, 3>() = orthonormalised(plain.topLeftCorner<3, 3>());
    const double next_distance = limit_of(iteration + 1);
    bool evaluated = false;  // `pass` already holds the correspondences at the new transform
    const bool coarse = stride > 1;
    const bool leave_coarse = coarse && x.tail<3>().norm() + x.head<3>().norm() * radius < params.coarse_until_motion_m;
    if (leave_coarse) {
      stride = 1;
      has_previous_step = false;  // the objective changes: start a new pair of updates
    }
    // Extrapolation only on the fine iterations: on the subsample it was seen to converge early.
    if (params.extrapolate && !coarse) {
      // Besl and McKay's accelerated ICP (1992, sec. IV-C), in its geometric-series form: when two
      // successive updates point the same way (within 10 degrees) and shrink by a ratio rho, the
      // remaining steps sum to about rho / (1 - rho) times the last one; try them at once (at most
      // kMaxExtrapolation times the step), then start a new pair. Updates are compared as
      // (rotation * rms radius, motion of the first centroid) so that both parts weigh alike.
      const Eigen::Vector3d pivot_motion =
          rotation_of(x.head<3>()) * (pivot - pass.centroid) + pass.centroid + x.tail<3>() - pivot;
      Vector6d step;
      step << x.head<3>() * radius, pivot_motion;
      if (has_previous_step) {
        const double norm = step.norm(), previous_norm = previous_step.norm();
        const double rho = previous_norm > 0.0 ? norm / previous_norm : 1.0;
        if (rho < 1.0 && step.dot(previous_step) > kCosExtrapolation * norm * previous_norm) {
          // Guard (a departure from Besl and McKay): keep the jump only if the eq. (4) error it
          // reaches, truncated at the next limit, is no larger than the plain step's.
          const double factor = std::min(rho / (1.0 - rho), kMaxExtrapolation);
          Eigen::Matrix4d jumped = update_about(pass.centroid, x, factor) * plain;
          jumped.topLeftCorner<3, 3>() = orthonormalised(jumped.topLeftCorner<3, 3>());
          // The plain step first: the search certificates are then anchored at the jump, which
          // is kept more often than not.
          Pass at_plain = registration.pass(plain, next_distance);
          Pass at_jump = registration.pass(jumped, next_distance);
          passes += 2;
          if (registration.truncated_error(at_jump, next_distance) <=
              registration.truncated_error(at_plain, next_distance)) {
            plain = jumped;
            pass = std::move(at_jump);
            ++extrapolations;
          } else {
            pass = std::move(at_plain);
          }
          evaluated = true;
          has_previous_step = false;
        } else {
          previous_step = step;
        }
      } else {
        previous_step = step;
        has_previous_step = true;
      }
    }
    transform = plain;
    distance = next_distance;
    if (!evaluated) {
      pass = registration.pass(transform, distance, stride);
      ++passes;
    }
    if (!coarse && x.head<3>().norm() < params.rotation_tolerance_rad &&
        x.tail<3>().norm() < params.translation_tolerance_m) {
      // Converged: report the statistics at the final estimate.
      result.transform = transform;
      result.iterations = iteration + 1;
      if (pass.count > 0) fill(result, pass, distance);
      return finish(StopReason::kConverged);
    }
  }
}

}  // namespace

RegistrationResult register_maps(const ElevationMap& source, const ElevationMap& target, const Eigen::Matrix4d& initial,
                                 const RegistrationParams& params) {
  if (params.use_classes && (!source.exists("class") || !target.exists("class"))) {
    throw std::invalid_argument(
        "class-weighted registration needs the \"class\" layer in both maps: run classify_terrain first");
  }
  check_registration_params(params);
  detail::check_rigid_transform(initial, "initial transform");
  // Only the cells that can take part (with classes, those of classes with a positive weight):
  // Registration would drop the others anyway, and on a map mostly of ground they are most of
  // its cells. The map's points are finite with valid classes by construction.
  ClassWeights keep = params.class_weights;  // > 0: the class's cells are needed
  if (params.ground_weight > 0.0) keep[static_cast<std::size_t>(TerrainClass::kGround)] = 1.0;
  const ClassWeights* weights = params.use_classes ? &keep : nullptr;
  std::size_t source_cells = 0, target_cells = 0;
  const ClassifiedPoints source_points = cells_of_map(source, weights, source_cells);
  const ClassifiedPoints target_points = cells_of_map(target, weights, target_cells);
  return register_checked(source_points, target_points, initial, params, source_cells == 0, target_cells == 0);
}

RegistrationResult register_maps_all_cells(const ElevationMap& source, const ElevationMap& target,
                                           const Eigen::Matrix4d& initial, RegistrationParams params) {
  params.use_classes = false;
  return register_maps(source, target, initial, params);
}

// --- k-d tree ---------------------------------------------------------------------------------

NearestNeighbor3d::NearestNeighbor3d(std::vector<Eigen::Vector3d> points) {
  if (points.size() >= std::numeric_limits<std::uint32_t>::max()) {
    throw std::invalid_argument("too many points for the nearest-neighbour index");
  }
  points_ = std::move(points);
  original_.resize(points_.size());
  std::iota(original_.begin(), original_.end(), std::uint32_t{0});
  if (points_.empty()) return;
  nodes_.reserve(2 * (points_.size() / kLeafSize + 1));
  build(0, static_cast<std::uint32_t>(points_.size()));
  // Store the points in leaf order so that a leaf scan reads contiguous memory.
  std::vector<Eigen::Vector3d> ordered(points_.size());
  position_.resize(points_.size());
  for (std::size_t k = 0; k < points_.size(); ++k) {
    ordered[k] = points_[original_[k]];
    position_[original_[k]] = static_cast<std::uint32_t>(k);
  }
  points_ = std::move(ordered);
}

std::int32_t NearestNeighbor3d::build(std::uint32_t begin, std::uint32_t end) {
  // original_ holds the permutation being partitioned; points_ is still in input order.
  const auto index = static_cast<std::int32_t>(nodes_.size());
  nodes_.emplace_back();
  if (end - begin <= kLeafSize) {
    nodes_[static_cast<std::size_t>(index)].begin = begin;
    nodes_[static_cast<std::size_t>(index)].end = end;
    return index;
  }
  Eigen::Vector3d low = points_[original_[begin]], high = low;
  for (std::uint32_t k = begin + 1; k < end; ++k) {
    low = low.cwiseMin(points_[original_[k]]);
    high = high.cwiseMax(points_[original_[k]]);
  }
  int axis = 0;
  (high - low).maxCoeff(&axis);
  const std::uint32_t middle = begin + (end - begin) / 2;
  std::nth_element(original_.begin() + begin, original_.begin() + middle, original_.begin() + end,
                   [&](std::uint32_t a, std::uint32_t b) { return points_[a][axis] < points_[b][axis]; });
  const double split = points_[original_[middle]][axis];
  const std::int32_t left = build(begin, middle);
  const std::int32_t right = build(middle, end);
  Node& node = nodes_[static_cast<std::size_t>(index)];
  node.axis = static_cast<std::int8_t>(axis);
  node.split = split;
  node.left = left;
  node.right = right;
  return index;
}

std::ptrdiff_t NearestNeighbor3d::nearest(const Eigen::Vector3d& query, double max_squared_distance,
                                          double& squared_distance) const {
  std::ptrdiff_t best = -1;
  double best_squared = max_squared_distance;
  if (nodes_.empty()) return best;
  // Depth-first with an explicit stack of (node, lower bound on its squared distance).
  struct Entry {
    std::int32_t node;
    double bound;
  };
  Entry stack[64];
  int top = 0;
  stack[top++] = {0, 0.0};
  while (top > 0) {
    const Entry entry = stack[--top];
    if (entry.bound > best_squared) continue;
    // Descend to the leaf on the query's side, pushing each far side that may still hold a
    // nearer point (its bound: the squared distance to the splitting plane).
    const Node* node = &nodes_[static_cast<std::size_t>(entry.node)];
    while (node->axis >= 0) {
      const double offset = query[node->axis] - node->split;
      const double far_bound = std::max(entry.bound, offset * offset);
      if (far_bound <= best_squared) stack[top++] = {offset < 0.0 ? node->right : node->left, far_bound};
      node = &nodes_[static_cast<std::size_t>(offset < 0.0 ? node->left : node->right)];
    }
    for (std::uint32_t k = node->begin; k < node->end; ++k) {
      const double d = (points_[k] - query).squaredNorm();
      if (d <= best_squared) {
        best_squared = d;
        best = static_cast<std::ptrdiff_t>(k);
      }
    }
  }
  if (best >= 0) {
    squared_distance = best_squared;
    return static_cast<std::ptrdiff_t>(original_[static_cast<std::size_t>(best)]);
  }
  return -1;
}

// --- 2D bucket grid -------------------------------------------------------------------------

namespace {
// Slack on the pruning bounds [buckets]: a point whose bucket was computed with rounding on the
// other side of a boundary is still examined, so the search stays exact.
constexpr double kBucketSlack = 1e-6;
}  // namespace

NearestNeighborGrid::NearestNeighborGrid(std::vector<Eigen::Vector3d> points, double bucket_size_m) {
  if (points.size() >= std::numeric_limits<std::uint32_t>::max()) {
    throw std::invalid_argument("too many points for the nearest-neighbour grid");
  }
  if (!(bucket_size_m >= 0.0 && std::isfinite(bucket_size_m))) {
    throw std::invalid_argument("nearest-neighbour grid bucket size must be finite and >= 0 [m]");
  }
  for (std::size_t k = 0; k < points.size(); ++k) {
    if (!points[k].allFinite()) {
      throw std::invalid_argument("nearest-neighbour grid point " + std::to_string(k) + " is NaN or Inf");
    }
  }
  const std::size_t n = points.size();
  if (n == 0) return;
  Eigen::Vector2d low = points[0].head<2>(), high = low;
  for (const Eigen::Vector3d& p : points) {
    low = low.cwiseMin(p.head<2>());
    high = high.cwiseMax(p.head<2>());
  }
  const Eigen::Vector2d extent = high - low;
  if (bucket_size_m == 0.0) {
    // Half the mean spacing over the box (about four buckets per point); a line of points (zero
    // area) gets a quarter of its spacing; a single column one bucket.
    const auto count = static_cast<double>(n);
    bucket_size_m = std::max(0.5 * std::sqrt(extent.x() * extent.y() / count), extent.maxCoeff() / (4.0 * count));
    if (!(bucket_size_m > 0.0)) bucket_size_m = 1.0;
  }
  const double columns = std::floor(extent.x() / bucket_size_m) + 1.0;
  const double rows = std::floor(extent.y() / bucket_size_m) + 1.0;
  if (columns * rows > static_cast<double>(std::numeric_limits<std::int32_t>::max())) {
    throw std::invalid_argument("nearest-neighbour grid bucket size " + std::to_string(bucket_size_m) +
                                " m gives more than 2^31 buckets over the points' extent");
  }
  bucket_size_m_ = bucket_size_m;
  inverse_bucket_size_ = 1.0 / bucket_size_m;
  origin_ = low;
  columns_ = static_cast<std::int64_t>(columns);
  rows_ = static_cast<std::int64_t>(rows);
  // Counting sort of the points by bucket.
  const auto bucket_of = [&](const Eigen::Vector3d& p) {
    const auto column = std::min(columns_ - 1, static_cast<std::int64_t>((p.x() - low.x()) * inverse_bucket_size_));
    const auto row = std::min(rows_ - 1, static_cast<std::int64_t>((p.y() - low.y()) * inverse_bucket_size_));
    return static_cast<std::size_t>(row * columns_ + column);
  };
  start_.assign(static_cast<std::size_t>(columns_ * rows_) + 1, 0);
  std::vector<std::uint32_t> bucket(n);
  for (std::size_t k = 0; k < n; ++k) {
    bucket[k] = static_cast<std::uint32_t>(bucket_of(points[k]));
    ++start_[bucket[k] + 1];
  }
  std::partial_sum(start_.begin(), start_.end(), start_.begin());
  std::vector<std::uint32_t> next(start_.begin(), start_.end() - 1);
  points_.resize(n);
  original_.resize(n);
  position_.resize(n);
  for (std::size_t k = 0; k < n; ++k) {
    const std::uint32_t slot = next[bucket[k]]++;
    points_[slot] = points[k];
    original_[slot] = static_cast<std::uint32_t>(k);
    position_[k] = slot;
  }
}

std::ptrdiff_t NearestNeighborGrid::nearest(const Eigen::Vector3d& query, double max_squared_distance,
                                            double& squared_distance) const {
  std::ptrdiff_t found[1] = {-1};
  double best[1];
  search<1, false>(query, max_squared_distance, found, best);
  if (found[0] < 0) return -1;
  squared_distance = best[0];
  return found[0];
}

std::ptrdiff_t NearestNeighborGrid::nearest_two(const Eigen::Vector3d& query, double max_squared_distance,
                                                std::array<std::ptrdiff_t, 2>& indices,
                                                std::array<double, 2>& squared_distances,
                                                double& others_squared_distance) const {
  std::ptrdiff_t found[2] = {-1, -1};
  double best[3];
  search<2, true>(query, max_squared_distance, found, best);
  indices = {found[0], found[1]};
  squared_distances = {best[0], best[1]};
  others_squared_distance = best[2];
  return found[0];
}

void NearestNeighborGrid::within(const Eigen::Vector3d& query, double radius, std::vector<std::uint32_t>& out) const {
  if (points_.empty() || !(radius >= 0.0)) return;
  // The buckets that can hold a point within the radius (with slack; the distance decides).
  const double reach = radius * inverse_bucket_size_ + kBucketSlack;
  const double u = (query.x() - origin_.x()) * inverse_bucket_size_;
  const double v = (query.y() - origin_.y()) * inverse_bucket_size_;
  const auto clamp_to = [](double value, std::int64_t count) {
    return static_cast<std::int64_t>(std::clamp(std::floor(value), 0.0, static_cast<double>(count - 1)));
  };
  if (u + reach < 0.0 || v + reach < 0.0 || u - reach >= static_cast<double>(columns_) ||
      v - reach >= static_cast<double>(rows_)) {
    return;
  }
  const std::int64_t first_column = clamp_to(u - reach, columns_), last_column = clamp_to(u + reach, columns_);
  const std::int64_t first_row = clamp_to(v - reach, rows_), last_row = clamp_to(v + reach, rows_);
  const double squared = radius * radius;
  for (std::int64_t row = first_row; row <= last_row; ++row) {
    const auto base = static_cast<std::size_t>(row * columns_);
    const std::uint32_t end = start_[base + static_cast<std::size_t>(last_column) + 1];
    for (std::uint32_t k = start_[base + static_cast<std::size_t>(first_column)]; k < end; ++k) {
      if ((points_[k] - query).squaredNorm() <= squared) out.push_back(original_[k]);
    }
  }
}

template <int kKeep, bool kBound>
void NearestNeighborGrid::search(const Eigen::Vector3d& query, double max_squared_distance, std::ptrdiff_t* found_out,
                                 double* best_out) const {
  constexpr int kLast = kBound ? kKeep : kKeep - 1;  // best[kLast] is the pruning distance
  // Kept in locals (registers) while scanning, copied out at the end.
  double best[kLast + 1];
  std::ptrdiff_t found[kKeep];
  for (int k = 0; k <= kLast; ++k) best[k] = max_squared_distance;
  for (int k = 0; k < kKeep; ++k) found[k] = -1;
  const auto copy_out = [&] {
    for (int k = 0; k <= kLast; ++k) best_out[k] = best[k];
    for (int k = 0; k < kKeep; ++k) {
      found_out[k] = found[k] >= 0 ? static_cast<std::ptrdiff_t>(original_[static_cast<std::size_t>(found[k])]) : -1;
    }
  };
  if (points_.empty()) return copy_out();
  // Pruning uses the largest distance kept: every point nearer than it is examined.
  double& prune = best[kLast];
  // The query in bucket units (it may lie outside the grid).
  const double u = (query.x() - origin_.x()) * inverse_bucket_size_;
  const double v = (query.y() - origin_.y()) * inverse_bucket_size_;
  const double bucket_squared = bucket_size_m_ * bucket_size_m_;
  const double last_column = static_cast<double>(columns_ - 1);
  const double qx = query.x(), qy = query.y(), qz = query.z();
  const Eigen::Vector3d* points = points_.data();
  // Scans the buckets of `row` whose x range can hold a point within `prune`, given that every
  // point of the row is at least `gap` buckets away in y. Points of consecutive buckets are
  // contiguous, so the scan is one loop.
  const auto scan_row = [&](std::int64_t row, double gap) {
    const double reach_squared = prune / bucket_squared - gap * gap;
    if (reach_squared < 0.0) return;
    const double reach = std::sqrt(reach_squared) + kBucketSlack;
    const double low = u - reach, high = u + reach;
    if (high < 0.0 || low >= static_cast<double>(columns_)) return;
    // Truncation of a non-negative value is floor.
    const std::size_t first = low <= 0.0 ? 0 : static_cast<std::size_t>(low);
    const std::size_t last =
        high >= last_column ? static_cast<std::size_t>(columns_ - 1) : static_cast<std::size_t>(high);
    const std::size_t base = static_cast<std::size_t>(row * columns_);
    const std::uint32_t end = start_[base + last + 1];
    for (std::uint32_t k = start_[base + first]; k < end; ++k) {
      const Eigen::Vector3d& point = points[k];
      const double dx = point.x() - qx, dy = point.y() - qy, dz = point.z() - qz;
      const double d = dx * dx + dy * dy + dz * dz;
      // Insert into the sorted best[] (the nearest first; a tie puts the new point first), without
      // branches: whether a point is nearer than those kept is data, not a pattern a branch
      // predictor learns, so the choices are masks (-1: take) and min/max. A point beyond
      // best[kLast] changes nothing. Slots go from the last down, each from old values.
      const auto index = static_cast<std::ptrdiff_t>(k);
      for (int slot = kLast; slot > 0; --slot) {
        if (slot < kKeep) {
          const std::ptrdiff_t shift = -static_cast<std::ptrdiff_t>(d <= best[slot - 1]);
          const std::ptrdiff_t take = -static_cast<std::ptrdiff_t>(d <= best[slot]);
          const std::ptrdiff_t kept = (index & take) | (found[slot] & ~take);
          found[slot] = (found[slot - 1] & shift) | (kept & ~shift);
        }
        best[slot] = std::min(std::max(d, best[slot - 1]), best[slot]);
      }
      const std::ptrdiff_t take = -static_cast<std::ptrdiff_t>(d <= best[0]);
      found[0] = (index & take) | (found[0] & ~take);
      best[0] = std::min(d, best[0]);
    }
  };
  // floor(v) clamped to [-1, rows_]: truncation of the non-negative v + 1 is its floor.
  const auto row_of_query = static_cast<std::int64_t>(std::clamp(v, -1.0, static_cast<double>(rows_)) + 1.0) - 1;
  // Upward from the query's row (gap 0 within it), then downward; a row whose gap alone exceeds
  // the pruning distance ends its direction.
  for (std::int64_t row = std::max<std::int64_t>(row_of_query, 0); row < rows_; ++row) {
    const double gap = std::max(0.0, static_cast<double>(row) - v - kBucketSlack);
    if (gap * gap * bucket_squared > prune) break;
    scan_row(row, gap);
  }
  for (std::int64_t row = std::min(row_of_query - 1, rows_ - 1); row >= 0; --row) {
    const double gap = std::max(0.0, v - static_cast<double>(row + 1) - kBucketSlack);
    if (gap * gap * bucket_squared > prune) break;
    scan_row(row, gap);
  }
  copy_out();
}

}  // namespace terracube
