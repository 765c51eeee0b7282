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
#include <utility>

#include "cloud_frame.hpp"
#include "ground_planes.hpp"
#include "map_points.hpp"
#include "registration_checks.hpp"

namespace terracube {

namespace {

// Rounding allowance of the nearest-neighbour certificates [m]: far above the error of the
// distances (about 1e-15 m at map scale), far below any distance that matters.
constexpr double kCertificateSlack = 1e-9;
// A search that finds nothing within the certificate reach looks this many times the distance
// limit far (see Registration::search).
constexpr double kEmptyReach = 1.5;

using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Vector6d = Eigen::Matrix<double, 6, 1>;
using detail::cells_of_map;
using detail::check_points;
using detail::fit_ground_planes;
using detail::GroundCells;
using detail::GroundPlane;

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
    from_target_ = params.pairing == Pairing::kTargetToSource;
    for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {  // each target point's weight, for from_target_
      if (params.use_classes) target_weight_ += class_weight_[c] * static_cast<double>(grids_[c].size());
    }
    if (!params.use_classes && class_begin_[kNumTerrainClasses] > 0)
      target_weight_ = static_cast<double>(grids_[0].size());
    if (params.use_classes && params.ground_weight > 0.0) set_up_ground(source, target, params);
  }

  bool has_common_class() const { return class_begin_[kNumTerrainClasses] > 0; }
  std::size_t active_size() const { return class_begin_[kNumTerrainClasses]; }

  /// The [TC] eq. (4) error of a pass truncated at `max_distance`: sum over the active source points of
  /// w min(d^2, max_distance^2), d the distance to the nearest target point of the class. A proper
  /// objective to compare poses with (unlike the RMSE, it does not fall when pairs drop out).
  double truncated_error(const Pass& pass, double max_distance) const {
    const double all = from_target_ ? target_weight_ : total_weight_;
    return pass.class_squared_error + (all - pass.class_weight_sum) * max_distance * max_distance;
  }

  /// The ground terms of a pass about o (unweighted).
  struct GroundTerms {
    Matrix6d normal = Matrix6d::Zero();
    Vector6d gradient = Vector6d::Zero();
    std::size_t count = 0;
    double error = 0.0;
  };

  /// Ground as planes (RegistrationParams::ground_weight): each source sample with the plane of
  /// the target cell under it, residual along the plane's normal n. About o, v = (a x n, n) with a
  /// the moved sample; about the centroid c of a pass, J = M v with M = [I, -[c]x; 0, I].
  GroundTerms ground_terms(const Motion& motion, const Eigen::Vector3d& o, double max_squared,
                           std::size_t stride) const {
    GroundTerms out;
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
      out.normal.noalias() += v * v.transpose();
      out.gradient -= d * v;
      out.error += d * d;
      ++out.count;
    }
    return out;
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
    const std::array<ClassMoments, kNumTerrainClasses> from_target =
        from_target_ ? moments_from_target(motion, o, max_squared, stride)
                     : std::array<ClassMoments, kNumTerrainClasses>{};
    for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
      if (class_begin_[c] == class_begin_[c + 1]) continue;
      const ClassMoments m = from_target_ ? from_target[c] : moments_from_source(c, motion, max_distance, stride);
      // [TC] eq. (4): the class's weight on each of its correspondences.
      const double w = class_weight_[c];
      result.count += m.count;
      result.per_class[c] += m.count;
      w_sum += w * static_cast<double>(m.count);
      error += w * m.squared;
      for (int i = 0; i < 3; ++i) sp[i] += w * m.p[i], sq[i] += w * m.q[i], spxq[i] += w * m.pxq[i];
      for (int i = 0; i < 6; ++i) spp[i] += w * m.pp[i];
    }
    const GroundTerms ground = ground_terms(motion, o, max_squared, stride);
    const double class_w_sum = w_sum;
    result.class_weight_sum = w_sum;
    result.class_squared_error = error;
    if (ground.count > 0) {
      result.count += ground.count;
      result.per_class[static_cast<std::size_t>(TerrainClass::kGround)] += ground.count;
      w_sum += ground_weight_ * static_cast<double>(ground.count);
      error += ground_weight_ * ground.error;
    }
    result.weight_sum = w_sum;
    result.weighted_squared_error = error;
    if (result.count == 0) return result;
    // [TC] eq. (A6) with per-class weights ([TC] eq. (4)). Unknowns x = (omega, t) about the weighted centroid
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
    if (ground.count > 0) {
      Matrix6d shift = Matrix6d::Identity();
      shift.topRightCorner<3, 3>() = -skew(c);
      result.normal += ground_weight_ * (shift * ground.normal * shift.transpose());
      result.gradient += ground_weight_ * (shift * ground.gradient);
    }
    result.centroid = c + o;
    return result;
  }

  /// Per class, the active source points that have a target point of their class within
  /// `distance` of them moved by `transform`: pass(transform, distance).per_class of the classes,
  /// without the moments and the certificates (the verdict's chance overlaps). Ground cells are
  /// not counted; from the target's side (Pairing::kTargetToSource) it is that pass's count.
  std::array<std::size_t, kNumTerrainClasses> partners_within(const Eigen::Matrix4d& transform, double distance) {
    if (from_target_) return pass(transform, distance).per_class;
    Motion motion{};
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) motion.r[3 * i + j] = transform(i, j);
      motion.t[i] = transform(i, 3);
    }
    const double max_squared = distance * distance;
    std::array<std::size_t, kNumTerrainClasses> count{};
    for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
      const NearestNeighborGrid& grid = grids_[class_grid_[c]];
      for (std::size_t slot = class_begin_[c]; slot < class_begin_[c + 1]; ++slot) {
        count[c] += grid.any_within(move(motion, slot), max_squared) ? 1 : 0;
      }
    }
    return count;
  }

  /// The moments of class c's correspondences when each moved source point looks for its partner
  /// (every stride-th point of the class when stride > 1): from its certificate where that still
  /// holds, else searched again. Relative to motion.o.
  ClassMoments moments_from_source(std::size_t c, const Motion& motion, double max_distance, std::size_t stride) {
    ClassMoments m;
    std::size_t num_deferred = 0;
    if (stride == 1) {
      for (std::size_t slot = class_begin_[c]; slot < class_begin_[c + 1]; ++slot) {
        check_one(slot, motion, max_distance, m, num_deferred);
      }
    } else {
      for (std::size_t k = coarse_begin_[c]; k < coarse_begin_[c + 1]; ++k) {
        check_one(coarse_[k], motion, max_distance, m, num_deferred);
      }
    }
    // The points whose certificate did not hold: searched again.
    const Eigen::Vector3d o(motion.o[0], motion.o[1], motion.o[2]);
    const double max_squared = max_distance * max_distance;
    for (std::size_t k = 0; k < num_deferred; ++k) {
      const std::uint32_t s = deferred_[k];
      const Eigen::Vector3d moved = move(motion, s);
      double squared = 0.0;
      search(class_grid_[c], moved, max_squared, s, squared);
      if (first_[s] >= 0 && squared <= max_squared) {
        m.add(moved - o, Eigen::Vector3d(first_x_[s], first_y_[s], first_z_[s]) - o, squared);
      }
    }
    return m;
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

  /// [TC] section 2.2, step 2: each target point of a grid pairs with its nearest moved source
  /// point among the classes that search that grid (its own class; every class without classes)
  /// within the limit; the moments go to the source point's class. With `stride` > 1 every
  /// stride-th target point takes part.
  std::array<ClassMoments, kNumTerrainClasses> moments_from_target(const Motion& motion, const Eigen::Vector3d& o,
                                                                   double max_squared, std::size_t stride) const {
    std::array<ClassMoments, kNumTerrainClasses> out;
    for (std::size_t g = 0; g < kNumTerrainClasses; ++g) {
      const NearestNeighborGrid& target = grids_[g];
      std::vector<Eigen::Vector3d> moved;
      std::vector<std::uint8_t> class_of;
      for (std::size_t c = 0; c < kNumTerrainClasses; ++c) {
        if (class_grid_[c] != g) continue;
        for (std::size_t slot = class_begin_[c]; slot < class_begin_[c + 1]; ++slot) {
          moved.push_back(move(motion, slot));
          class_of.push_back(static_cast<std::uint8_t>(c));
        }
      }
      if (target.size() == 0 || moved.empty()) continue;
      const NearestNeighborGrid source(moved);
      for (std::size_t k = 0; k < target.size(); k += stride) {
        double squared = 0.0;
        const std::ptrdiff_t s = source.nearest(target.point(k), max_squared, squared);
        if (s >= 0) out[class_of[s]].add(moved[s] - o, target.point(k) - o, squared);
      }
    }
    return out;
  }

  /// Source point `slot` moved, .
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
  // [class_begin_[c], class_begin_[c + 1]), with its weight ([TC] eq. (4); 0: none take part) and grid.
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
  bool from_target_ = false;        // RegistrationParams::pairing is kTargetToSource
  double target_weight_ = 0.0;      // of the target points that take part, for from_target_
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

/// register_points after the checks; `*_empty`: whether the source (target) has no point at all.
RegistrationResult register_checked(const ClassifiedPoints& source, const ClassifiedPoints& target,
                                    const Eigen::Matrix4d& initial, const RegistrationParams& params, bool source_empty,
                                    bool target_empty);

}  // namespace

RegistrationResult register_points(const ClassifiedPoints& source, const ClassifiedPoints& target,
                                   const Eigen::Matrix4d& initial, const RegistrationParams& params) {
  check_registration_params(params);
  detail::check_rigid_transform(initial, "initial transform");
  check_points(source, "source");
  check_points(target, "target");
  return register_checked(source, target, initial, params, source.size() == 0, target.size() == 0);
}

namespace {

/// Besl and McKay's accelerated ICP (1992, sec. IV-C), in its geometric-series form: when two
/// successive updates point the same way (within 10 degrees) and shrink by a ratio rho, the
/// remaining steps sum to about rho / (1 - rho) times the last one; try them at once (at most
/// kMaxExtrapolation times the step), then start a new pair. Updates are compared as
/// (rotation * rms radius, motion of the first centroid) so that both parts weigh alike.
struct Extrapolation {
  Eigen::Vector3d pivot = Eigen::Vector3d::Zero();  ///< the first pass's centroid
  double radius = 1.0;                              ///< its rms radius (the length scale)
  Vector6d previous_step = Vector6d::Zero();
  bool has_previous_step = false;
  int passes = 0;  ///< passes evaluated here
  int jumps = 0;   ///< jumps kept

  /// After the update `x` (about pass.centroid) that gave `plain`: when a jump is due, evaluates
  /// the plain step and the jump at `next_distance`, keeps the better one in `plain` and its pass
  /// in `pass`, and returns true; else records the step and returns false.
  bool try_jump(Registration& registration, const Vector6d& x, double next_distance, Eigen::Matrix4d& plain,
                Pass& pass) {
    const Eigen::Vector3d pivot_motion =
        rotation_of(x.head<3>()) * (pivot - pass.centroid) + pass.centroid + x.tail<3>() - pivot;
    Vector6d step;
    step << x.head<3>() * radius, pivot_motion;
    if (!has_previous_step) {
      previous_step = step;
      has_previous_step = true;
      return false;
    }
    const double norm = step.norm(), previous_norm = previous_step.norm();
    const double rho = previous_norm > 0.0 ? norm / previous_norm : 1.0;
    if (!(rho < 1.0 && step.dot(previous_step) > kCosExtrapolation * norm * previous_norm)) {
      previous_step = step;
      return false;
    }
    // Guard (a departure from Besl and McKay): keep the jump only if the [TC] eq. (4) error it
    // reaches, truncated at the next limit, is no larger than the plain step's.
    const double factor = std::min(rho / (1.0 - rho), kMaxExtrapolation);
    Eigen::Matrix4d jumped = update_about(pass.centroid, x, factor) * plain;
    jumped.topLeftCorner<3, 3>() = orthonormalised(jumped.topLeftCorner<3, 3>());
    // The plain step first: the search certificates are then anchored at the jump, which is kept
    // more often than not.
    Pass at_plain = registration.pass(plain, next_distance);
    Pass at_jump = registration.pass(jumped, next_distance);
    passes += 2;
    if (registration.truncated_error(at_jump, next_distance) <= registration.truncated_error(at_plain, next_distance)) {
      plain = jumped;
      pass = std::move(at_jump);
      ++jumps;
    } else {
      pass = std::move(at_plain);
    }
    has_previous_step = false;
    return true;
  }
};

/// Why the ICP stops at iteration `iteration` with the correspondences `pass` (already in
/// `result`), or kConverged to go on.
StopReason stop_reason(const RegistrationResult& result, const Pass& pass, const RegistrationParams& params,
                       int iteration) {
  if (pass.count < params.min_correspondences) return StopReason::kTooFewCorrespondences;
  if (result.rmse_m < params.error_threshold_m) return StopReason::kErrorBelowThreshold;
  if (result.eigenvalues(0) <= params.degeneracy_threshold * result.eigenvalues(5)) return StopReason::kDegenerate;
  if (iteration == params.max_iterations) return StopReason::kMaxIterations;
  return StopReason::kConverged;
}

/// The ICP iterations of [TC] section 2.2 from `start`: fills `result` (all but the verdict),
/// with the constraint analysis at the final estimate. Returns the final class pairs' weight and
/// rms radius (ground planes not counted), the verdict's units.
detail::PairWeight iterate(Registration& registration, const Eigen::Matrix4d& start, const RegistrationParams& params,
                           RegistrationResult& result) {
  // The distance limit of iteration k (from 0).
  const auto limit_of = [&](int iteration) {
    return std::max(params.min_correspondence_distance_m,
                    params.max_correspondence_distance_m * std::pow(params.correspondence_distance_decay, iteration));
  };
  Eigen::Matrix4d transform = start;
  double distance = limit_of(0);
  // Coarse to fine: the first iterations use every coarse_subsample-th source point, until an
  // update moves the points less than coarse_until_motion_m (or registration would stop).
  auto stride = static_cast<std::size_t>(params.coarse_subsample);
  if (registration.active_size() / stride < kMinCoarsePoints) stride = 1;
  Pass pass = registration.pass(transform, distance, stride);
  int passes = 1;
  Extrapolation extrapolation;
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
    result.passes = passes + extrapolation.passes;
    result.extrapolations = extrapolation.jumps;
    return detail::PairWeight{pass.class_weight_sum, pass.class_radius};
  };
  for (int iteration = 0;; ++iteration) {
    // `pass` holds the correspondences at `transform` within `distance`.
    result.transform = transform;
    result.iterations = iteration;
    fill(result, pass, distance);
    const StopReason stop = stop_reason(result, pass, params, iteration);  // kConverged: go on
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
      extrapolation.pivot = pass.centroid;
      // rms distance of the class correspondences from their centroid (Pass::class_radius)
      extrapolation.radius = pass.class_radius;
    }
    // [TC] eq. (A6): H x = g, solved by LDLT.
    const Vector6d x = pass.normal.ldlt().solve(pass.gradient);
    if (!x.allFinite()) return finish(StopReason::kDegenerate);
    // The update about the centroid c: p -> R (p - c) + c + t, composed exactly (no small-angle matrix).
    Eigen::Matrix4d plain = update_about(pass.centroid, x, 1.0) * transform;
    plain.topLeftCorner<3, 3>() = orthonormalised(plain.topLeftCorner<3, 3>());
    const double next_distance = limit_of(iteration + 1);
    bool evaluated = false;  // `pass` already holds the correspondences at the new transform
    const bool coarse = stride > 1;
    const bool leave_coarse =
        coarse && x.tail<3>().norm() + x.head<3>().norm() * extrapolation.radius < params.coarse_until_motion_m;
    if (leave_coarse) {
      stride = 1;
      extrapolation.has_previous_step = false;  // the objective changes: start a new pair of updates
    }
    // Extrapolation only on the fine iterations: on the subsample it was seen to converge early.
    if (params.extrapolate && !coarse) evaluated = extrapolation.try_jump(registration, x, next_distance, plain, pass);
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

RegistrationResult register_checked(const ClassifiedPoints& source, const ClassifiedPoints& target,
                                    const Eigen::Matrix4d& initial, const RegistrationParams& params, bool source_empty,
                                    bool target_empty) {
  RegistrationResult result;
  // Issue 38: the ICP starts from the correlative search's best hypothesis near `initial`.
  const Eigen::Matrix4d start =
      params.correlative_search ? correlative_search(source, target, initial, params.search).transform : initial;
  result.transform = start;
  result.icp_start = start;
  // The source points that take part, per class (the verdict's denominators).
  std::array<std::size_t, kNumTerrainClasses> source_per_class{};
  for (const std::uint8_t c : source.classes)
    source_per_class[c] += !params.use_classes || params.class_weights[c] > 0.0;
  Registration registration(source, target, params);
  // The verdict's inliers: partners within min_correspondence_distance_m at the final estimate,
  // whatever distance limit the ICP stopped at.
  std::array<std::size_t, kNumTerrainClasses> inliers{};
  detail::PairWeight pairs;
  if (registration.has_common_class()) {
    pairs = iterate(registration, start, params, result);
    const double inlier_distance = params.min_correspondence_distance_m;
    inliers = result.correspondence_distance_m == inlier_distance
                  ? result.correspondences_per_class
                  : registration.pass(result.transform, inlier_distance).per_class;
    // What coincidence alone gives: the overlap at the result moved by 1 m along +-x and +-y, the
    // least of the four (a corridor keeps its overlap along itself, not across).
    double chance = 1.0;
    for (const auto& [dx, dy] :
         {std::pair{1.0, 0.0}, std::pair{-1.0, 0.0}, std::pair{0.0, 1.0}, std::pair{0.0, -1.0}}) {
      Eigen::Matrix4d moved = result.transform;
      moved(0, 3) += dx;
      moved(1, 3) += dy;
      chance = std::min(chance, detail::object_overlap(registration.partners_within(moved, inlier_distance),
                                                       source_per_class, params.use_classes));
    }
    result.chance_overlap = chance;
  } else {
    result.reason = source_empty || target_empty ? StopReason::kTooFewCorrespondences : StopReason::kNoCommonClass;
    result.rmse_m = std::numeric_limits<double>::quiet_NaN();
  }
  detail::judge_registration(result, source_per_class, inliers, params, pairs);
  return result;
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

}  // namespace terracube
