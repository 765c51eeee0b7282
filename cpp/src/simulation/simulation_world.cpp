// The simulator's loop world (a road, tree rows, buildings, a bridge, a tunnel), trajectories
// along it and the scan sequences cast from them (simulation.hpp).
#include <algorithm>
#include <cmath>
#include <memory>
#include <utility>

#include "cloud_frame.hpp"
#include "simulation_support.hpp"
#include "terracube/simulation.hpp"

namespace terracube::simulation {

using namespace support;  // NOLINT: the simulator's private helpers

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
  for (const Eigen::Matrix4d& pose : trajectory_.poses) detail::check_rigid_transform(pose, "pose");
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
