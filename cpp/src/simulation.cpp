#include "terracube/simulation.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <random>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "number_text.hpp"

namespace terracube::simulation {

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kHitEpsilon = 1e-9;  // crossings nearer than this along a ray are the origin itself

double deg2rad(double degrees) { return degrees * kPi / 180.0; }

[[noreturn]] void fail(const std::string& message) { throw std::invalid_argument(message); }

void require_finite(double value, const char* name) {
  if (!std::isfinite(value)) fail(std::string(name) + " must be finite, got " + detail::number_text(value));
}

void require_positive(double value, const char* name) {
  if (!std::isfinite(value) || !(value > 0.0))
    fail(std::string(name) + " must be positive, got " + detail::number_text(value));
}

void require_non_negative(double value, const char* name) {
  if (!std::isfinite(value) || value < 0.0)
    fail(std::string(name) + " must be >= 0, got " + detail::number_text(value));
}

double clamp01(double value) { return std::min(1.0, std::max(0.0, value)); }

double wrap_angle(double angle) { return std::remainder(angle, 2.0 * kPi); }

/// SplitMix64: decorrelates (seed, index) pairs into seeds for independent generators.
std::uint64_t mix_seed(std::uint64_t value) {
  value += 0x9E3779B97F4A7C15ULL;
  value = (value ^ (value >> 30)) * 0xBF58476D1CE4E5B9ULL;
  value = (value ^ (value >> 27)) * 0x94D049BB133111EBULL;
  return value ^ (value >> 31);
}

/// Standard normal deviates by Box-Muller on std::mt19937_64 (whose output the standard fixes), so
/// sequences are identical on every platform, unlike std::normal_distribution.
class Gaussian {
 public:
  explicit Gaussian(std::uint64_t seed) : engine_(seed) {}
  double operator()() {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    const double u1 = 1.0 - uniform();  // (0, 1]
    const double u2 = uniform();
    const double radius = std::sqrt(-2.0 * std::log(u1));
    spare_ = radius * std::sin(2.0 * kPi * u2);
    has_spare_ = true;
    return radius * std::cos(2.0 * kPi * u2);
  }
  double uniform() { return static_cast<double>(engine_() >> 11) * (1.0 / 9007199254740992.0); }  // [0, 1)

 private:
  std::mt19937_64 engine_;
  double spare_ = 0.0;
  bool has_spare_ = false;
};

/// Roots of a t^2 + b t + c = 0 (a > 0) in ascending order, numerically stable; false if none.
bool solve_quadratic(double a, double b, double c, double& t0, double& t1) {
  const double discriminant = b * b - 4.0 * a * c;
  if (discriminant < 0.0 || a <= 0.0) return false;
  const double root = std::sqrt(discriminant);
  const double q = -0.5 * (b + (b >= 0.0 ? root : -root));
  t0 = q / a;
  t1 = q != 0.0 ? c / q : t0;
  if (t0 > t1) std::swap(t0, t1);
  return true;
}

double first_after_epsilon(double t0, double t1) {
  if (t0 > kHitEpsilon) return t0;
  if (t1 > kHitEpsilon) return t1;
  return kInf;
}

double intersect_box(const Primitive& box, const Eigen::Vector3d& origin, const Eigen::Vector3d& direction) {
  // Slabs in the box frame (rotated by -yaw about z).
  const double c = std::cos(box.yaw_rad), s = std::sin(box.yaw_rad);
  const Eigen::Vector3d rel = origin - box.center;
  const Eigen::Vector3d q(c * rel.x() + s * rel.y(), -s * rel.x() + c * rel.y(), rel.z());
  const Eigen::Vector3d d(c * direction.x() + s * direction.y(), -s * direction.x() + c * direction.y(), direction.z());
  double t_near = -kInf, t_far = kInf;
  for (int axis = 0; axis < 3; ++axis) {
    const double h = box.half_extents[axis];
    if (d[axis] == 0.0) {
      if (std::abs(q[axis]) > h) return kInf;
      continue;
    }
    double t0 = (-h - q[axis]) / d[axis], t1 = (h - q[axis]) / d[axis];
    if (t0 > t1) std::swap(t0, t1);
    t_near = std::max(t_near, t0);
    t_far = std::min(t_far, t1);
  }
  if (t_near > t_far) return kInf;
  return first_after_epsilon(t_near, t_far);
}

double intersect_cylinder(const Primitive& cylinder, const Eigen::Vector3d& origin, const Eigen::Vector3d& direction) {
  const double radius = cylinder.half_extents.x();
  const double z_min = cylinder.center.z() - cylinder.half_extents.z();
  const double z_max = cylinder.center.z() + cylinder.half_extents.z();
  const double qx = origin.x() - cylinder.center.x(), qy = origin.y() - cylinder.center.y();
  double best = kInf;
  // Side: |q_xy + t d_xy| = r with z in [z_min, z_max].
  const double a = direction.x() * direction.x() + direction.y() * direction.y();
  double t0 = 0.0, t1 = 0.0;
  if (a > 0.0 && solve_quadratic(a, 2.0 * (qx * direction.x() + qy * direction.y()),
                                 qx * qx + qy * qy - radius * radius, t0, t1)) {
    for (double t : {t0, t1}) {
      const double z = origin.z() + t * direction.z();
      if (t > kHitEpsilon && t < best && z >= z_min && z <= z_max) best = t;
    }
  }
  // Caps: z = z_min or z_max with |q_xy + t d_xy| <= r.
  if (direction.z() != 0.0) {
    for (double z_cap : {z_min, z_max}) {
      const double t = (z_cap - origin.z()) / direction.z();
      const double x = qx + t * direction.x(), y = qy + t * direction.y();
      if (t > kHitEpsilon && t < best && x * x + y * y <= radius * radius) best = t;
    }
  }
  return best;
}

double intersect_ellipsoid(const Primitive& ellipsoid, const Eigen::Vector3d& origin,
                           const Eigen::Vector3d& direction) {
  // Scaled to the unit sphere: |q + t e| = 1.
  const Eigen::Vector3d q = (origin - ellipsoid.center).cwiseQuotient(ellipsoid.half_extents);
  const Eigen::Vector3d e = direction.cwiseQuotient(ellipsoid.half_extents);
  double t0 = 0.0, t1 = 0.0;
  if (!solve_quadratic(e.squaredNorm(), 2.0 * q.dot(e), q.squaredNorm() - 1.0, t0, t1)) return kInf;
  return first_after_epsilon(t0, t1);
}

Eigen::Matrix4d make_pose(const Eigen::Vector3d& position, double yaw, double pitch, double roll) {
  Eigen::Matrix4d pose = Eigen::Matrix4d::Identity();
  pose.topLeftCorner<3, 3>() =
      (Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(pitch, Eigen::Vector3d::UnitY()) *
       Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()))
          .toRotationMatrix();
  pose.topRightCorner<3, 1>() = position;
  return pose;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Labels

const char* to_string(Label label) {
  switch (label) {
    case Label::kGround:
      return "ground";
    case Label::kWall:
      return "wall";
    case Label::kBuilding:
      return "building";
    case Label::kTrunk:
      return "trunk";
    case Label::kCanopy:
      return "canopy";
    case Label::kTunnelWall:
      return "tunnel_wall";
    case Label::kTunnelCeiling:
      return "tunnel_ceiling";
    case Label::kBridgeDeck:
      return "bridge_deck";
    case Label::kPillar:
      return "pillar";
  }
  return "unknown";
}

bool is_overhang(Label label) {
  return label == Label::kCanopy || label == Label::kTunnelCeiling || label == Label::kBridgeDeck;
}

// ---------------------------------------------------------------------------------------------
// Terrain

namespace {

/// Along/across offsets of (x, y) from a ramp's centre line.
void ramp_offsets(const Ramp& ramp, double x, double y, double& along, double& across) {
  const double c = std::cos(ramp.heading_rad), s = std::sin(ramp.heading_rad);
  const double dx = x - ramp.center.x(), dy = y - ramp.center.y();
  along = c * dx + s * dy;
  across = -s * dx + c * dy;
}

/// Trapezoid profile value and slope: 1 on the plateau, linear to 0 over `ramp` beyond it.
void trapezoid(double offset, double half_plateau, double ramp, double& value, double& slope) {
  const double distance = std::abs(offset);
  value = clamp01((half_plateau + ramp - distance) / ramp);
  const bool sloped = distance >= half_plateau && distance < half_plateau + ramp;
  slope = sloped ? (offset >= 0.0 ? -1.0 : 1.0) / ramp : 0.0;
}

}  // namespace

double Terrain::height(double x, double y) const {
  double z = base_height_m;
  for (const Ramp& ramp : ramps) {
    double along = 0.0, across = 0.0, p = 0.0, q = 0.0, unused = 0.0;
    ramp_offsets(ramp, x, y, along, across);
    trapezoid(along, 0.5 * ramp.plateau_length_m, ramp.ramp_length_m, p, unused);
    if (p == 0.0) continue;
    trapezoid(across, ramp.half_width_m, ramp.side_falloff_m, q, unused);
    z += ramp.height_m * p * q;
  }
  for (const Hill& hill : hills) {
    const double r2 = (Eigen::Vector2d(x, y) - hill.center).squaredNorm();
    const double radius2 = hill.radius_m * hill.radius_m;
    if (r2 >= radius2) continue;
    const double u = 1.0 - r2 / radius2;
    z += hill.height_m * u * u;
  }
  return z;
}

Eigen::Vector2d Terrain::gradient(double x, double y) const {
  Eigen::Vector2d g = Eigen::Vector2d::Zero();
  for (const Ramp& ramp : ramps) {
    double along = 0.0, across = 0.0, p = 0.0, dp = 0.0, q = 0.0, dq = 0.0;
    ramp_offsets(ramp, x, y, along, across);
    trapezoid(along, 0.5 * ramp.plateau_length_m, ramp.ramp_length_m, p, dp);
    trapezoid(across, ramp.half_width_m, ramp.side_falloff_m, q, dq);
    const Eigen::Vector2d forward(std::cos(ramp.heading_rad), std::sin(ramp.heading_rad));
    const Eigen::Vector2d left(-forward.y(), forward.x());
    g += ramp.height_m * (dp * q * forward + p * dq * left);
  }
  for (const Hill& hill : hills) {
    const Eigen::Vector2d offset = Eigen::Vector2d(x, y) - hill.center;
    const double radius2 = hill.radius_m * hill.radius_m;
    const double u = 1.0 - offset.squaredNorm() / radius2;
    if (u <= 0.0) continue;
    g += -4.0 * hill.height_m * u / radius2 * offset;
  }
  return g;
}

double Terrain::max_slope() const {
  double bound = 0.0;
  for (const Ramp& ramp : ramps) {
    bound += std::abs(ramp.height_m) * std::hypot(1.0 / ramp.ramp_length_m, 1.0 / ramp.side_falloff_m);
  }
  // max |grad| of a (1 - r^2/R^2)^2 is at r = R / sqrt(3): 8 |a| / (3 sqrt(3) R).
  for (const Hill& hill : hills) bound += 8.0 * std::abs(hill.height_m) / (3.0 * std::sqrt(3.0) * hill.radius_m);
  return bound;
}

double Terrain::max_height() const {
  double top = base_height_m;
  for (const Ramp& ramp : ramps) top += std::max(0.0, ramp.height_m);
  for (const Hill& hill : hills) top += std::max(0.0, hill.height_m);
  return top;
}

void validate(const Terrain& terrain) {
  require_finite(terrain.base_height_m, "terrain base_height_m");
  for (const Ramp& ramp : terrain.ramps) {
    require_finite(ramp.center.x(), "ramp center x");
    require_finite(ramp.center.y(), "ramp center y");
    require_finite(ramp.heading_rad, "ramp heading_rad");
    require_finite(ramp.height_m, "ramp height_m");
    require_positive(ramp.ramp_length_m, "ramp ramp_length_m");
    require_non_negative(ramp.plateau_length_m, "ramp plateau_length_m");
    require_non_negative(ramp.half_width_m, "ramp half_width_m");
    require_positive(ramp.side_falloff_m, "ramp side_falloff_m");
  }
  for (const Hill& hill : terrain.hills) {
    require_finite(hill.center.x(), "hill center x");
    require_finite(hill.center.y(), "hill center y");
    require_finite(hill.height_m, "hill height_m");
    require_positive(hill.radius_m, "hill radius_m");
  }
}

namespace {

/// Whether origin + t * direction, t in [0, t_max], passes over the rectangle |x'| < a, |y'| < b of
/// the frame centred at `center` and rotated by `heading` (the xy slab test).
bool crosses_footprint(const Eigen::Vector2d& center, double heading, double a, double b, const Eigen::Vector3d& origin,
                       const Eigen::Vector3d& direction, double t_max) {
  const double c = std::cos(heading), s = std::sin(heading);
  const double qx = origin.x() - center.x(), qy = origin.y() - center.y();
  const double q[2] = {c * qx + s * qy, -s * qx + c * qy};
  const double d[2] = {c * direction.x() + s * direction.y(), -s * direction.x() + c * direction.y()};
  const double half[2] = {a, b};
  double t_near = 0.0, t_far = t_max;
  for (int axis = 0; axis < 2; ++axis) {
    if (d[axis] == 0.0) {
      if (std::abs(q[axis]) >= half[axis]) return false;
      continue;
    }
    double t0 = (-half[axis] - q[axis]) / d[axis], t1 = (half[axis] - q[axis]) / d[axis];
    if (t0 > t1) std::swap(t0, t1);
    t_near = std::max(t_near, t0);
    t_far = std::min(t_far, t1);
  }
  return t_near <= t_far;
}

}  // namespace

double intersect_terrain(const Terrain& terrain, const Eigen::Vector3d& origin, const Eigen::Vector3d& direction,
                         double t_max) {
  const auto gap = [&](double t) {
    return origin.z() + t * direction.z() -
           terrain.height(origin.x() + t * direction.x(), origin.y() + t * direction.y());
  };
  const double f0 = gap(0.0);
  if (!(f0 > 0.0)) return 0.0;  // the origin is on or below the surface
  // Only the features whose footprint the segment [0, t_max] passes over shape the terrain under
  // it: their slope bounds add up to S, their heights to the highest the surface gets there.
  double slope = 0.0, top = terrain.base_height_m;
  for (const Ramp& ramp : terrain.ramps) {
    if (crosses_footprint(ramp.center, ramp.heading_rad, ramp.ramp_length_m + 0.5 * ramp.plateau_length_m,
                          ramp.half_width_m + ramp.side_falloff_m, origin, direction, t_max)) {
      slope += std::abs(ramp.height_m) * std::hypot(1.0 / ramp.ramp_length_m, 1.0 / ramp.side_falloff_m);
      top += std::max(0.0, ramp.height_m);
    }
  }
  for (const Hill& hill : terrain.hills) {
    if (crosses_footprint(hill.center, 0.0, hill.radius_m, hill.radius_m, origin, direction, t_max)) {
      slope += 8.0 * std::abs(hill.height_m) / (3.0 * std::sqrt(3.0) * hill.radius_m);
      top += std::max(0.0, hill.height_m);
    }
  }
  if (slope == 0.0) {  // flat under the whole segment: the plane z = base
    if (!(direction.z() < 0.0)) return kInf;
    const double t = (terrain.base_height_m - origin.z()) / direction.z();
    return t <= t_max ? t : kInf;
  }
  // Lipschitz march: |d gap / dt| <= |d_z| + S |d_xy|, so a step of gap / rate cannot cross the
  // surface; grazing rays creep at min_step. The crossing step is then refined.
  const double rate = std::abs(direction.z()) + slope * std::hypot(direction.x(), direction.y());
  const double min_step = 1e-2 * direction.norm();
  double t = 0.0, f = f0;
  for (int iteration = 0; iteration < 100000 && t <= t_max; ++iteration) {
    if (direction.z() >= 0.0 && origin.z() + t * direction.z() > top) return kInf;
    const double next = t + std::max(f / rate, min_step);
    const double f_next = gap(next);
    if (f_next <= 0.0) {
      // Illinois (modified regula falsi) on [t, next], gap(t) > 0 >= gap(next): exact in one step
      // on a planar piece, bisection-safe at the kinks of the ramps.
      double low = t, high = next, f_low = f, f_high = f_next;
      int side = 0;
      for (int k = 0; k < 100 && high - low > 1e-12 * (1.0 + high) && f_high != 0.0; ++k) {
        double mid = (low * f_high - high * f_low) / (f_high - f_low);
        if (!(mid > low && mid < high)) mid = 0.5 * (low + high);
        const double f_mid = gap(mid);
        if (f_mid > 0.0) {
          low = mid;
          f_low = f_mid;
          if (side == 1) f_high *= 0.5;
          side = 1;
        } else {
          high = mid;
          f_high = f_mid;
          if (side == -1) f_low *= 0.5;
          side = -1;
        }
      }
      return high <= t_max ? high : kInf;
    }
    t = next;
    f = f_next;
  }
  return kInf;
}

// ---------------------------------------------------------------------------------------------
// Primitives

Primitive Primitive::box(const Eigen::Vector3d& center, const Eigen::Vector3d& half_extents, double yaw_rad,
                         Label label) {
  Primitive p;
  p.kind = PrimitiveKind::kBox;
  p.label = label;
  p.center = center;
  p.half_extents = half_extents;
  p.yaw_rad = yaw_rad;
  return p;
}

Primitive Primitive::cylinder(double x, double y, double radius, double z_min, double z_max, Label label) {
  Primitive p;
  p.kind = PrimitiveKind::kCylinder;
  p.label = label;
  p.center = Eigen::Vector3d(x, y, 0.5 * (z_min + z_max));
  p.half_extents = Eigen::Vector3d(radius, radius, 0.5 * (z_max - z_min));
  return p;
}

Primitive Primitive::ellipsoid(const Eigen::Vector3d& center, const Eigen::Vector3d& radii, Label label) {
  Primitive p;
  p.kind = PrimitiveKind::kEllipsoid;
  p.label = label;
  p.center = center;
  p.half_extents = radii;
  return p;
}

Eigen::Vector4d Primitive::xy_bounds() const {
  double ex = half_extents.x(), ey = half_extents.y();
  if (kind == PrimitiveKind::kBox) {
    const double c = std::abs(std::cos(yaw_rad)), s = std::abs(std::sin(yaw_rad));
    ex = c * half_extents.x() + s * half_extents.y();
    ey = s * half_extents.x() + c * half_extents.y();
  }
  return {center.x() - ex, center.y() - ey, center.x() + ex, center.y() + ey};
}

void validate(const Primitive& primitive) {
  if (static_cast<int>(primitive.kind) > 2) fail("primitive kind must be box, cylinder or ellipsoid");
  if (static_cast<int>(primitive.label) >= kNumLabels) fail("primitive label out of range");
  if (!primitive.center.allFinite()) fail("primitive center must be finite");
  require_finite(primitive.yaw_rad, "primitive yaw_rad");
  for (int axis = 0; axis < 3; ++axis) require_positive(primitive.half_extents[axis], "primitive half extents");
  if (primitive.kind == PrimitiveKind::kCylinder && primitive.half_extents.x() != primitive.half_extents.y()) {
    fail("a cylinder's half_extents must be (radius, radius, half height)");
  }
}

double intersect(const Primitive& primitive, const Eigen::Vector3d& origin, const Eigen::Vector3d& direction) {
  switch (primitive.kind) {
    case PrimitiveKind::kBox:
      return intersect_box(primitive, origin, direction);
    case PrimitiveKind::kCylinder:
      return intersect_cylinder(primitive, origin, direction);
    case PrimitiveKind::kEllipsoid:
      return intersect_ellipsoid(primitive, origin, direction);
  }
  return kInf;
}

// ---------------------------------------------------------------------------------------------
// Scene

Scene::Scene(Terrain terrain, std::vector<Primitive> primitives, double grid_cell_m)
    : terrain_(std::move(terrain)), primitives_(std::move(primitives)), cell_m_(grid_cell_m) {
  validate(terrain_);
  require_positive(grid_cell_m, "grid_cell_m");
  if (primitives_.size() >= std::numeric_limits<std::uint32_t>::max()) fail("too many primitives");
  for (const Primitive& primitive : primitives_) validate(primitive);
  if (primitives_.empty()) {
    cell_begin_.assign(1, 0);
    return;
  }
  Eigen::Vector2d low = Eigen::Vector2d::Constant(kInf), high = Eigen::Vector2d::Constant(-kInf);
  for (const Primitive& primitive : primitives_) {
    const Eigen::Vector4d b = primitive.xy_bounds();
    low = low.cwiseMin(b.head<2>());
    high = high.cwiseMax(b.tail<2>());
  }
  grid_min_ = low;
  const double cells_x = std::ceil((high.x() - low.x()) / cell_m_), cells_y = std::ceil((high.y() - low.y()) / cell_m_);
  if (cells_x * cells_y > 5e7) fail("the primitives span too many grid cells; increase grid_cell_m");
  nx_ = std::max(1, static_cast<int>(cells_x));
  ny_ = std::max(1, static_cast<int>(cells_y));
  const auto cell_range = [&](const Primitive& primitive, int& x0, int& y0, int& x1, int& y1) {
    const Eigen::Vector4d b = primitive.xy_bounds();
    x0 = std::clamp(static_cast<int>(std::floor((b[0] - grid_min_.x()) / cell_m_)), 0, nx_ - 1);
    y0 = std::clamp(static_cast<int>(std::floor((b[1] - grid_min_.y()) / cell_m_)), 0, ny_ - 1);
    x1 = std::clamp(static_cast<int>(std::floor((b[2] - grid_min_.x()) / cell_m_)), 0, nx_ - 1);
    y1 = std::clamp(static_cast<int>(std::floor((b[3] - grid_min_.y()) / cell_m_)), 0, ny_ - 1);
  };
  // Counting pass, then fill (CSR).
  cell_begin_.assign(static_cast<std::size_t>(nx_) * ny_ + 1, 0);
  for (const Primitive& primitive : primitives_) {
    int x0, y0, x1, y1;
    cell_range(primitive, x0, y0, x1, y1);
    for (int iy = y0; iy <= y1; ++iy) {
      for (int ix = x0; ix <= x1; ++ix) ++cell_begin_[static_cast<std::size_t>(iy) * nx_ + ix + 1];
    }
  }
  for (std::size_t k = 1; k < cell_begin_.size(); ++k) cell_begin_[k] += cell_begin_[k - 1];
  cell_items_.resize(cell_begin_.back());
  std::vector<std::uint32_t> fill(cell_begin_.begin(), cell_begin_.end() - 1);
  for (std::uint32_t index = 0; index < primitives_.size(); ++index) {
    int x0, y0, x1, y1;
    cell_range(primitives_[index], x0, y0, x1, y1);
    for (int iy = y0; iy <= y1; ++iy) {
      for (int ix = x0; ix <= x1; ++ix) cell_items_[fill[static_cast<std::size_t>(iy) * nx_ + ix]++] = index;
    }
  }
}

namespace {

/// Keeps the nearer of two hits; equal ranges go to the lower primitive index (so the grid walk
/// and the brute force agree exactly).
void consider(RayHit& best, double t, std::int32_t index, Label label) {
  if (t < best.range_m || (t == best.range_m && t < kInf && index < best.primitive)) {
    best.range_m = t;
    best.primitive = index;
    best.label = label;
  }
}

/// The primitive hit when it is at or before the terrain's, else the terrain's; none beyond max_range_m.
RayHit nearest_of(RayHit best, double terrain_t, double max_range_m) {
  if (terrain_t < best.range_m) {
    best.range_m = terrain_t;
    best.primitive = -1;
    best.label = Label::kGround;
  }
  if (best.range_m > max_range_m) best = RayHit{};
  return best;
}

}  // namespace

RayHit Scene::intersect_brute_force(const Eigen::Vector3d& origin, const Eigen::Vector3d& direction,
                                    double max_range_m) const {
  const double terrain_t = intersect_terrain(terrain_, origin, direction, max_range_m);
  RayHit best;
  for (std::size_t index = 0; index < primitives_.size(); ++index) {
    const Primitive& primitive = primitives_[index];
    consider(best, simulation::intersect(primitive, origin, direction), static_cast<std::int32_t>(index),
             primitive.label);
  }
  return nearest_of(best, terrain_t, max_range_m);
}

RayHit Scene::intersect(const Eigen::Vector3d& origin, const Eigen::Vector3d& direction, double max_range_m) const {
  std::vector<std::uint32_t> mailbox(primitives_.size(), 0);
  return intersect(origin, direction, max_range_m, mailbox, 1);
}

RayHit Scene::intersect(const Eigen::Vector3d& origin, const Eigen::Vector3d& direction, double max_range_m,
                        std::vector<std::uint32_t>& mailbox, std::uint32_t ray_id) const {
  // The terrain first: no cell beyond its hit needs a visit.
  const double terrain_t = intersect_terrain(terrain_, origin, direction, max_range_m);
  RayHit best;
  if (mailbox.size() < primitives_.size()) mailbox.resize(primitives_.size(), 0);
  if (!primitives_.empty()) {
    // Clip the ray's xy projection to the grid rectangle: [t_enter, t_leave] within [0, max_range].
    const Eigen::Vector2d o = origin.head<2>(), d = direction.head<2>();
    const Eigen::Vector2d grid_max = grid_min_ + cell_m_ * Eigen::Vector2d(nx_, ny_);
    double t_enter = 0.0, t_leave = std::min(max_range_m, terrain_t);
    for (int axis = 0; axis < 2; ++axis) {
      if (d[axis] == 0.0) {
        if (o[axis] < grid_min_[axis] || o[axis] > grid_max[axis]) t_enter = kInf;
        continue;
      }
      double t0 = (grid_min_[axis] - o[axis]) / d[axis], t1 = (grid_max[axis] - o[axis]) / d[axis];
      if (t0 > t1) std::swap(t0, t1);
      t_enter = std::max(t_enter, t0);
      t_leave = std::min(t_leave, t1);
    }
    if (t_enter <= t_leave) {
      // Amanatides & Woo's walk over the cells the projection crosses.
      const Eigen::Vector2d start = o + t_enter * d;
      int cell[2], step[2];
      double t_next[2], t_delta[2];
      const int counts[2] = {nx_, ny_};
      for (int axis = 0; axis < 2; ++axis) {
        cell[axis] =
            std::clamp(static_cast<int>(std::floor((start[axis] - grid_min_[axis]) / cell_m_)), 0, counts[axis] - 1);
        if (d[axis] > 0.0) {
          step[axis] = 1;
          t_next[axis] = (grid_min_[axis] + (cell[axis] + 1) * cell_m_ - o[axis]) / d[axis];
          t_delta[axis] = cell_m_ / d[axis];
        } else if (d[axis] < 0.0) {
          step[axis] = -1;
          t_next[axis] = (grid_min_[axis] + cell[axis] * cell_m_ - o[axis]) / d[axis];
          t_delta[axis] = -cell_m_ / d[axis];
        } else {
          step[axis] = 0;
          t_next[axis] = kInf;
          t_delta[axis] = kInf;
        }
      }
      while (true) {
        const std::size_t c = static_cast<std::size_t>(cell[1]) * nx_ + cell[0];
        for (std::uint32_t k = cell_begin_[c]; k < cell_begin_[c + 1]; ++k) {
          const std::uint32_t index = cell_items_[k];
          if (mailbox[index] == ray_id) continue;
          mailbox[index] = ray_id;
          const Primitive& primitive = primitives_[index];
          consider(best, simulation::intersect(primitive, origin, direction), static_cast<std::int32_t>(index),
                   primitive.label);
        }
        const int axis = t_next[0] < t_next[1] ? 0 : 1;
        const double t_exit = t_next[axis];
        // Cells further on start at t_exit: nothing there can beat a hit at or before it.
        if (best.range_m <= t_exit || t_exit > t_leave) break;
        cell[axis] += step[axis];
        if (cell[axis] < 0 || cell[axis] >= counts[axis]) break;
        t_next[axis] += t_delta[axis];
      }
    }
  }
  return nearest_of(best, terrain_t, max_range_m);
}

// ---------------------------------------------------------------------------------------------
// Sensors

void validate(const SensorModel& model) {
  const auto check_ranges = [](double min_range, double max_range, double sigma) {
    require_non_negative(min_range, "min_range_m");
    require_positive(max_range, "max_range_m");
    if (!(min_range < max_range)) {
      fail("min_range_m must be below max_range_m, got " + detail::number_text(min_range) +
           " >= " + detail::number_text(max_range));
    }
    require_non_negative(sigma, "range_noise_sigma_m");
  };
  const auto check_angle = [](double degrees, const char* name) {
    require_finite(degrees, name);
    if (degrees < -90.0 || degrees > 90.0) fail(std::string(name) + " must lie in [-90, 90] degrees");
  };
  if (const auto* lidar = std::get_if<RotatingLidar>(&model)) {
    if (lidar->channels < 1) fail("channels must be positive, got " + std::to_string(lidar->channels));
    if (lidar->steps_per_revolution < 1) {
      fail("steps_per_revolution must be positive, got " + std::to_string(lidar->steps_per_revolution));
    }
    check_angle(lidar->vertical_fov_min_deg, "vertical_fov_min_deg");
    check_angle(lidar->vertical_fov_max_deg, "vertical_fov_max_deg");
    if (lidar->vertical_fov_min_deg > lidar->vertical_fov_max_deg) {
      fail("vertical_fov_min_deg must not exceed vertical_fov_max_deg");
    }
    if (static_cast<double>(lidar->channels) * lidar->steps_per_revolution > 1e8) fail("more than 1e8 rays per scan");
    check_ranges(lidar->min_range_m, lidar->max_range_m, lidar->range_noise_sigma_m);
  } else {
    const auto& scanner = std::get<Tilting2DScanner>(model);
    if (scanner.beams_per_line < 1)
      fail("beams_per_line must be positive, got " + std::to_string(scanner.beams_per_line));
    if (scanner.lines < 1) fail("lines must be positive, got " + std::to_string(scanner.lines));
    require_positive(scanner.horizontal_fov_deg, "horizontal_fov_deg");
    if (scanner.horizontal_fov_deg > 360.0) fail("horizontal_fov_deg must not exceed 360");
    check_angle(scanner.tilt_from_deg, "tilt_from_deg");
    check_angle(scanner.tilt_to_deg, "tilt_to_deg");
    if (static_cast<double>(scanner.beams_per_line) * scanner.lines > 1e8) fail("more than 1e8 rays per scan");
    check_ranges(scanner.min_range_m, scanner.max_range_m, scanner.range_noise_sigma_m);
  }
}

std::vector<Eigen::Vector3d> sensor_rays(const SensorModel& model) {
  validate(model);
  std::vector<Eigen::Vector3d> rays;
  const auto spread = [](double from, double to, int count, int k) {
    return count == 1 ? from : from + (to - from) * k / (count - 1);
  };
  if (const auto* lidar = std::get_if<RotatingLidar>(&model)) {
    rays.reserve(static_cast<std::size_t>(lidar->channels) * lidar->steps_per_revolution);
    std::vector<double> cos_elevation(lidar->channels), sin_elevation(lidar->channels);
    for (int c = 0; c < lidar->channels; ++c) {
      const double elevation =
          deg2rad(spread(lidar->vertical_fov_min_deg, lidar->vertical_fov_max_deg, lidar->channels, c));
      cos_elevation[c] = std::cos(elevation);
      sin_elevation[c] = std::sin(elevation);
    }
    for (int j = 0; j < lidar->steps_per_revolution; ++j) {
      const double azimuth = 2.0 * kPi * j / lidar->steps_per_revolution;
      const double ca = std::cos(azimuth), sa = std::sin(azimuth);
      for (int c = 0; c < lidar->channels; ++c)
        rays.emplace_back(cos_elevation[c] * ca, cos_elevation[c] * sa, sin_elevation[c]);
    }
  } else {
    const auto& scanner = std::get<Tilting2DScanner>(model);
    rays.reserve(static_cast<std::size_t>(scanner.beams_per_line) * scanner.lines);
    const double half_fov = 0.5 * scanner.horizontal_fov_deg;
    for (int line = 0; line < scanner.lines; ++line) {
      const double tilt = deg2rad(spread(scanner.tilt_from_deg, scanner.tilt_to_deg, scanner.lines, line));
      for (int beam = 0; beam < scanner.beams_per_line; ++beam) {
        const double a = deg2rad(spread(-half_fov, half_fov, scanner.beams_per_line, beam));
        rays.emplace_back(std::cos(tilt) * std::cos(a), std::sin(a), std::sin(tilt) * std::cos(a));
      }
    }
  }
  return rays;
}

void check_rigid(const Eigen::Matrix4d& pose, const std::string& name) {
  if (!pose.allFinite()) fail(name + " must be finite (it holds NaN or Inf)");
  const Eigen::Matrix3d r = pose.topLeftCorner<3, 3>();
  const double orthogonality = (r.transpose() * r - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (orthogonality > 1e-6 || std::abs(r.determinant() - 1.0) > 1e-6 || pose(3, 0) != 0.0 || pose(3, 1) != 0.0 ||
      pose(3, 2) != 0.0 || pose(3, 3) != 1.0) {
    std::ostringstream text;
    text << name << " must be a rigid transform (orthonormal rotation, det +1, last row 0 0 0 1); |R^T R - I| = "
         << orthogonality << ", det R = " << r.determinant();
    fail(text.str());
  }
}

Scan cast_scan(const Scene& scene, const Eigen::Matrix4d& world_T_sensor, const SensorModel& model,
               std::uint64_t seed) {
  validate(model);
  check_rigid(world_T_sensor, "world_T_sensor");
  double min_range = 0.0, max_range = 0.0, sigma = 0.0;
  std::visit(
      [&](const auto& m) {
        min_range = m.min_range_m;
        max_range = m.max_range_m;
        sigma = m.range_noise_sigma_m;
      },
      model);
  const std::vector<Eigen::Vector3d> rays = sensor_rays(model);
  const Eigen::Matrix3d rotation = world_T_sensor.topLeftCorner<3, 3>();
  const Eigen::Vector3d origin = world_T_sensor.topRightCorner<3, 1>();
  Gaussian noise(seed);
  std::vector<std::uint32_t> mailbox(scene.primitives().size(), 0);
  Scan scan;
  scan.points.reserve(rays.size());
  scan.labels.reserve(rays.size());
  scan.ray_indices.reserve(rays.size());
  for (std::size_t i = 0; i < rays.size(); ++i) {
    const RayHit hit =
        scene.intersect(origin, rotation * rays[i], max_range, mailbox, static_cast<std::uint32_t>(i + 1));
    if (!hit.hit() || hit.range_m < min_range) continue;
    const double range = sigma > 0.0 ? hit.range_m + sigma * noise() : hit.range_m;
    scan.points.push_back((range * rays[i]).cast<float>());
    scan.labels.push_back(hit.label);
    scan.ray_indices.push_back(static_cast<std::uint32_t>(i));
  }
  return scan;
}

// ---------------------------------------------------------------------------------------------
// Road

RoadPath::RoadPath(std::vector<Piece> pieces, bool closed) : pieces_(std::move(pieces)), closed_(closed) {
  if (pieces_.empty()) fail("a road needs at least one piece");
  for (const Piece& piece : pieces_) {
    if (!piece.start.allFinite()) fail("road piece start must be finite");
    require_finite(piece.heading_rad, "road piece heading_rad");
    require_positive(piece.length_m, "road piece length_m");
    require_finite(piece.curvature, "road piece curvature");
    piece_start_.push_back(length_);
    length_ += piece.length_m;
  }
}

const RoadPath::Piece& RoadPath::piece_at(double& s) const {
  if (pieces_.empty()) fail("empty road");
  if (closed_) {
    s = std::fmod(s, length_);
    if (s < 0.0) s += length_;
  } else {
    s = std::clamp(s, 0.0, length_);
  }
  std::size_t k =
      static_cast<std::size_t>(std::upper_bound(piece_start_.begin(), piece_start_.end(), s) - piece_start_.begin());
  k = k == 0 ? 0 : k - 1;
  s -= piece_start_[k];
  return pieces_[k];
}

Eigen::Vector2d RoadPath::position(double s) const {
  const Piece& piece = piece_at(s);
  const double h = piece.heading_rad;
  if (piece.curvature == 0.0) return piece.start + s * Eigen::Vector2d(std::cos(h), std::sin(h));
  const double radius = 1.0 / piece.curvature;
  const Eigen::Vector2d centre = piece.start + radius * Eigen::Vector2d(-std::sin(h), std::cos(h));
  const double angle = h + piece.curvature * s;
  return centre + radius * Eigen::Vector2d(std::sin(angle), -std::cos(angle));
}

double RoadPath::heading_rad(double s) const {
  const Piece& piece = piece_at(s);
  return wrap_angle(piece.heading_rad + piece.curvature * s);
}

// ---------------------------------------------------------------------------------------------
// Loop scene

namespace {

struct SceneBuilder {
  const LoopSceneParams& params;
  const RoadPath& road;
  Terrain& terrain;
  std::vector<Primitive>& primitives;
  Gaussian random;
  std::vector<std::pair<double, double>> keep_clear;  // (arc length, half length) without roadside objects

  double uniform(double low, double high) { return low + (high - low) * random.uniform(); }
  Eigen::Vector2d forward(double s) const { return {std::cos(road.heading_rad(s)), std::sin(road.heading_rad(s))}; }
  Eigen::Vector2d left(double s) const {
    const Eigen::Vector2d f = forward(s);
    return {-f.y(), f.x()};
  }
  bool clear(double s) const {
    for (const auto& [centre, half] : keep_clear) {
      double distance = std::abs(s - centre);
      if (road.closed()) distance = std::min(distance, road.length_m() - distance);
      if (distance < half) return false;
    }
    return true;
  }

  void ramp(double s) {
    Ramp r;
    r.center = road.position(s);
    r.heading_rad = road.heading_rad(s);
    r.height_m = params.ramp_height_m;
    r.ramp_length_m = params.ramp_length_m;
    r.plateau_length_m = params.ramp_plateau_m;
    r.half_width_m = 0.5 * params.road_width_m + 2.0;
    r.side_falloff_m = 8.0;
    terrain.ramps.push_back(r);
  }

  /// Two side walls, a ceiling slab over both and portal walls sideways at both ends.
  void tunnel(double s) {
    const Eigen::Vector2d p = road.position(s), f = forward(s), n = left(s);
    const double yaw = road.heading_rad(s), z0 = terrain.height(p.x(), p.y());
    const double half_road = 0.5 * params.road_width_m, clearance = params.tunnel_clearance_m;
    const double half_length = 0.5 * params.tunnel_length_m, thickness = 0.5, roof = 0.6;
    const double wall_bottom = z0 - 0.5, wall_top = z0 + clearance;
    for (double side : {-1.0, 1.0}) {
      const Eigen::Vector2d c = p + side * (half_road + 0.5 + 0.5 * thickness) * n;
      primitives.push_back(Primitive::box({c.x(), c.y(), 0.5 * (wall_bottom + wall_top)},
                                          {half_length, 0.5 * thickness, 0.5 * (wall_top - wall_bottom)}, yaw,
                                          Label::kTunnelWall));
      for (double end : {-1.0, 1.0}) {  // portals: 5 m of facade beside each opening
        const Eigen::Vector2d q = p + end * (half_length - 0.5 * thickness) * f + side * (half_road + 1.0 + 2.5) * n;
        primitives.push_back(Primitive::box({q.x(), q.y(), 0.5 * (wall_bottom + wall_top + roof)},
                                            {0.5 * thickness, 2.5, 0.5 * (wall_top + roof - wall_bottom)}, yaw,
                                            Label::kTunnelWall));
      }
    }
    primitives.push_back(Primitive::box({p.x(), p.y(), wall_top + 0.5 * roof},
                                        {half_length, half_road + 0.5 + thickness, 0.5 * roof}, yaw,
                                        Label::kTunnelCeiling));
    keep_clear.emplace_back(s, half_length + 5.0);
  }

  /// A deck across the road on four pillars.
  void bridge(double s) {
    const Eigen::Vector2d p = road.position(s), f = forward(s), n = left(s);
    const double yaw = road.heading_rad(s), z0 = terrain.height(p.x(), p.y());
    const double half_road = 0.5 * params.road_width_m, half_deck = 0.5 * params.bridge_deck_width_m;
    const double bottom = z0 + params.bridge_clearance_m, thickness = 0.8;
    primitives.push_back(Primitive::box({p.x(), p.y(), bottom + 0.5 * thickness},
                                        {half_deck, half_road + 8.0, 0.5 * thickness}, yaw, Label::kBridgeDeck));
    for (double side : {-1.0, 1.0}) {
      for (double along : {-1.0, 1.0}) {
        const Eigen::Vector2d q = p + side * (half_road + 2.0) * n + along * std::max(0.0, half_deck - 0.8) * f;
        primitives.push_back(Primitive::cylinder(q.x(), q.y(), 0.4, z0 - 0.5, bottom, Label::kPillar));
      }
    }
    keep_clear.emplace_back(s, half_deck + 5.0);
  }

  /// A tree: trunk into an ellipsoidal canopy whose underside is canopy_bottom_m above the ground.
  void tree(const Eigen::Vector2d& at) {
    const double z0 = terrain.height(at.x(), at.y());
    const double radius_xy = uniform(1.8, 2.6), radius_z = uniform(1.2, 1.7);
    const double canopy_centre = z0 + params.canopy_bottom_m + radius_z;
    primitives.push_back(
        Primitive::cylinder(at.x(), at.y(), uniform(0.15, 0.25), z0 - 0.3, canopy_centre, Label::kTrunk));
    primitives.push_back(
        Primitive::ellipsoid({at.x(), at.y(), canopy_centre}, {radius_xy, radius_xy, radius_z}, Label::kCanopy));
  }

  void trees() {
    const double end = road.length_m() - (road.closed() ? 0.5 * params.tree_spacing_m : 0.0);
    for (double side : {-1.0, 1.0}) {
      for (double s = 0.5 * params.tree_spacing_m * (side > 0 ? 1.0 : 2.0); s < end; s += params.tree_spacing_m) {
        const double at = s + uniform(-1.0, 1.0);
        if (!clear(at)) continue;
        tree(road.position(at) + side * (0.5 * params.road_width_m + uniform(2.0, 3.0)) * left(at));
      }
    }
  }

  /// Buildings along a straight stretch [s0, s1] on one side, front faces `offset` from the centreline.
  void buildings(double s0, double s1, double side, double offset) {
    double s = s0;
    while (true) {
      const double length = uniform(8.0, 14.0), depth = uniform(6.0, 10.0), height = uniform(5.0, 12.0);
      if (s + length > s1) break;
      const double mid = s + 0.5 * length;
      if (clear(s) && clear(mid) && clear(s + length)) {
        const Eigen::Vector2d c = road.position(mid) + side * (offset + 0.5 * depth) * left(mid);
        double z0 = kInf;
        for (double t : {s, mid, s + length})
          z0 = std::min(z0, terrain.height(road.position(t).x(), road.position(t).y()));
        primitives.push_back(Primitive::box({c.x(), c.y(), z0 - 0.5 + 0.5 * (height + 0.5)},
                                            {0.5 * length, 0.5 * depth, 0.5 * (height + 0.5)}, road.heading_rad(mid),
                                            Label::kBuilding));
      }
      s += length + uniform(3.0, 6.0);
    }
  }

  /// A garden wall (1.5 m above the local ground) in 4 m segments along [s0, s1].
  void wall(double s0, double s1, double side, double offset) {
    for (double s = s0; s + 4.0 <= s1; s += 4.0) {
      const double mid = s + 2.0;
      if (!clear(mid)) continue;
      const Eigen::Vector2d c = road.position(mid) + side * offset * left(mid);
      double low = kInf, high = -kInf;
      for (double t : {s, mid, s + 4.0}) {
        const Eigen::Vector2d q = road.position(t) + side * offset * left(t);
        low = std::min(low, terrain.height(q.x(), q.y()));
        high = std::max(high, terrain.height(q.x(), q.y()));
      }
      const double bottom = low - 0.3, top = high + 1.5;
      primitives.push_back(Primitive::box({c.x(), c.y(), 0.5 * (bottom + top)}, {2.0, 0.15, 0.5 * (top - bottom)},
                                          road.heading_rad(mid), Label::kWall));
    }
  }
};

void validate(const LoopSceneParams& p) {
  require_positive(p.road_width_m, "road_width_m");
  require_positive(p.tree_spacing_m, "tree_spacing_m");
  require_positive(p.tunnel_length_m, "tunnel_length_m");
  require_positive(p.tunnel_clearance_m, "tunnel_clearance_m");
  require_positive(p.bridge_clearance_m, "bridge_clearance_m");
  require_positive(p.bridge_deck_width_m, "bridge_deck_width_m");
  require_finite(p.ramp_height_m, "ramp_height_m");
  require_positive(p.ramp_length_m, "ramp_length_m");
  require_non_negative(p.ramp_plateau_m, "ramp_plateau_m");
  require_positive(p.canopy_bottom_m, "canopy_bottom_m");
  require_positive(p.grid_cell_m, "grid_cell_m");
  if (p.path == PathShape::kLoop) {
    require_positive(p.corner_radius_m, "corner_radius_m");
    require_positive(p.loop_length_m, "loop_length_m");
    require_positive(p.loop_width_m, "loop_width_m");
    const double bottom = p.loop_length_m - 2.0 * p.corner_radius_m, right = p.loop_width_m - 2.0 * p.corner_radius_m;
    if (!(bottom > 0.0) || !(right > 0.0)) fail("loop_length_m and loop_width_m must exceed 2 * corner_radius_m");
    if (p.with_ramp && bottom < 2.0 * p.ramp_length_m + p.ramp_plateau_m) {
      fail("the loop's bottom straight (loop_length_m - 2 corner_radius_m) is shorter than the ramp");
    }
    if (p.with_tunnel && right < p.tunnel_length_m) {
      fail("the loop's side straight (loop_width_m - 2 corner_radius_m) is shorter than the tunnel");
    }
  } else if (p.path == PathShape::kStraight) {
    require_positive(p.straight_length_m, "straight_length_m");
  } else {
    fail("path must be loop or straight");
  }
}

}  // namespace

SyntheticWorld make_loop_scene(const LoopSceneParams& params) {
  validate(params);
  RoadPath road;
  // Arc lengths of the ramp, tunnel and bridge; straight stretches for buildings and walls.
  double s_ramp = 0.0, s_tunnel = 0.0, s_bridge = 0.0;
  if (params.path == PathShape::kLoop) {
    const double a = 0.5 * params.loop_length_m, b = 0.5 * params.loop_width_m, r = params.corner_radius_m;
    const double long_side = params.loop_length_m - 2.0 * r, short_side = params.loop_width_m - 2.0 * r;
    const double arc = 0.5 * kPi * r, k = 1.0 / r;
    road = RoadPath({{{-a + r, -b}, 0.0, long_side, 0.0},
                     {{a - r, -b}, 0.0, arc, k},
                     {{a, -b + r}, 0.5 * kPi, short_side, 0.0},
                     {{a, b - r}, 0.5 * kPi, arc, k},
                     {{a - r, b}, kPi, long_side, 0.0},
                     {{-a + r, b}, kPi, arc, k},
                     {{-a, b - r}, 1.5 * kPi, short_side, 0.0},
                     {{-a, -b + r}, 1.5 * kPi, arc, k}},
                    true);
    s_ramp = 0.5 * long_side;
    s_tunnel = long_side + arc + 0.5 * short_side;
    s_bridge = long_side + short_side + 2.0 * arc + 0.5 * long_side;
  } else {
    road = RoadPath({{{0.0, 0.0}, 0.0, params.straight_length_m, 0.0}}, false);
    s_ramp = 0.25 * params.straight_length_m;
    s_tunnel = 0.5 * params.straight_length_m;
    s_bridge = 0.75 * params.straight_length_m;
  }

  Terrain terrain;
  std::vector<Primitive> primitives;
  SceneBuilder build{params, road, terrain, primitives, Gaussian(params.seed), {}};
  if (params.with_ramp) build.ramp(s_ramp);
  if (params.with_tunnel) build.tunnel(s_tunnel);
  if (params.with_bridge) build.bridge(s_bridge);
  const double front = 0.5 * params.road_width_m + 7.0, garden = 0.5 * params.road_width_m + 6.0;
  if (params.path == PathShape::kLoop) {
    const double r = params.corner_radius_m, arc = 0.5 * kPi * r;
    const double long_side = params.loop_length_m - 2.0 * r, short_side = params.loop_width_m - 2.0 * r;
    const double right_start = long_side + arc, top_start = right_start + short_side + arc;
    const double left_start = top_start + long_side + arc;
    if (params.with_buildings) {
      build.buildings(left_start, left_start + short_side, -1.0, front);  // outside the loop
      build.buildings(top_start, top_start + long_side, -1.0, front);
      // A block in the middle of the loop, when it fits.
      const double inner_x = params.loop_length_m - 2.0 * front, inner_y = params.loop_width_m - 2.0 * front;
      if (inner_x > 4.0 && inner_y > 4.0) {
        const double z0 = terrain.height(0.0, 0.0);
        primitives.push_back(Primitive::box({0.0, 0.0, z0 + 3.75},
                                            {std::min(10.0, 0.5 * inner_x), std::min(4.0, 0.5 * inner_y), 4.25}, 0.0,
                                            Label::kBuilding));
      }
      build.wall(0.0, long_side, -1.0, garden);
      build.wall(right_start, right_start + short_side, -1.0, garden);
    }
    terrain.hills.push_back({Eigen::Vector2d(0.0, -0.5 * params.loop_width_m - 30.0), 4.0, 15.0});
  } else {
    if (params.with_buildings) {
      build.buildings(0.0, params.straight_length_m, 1.0, front);
      build.wall(0.0, params.straight_length_m, -1.0, garden);
      build.buildings(0.0, params.straight_length_m, -1.0, front + 4.0);
    }
    terrain.hills.push_back({Eigen::Vector2d(0.5 * params.straight_length_m, 35.0), 4.0, 15.0});
  }
  if (params.with_trees) build.trees();
  return SyntheticWorld{Scene(std::move(terrain), std::move(primitives), params.grid_cell_m), road, params};
}

// ---------------------------------------------------------------------------------------------
// Trajectory

Trajectory generate_trajectory(const SyntheticWorld& world, const TrajectoryParams& params) {
  require_positive(params.scan_spacing_m, "scan_spacing_m");
  if (params.laps < 1) fail("laps must be positive, got " + std::to_string(params.laps));
  require_positive(params.mount_height_m, "mount_height_m");
  require_finite(params.lateral_offset_m, "lateral_offset_m");
  require_finite(params.start_arc_length_m, "start_arc_length_m");
  require_finite(params.yaw_bias_rad_per_m, "yaw_bias_rad_per_m");
  require_non_negative(params.yaw_random_walk_rad_per_sqrt_m, "yaw_random_walk_rad_per_sqrt_m");
  require_finite(params.translation_scale_error, "translation_scale_error");
  if (params.translation_scale_error <= -1.0) fail("translation_scale_error must exceed -1");
  require_non_negative(params.translation_random_walk_m_per_sqrt_m, "translation_random_walk_m_per_sqrt_m");
  require_non_negative(params.roll_pitch_noise_rad, "roll_pitch_noise_rad");
  const RoadPath& road = world.road;
  const Terrain& terrain = world.scene.terrain();
  const double distance = road.closed() ? params.laps * road.length_m() : road.length_m() - params.start_arc_length_m;
  if (!(distance >= 0.0)) fail("start_arc_length_m lies beyond the end of the road");
  const double count = std::floor(distance / params.scan_spacing_m + 1e-9) + 1.0;
  if (count > 1e7) fail("more than 1e7 keyframes; increase scan_spacing_m");
  const auto keyframes = static_cast<std::size_t>(count);

  Trajectory out;
  out.poses.reserve(keyframes);
  out.odometry.reserve(keyframes);
  std::vector<double> yaw(keyframes), pitch(keyframes), roll(keyframes);
  for (std::size_t k = 0; k < keyframes; ++k) {
    const double s = params.start_arc_length_m + static_cast<double>(k) * params.scan_spacing_m;
    const double heading = road.heading_rad(s);
    const Eigen::Vector2d forward(std::cos(heading), std::sin(heading)), left(-forward.y(), forward.x());
    const Eigen::Vector2d xy = road.position(s) + params.lateral_offset_m * left;
    const Eigen::Vector2d g = terrain.gradient(xy.x(), xy.y());
    // Sensor z axis on the terrain normal (-g_f, -g_l, 1): tan(pitch) = -g_f, tan(roll) = g_l cos(pitch).
    pitch[k] = -std::atan(g.dot(forward));
    roll[k] = std::atan(g.dot(left) * std::cos(pitch[k]));
    yaw[k] = heading;
    out.arc_length_m.push_back(s);
    out.poses.push_back(make_pose({xy.x(), xy.y(), terrain.height(xy.x(), xy.y()) + params.mount_height_m}, heading,
                                  pitch[k], roll[k]));
  }

  // Odometry: integrate the true relative motion with drift (see TrajectoryParams).
  Gaussian random(mix_seed(params.seed));
  double odometry_yaw = yaw[0];
  Eigen::Vector3d odometry_position = out.poses[0].topRightCorner<3, 1>();
  out.odometry.push_back(out.poses[0]);
  for (std::size_t k = 1; k < keyframes; ++k) {
    const Eigen::Vector3d previous = out.poses[k - 1].topRightCorner<3, 1>();
    const Eigen::Vector3d step_world = out.poses[k].topRightCorner<3, 1>() - previous;
    const double travelled = step_world.norm(), root = std::sqrt(travelled);
    const Eigen::Matrix3d true_heading(Eigen::AngleAxisd(yaw[k - 1], Eigen::Vector3d::UnitZ()));
    const Eigen::Matrix3d odometry_heading(Eigen::AngleAxisd(odometry_yaw, Eigen::Vector3d::UnitZ()));
    Eigen::Vector3d step =
        odometry_heading * ((1.0 + params.translation_scale_error) * (true_heading.transpose() * step_world));
    if (params.translation_random_walk_m_per_sqrt_m > 0.0) {
      for (int axis = 0; axis < 3; ++axis) step[axis] += params.translation_random_walk_m_per_sqrt_m * root * random();
    }
    odometry_position += step;
    odometry_yaw += wrap_angle(yaw[k] - yaw[k - 1]) + params.yaw_bias_rad_per_m * travelled;
    if (params.yaw_random_walk_rad_per_sqrt_m > 0.0)
      odometry_yaw += params.yaw_random_walk_rad_per_sqrt_m * root * random();
    double odometry_pitch = pitch[k], odometry_roll = roll[k];
    if (params.roll_pitch_noise_rad > 0.0) {
      odometry_pitch += params.roll_pitch_noise_rad * random();
      odometry_roll += params.roll_pitch_noise_rad * random();
    }
    out.odometry.push_back(make_pose(odometry_position, odometry_yaw, odometry_pitch, odometry_roll));
  }
  return out;
}

// ---------------------------------------------------------------------------------------------
// Sequence

SyntheticSequence::SyntheticSequence(std::shared_ptr<const SyntheticWorld> world, SensorModel sensor,
                                     Trajectory trajectory, std::uint64_t seed)
    : world_(std::move(world)), sensor_(std::move(sensor)), trajectory_(std::move(trajectory)), seed_(seed) {
  if (!world_) fail("a sequence needs a world");
  validate(sensor_);
  if (trajectory_.poses.size() != trajectory_.odometry.size()) fail("poses and odometry differ in length");
  for (const Eigen::Matrix4d& pose : trajectory_.poses) check_rigid(pose, "pose");
}

Scan SyntheticSequence::scan(std::size_t k) const {
  if (k >= size()) {
    throw std::out_of_range("scan index " + std::to_string(k) + " out of range for a sequence of " +
                            std::to_string(size()) + " scans");
  }
  return cast_scan(world_->scene, trajectory_.poses[k], sensor_, mix_seed(seed_ ^ mix_seed(k)));
}

SyntheticSequence generate_sequence(const LoopSceneParams& scene, const TrajectoryParams& trajectory,
                                    const SensorModel& sensor, std::uint64_t seed) {
  auto world = std::make_shared<const SyntheticWorld>(make_loop_scene(scene));
  Trajectory poses = generate_trajectory(*world, trajectory);
  return SyntheticSequence(std::move(world), sensor, std::move(poses), seed);
}

}  // namespace terracube::simulation
