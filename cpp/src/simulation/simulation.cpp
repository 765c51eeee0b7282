#include "terracube/simulation.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <random>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "cloud_frame.hpp"
#include "simulation_support.hpp"

namespace terracube::simulation {

using namespace support;  // NOLINT: the simulator's private helpers

namespace {

constexpr double kHitEpsilon = 1e-9;  // crossings nearer than this along a ray are the origin itself

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

Scan cast_scan(const Scene& scene, const Eigen::Matrix4d& world_T_sensor, const SensorModel& model,
               std::uint64_t seed) {
  validate(model);
  detail::check_rigid_transform(world_T_sensor, "world_T_sensor");
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

}  // namespace terracube::simulation
