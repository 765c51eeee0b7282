// Synthetic LiDAR sequences: a scene of analytic primitives with semantic labels, ray-cast scans
// of a rotating multi-beam LiDAR or a tilting 2D scanner, and a robot driving a closed loop (or a
// straight road) with ground-truth poses and drifting odometry. Tests and benchmarks use it for
// long runs with loops and exact ground truth.
//
// Design:
// - The terrain is a heightfield z = h(x, y): a base height plus ramps (trapezoidal profiles along
//   a heading, flat on top, with linear side falloff) and compact quartic hills. Rays meet it by
//   Lipschitz marching (the gap z - h never changes faster than |d_z| + S |d_xy|, S a bound on
//   |grad h|, so no crossing is skipped) followed by bisection of the bracketing step.
// - Everything else is a primitive: a box rotated about z (walls, buildings, tunnel walls and
//   ceiling, bridge deck), a vertical cylinder (trunks, pillars) or an axis-aligned ellipsoid
//   (canopies). Each carries a Label.
// - A uniform 2D grid over the primitives' xy bounds, walked cell by cell along the ray
//   (Amanatides & Woo's DDA), tests only the primitives near the ray and stops at the first cell
//   whose exit lies beyond the nearest hit found so far. Rays take the nearest surface among the
//   primitives and the terrain; intersect_brute_force() tests every primitive (a reference).
// - Scans are in the SENSOR frame (x forward, y left, z up); a ray returns a point when its first
//   surface lies in [min_range_m, max_range_m]; Gaussian noise is then added to the range.
// - Poses are world <- sensor 4x4 rigid transforms, attitude R = Rz(yaw) Ry(pitch) Rx(roll) (the
//   convention of leveling_transform() in collapse.hpp, so Ry(pitch) Rx(roll) levels a scan).
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <variant>
#include <vector>

namespace terracube::simulation {

/// Semantic label of a surface (uint8). Canopy, tunnel ceiling and bridge deck are overhangs.
enum class Label : std::uint8_t {
  kGround = 0,
  kWall = 1,
  kBuilding = 2,
  kTrunk = 3,
  kCanopy = 4,
  kTunnelWall = 5,
  kTunnelCeiling = 6,
  kBridgeDeck = 7,
  kPillar = 8,
};
inline constexpr int kNumLabels = 9;

/// A short lower-case name ("ground", "tunnel_ceiling", ...).
const char* to_string(Label label);

/// True for the labels of surfaces a ground robot can drive under (canopy, ceiling, deck).
bool is_overhang(Label label);

// ---------------------------------------------------------------------------------------------
// Terrain

/// A road ramp: up over ramp_length_m, flat for plateau_length_m, down over ramp_length_m, along
/// `heading_rad` through `center`; full height within half_width_m of that line, falling linearly
/// to 0 over side_falloff_m beyond it. h = height * p(s) * q(l) with s, l the along/across offsets.
struct Ramp {
  Eigen::Vector2d center = Eigen::Vector2d::Zero();  ///< middle of the plateau [m]
  double heading_rad = 0.0;
  double height_m = 2.0;
  double ramp_length_m = 15.0;    ///< > 0
  double plateau_length_m = 6.0;  ///< >= 0
  double half_width_m = 6.0;      ///< >= 0
  double side_falloff_m = 8.0;    ///< > 0
};

/// A compact hill h = height * (1 - r^2 / radius^2)^2 for r < radius, 0 beyond (C1 continuous).
struct Hill {
  Eigen::Vector2d center = Eigen::Vector2d::Zero();
  double height_m = 1.0;
  double radius_m = 10.0;  ///< > 0
};

/// The heightfield z = base_height_m + sum of ramps + sum of hills.
struct Terrain {
  double base_height_m = 0.0;
  std::vector<Ramp> ramps;
  std::vector<Hill> hills;

  double height(double x, double y) const;
  /// (dh/dx, dh/dy); at a kink of a ramp profile, the one-sided slope of the side s >= 0.
  Eigen::Vector2d gradient(double x, double y) const;
  /// An upper bound S of |grad h| everywhere (the sum of the features' bounds).
  double max_slope() const;
  /// Upper bound of h (base plus the positive feature heights).
  double max_height() const;
};

/// Throws std::invalid_argument naming the first bad field.
void validate(const Terrain& terrain);

/// First t > 0 with origin + t * direction on the terrain surface (direction need not be unit),
/// or +inf when there is none up to t_max; 0 when the origin is on or below the surface. Only the
/// ramps and hills whose footprint the segment [0, t_max] passes over enter the slope bound, so the
/// refined crossing can differ in the last bits between calls with different t_max: callers that
/// compare results (Scene's two casts) pass the same t_max.
double intersect_terrain(const Terrain& terrain, const Eigen::Vector3d& origin, const Eigen::Vector3d& direction,
                         double t_max);

// ---------------------------------------------------------------------------------------------
// Primitives

enum class PrimitiveKind : std::uint8_t { kBox = 0, kCylinder = 1, kEllipsoid = 2 };

/// One analytic solid. Box: centre, half extents along its own axes, rotated by yaw_rad about z.
/// Cylinder (vertical): centre (x, y, mid height), half_extents = (radius, radius, half height).
/// Ellipsoid (axis-aligned): centre, half_extents = the three radii.
struct Primitive {
  PrimitiveKind kind = PrimitiveKind::kBox;
  Label label = Label::kWall;
  Eigen::Vector3d center = Eigen::Vector3d::Zero();        ///< [m]
  Eigen::Vector3d half_extents = Eigen::Vector3d::Ones();  ///< [m], > 0
  double yaw_rad = 0.0;                                    ///< boxes only

  static Primitive box(const Eigen::Vector3d& center, const Eigen::Vector3d& half_extents, double yaw_rad, Label label);
  static Primitive cylinder(double x, double y, double radius, double z_min, double z_max, Label label);
  static Primitive ellipsoid(const Eigen::Vector3d& center, const Eigen::Vector3d& radii, Label label);
  /// xy bounds (min x, min y, max x, max y) [m].
  Eigen::Vector4d xy_bounds() const;
};

/// Throws std::invalid_argument for non-finite values or non-positive extents.
void validate(const Primitive& primitive);

/// First t > 0 (beyond 1e-9) at which origin + t * direction crosses the primitive's surface
/// (entering it, or leaving it when the origin is inside), +inf when none.
double intersect(const Primitive& primitive, const Eigen::Vector3d& origin, const Eigen::Vector3d& direction);

// ---------------------------------------------------------------------------------------------
// Scene

/// A ray's first surface.
struct RayHit {
  double range_m = std::numeric_limits<double>::infinity();  ///< +inf: no surface
  Label label = Label::kGround;
  std::int32_t primitive = -1;  ///< index into Scene::primitives(), -1 for the terrain
  bool hit() const { return range_m < std::numeric_limits<double>::infinity(); }
};

/// Terrain plus primitives, with a uniform 2D grid over the primitives' xy bounds.
class Scene {
 public:
  /// Validates everything (std::invalid_argument). grid_cell_m > 0 is the grid's cell edge.
  Scene(Terrain terrain, std::vector<Primitive> primitives, double grid_cell_m = 2.0);

  const Terrain& terrain() const { return terrain_; }
  const std::vector<Primitive>& primitives() const { return primitives_; }
  double grid_cell_m() const { return cell_m_; }

  /// Nearest surface along a unit `direction` from `origin` up to max_range_m, through the grid.
  RayHit intersect(const Eigen::Vector3d& origin, const Eigen::Vector3d& direction, double max_range_m) const;
  /// The same by testing every primitive (the reference for the grid).
  RayHit intersect_brute_force(const Eigen::Vector3d& origin, const Eigen::Vector3d& direction,
                               double max_range_m) const;

  /// Grid walk with a caller-owned mailbox (one stamp per primitive, so a primitive spanning
  /// several cells is tested once per ray); `ray_id` must differ between consecutive calls.
  RayHit intersect(const Eigen::Vector3d& origin, const Eigen::Vector3d& direction, double max_range_m,
                   std::vector<std::uint32_t>& mailbox, std::uint32_t ray_id) const;

 private:
  Terrain terrain_;
  std::vector<Primitive> primitives_;
  double cell_m_ = 2.0;
  Eigen::Vector2d grid_min_ = Eigen::Vector2d::Zero();
  int nx_ = 0, ny_ = 0;
  std::vector<std::uint32_t> cell_begin_;  // CSR offsets, nx * ny + 1
  std::vector<std::uint32_t> cell_items_;
};

// ---------------------------------------------------------------------------------------------
// Sensor models

/// A spinning multi-beam LiDAR (defaults: an Ouster OS1-64-like 64 x 1024 with +-22.5 degrees, which
/// sees ceilings and canopies overhead; KITTI's HDL-64E is -24.9 .. +2 and sees almost none): `channels` beams evenly
/// spread in elevation over [vertical_fov_min_deg, vertical_fov_max_deg], fired at `steps_per_revolution` azimuths 2 pi
/// j / steps (j = 0 first, azimuth 0 = +x, counter-clockwise).
struct RotatingLidar {
  int channels = 64;                    ///< >= 1
  double vertical_fov_min_deg = -22.5;  ///< elevation of channel 0, in [-90, 90]
  double vertical_fov_max_deg = 22.5;   ///< elevation of the last channel, >= min
  int steps_per_revolution = 1024;      ///< >= 1
  double min_range_m = 0.5;             ///< >= 0; nearer first surfaces give no return
  double max_range_m = 100.0;           ///< > min_range_m
  double range_noise_sigma_m = 0.02;    ///< Gaussian range noise [m], >= 0
};

/// A 2D scanner nodding about its y axis: each line is a fan of `beams_per_line` beams evenly
/// over [-horizontal_fov_deg / 2, +horizontal_fov_deg / 2] about +x in a plane tilted up by the
/// line's tilt angle; `lines` tilts evenly from tilt_from_deg to tilt_to_deg. Beam (a, tilt):
/// (cos tilt cos a, sin a, sin tilt cos a).
struct Tilting2DScanner {
  int beams_per_line = 541;           ///< >= 1
  double horizontal_fov_deg = 270.0;  ///< in (0, 360]
  double tilt_from_deg = -40.0;       ///< in [-90, 90]
  double tilt_to_deg = 40.0;          ///< in [-90, 90]
  int lines = 80;                     ///< >= 1
  double min_range_m = 0.3;
  double max_range_m = 60.0;
  double range_noise_sigma_m = 0.01;
};

using SensorModel = std::variant<RotatingLidar, Tilting2DScanner>;

/// Throws std::invalid_argument naming the first bad field.
void validate(const SensorModel& model);

/// Unit ray directions in the sensor frame, in firing order: RotatingLidar azimuth-major
/// (index = step * channels + channel), Tilting2DScanner line-major (index = line * beams + beam).
std::vector<Eigen::Vector3d> sensor_rays(const SensorModel& model);

/// One simulated scan in the sensor frame.
struct Scan {
  std::vector<Eigen::Vector3f> points;     ///< [m], sensor frame
  std::vector<Label> labels;               ///< one per point
  std::vector<std::uint32_t> ray_indices;  ///< index into sensor_rays(model), ascending
  std::size_t size() const { return points.size(); }
};

/// Casts every ray of `model` from world_T_sensor (a rigid 4x4, world <- sensor) and returns the
/// points in the sensor frame. The range noise comes from `seed` alone (deterministic). Throws
/// std::invalid_argument for an invalid model or a non-finite or non-rigid pose.
Scan cast_scan(const Scene& scene, const Eigen::Matrix4d& world_T_sensor, const SensorModel& model,
               std::uint64_t seed = 0);

// ---------------------------------------------------------------------------------------------
// Road and loop scene

/// A planar road centreline of straight and circular pieces, parameterised by arc length.
class RoadPath {
 public:
  struct Piece {
    Eigen::Vector2d start = Eigen::Vector2d::Zero();
    double heading_rad = 0.0;  ///< at the start
    double length_m = 0.0;
    double curvature = 0.0;  ///< 1 / radius, > 0 turns left, 0 straight
  };
  RoadPath() = default;
  RoadPath(std::vector<Piece> pieces, bool closed);

  double length_m() const { return length_; }
  bool closed() const { return closed_; }
  const std::vector<Piece>& pieces() const { return pieces_; }
  /// Position and heading at arc length s (wrapped into [0, length) when closed, clamped otherwise).
  Eigen::Vector2d position(double s) const;
  double heading_rad(double s) const;

 private:
  const Piece& piece_at(double& s) const;  // s becomes the offset within the piece
  std::vector<Piece> pieces_;
  std::vector<double> piece_start_;
  double length_ = 0.0;
  bool closed_ = false;
};

enum class PathShape : std::uint8_t { kLoop = 0, kStraight = 1 };

/// Parameters of make_loop_scene. The loop's centreline is a rounded rectangle centred at the
/// origin, driven counter-clockwise from the start of its bottom side; the ramp sits mid bottom,
/// the tunnel mid right, the bridge mid top, buildings along the left side and in the middle.
/// The straight road runs from (0, 0) along +x with the ramp, tunnel and bridge at 1/4, 1/2, 3/4.
struct LoopSceneParams {
  PathShape path = PathShape::kLoop;
  double loop_length_m = 80.0;       ///< x extent of the centreline, > 2 * corner_radius_m
  double loop_width_m = 50.0;        ///< y extent of the centreline, > 2 * corner_radius_m
  double corner_radius_m = 10.0;     ///< > 0
  double straight_length_m = 200.0;  ///< PathShape::kStraight, > 0
  double road_width_m = 6.0;         ///< > 0
  bool with_tunnel = true;
  bool with_bridge = true;
  bool with_ramp = true;
  bool with_trees = true;
  bool with_buildings = true;
  double tunnel_length_m = 16.0;
  double tunnel_clearance_m = 4.0;   ///< ground to the ceiling's underside
  double bridge_clearance_m = 5.0;   ///< ground to the deck's underside
  double bridge_deck_width_m = 6.0;  ///< along the road
  double ramp_height_m = 2.0;
  double ramp_length_m = 12.0;  ///< each of the up and down parts
  double ramp_plateau_m = 8.0;
  double tree_spacing_m = 9.0;   ///< along each roadside, > 0
  double canopy_bottom_m = 3.2;  ///< above the ground, above the robot: an overhang
  std::uint64_t seed = 7;        ///< jitter of trees and building sizes
  double grid_cell_m = 2.0;
};

/// A scene and the road a robot drives through it.
struct SyntheticWorld {
  Scene scene;
  RoadPath road;
  LoopSceneParams params;
};

/// Builds the loop (or straight) scene. Throws std::invalid_argument for bad parameters.
SyntheticWorld make_loop_scene(const LoopSceneParams& params = {});

// ---------------------------------------------------------------------------------------------
// Trajectory and odometry

/// Parameters of generate_trajectory. The drift terms act per metre travelled (d_k between
/// keyframes): yaw += yaw_bias * d + yaw_random_walk * sqrt(d) * N(0, 1); the true displacement,
/// expressed in the previous true heading, is scaled by (1 + translation_scale_error), rotated
/// by the previous odometry heading and gets translation_random_walk * sqrt(d) * N(0, 1) per
/// axis; roll and pitch are the truth plus roll_pitch_noise_rad * N(0, 1) each (IMU-like: they
/// do not accumulate). All zero: odometry == ground truth.
struct TrajectoryParams {
  double scan_spacing_m = 0.5;    ///< arc length between keyframes, > 0
  int laps = 1;                   ///< >= 1; a straight road is driven once
  double mount_height_m = 0.8;    ///< sensor above the terrain, vertically [m], > 0
  double lateral_offset_m = 0.0;  ///< left of the centreline [m]
  double start_arc_length_m = 0.0;
  double yaw_bias_rad_per_m = 2e-4;
  double yaw_random_walk_rad_per_sqrt_m = 1e-3;
  double translation_scale_error = 0.01;
  double translation_random_walk_m_per_sqrt_m = 0.0;
  double roll_pitch_noise_rad = 1e-3;
  std::uint64_t seed = 1;
};

/// Ground truth and odometry, one world <- sensor pose per keyframe.
struct Trajectory {
  std::vector<Eigen::Matrix4d> poses;
  std::vector<Eigen::Matrix4d> odometry;  ///< starts at poses[0]
  std::vector<double> arc_length_m;       ///< along the road, unwrapped (grows past a lap)
};

/// Keyframes every scan_spacing_m along the road (K = floor(laps * length / spacing) + 1 on a
/// loop, so the last lies within one spacing of the first; floor(length / spacing) + 1 on a
/// straight road). Sensor at (x, y, h(x, y) + mount_height), yaw the road heading, pitch and
/// roll from the terrain gradient: pitch = -atan(g_forward), roll = atan(g_left cos(pitch)) puts
/// the sensor's z axis on the terrain normal.
Trajectory generate_trajectory(const SyntheticWorld& world, const TrajectoryParams& params = {});

/// World, sensor, trajectory; scan(k) is cast on demand (long runs never hold all scans).
class SyntheticSequence {
 public:
  SyntheticSequence(std::shared_ptr<const SyntheticWorld> world, SensorModel sensor, Trajectory trajectory,
                    std::uint64_t seed);
  std::size_t size() const { return trajectory_.poses.size(); }
  /// Scan k cast from poses[k] with seed derived from (seed, k); std::out_of_range for k >= size.
  Scan scan(std::size_t k) const;
  const Trajectory& trajectory() const { return trajectory_; }
  const SyntheticWorld& world() const { return *world_; }
  const SensorModel& sensor() const { return sensor_; }
  std::uint64_t seed() const { return seed_; }

 private:
  std::shared_ptr<const SyntheticWorld> world_;
  SensorModel sensor_;
  Trajectory trajectory_;
  std::uint64_t seed_ = 0;
};

/// make_loop_scene + generate_trajectory + a SyntheticSequence.
SyntheticSequence generate_sequence(const LoopSceneParams& scene, const TrajectoryParams& trajectory,
                                    const SensorModel& sensor, std::uint64_t seed = 0);

}  // namespace terracube::simulation
