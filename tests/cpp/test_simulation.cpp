#include <gtest/gtest.h>
#include <terracube/collapse.hpp>
#include <terracube/simulation.hpp>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <stdexcept>
#include <vector>

namespace terracube::simulation {
namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kInf = std::numeric_limits<double>::infinity();

Eigen::Matrix4d pose_at(const Eigen::Vector3d& position, double yaw = 0.0, double pitch = 0.0, double roll = 0.0) {
  Eigen::Matrix4d t = Eigen::Matrix4d::Identity();
  t.topLeftCorner<3, 3>() =
      (Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(pitch, Eigen::Vector3d::UnitY()) *
       Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()))
          .toRotationMatrix();
  t.topRightCorner<3, 1>() = position;
  return t;
}

Terrain flat(double height) {
  Terrain terrain;
  terrain.base_height_m = height;
  return terrain;
}

double yaw_of(const Eigen::Matrix4d& pose) { return std::atan2(pose(1, 0), pose(0, 0)); }

// --- single rays against analytic answers ------------------------------------------------------

TEST(RayCasting, RayStraightDownMeetsFlatGroundAtItsHeight) {
  const Scene scene(flat(1.5), {});
  const RayHit hit = scene.intersect({3.0, 4.0, 10.0}, {0.0, 0.0, -1.0}, 100.0);
  ASSERT_TRUE(hit.hit());
  EXPECT_NEAR(hit.range_m, 8.5, 1e-9);
  EXPECT_EQ(hit.label, Label::kGround);
  EXPECT_EQ(hit.primitive, -1);
  // Upward and level rays above flat ground never meet it; the range limit applies.
  EXPECT_FALSE(scene.intersect({0, 0, 2}, {0, 0, 1}, 100.0).hit());
  EXPECT_FALSE(scene.intersect({0, 0, 2}, {1, 0, 0}, 100.0).hit());
  EXPECT_FALSE(scene.intersect({3.0, 4.0, 10.0}, {0.0, 0.0, -1.0}, 8.0).hit());
}

TEST(RayCasting, HorizontalRayMeetsWallAtItsDistance) {
  for (const double yaw_deg : {0.0, 30.0, 135.0}) {
    const double yaw = yaw_deg * kPi / 180.0;
    const Eigen::Vector3d u(std::cos(yaw), std::sin(yaw), 0.0);
    // A wall 1 m thick whose near face is 9.5 m away along u, rotated with u.
    const Scene scene(flat(0.0),
                      {Primitive::box(10.0 * u + Eigen::Vector3d(0, 0, 2), {0.5, 5.0, 2.0}, yaw, Label::kWall)});
    const RayHit hit = scene.intersect({0, 0, 1}, u, 100.0);
    ASSERT_TRUE(hit.hit());
    EXPECT_NEAR(hit.range_m, 9.5, 1e-9) << yaw_deg;
    EXPECT_EQ(hit.label, Label::kWall);
    // 20 degrees off the face normal: 9.5 / cos(20 deg).
    const double off = 20.0 * kPi / 180.0;
    const Eigen::Vector3d oblique(std::cos(yaw + off), std::sin(yaw + off), 0.0);
    EXPECT_NEAR(scene.intersect({0, 0, 1}, oblique, 100.0).range_m, 9.5 / std::cos(off), 1e-9);
    // Over the wall (top at 4 m) the ray passes.
    EXPECT_FALSE(scene.intersect({0, 0, 4.5}, u, 100.0).hit());
  }
}

TEST(RayCasting, CylinderSideAndCap) {
  const Primitive trunk = Primitive::cylinder(5.0, 0.0, 0.5, 0.0, 3.0, Label::kTrunk);
  const Scene scene(flat(-1.0), {trunk});
  EXPECT_NEAR(scene.intersect({0, 0, 1}, {1, 0, 0}, 100).range_m, 4.5, 1e-9);
  // Off-centre by 0.3: x = 5 - sqrt(0.5^2 - 0.3^2) = 4.6.
  EXPECT_NEAR(scene.intersect({0, 0.3, 1}, {1, 0, 0}, 100).range_m, 4.6, 1e-9);
  // From above onto the top cap at z = 3.
  const RayHit cap = scene.intersect({5.0, 0.2, 10.0}, {0, 0, -1}, 100);
  EXPECT_NEAR(cap.range_m, 7.0, 1e-9);
  EXPECT_EQ(cap.label, Label::kTrunk);
  // Above the cylinder the ray flies on (and meets nothing: the ground is below).
  EXPECT_FALSE(scene.intersect({0, 0, 3.5}, {1, 0, 0}, 100).hit());
  // Passing beside it (|y| > r), it misses.
  EXPECT_EQ(intersect(trunk, {0, 0.6, 1}, {1, 0, 0}), kInf);
  // From inside, the first crossing is the way out.
  EXPECT_NEAR(intersect(trunk, {5, 0, 1}, {1, 0, 0}), 0.5, 1e-12);
}

TEST(RayCasting, EllipsoidAndSphere) {
  const Primitive canopy = Primitive::ellipsoid({0, 0, 5}, {2, 3, 1}, Label::kCanopy);
  EXPECT_NEAR(intersect(canopy, {10, 0, 5}, {-1, 0, 0}), 8.0, 1e-12);
  EXPECT_NEAR(intersect(canopy, {0, 10, 5}, {0, -1, 0}), 7.0, 1e-12);
  EXPECT_NEAR(intersect(canopy, {0, 0, 0}, {0, 0, 1}), 4.0, 1e-12);
  // Oblique ray from (-10, 1, 5) along (1, 0, 0): x^2/4 + 1/9 = 1 -> x = -2 sqrt(8/9).
  EXPECT_NEAR(intersect(canopy, {-10, 1, 5}, {1, 0, 0}), 10.0 - 2.0 * std::sqrt(8.0 / 9.0), 1e-12);
  EXPECT_EQ(intersect(canopy, {-10, 3.1, 5}, {1, 0, 0}), kInf);
  // A sphere of radius 2 at distance 10 along a diagonal.
  const Eigen::Vector3d u = Eigen::Vector3d(1, 2, 2).normalized();
  const Primitive sphere = Primitive::ellipsoid(10.0 * u, {2, 2, 2}, Label::kCanopy);
  EXPECT_NEAR(intersect(sphere, {0, 0, 0}, u), 8.0, 1e-12);
}

TEST(RayCasting, SlopeIntersectionMatchesTheAnalyticPlane) {
  Terrain terrain;
  Ramp ramp;
  ramp.center = {0.0, 0.0};
  ramp.heading_rad = 0.0;
  ramp.height_m = 3.0;
  ramp.ramp_length_m = 15.0;
  ramp.plateau_length_m = 6.0;
  ramp.half_width_m = 100.0;
  ramp.side_falloff_m = 10.0;
  terrain.ramps.push_back(ramp);
  // On the rising part x in [-18, -3] the terrain is the plane z = 0.2 (x + 18).
  EXPECT_NEAR(terrain.height(-10.0, 4.0), 1.6, 1e-12);
  EXPECT_NEAR(terrain.gradient(-10.0, 4.0).x(), 0.2, 1e-12);
  EXPECT_NEAR(terrain.gradient(-10.0, 4.0).y(), 0.0, 1e-12);
  EXPECT_NEAR(terrain.height(0.0, 0.0), 3.0, 1e-12);   // plateau
  EXPECT_NEAR(terrain.height(10.0, 0.0), 1.6, 1e-12);  // falling part, mirrored
  EXPECT_NEAR(terrain.height(30.0, 0.0), 0.0, 1e-12);
  const Scene scene(terrain, {});
  const Eigen::Vector3d origin(-15.0, 1.0, 5.0);
  for (const Eigen::Vector3d& d : {Eigen::Vector3d(1, 0, -1).normalized(), Eigen::Vector3d(1, 0.3, -0.6).normalized(),
                                   Eigen::Vector3d(0, 0, -1), Eigen::Vector3d(-0.2, 0.1, -1).normalized()}) {
    // origin.z + t d.z = 0.2 (origin.x + t d.x + 18)
    const double expected = (origin.z() - 0.2 * (origin.x() + 18.0)) / (0.2 * d.x() - d.z());
    const RayHit hit = scene.intersect(origin, d, 100.0);
    ASSERT_TRUE(hit.hit());
    EXPECT_NEAR(hit.range_m, expected, 1e-7) << d.transpose();
  }
}

TEST(RayCasting, RayUnderTheBridgeDeckMeetsTheGroundBeyond) {
  const Primitive deck = Primitive::box({20, 0, 5.4}, {3, 10, 0.4}, 0.0, Label::kBridgeDeck);
  const Scene scene(flat(0.0), {deck});
  // Slightly down from 1 m: under the deck (z = 0.6 at x = 20) to the ground at x = 50.
  const Eigen::Vector3d down = Eigen::Vector3d(1, 0, -0.02).normalized();
  const RayHit ground = scene.intersect({0, 0, 1}, down, 100);
  ASSERT_TRUE(ground.hit());
  EXPECT_EQ(ground.label, Label::kGround);
  EXPECT_NEAR(ground.range_m, 50.0 * std::sqrt(1.0 + 0.02 * 0.02), 1e-7);
  // Steeper up: the deck's near face at x = 17 (z = 5.25 lies within [5, 5.8]).
  const Eigen::Vector3d up = Eigen::Vector3d(1, 0, 0.25).normalized();
  const RayHit face = scene.intersect({0, 0, 1}, up, 100);
  EXPECT_EQ(face.label, Label::kBridgeDeck);
  EXPECT_NEAR(face.range_m, 17.0 * std::sqrt(1.0 + 0.25 * 0.25), 1e-9);
  // Straight up from under the deck: its underside at 5 m.
  EXPECT_NEAR(scene.intersect({20, 3, 1}, {0, 0, 1}, 100).range_m, 4.0, 1e-9);
}

TEST(RayCasting, NearestHitWinsWhenPrimitivesOverlap) {
  const Primitive far_wall = Primitive::box({12, 0, 2}, {2, 4, 2}, 0.0, Label::kBuilding);  // near face x = 10
  const Primitive near_wall = Primitive::box({9.5, 0, 1}, {0.5, 1, 1}, 0.0, Label::kWall);  // x = 9, inside far
  const Primitive trunk = Primitive::cylinder(5, 0, 0.3, 0, 4, Label::kTrunk);
  const Primitive canopy = Primitive::ellipsoid({5, 0, 4.5}, {2, 2, 1.2}, Label::kCanopy);
  for (const bool reversed : {false, true}) {
    std::vector<Primitive> primitives = {far_wall, near_wall, trunk, canopy};
    if (reversed) std::reverse(primitives.begin(), primitives.end());
    const Scene scene(flat(0), primitives);
    EXPECT_EQ(scene.intersect({0, 3, 1}, {1, 0, 0}, 100).label, Label::kBuilding);  // beside the small wall
    EXPECT_NEAR(scene.intersect({0, 3, 1}, {1, 0, 0}, 100).range_m, 10.0, 1e-9);
    EXPECT_EQ(scene.intersect({0, 0.5, 1}, {1, 0, 0}, 100).label, Label::kWall);  // the nearer box
    EXPECT_NEAR(scene.intersect({0, 0.5, 1}, {1, 0, 0}, 100).range_m, 9.0, 1e-9);
    EXPECT_EQ(scene.intersect({0, 0, 1}, {1, 0, 0}, 100).label, Label::kTrunk);     // trunk before walls
    EXPECT_EQ(scene.intersect({0, 0, 4.5}, {1, 0, 0}, 100).label, Label::kCanopy);  // canopy hides trunk
    EXPECT_NEAR(scene.intersect({0, 0, 4.5}, {1, 0, 0}, 100).range_m, 3.0, 1e-9);
    // The ground in front of everything.
    EXPECT_EQ(scene.intersect({0, 0, 1}, Eigen::Vector3d(1, 0, -1).normalized(), 100).label, Label::kGround);
  }
}

// --- the grid against a brute-force cast written here -------------------------------------------

/// Independent reference: every ray direction from the sensor's parameters, every primitive
/// tested; the same tie rule as documented (nearest, then lowest index; the terrain, marched up to
/// max_range_m, only when strictly nearer).
Scan brute_force_scan(const Scene& scene, const Eigen::Matrix4d& world_T_sensor, const RotatingLidar& lidar) {
  Scan scan;
  const Eigen::Matrix3d r = world_T_sensor.topLeftCorner<3, 3>();
  const Eigen::Vector3d origin = world_T_sensor.topRightCorner<3, 1>();
  for (int j = 0; j < lidar.steps_per_revolution; ++j) {
    const double azimuth = 2.0 * kPi * j / lidar.steps_per_revolution;
    for (int c = 0; c < lidar.channels; ++c) {
      const double elevation = (lidar.vertical_fov_min_deg +
                                (lidar.vertical_fov_max_deg - lidar.vertical_fov_min_deg) * c / (lidar.channels - 1)) *
                               kPi / 180.0;
      const Eigen::Vector3d ray(std::cos(elevation) * std::cos(azimuth), std::cos(elevation) * std::sin(azimuth),
                                std::sin(elevation));
      const Eigen::Vector3d d = r * ray;
      double best = kInf;
      Label label = Label::kGround;
      for (const Primitive& primitive : scene.primitives()) {
        const double t = intersect(primitive, origin, d);
        if (t < best) {
          best = t;
          label = primitive.label;
        }
      }
      const double ground = intersect_terrain(scene.terrain(), origin, d, lidar.max_range_m);
      if (ground < best) {
        best = ground;
        label = Label::kGround;
      }
      if (best > lidar.max_range_m || best < lidar.min_range_m) continue;
      scan.points.push_back((best * ray).cast<float>());
      scan.labels.push_back(label);
      scan.ray_indices.push_back(static_cast<std::uint32_t>(j * lidar.channels + c));
    }
  }
  return scan;
}

TEST(RayCasting, GridWalkGivesTheBruteForceScanExactly) {
  const SyntheticWorld world = make_loop_scene();
  ASSERT_GT(world.scene.primitives().size(), 100u);
  TrajectoryParams tp;
  tp.scan_spacing_m = 7.0;
  const Trajectory trajectory = generate_trajectory(world, tp);
  RotatingLidar lidar;
  lidar.steps_per_revolution = 256;
  lidar.range_noise_sigma_m = 0.0;
  std::size_t compared = 0;
  for (std::size_t k = 0; k < trajectory.poses.size(); k += 4) {
    const Scan fast = cast_scan(world.scene, trajectory.poses[k], lidar, 3);
    const Scan reference = brute_force_scan(world.scene, trajectory.poses[k], lidar);
    ASSERT_EQ(fast.size(), reference.size()) << "keyframe " << k;
    ASSERT_GT(fast.size(), 5000u);
    for (std::size_t i = 0; i < fast.size(); ++i) {
      ASSERT_EQ(fast.ray_indices[i], reference.ray_indices[i]);
      ASSERT_EQ(fast.points[i], reference.points[i]) << "keyframe " << k << " ray " << fast.ray_indices[i];
      ASSERT_EQ(fast.labels[i], reference.labels[i]);
    }
    compared += fast.size();
  }
  EXPECT_GT(compared, 50000u);
  // A full 64 x 1024 scan at a pose off the road, against Scene::intersect_brute_force.
  const Eigen::Matrix4d pose = pose_at({-10.0, 12.0, 1.0}, 0.4, 0.05, -0.03);
  const Scan full = cast_scan(world.scene, pose, RotatingLidar{}, 9);
  const std::vector<Eigen::Vector3d> rays = sensor_rays(RotatingLidar{});
  std::size_t hits = 0;
  for (std::size_t i = 0; i < rays.size(); ++i) {
    const RayHit slow =
        world.scene.intersect_brute_force(pose.topRightCorner<3, 1>(), pose.topLeftCorner<3, 3>() * rays[i], 100.0);
    const RayHit fast = world.scene.intersect(pose.topRightCorner<3, 1>(), pose.topLeftCorner<3, 3>() * rays[i], 100.0);
    ASSERT_EQ(slow.range_m, fast.range_m) << i;
    ASSERT_EQ(slow.primitive, fast.primitive) << i;
    hits += slow.hit() && slow.range_m >= 0.5;
  }
  EXPECT_EQ(full.size(), hits);
}

// --- sensor geometry and noise --------------------------------------------------------------------

TEST(Sensors, RotatingLidarRaysAndChannelElevations) {
  RotatingLidar lidar;
  lidar.channels = 16;
  lidar.vertical_fov_min_deg = -15.0;
  lidar.vertical_fov_max_deg = 15.0;
  lidar.steps_per_revolution = 360;
  const std::vector<Eigen::Vector3d> rays = sensor_rays(lidar);
  ASSERT_EQ(rays.size(), 16u * 360u);
  for (int j = 0; j < 360; j += 7) {
    for (int c = 0; c < 16; ++c) {
      const Eigen::Vector3d& ray = rays[static_cast<std::size_t>(j) * 16 + c];
      EXPECT_NEAR(ray.norm(), 1.0, 1e-12);
      EXPECT_NEAR(std::atan2(ray.z(), ray.head<2>().norm()) * 180.0 / kPi, -15.0 + 2.0 * c, 1e-9);
      EXPECT_NEAR(std::remainder(std::atan2(ray.y(), ray.x()) * 180.0 / kPi - j, 360.0), 0.0, 1e-9);
    }
  }
  // Inside a closed room every ray returns a point.
  const Scene room(flat(-2.0), {Primitive::box({0, 0, 1}, {6, 5, 4}, 0.3, Label::kBuilding)});
  EXPECT_EQ(cast_scan(room, pose_at({1, 1, 0}), lidar, 0).size(), rays.size());
}

TEST(Sensors, TiltingScannerLinesLieInTiltedPlanes) {
  Tilting2DScanner scanner;
  scanner.beams_per_line = 181;
  scanner.horizontal_fov_deg = 180.0;
  scanner.tilt_from_deg = -30.0;
  scanner.tilt_to_deg = 30.0;
  scanner.lines = 13;
  const std::vector<Eigen::Vector3d> rays = sensor_rays(scanner);
  ASSERT_EQ(rays.size(), 181u * 13u);
  for (int line = 0; line < 13; ++line) {
    const double tilt = (-30.0 + 5.0 * line) * kPi / 180.0;
    const Eigen::Vector3d normal(-std::sin(tilt), 0.0, std::cos(tilt));  // of the tilted scan plane
    const Eigen::Vector3d& centre = rays[static_cast<std::size_t>(line) * 181 + 90];
    EXPECT_NEAR((centre - Eigen::Vector3d(std::cos(tilt), 0, std::sin(tilt))).norm(), 0.0, 1e-12);
    for (int beam = 0; beam < 181; ++beam) {
      const Eigen::Vector3d& ray = rays[static_cast<std::size_t>(line) * 181 + beam];
      EXPECT_NEAR(ray.dot(normal), 0.0, 1e-12);
      EXPECT_NEAR(ray.norm(), 1.0, 1e-12);
      EXPECT_NEAR(std::asin(std::clamp(ray.y(), -1.0, 1.0)) * 180.0 / kPi, -90.0 + beam, 1e-9);  // in-plane angle
    }
  }
  // The tilting scanner looking at a wall 5 m ahead: its points have x = 5 (sensor frame, no noise).
  scanner.range_noise_sigma_m = 0.0;
  scanner.horizontal_fov_deg = 60.0;
  const Scene wall(flat(-10.0), {Primitive::box({5.5, 0, 0}, {0.5, 50, 50}, 0.0, Label::kWall)});
  const Scan scan = cast_scan(wall, Eigen::Matrix4d::Identity(), scanner, 0);
  EXPECT_EQ(scan.size(), 181u * 13u);
  for (const Eigen::Vector3f& p : scan.points) EXPECT_NEAR(p.x(), 5.0f, 1e-5f);
}

TEST(Sensors, RangeNoiseHasZeroMeanAndTheConfiguredSigma) {
  // From the centre of a sphere of radius 20 every ray leaves it at range 20.
  const Scene bubble(flat(-100.0), {Primitive::ellipsoid({0, 0, 0}, {20, 20, 20}, Label::kBuilding)});
  RotatingLidar lidar;
  lidar.range_noise_sigma_m = 0.05;
  const Scan scan = cast_scan(bubble, Eigen::Matrix4d::Identity(), lidar, 11);
  ASSERT_EQ(scan.size(), 64u * 1024u);
  double sum = 0.0, sum2 = 0.0;
  for (const Eigen::Vector3f& p : scan.points) {
    const double e = p.cast<double>().norm() - 20.0;
    sum += e;
    sum2 += e * e;
  }
  const double n = static_cast<double>(scan.size()), mean = sum / n, sd = std::sqrt(sum2 / n - mean * mean);
  EXPECT_LT(std::abs(mean), 4.0 * 0.05 / std::sqrt(n));  // 4 standard errors
  EXPECT_NEAR(sd, 0.05, 0.05 * 0.02);                    // ~7 standard errors of sd
  // The same seed repeats the scan bit for bit; another seed differs.
  const Scan again = cast_scan(bubble, Eigen::Matrix4d::Identity(), lidar, 11);
  const Scan other = cast_scan(bubble, Eigen::Matrix4d::Identity(), lidar, 12);
  EXPECT_EQ(again.points, scan.points);
  EXPECT_NE(other.points, scan.points);
  // Without noise every range is exactly 20 (float rounding).
  lidar.range_noise_sigma_m = 0.0;
  for (const Eigen::Vector3f& p : cast_scan(bubble, Eigen::Matrix4d::Identity(), lidar, 11).points) {
    EXPECT_NEAR(p.norm(), 20.0f, 2e-5f);
  }
}

TEST(Sensors, BadInputRaisesNamingTheProblem) {
  const Scene scene(flat(0), {});
  const auto message = [&](const SensorModel& model, const Eigen::Matrix4d& pose) -> std::string {
    try {
      cast_scan(scene, pose, model, 0);
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
    return "no exception";
  };
  const Eigen::Matrix4d identity = Eigen::Matrix4d::Identity();
  RotatingLidar lidar;
  lidar.channels = 0;
  EXPECT_NE(message(lidar, identity).find("channels"), std::string::npos);
  lidar = {};
  lidar.steps_per_revolution = -3;
  EXPECT_NE(message(lidar, identity).find("steps_per_revolution"), std::string::npos);
  lidar = {};
  lidar.max_range_m = 0.0;
  EXPECT_NE(message(lidar, identity).find("max_range_m"), std::string::npos);
  lidar = {};
  lidar.min_range_m = -1.0;
  EXPECT_NE(message(lidar, identity).find("min_range_m"), std::string::npos);
  lidar = {};
  lidar.min_range_m = 50.0;
  lidar.max_range_m = 50.0;
  EXPECT_NE(message(lidar, identity).find("below max_range_m"), std::string::npos);
  lidar = {};
  lidar.range_noise_sigma_m = std::nan("");
  EXPECT_NE(message(lidar, identity).find("range_noise_sigma_m"), std::string::npos);
  lidar = {};
  lidar.vertical_fov_min_deg = 10;
  lidar.vertical_fov_max_deg = -10;
  EXPECT_NE(message(lidar, identity).find("vertical_fov"), std::string::npos);
  Tilting2DScanner scanner;
  scanner.lines = 0;
  EXPECT_NE(message(scanner, identity).find("lines"), std::string::npos);
  scanner = {};
  scanner.beams_per_line = 0;
  EXPECT_NE(message(scanner, identity).find("beams_per_line"), std::string::npos);
  scanner = {};
  scanner.horizontal_fov_deg = 0;
  EXPECT_NE(message(scanner, identity).find("horizontal_fov_deg"), std::string::npos);
  Eigen::Matrix4d nan_pose = identity;
  nan_pose(0, 3) = std::nan("");
  EXPECT_NE(message(RotatingLidar{}, nan_pose).find("NaN"), std::string::npos);
  Eigen::Matrix4d scaled = identity;
  scaled(1, 1) = 1.1;
  EXPECT_NE(message(RotatingLidar{}, scaled).find("rigid"), std::string::npos);
  Eigen::Matrix4d mirrored = identity;
  mirrored(2, 2) = -1.0;
  EXPECT_NE(message(RotatingLidar{}, mirrored).find("rigid"), std::string::npos);
  EXPECT_THROW(Scene(flat(0), {}, 0.0), std::invalid_argument);
  EXPECT_THROW(Scene(flat(std::nan("")), {}), std::invalid_argument);
  EXPECT_THROW(Scene(flat(0), {Primitive::box({0, 0, 0}, {1, 0, 1}, 0, Label::kWall)}), std::invalid_argument);
  LoopSceneParams bad;
  bad.loop_length_m = 15.0;
  EXPECT_THROW(make_loop_scene(bad), std::invalid_argument);
  bad = {};
  bad.road_width_m = -1.0;
  EXPECT_THROW(make_loop_scene(bad), std::invalid_argument);
  const SyntheticWorld world = make_loop_scene();
  TrajectoryParams tp;
  tp.scan_spacing_m = 0.0;
  EXPECT_THROW(generate_trajectory(world, tp), std::invalid_argument);
  tp = {};
  tp.laps = 0;
  EXPECT_THROW(generate_trajectory(world, tp), std::invalid_argument);
}

// --- trajectory and odometry ---------------------------------------------------------------------

TrajectoryParams exact_odometry() {
  TrajectoryParams tp;
  tp.yaw_bias_rad_per_m = 0.0;
  tp.yaw_random_walk_rad_per_sqrt_m = 0.0;
  tp.translation_scale_error = 0.0;
  tp.translation_random_walk_m_per_sqrt_m = 0.0;
  tp.roll_pitch_noise_rad = 0.0;
  return tp;
}

TEST(Trajectory, LoopClosesWithEvenSpacingAtMountHeight) {
  const SyntheticWorld world = make_loop_scene();
  const double r = 10.0, length = 2 * (60.0 + 30.0) + 2 * kPi * r;  // default rounded rectangle
  EXPECT_NEAR(world.road.length_m(), length, 1e-9);
  for (const int laps : {1, 2}) {
    TrajectoryParams tp;
    tp.laps = laps;
    const Trajectory t = generate_trajectory(world, tp);
    ASSERT_EQ(t.poses.size(), static_cast<std::size_t>(std::floor(laps * length / 0.5)) + 1);
    const Eigen::Vector3d first = t.poses.front().topRightCorner<3, 1>(), last = t.poses.back().topRightCorner<3, 1>();
    EXPECT_LE((last - first).norm(), 0.5 + 1e-9);
    EXPECT_GT((last - first).norm(), 0.0);
    for (std::size_t k = 0; k < t.poses.size(); ++k) {
      const Eigen::Vector3d p = t.poses[k].topRightCorner<3, 1>();
      EXPECT_NEAR(p.z() - world.scene.terrain().height(p.x(), p.y()), 0.8, 1e-12);
      if (k > 0) {
        const double chord = (p.head<2>() - t.poses[k - 1].topRightCorner<2, 1>()).norm();
        EXPECT_LE(chord, 0.5 + 1e-9);
        EXPECT_GE(chord, 2.0 * r * std::sin(0.25 / r) - 1e-9);  // chord of 0.5 m of arc on a corner
      }
    }
  }
}

TEST(Trajectory, RollAndPitchFollowTheRamp) {
  const SyntheticWorld world = make_loop_scene();
  TrajectoryParams tp = exact_odometry();
  tp.lateral_offset_m = 1.5;
  const Trajectory t = generate_trajectory(world, tp);
  // Bottom straight, heading +x from x = -30; the ramp's plateau is centred at x = 0, 2 m high,
  // rising over x in [-16, -4]: slope 2/12 -> pitch = -atan(1/6), no roll (within the flat band).
  const double slope = 2.0 / 12.0;
  int checked = 0;
  for (std::size_t k = 0; k < t.poses.size(); ++k) {
    const Eigen::Vector3d p = t.poses[k].topRightCorner<3, 1>();
    if (t.arc_length_m[k] > 60.0) break;
    const Eigen::Matrix3d r = t.poses[k].topLeftCorner<3, 3>();
    if (p.x() > -15.5 && p.x() < -4.5) {
      EXPECT_NEAR(p.z() - 0.8, slope * (p.x() + 16.0), 1e-9);
      const Eigen::Vector3d normal = Eigen::Vector3d(-slope, 0.0, 1.0).normalized();
      EXPECT_NEAR(r.col(2).dot(normal), 1.0, 1e-12);  // sensor z on the terrain normal
      EXPECT_NEAR(std::asin(-r(2, 0)), -std::atan(slope), 1e-12);
      EXPECT_NEAR(r(2, 1), 0.0, 1e-12);
      ++checked;
    } else if (p.x() > 5.5 && p.x() < 14.5) {
      EXPECT_NEAR(std::asin(-r(2, 0)), std::atan(slope), 1e-12);  // going down
      ++checked;
    } else if (p.x() < -18.0 || p.x() > 18.0) {
      EXPECT_NEAR((r - Eigen::Matrix3d::Identity()).norm(), 0.0, 1e-12);  // flat, heading +x
    }
  }
  EXPECT_GT(checked, 35);
  // Beside the flat band (on the side falloff) the sensor rolls with the lateral slope.
  tp.lateral_offset_m = 0.5 * 6.0 + 2.0 + 3.0;  // 3 m into the falloff, on the plateau
  const Trajectory side = generate_trajectory(world, tp);
  for (std::size_t k = 0; k < side.poses.size() && side.arc_length_m[k] < 60.0; ++k) {
    const Eigen::Vector3d p = side.poses[k].topRightCorner<3, 1>();
    if (std::abs(p.x()) > 3.5) continue;
    const Eigen::Vector3d normal = Eigen::Vector3d(0.0, 2.0 / 8.0, 1.0).normalized();  // falling to +y (left)
    EXPECT_NEAR(side.poses[k].col(2).head<3>().dot(normal), 1.0, 1e-12);
  }
}

TEST(Trajectory, OdometryWithoutNoiseIsTheGroundTruth) {
  const SyntheticWorld world = make_loop_scene();
  TrajectoryParams tp = exact_odometry();
  tp.laps = 2;
  const Trajectory t = generate_trajectory(world, tp);
  for (std::size_t k = 0; k < t.poses.size(); ++k) {
    ASSERT_LT((t.odometry[k] - t.poses[k]).cwiseAbs().maxCoeff(), 1e-9) << k;
  }
}

TEST(Trajectory, DriftGrowsWithDistanceAsParameterised) {
  LoopSceneParams straight;
  straight.path = PathShape::kStraight;
  const SyntheticWorld world = make_loop_scene(straight);
  // Scale error alone: on a straight road the odometry is the truth stretched about the start.
  TrajectoryParams tp = exact_odometry();
  tp.translation_scale_error = 0.02;
  Trajectory t = generate_trajectory(world, tp);
  const Eigen::Vector3d start = t.poses[0].topRightCorner<3, 1>();
  for (std::size_t k = 0; k < t.poses.size(); ++k) {
    const Eigen::Vector3d truth = t.poses[k].topRightCorner<3, 1>();
    EXPECT_NEAR((t.odometry[k].topRightCorner<3, 1>() - truth).norm(), 0.02 * (truth - start).norm(), 1e-9);
    EXPECT_LT((t.odometry[k].topLeftCorner<3, 3>() - t.poses[k].topLeftCorner<3, 3>()).norm(), 1e-12);
  }
  // Yaw bias alone: the heading error is bias * distance travelled.
  tp = exact_odometry();
  tp.yaw_bias_rad_per_m = 1e-3;
  t = generate_trajectory(world, tp);
  double travelled = 0.0;
  for (std::size_t k = 1; k < t.poses.size(); ++k) {
    travelled += (t.poses[k].topRightCorner<3, 1>() - t.poses[k - 1].topRightCorner<3, 1>()).norm();
    EXPECT_NEAR(std::remainder(yaw_of(t.odometry[k]) - yaw_of(t.poses[k]), 2 * kPi), 1e-3 * travelled, 1e-9);
  }
  // Random walk alone: the variance of the final heading error is sigma^2 * distance (200 seeds).
  tp = exact_odometry();
  tp.yaw_random_walk_rad_per_sqrt_m = 2e-3;
  double sum2 = 0.0, distance = 0.0;
  const int seeds = 200;
  for (int seed = 0; seed < seeds; ++seed) {
    tp.seed = static_cast<std::uint64_t>(seed);
    t = generate_trajectory(world, tp);
    const double e = std::remainder(yaw_of(t.odometry.back()) - yaw_of(t.poses.back()), 2 * kPi);
    sum2 += e * e;
    if (seed == 0) {
      for (std::size_t k = 1; k < t.poses.size(); ++k) {
        distance += (t.poses[k].topRightCorner<3, 1>() - t.poses[k - 1].topRightCorner<3, 1>()).norm();
      }
    }
  }
  const double ratio = (sum2 / seeds) / (2e-3 * 2e-3 * distance);
  EXPECT_GT(ratio, 0.7);
  EXPECT_LT(ratio, 1.35);
  // Roll/pitch noise does not accumulate (IMU-like).
  tp = exact_odometry();
  tp.roll_pitch_noise_rad = 1e-3;
  t = generate_trajectory(world, tp);
  double largest = 0.0;
  for (std::size_t k = 0; k < t.poses.size(); ++k) {
    const Eigen::Matrix3d delta = t.poses[k].topLeftCorner<3, 3>().transpose() * t.odometry[k].topLeftCorner<3, 3>();
    largest = std::max(largest, Eigen::AngleAxisd(delta).angle());
  }
  EXPECT_GT(largest, 1e-3);
  EXPECT_LT(largest, 7e-3);
  // Seeded: the same seed repeats, another differs.
  tp = TrajectoryParams{};
  const Trajectory a = generate_trajectory(world, tp), b = generate_trajectory(world, tp);
  tp.seed = 99;
  const Trajectory c = generate_trajectory(world, tp);
  EXPECT_EQ(a.odometry.back(), b.odometry.back());
  EXPECT_NE(a.odometry.back(), c.odometry.back());
}

TEST(Sequence, CastsScansOnDemandDeterministically) {
  RotatingLidar lidar;
  lidar.channels = 16;
  lidar.steps_per_revolution = 256;
  TrajectoryParams tp;
  tp.scan_spacing_m = 3.0;
  const SyntheticSequence sequence = generate_sequence(LoopSceneParams{}, tp, lidar, 5);
  ASSERT_EQ(sequence.size(), sequence.trajectory().poses.size());
  const Scan a = sequence.scan(3), b = sequence.scan(3), c = sequence.scan(4);
  EXPECT_EQ(a.points, b.points);
  EXPECT_NE(a.points, c.points);
  // Noise-free, scan k is cast_scan from poses[k].
  lidar.range_noise_sigma_m = 0.0;
  const SyntheticSequence exact = generate_sequence(LoopSceneParams{}, tp, lidar, 5);
  EXPECT_EQ(exact.scan(7).points, cast_scan(exact.world().scene, exact.trajectory().poses[7], lidar, 0).points);
  EXPECT_THROW(sequence.scan(sequence.size()), std::out_of_range);
}

// --- the library on simulated scans: collapsible cubes remove the overhangs --------------------

struct Rates {
  std::size_t overhang = 0, overhang_removed = 0;    // canopy, ceiling, deck points
  std::size_t removable = 0, removable_removed = 0;  // ... in columns holding ground and no solid
  std::size_t other = 0, other_kept = 0;             // all other points
};

/// A 128 x 1024 scan (+-45 degrees, an OS0-like sensor that sees the overhangs above it) at the
/// keyframe nearest `target`, leveled by the true roll/pitch, through collapse_overhangs (edge
/// 0.5 m, sigma from a 1.2 m robot, crop 12 m). Independently of the algorithm, an overhang point
/// is "removable" when its cube column also holds a ground point and no point of a solid that
/// reaches up from the ground (trunk, wall, pillar, ...): Algorithm 1 must collapse those.
Rates collapse_rates(const SyntheticWorld& world, const Trajectory& t, const Eigen::Vector2d& target, Label expect) {
  std::size_t best = 0;
  for (std::size_t k = 0; k < t.poses.size(); ++k) {
    if ((t.poses[k].topRightCorner<2, 1>() - target).norm() < (t.poses[best].topRightCorner<2, 1>() - target).norm()) {
      best = k;
    }
  }
  RotatingLidar wide;
  wide.channels = 128;
  wide.vertical_fov_min_deg = -45.0;
  wide.vertical_fov_max_deg = 45.0;
  const Scan scan = cast_scan(world.scene, t.poses[best], wide, 21);
  const Eigen::Matrix3d r = t.poses[best].topLeftCorner<3, 3>();
  const double pitch = std::asin(-r(2, 0)), roll = std::atan2(r(2, 1), r(2, 2));
  const double crop = 12.0;
  CollapseParams params;
  params.edge_m = 0.5;
  params.sigma = sigma_from_robot_height(1.2, params.edge_m);
  params.transform = leveling_transform(roll, pitch);
  params.crop = CropBox{Eigen::Vector3d(-crop, -crop, -5), Eigen::Vector3d(crop, crop, 15)};
  std::vector<Eigen::Vector3d> points;
  for (const Eigen::Vector3f& p : scan.points) points.push_back(p.cast<double>());
  const CollapseResult result = collapse_overhangs(points, params);
  // Column contents, with the CBC's own column quantisation ([CBC] eqs. (4)-(5)).
  const auto column = [&](const Eigen::Vector3d& leveled) {
    return std::make_pair(quantize(leveled.x(), result.grid.min_corner.x(), 1.0 / params.edge_m),
                          quantize(leveled.y(), result.grid.min_corner.y(), 1.0 / params.edge_m));
  };
  std::map<std::pair<std::int64_t, std::int64_t>, std::pair<bool, bool>> columns;  // (has ground, has solid)
  std::vector<Eigen::Vector3d> leveled(points.size());
  std::vector<bool> used(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) {
    leveled[i] = params.transform.topLeftCorner<3, 3>() * points[i];
    used[i] = leveled[i].head<2>().cwiseAbs().maxCoeff() <= crop && leveled[i].z() >= -5 && leveled[i].z() <= 15;
    if (!used[i]) continue;
    auto& flags = columns[column(leveled[i])];
    if (scan.labels[i] == Label::kGround) flags.first = true;
    if (scan.labels[i] != Label::kGround && !is_overhang(scan.labels[i])) flags.second = true;
  }
  Rates rates;
  bool seen = false;
  for (std::size_t i = 0; i < points.size(); ++i) {
    if (!used[i]) continue;
    seen = seen || scan.labels[i] == expect;
    if (is_overhang(scan.labels[i])) {
      ++rates.overhang;
      rates.overhang_removed += result.overhang[i];
      const auto& flags = columns[column(leveled[i])];
      if (flags.first && !flags.second) {
        ++rates.removable;
        rates.removable_removed += result.overhang[i];
      }
    } else {
      ++rates.other;
      rates.other_kept += !result.overhang[i];
    }
  }
  EXPECT_TRUE(seen) << "no " << to_string(expect) << " points near the target";
  return rates;
}

TEST(Semantics, CollapsibleCubesRemoveCeilingDeckAndCanopyButKeepGroundAndWalls) {
  const SyntheticWorld world = make_loop_scene();
  const Trajectory t = generate_trajectory(world, exact_odometry());
  const std::map<std::string, std::pair<Eigen::Vector2d, Label>> places = {
      {"bridge", {{0.0, 25.0}, Label::kBridgeDeck}},
      {"tunnel", {{40.0, 0.0}, Label::kTunnelCeiling}},
      {"trees", {{-40.0, 0.0}, Label::kCanopy}},
  };
  for (const auto& [name, place] : places) {
    const Rates rates = collapse_rates(world, t, place.first, place.second);
    const double removed = static_cast<double>(rates.overhang_removed) / rates.overhang;
    const double removable = static_cast<double>(rates.removable_removed) / rates.removable;
    const double kept = static_cast<double>(rates.other_kept) / rates.other;
    std::printf("%s: overhang points removed %.3f of %zu (%.3f of the %zu over ground), others kept %.4f of %zu\n",
                name.c_str(), removed, rates.overhang, removable, rates.removable, kept, rates.other);
    EXPECT_GT(rates.overhang, 2000u) << name;
    EXPECT_GT(removed, 0.6) << name;     // the rest lie in columns without ground returns or above trunks
    EXPECT_GT(removable, 0.97) << name;  // over ground and nothing else: collapsed
    EXPECT_GT(kept, 0.995) << name;
  }
}

}  // namespace
}  // namespace terracube::simulation
