// Mapper: the tiled global map against a naive accumulation, fusion against build_elevation_map on
// world points, chaining against ground truth, loop closing on drifting odometry, bad input.
#include <gtest/gtest.h>
#include <terracube/mapper.hpp>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <random>
#include <string>
#include <vector>

namespace terracube {
namespace {

Eigen::Matrix4d pose_xyyaw(double x, double y, double z, double yaw) {
  Eigen::Matrix4d t = Eigen::Matrix4d::Identity();
  t.topLeftCorner<3, 3>() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  t.topRightCorner<3, 1>() = Eigen::Vector3d(x, y, z);
  return t;
}

/// A world of sampled surfaces (no occlusion): ground, building walls, posts and tree canopies,
/// spread irregularly so that every place looks different to the ICP.
std::vector<Eigen::Vector3d> world_cloud(std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, 0.01);
  std::vector<Eigen::Vector3d> world;
  // Offset by 0.05 m so that no ground point lies on a cell border of a 0.1/0.2 m grid.
  for (double x = -34.95; x <= 75.0; x += 0.3) {
    for (double y = -34.95; y <= 75.0; y += 0.3) world.emplace_back(x, y, 0.02 * std::sin(0.3 * x) + noise(rng));
  }
  // Walls: random boxes off the road (the road is the square loop 0..40).
  for (int b = 0; b < 40; ++b) {
    double cx = -30.0 + 100.0 * unit(rng), cy = -30.0 + 100.0 * unit(rng);
    const bool on_road = (std::abs(cx) < 4 || std::abs(cx - 40) < 4 || std::abs(cy) < 4 || std::abs(cy - 40) < 4) &&
                         cx > -4 && cx < 44 && cy > -4 && cy < 44;
    if (on_road) continue;
    const double sx = 1.0 + 5.0 * unit(rng), sy = 1.0 + 5.0 * unit(rng), h = 1.0 + 3.0 * unit(rng);
    for (double z = 0.1; z < h; z += 0.2) {
      for (double s = 0.0; s <= 1.0; s += 0.2 / std::max(sx, sy)) {
        world.emplace_back(cx + sx * s, cy, z);
        world.emplace_back(cx + sx * s, cy + sy, z);
        world.emplace_back(cx, cy + sy * s, z);
        world.emplace_back(cx + sx, cy + sy * s, z);
      }
    }
  }
  // Posts and trees with canopies (overhang) along the road.
  for (int t = 0; t < 60; ++t) {
    const double along = 160.0 * unit(rng), side = unit(rng) < 0.5 ? -5.0 : 5.0;
    Eigen::Vector2d c;
    if (along < 40)
      c = {along, side};
    else if (along < 80)
      c = {40 + side, along - 40};
    else if (along < 120)
      c = {120 - along, 40 + side};
    else
      c = {side, 160 - along};
    for (double z = 0.0; z < 3.0; z += 0.1) {
      for (int a = 0; a < 8; ++a) {
        world.emplace_back(c.x() + 0.15 * std::cos(a * 0.785), c.y() + 0.15 * std::sin(a * 0.785), z);
      }
    }
    if (t % 2 == 0) {
      for (int k = 0; k < 300; ++k) {
        const Eigen::Vector3d d(unit(rng) - 0.5, unit(rng) - 0.5, unit(rng) - 0.5);
        world.push_back(Eigen::Vector3d(c.x(), c.y(), 4.0) + 3.0 * d);
      }
    }
  }
  return world;
}

/// The world points within `range` of the sensor, in the sensor frame.
std::vector<Eigen::Vector3f> scan_of(const std::vector<Eigen::Vector3d>& world, const Eigen::Matrix4d& world_sensor,
                                     double range) {
  const Eigen::Matrix3d r = world_sensor.topLeftCorner<3, 3>();
  const Eigen::Vector3d t = world_sensor.topRightCorner<3, 1>();
  std::vector<Eigen::Vector3f> scan;
  for (const Eigen::Vector3d& p : world) {
    if ((p - t).head<2>().norm() > range) continue;
    scan.push_back((r.transpose() * (p - t)).cast<float>());
  }
  return scan;
}

/// `pose` with a little roll and pitch, varying with the scan number k.
Eigen::Matrix4d wobbled(Eigen::Matrix4d pose, double k) {
  pose.topLeftCorner<3, 3>() =
      pose.topLeftCorner<3, 3>() *
      Eigen::AngleAxisd(0.02 * std::sin(0.3 * k), Eigen::Vector3d::UnitY()).toRotationMatrix() *
      Eigen::AngleAxisd(0.02 * std::cos(0.2 * k), Eigen::Vector3d::UnitX()).toRotationMatrix();
  return pose;
}

/// Ground-truth poses around the square loop (0,0) -> (40,0) -> (40,40) -> (0,40), `step` apart,
/// the sensor 1.8 m up with a little roll and pitch.
std::vector<Eigen::Matrix4d> square_loop(double step, int laps_extra_steps) {
  std::vector<Eigen::Matrix4d> poses;
  const int per_side = static_cast<int>(std::round(40.0 / step));
  for (int k = 0; k < 4 * per_side + laps_extra_steps; ++k) {
    const int side = (k / per_side) % 4;
    const double s = (k % per_side) * step;
    const double corners[4][3] = {{0, 0, 0}, {40, 0, M_PI / 2}, {40, 40, M_PI}, {0, 40, -M_PI / 2}};
    const double x = corners[side][0] + s * std::cos(corners[side][2]);
    const double y = corners[side][1] + s * std::sin(corners[side][2]);
    poses.push_back(wobbled(pose_xyyaw(x, y, 1.8, corners[side][2]), k));
  }
  return poses;
}

/// Ground-truth poses `step` apart along the square loop's first side, around its first corner
/// on a 5 m radius (as a vehicle turns: 0.1 rad per 0.5 m) and up its second side; the sensor
/// 1.8 m up with a little roll and pitch.
std::vector<Eigen::Matrix4d> rounded_corner_path(double step) {
  const double radius = 5.0, straight = 35.0, arc = radius * M_PI / 2;
  std::vector<Eigen::Matrix4d> poses;
  for (double s = 0.0; s <= 2 * straight + arc; s += step) {
    Eigen::Matrix4d pose;
    if (s < straight) {
      pose = pose_xyyaw(s, 0, 1.8, 0);
    } else if (s < straight + arc) {
      const double angle = (s - straight) / radius;
      pose = pose_xyyaw(straight + radius * std::sin(angle), radius - radius * std::cos(angle), 1.8, angle);
    } else {
      pose = pose_xyyaw(40, radius + s - straight - arc, 1.8, M_PI / 2);
    }
    poses.push_back(wobbled(pose, static_cast<double>(poses.size())));
  }
  return poses;
}

/// What an IMU gives of `pose` (world <- sensor): its roll and pitch, no yaw and no position.
Eigen::Matrix4d attitude_of(const Eigen::Matrix4d& pose) {
  Eigen::Matrix4d attitude = Eigen::Matrix4d::Identity();
  const double yaw = std::atan2(pose(1, 0), pose(0, 0));
  attitude.topLeftCorner<3, 3>() = pose_xyyaw(0, 0, 0, -yaw).topLeftCorner<3, 3>() * pose.topLeftCorner<3, 3>();
  return attitude;
}

/// Odometry: the true steps, each turned by `yaw_per_step` and scaled by (1 + scale_error).
std::vector<Eigen::Matrix4d> drifting_odometry(const std::vector<Eigen::Matrix4d>& truth, double yaw_per_step,
                                               double scale_error) {
  std::vector<Eigen::Matrix4d> odometry{truth.front()};
  for (std::size_t k = 1; k < truth.size(); ++k) {
    Eigen::Matrix4d step = truth[k - 1].inverse() * truth[k];
    step.topRightCorner<3, 1>() *= 1.0 + scale_error;
    step = pose_xyyaw(0, 0, 0, yaw_per_step) * step;
    odometry.push_back(odometry.back() * step);
  }
  return odometry;
}

double position_rmse(const std::vector<Eigen::Matrix4d>& a, const std::vector<Eigen::Matrix4d>& b) {
  double sum = 0.0;
  for (std::size_t k = 0; k < a.size(); ++k) {
    sum += (a[k].topRightCorner<3, 1>() - b[k].topRightCorner<3, 1>()).squaredNorm();
  }
  return std::sqrt(sum / static_cast<double>(a.size()));
}

TEST(TiledElevationMap, MatchesNaiveAccumulationAcrossTilesAndNegativeCoordinates) {
  TiledElevationMap tiles(0.25);
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> where(-40.0, 25.0), height(-2.0, 3.0), spread(0.0, 0.4);
  struct Naive {
    double count = 0, sum = 0, squares = 0;
    float min = INFINITY, max = -INFINITY;
    bool disc = false;
  };
  std::map<std::pair<long, long>, Naive> naive;
  for (int k = 0; k < 20000; ++k) {
    const double x = where(rng), y = where(rng);
    const float mean = static_cast<float>(height(rng)), sd = static_cast<float>(spread(rng));
    const float lo = mean - 2 * sd, hi = mean + 2 * sd;
    const auto count = static_cast<std::uint32_t>(1 + k % 7);
    const bool disc = k % 13 == 0;
    tiles.fuse(x, y, lo, hi, mean, sd, count, disc);
    Naive& n = naive[{static_cast<long>(std::floor(x / 0.25)), static_cast<long>(std::floor(y / 0.25))}];
    const double c = count;
    n.count += c, n.sum += c * mean, n.squares += c * (double(sd) * sd + double(mean) * mean);
    n.min = std::min(n.min, lo), n.max = std::max(n.max, hi), n.disc |= disc;
  }
  EXPECT_GT(tiles.num_tiles(), 4u);
  const ElevationMap map = tiles.to_map();
  const MapGeometry& g = map.geometry();
  std::size_t with_data = 0;
  for (int i = 0; i < g.size.x(); ++i) {
    for (int j = 0; j < g.size.y(); ++j) {
      const Eigen::Vector2d c = g.position_of({i, j});
      const auto it =
          naive.find({static_cast<long>(std::floor(c.x() / 0.25)), static_cast<long>(std::floor(c.y() / 0.25))});
      if (it == naive.end()) {
        EXPECT_EQ(map.get("count")(i, j), 0.0f);
        EXPECT_TRUE(std::isnan(map.get("max")(i, j)));
        continue;
      }
      ++with_data;
      const Naive& n = it->second;
      ASSERT_EQ(map.get("count")(i, j), static_cast<float>(n.count));
      EXPECT_EQ(map.get("min")(i, j), n.min);
      EXPECT_EQ(map.get("max")(i, j), n.max);
      const double mean = n.sum / n.count;
      EXPECT_NEAR(map.get("mean")(i, j), mean, 1e-5);
      EXPECT_NEAR(map.get("std_dev")(i, j), std::sqrt(std::max(0.0, n.squares / n.count - mean * mean)), 1e-4);
      EXPECT_EQ(map.get("discontinuity")(i, j), n.disc ? 1.0f : 0.0f);
    }
  }
  EXPECT_EQ(with_data, naive.size());
}

TEST(Mapper, OneScanOnAGridAlignedPoseEqualsTheElevationMapOfTheWorldPoints) {
  const auto world = world_cloud(1);
  const Eigen::Matrix4d pose = pose_xyyaw(10.0, 0.0, 1.8, 0.0);  // a multiple of the resolution, level
  const auto scan = scan_of(world, pose, 15.0);
  MapperParams params;
  params.min_range_m = 0.0;
  Mapper mapper(params);
  const ScanReport report = mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), pose);
  EXPECT_TRUE(report.keyframe);
  EXPECT_EQ(report.index, 0);
  const ElevationMap global = mapper.global_map(false);

  // Reference: the world-frame points (of the scan) binned directly.
  std::vector<Eigen::Vector3d> world_points;
  for (const auto& p : scan)
    world_points.push_back(pose.topLeftCorner<3, 3>() * p.cast<double>() + pose.topRightCorner<3, 1>());
  ElevationParams elevation;
  elevation.resolution_m = params.resolution_m;
  elevation.origin_m = global.geometry().origin_m;
  elevation.size = global.geometry().size;
  const ElevationMap reference = build_elevation_map(PointsView<double>(world_points), elevation);
  std::size_t cells = 0;
  for (int i = 0; i < global.geometry().size.x(); ++i) {
    for (int j = 0; j < global.geometry().size.y(); ++j) {
      const float c = reference.get("count")(i, j);
      ASSERT_EQ(global.get("count")(i, j), c) << i << " " << j;
      if (c == 0.0f) continue;
      ++cells;
      EXPECT_NEAR(global.get("max")(i, j), reference.get("max")(i, j), 1e-5);
      EXPECT_NEAR(global.get("min")(i, j), reference.get("min")(i, j), 1e-5);
      EXPECT_NEAR(global.get("mean")(i, j), reference.get("mean")(i, j), 1e-5);
      EXPECT_NEAR(global.get("std_dev")(i, j), reference.get("std_dev")(i, j), 1e-3);
      EXPECT_EQ(global.get("discontinuity")(i, j), reference.get("discontinuity")(i, j));
    }
  }
  EXPECT_GT(cells, 5000u);
}

TEST(Mapper, PointsOutsideTheRangeLimitsTakeNoPartAndAreCounted) {
  const auto world = world_cloud(2);
  const Eigen::Matrix4d pose = pose_xyyaw(10.0, 0.0, 1.8, 0.0);
  const auto scan = scan_of(world, pose, 15.0);
  MapperParams params;
  params.min_range_m = 2.0;
  params.max_range_m = 9.0;
  params.loop_closing = false;
  Mapper mapper(params);
  // Reference: the points within [2, 9] m of the sensor, picked plainly, fed without limits.
  std::vector<Eigen::Vector3f> within;
  for (const auto& p : scan) {
    const double range = p.cast<double>().norm();
    if (range >= 2.0 && range <= 9.0) within.push_back(p);
  }
  const std::size_t left_out = scan.size() - within.size();
  ASSERT_GT(left_out, 100u);
  ASSERT_GT(within.size(), 1000u);
  MapperParams unlimited = params;
  unlimited.min_range_m = 0.0;
  unlimited.max_range_m = std::numeric_limits<double>::infinity();
  Mapper reference(unlimited);
  for (int k = 0; k < 2; ++k) {  // the count adds up over the scans
    const ScanReport report = mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), pose);
    EXPECT_EQ(report.num_out_of_range, left_out);
    EXPECT_EQ(reference.add_scan(PointsView<float>(within.data()->data(), within.size()), pose).num_out_of_range, 0u);
  }
  EXPECT_EQ(mapper.points_out_of_range(), 2 * left_out);
  EXPECT_EQ(reference.points_out_of_range(), 0u);
  EXPECT_EQ(mapper.global_map(false).get("count"), reference.global_map(false).get("count"));
  const Layer max = mapper.global_map(false).get("max"), expected = reference.global_map(false).get("max");
  EXPECT_TRUE((max.array() == expected.array() || (max.array().isNaN() && expected.array().isNaN())).all());
}

TEST(Mapper, AccumulatedLocalMapsHoldTheScansSinceThePreviousKeyframe) {
  const auto world = world_cloud(5);
  MapperParams params;
  params.min_range_m = 0.0;
  params.keyframe_distance_m = 2.0;
  params.max_scans_per_local_map = 2;
  params.use_registration = false;
  params.loop_closing = false;
  Mapper mapper(params);
  std::vector<std::vector<Eigen::Vector3f>> scans;
  for (int k = 0; k < 3; ++k) {  // scans at x = 0, 1, 2: keyframes at 0 (alone) and 2 (with scan 1)
    const Eigen::Matrix4d pose = pose_xyyaw(1.0 * k, 0.0, 1.8, 0.0);
    scans.push_back(scan_of(world, pose, 8.0));
    mapper.add_scan(PointsView<float>(scans.back().data()->data(), scans.back().size()), pose);
  }
  ASSERT_EQ(mapper.num_keyframes(), 2u);
  // Reference: scans 1 and 2 moved into keyframe 1's leveled frame (the sensor at x = 2), binned.
  std::vector<Eigen::Vector3d> points;
  for (int k = 1; k < 3; ++k) {
    for (const auto& p : scans[k]) points.push_back(p.cast<double>() + Eigen::Vector3d(k - 2.0, 0, 0));
  }
  const ElevationMap& local = mapper.local_map(1);
  ElevationParams elevation;
  elevation.resolution_m = params.resolution_m;
  elevation.origin_m = local.geometry().origin_m;
  elevation.size = local.geometry().size;
  const ElevationMap reference = build_elevation_map(PointsView<double>(points), elevation);
  EXPECT_EQ(local.get("count"), reference.get("count"));
  EXPECT_GT(local.get("count").sum(), static_cast<float>(scans[2].size()));
  for (int i = 0; i < local.geometry().size.x(); ++i) {
    for (int j = 0; j < local.geometry().size.y(); ++j) {
      if (reference.get("count")(i, j) > 0) {
        EXPECT_NEAR(local.get("max")(i, j), reference.get("max")(i, j), 1e-5);
      }
    }
  }
  // max_scans_per_local_map = 1: keyframe 1 holds its own scan only.
  params.max_scans_per_local_map = 1;
  Mapper single(params);
  for (int k = 0; k < 3; ++k) {
    single.add_scan(PointsView<float>(scans[k].data()->data(), scans[k].size()), pose_xyyaw(1.0 * k, 0.0, 1.8, 0.0));
  }
  EXPECT_EQ(single.local_map(1).get("count").sum(), static_cast<float>(scans[2].size()));
}

TEST(Mapper, KeyframesEveryKeyframeDistanceOfTravel) {
  MapperParams params;
  params.use_registration = false;
  params.loop_closing = false;
  Mapper mapper(params);
  const std::vector<Eigen::Vector3f> scan = {{5, 0, -1.8f}, {0, 5, -1.8f}, {-5, 0, -1.8f}};
  std::vector<std::size_t> expected;
  for (int k = 0; k < 40; ++k) {  // 0.5 m per scan: a keyframe every 6 scans
    const ScanReport r =
        mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), pose_xyyaw(0.5 * k, 0, 0, 0));
    if (k % 6 == 0) expected.push_back(static_cast<std::size_t>(k));
    EXPECT_EQ(r.keyframe, k % 6 == 0) << k;
    // Without registration the estimate is odometry: every scan's pose is its own odometry.
    EXPECT_LT((r.pose - pose_xyyaw(0.5 * k, 0, 0, 0)).norm(), 1e-12) << k;
  }
  EXPECT_EQ(mapper.keyframe_scan_indices(), expected);
  // Turning in place also makes keyframes.
  const ScanReport turned =
      mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), pose_xyyaw(19.5, 0, 0, 0.6));
  EXPECT_TRUE(turned.keyframe);
}

TEST(Mapper, ChainingByRegistrationBeatsDriftingOdometry) {
  const auto world = world_cloud(2);
  const auto truth = square_loop(1.0, 0);
  const auto odometry = drifting_odometry(truth, 0.004, 0.02);
  MapperParams params;
  params.loop_closing = false;
  Mapper mapper(params);
  for (std::size_t k = 0; k < truth.size(); ++k) {
    const auto scan = scan_of(world, truth[k], 20.0);
    mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), odometry[k]);
  }
  const auto indices = mapper.keyframe_scan_indices();
  std::vector<Eigen::Matrix4d> truth_k, odometry_k;
  for (const std::size_t i : indices) truth_k.push_back(truth[i]), odometry_k.push_back(odometry[i]);
  const double odometry_error = position_rmse(odometry_k, truth_k);
  const double mapper_error = position_rmse(mapper.keyframe_poses(), truth_k);
  std::cout << "keyframes " << indices.size() << ": odometry RMSE " << odometry_error << " m, registered "
            << mapper_error << " m\n";
  EXPECT_GT(indices.size(), 40u);
  EXPECT_GT(odometry_error, 1.0);
  EXPECT_LT(mapper_error, 0.25 * odometry_error);
  const MapperTimings& t = mapper.timings();
  EXPECT_EQ(t.keyframes, indices.size());
  EXPECT_EQ(t.scans, truth.size());
}

TEST(Mapper, LidarOnlyRegistersEveryScanAndMakesKeyframesByItsOwnTravel) {
  // Every scan, 0.5 m apart, of a drive round a corner, with no odometry: only an IMU's attitude
  // (the true roll and pitch, no yaw, no position).
  const auto world = world_cloud(2);
  const auto truth = rounded_corner_path(0.5);
  MapperParams params;
  params.lidar_only = true;
  params.loop_closing = false;
  Mapper mapper(params);
  std::vector<Eigen::Matrix4d> estimates, poses;  // ScanReport::pose, and it aligned with the truth
  std::vector<std::size_t> keyframe_reports;
  for (const Eigen::Matrix4d& pose : truth) {
    const auto scan = scan_of(world, pose, 20.0);
    const ScanReport r = mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), attitude_of(pose));
    if (r.keyframe) keyframe_reports.push_back(estimates.size());
    estimates.push_back(r.pose);
    poses.push_back(truth.front() * estimates.front().inverse() * r.pose);  // the estimates start at the identity
  }
  const MapperTimings& t = mapper.timings();
  EXPECT_EQ(t.registered_steps + t.untrusted_steps, truth.size() - 1);  // every scan after the first
  const double error = position_rmse(poses, truth);
  std::cout << "scans " << truth.size() << ", keyframes " << mapper.num_keyframes() << ", untrusted "
            << t.untrusted_steps << ": per-scan position RMSE " << error << " m\n";
  EXPECT_LT(error, 0.1);  // measured: 0.018 m over the 78 m
  // Keyframes, naively from the per-scan estimates: once they travelled 3 m (keyframe_distance_m)
  // or turned 0.5 rad (keyframe_rotation_rad) since the newest keyframe.
  std::vector<std::size_t> expected{0};
  const auto yaw_of = [](const Eigen::Matrix4d& p) { return std::atan2(p(1, 0), p(0, 0)); };
  double path = 0.0, keyframe_path = 0.0;
  for (std::size_t k = 1; k < estimates.size(); ++k) {
    path += (estimates[k].topRightCorner<3, 1>() - estimates[k - 1].topRightCorner<3, 1>()).norm();
    const double turn = std::remainder(yaw_of(estimates[k]) - yaw_of(estimates[expected.back()]), 2 * M_PI);
    if (path - keyframe_path >= 3.0 || std::abs(turn) >= 0.5) expected.push_back(k), keyframe_path = path;
  }
  EXPECT_EQ(mapper.keyframe_scan_indices(), expected);
  EXPECT_EQ(keyframe_reports, expected);
  const auto keyframe_poses = mapper.keyframe_poses();
  for (std::size_t k = 0; k < expected.size(); ++k) {
    EXPECT_LT((keyframe_poses[k] - estimates[expected[k]]).norm(), 1e-12) << k;
  }
}

TEST(Mapper, StepsTakeTheirHeightFromTheSharedGround) {
  // LiDAR-only round the corner: the ICP leaves the ground out, so only the posts, walls and crowns
  // hold the height; with ground_step_height the ground the maps share does.
  const auto world = world_cloud(2);
  const auto truth = rounded_corner_path(0.5);
  double worst[2] = {0.0, 0.0};
  for (const bool ground : {false, true}) {
    MapperParams params;
    params.lidar_only = true;
    params.loop_closing = false;
    params.ground_step_height = ground;
    Mapper mapper(params);
    for (const Eigen::Matrix4d& pose : truth) {
      const auto scan = scan_of(world, pose, 20.0);
      const ScanReport r = mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), attitude_of(pose));
      worst[ground] = std::max(worst[ground], std::abs(r.pose(2, 3) - (pose(2, 3) - truth.front()(2, 3))));
    }
  }
  std::cout << "worst height error: ICP " << worst[0] << " m, shared ground " << worst[1] << " m\n";
  EXPECT_LT(worst[1], 0.05);
  EXPECT_LT(worst[1], 0.5 * worst[0]);
}

TEST(Mapper, LocalMapsOnSeveralThreadsGiveTheOneThreadPosesAndGlobalMap) {
  // Five scans a local map (about 70,000 points: enough for two threads), registration on.
  const auto world = world_cloud(3);
  const auto truth = square_loop(1.0, 0);
  const auto odometry = drifting_odometry(truth, 0.004, 0.02);
  auto run = [&](int threads) {
    MapperParams params;
    params.loop_closing = false;
    params.max_scans_per_local_map = 5;
    params.num_threads = threads;
    Mapper mapper(params);
    for (std::size_t k = 0; k < 24; ++k) {
      const auto scan = scan_of(world, truth[k], 20.0);
      mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), odometry[k]);
    }
    return std::make_pair(mapper.keyframe_poses(), mapper.global_map());
  };
  const auto [poses, map] = run(1);
  const auto [threaded_poses, threaded_map] = run(2);
  ASSERT_EQ(threaded_poses.size(), poses.size());
  ASSERT_GE(poses.size(), 5u);
  for (std::size_t k = 0; k < poses.size(); ++k) EXPECT_EQ(threaded_poses[k], poses[k]) << "keyframe " << k;
  ASSERT_EQ(threaded_map.layers(), map.layers());
  for (const std::string& name : map.layers()) {
    const Layer& a = threaded_map.get(name);
    const Layer& b = map.get(name);
    EXPECT_EQ(a.array().isNaN().matrix(), b.array().isNaN().matrix()) << name;
    EXPECT_EQ(a.array().isNaN().select(0.0F, a.array()).matrix(), b.array().isNaN().select(0.0F, b.array()).matrix())
        << name;
  }
  MapperParams bad;
  bad.num_threads = -1;
  EXPECT_THROW(Mapper{bad}, std::invalid_argument);
}

TEST(Mapper, YawOnlyStepsKeepOdometrysRollAndPitch) {
  const auto world = world_cloud(6);
  const auto truth = square_loop(1.0, 0);
  auto run = [&](bool yaw_only) {
    MapperParams params;
    params.loop_closing = false;
    params.yaw_only_registration = yaw_only;
    Mapper mapper(params);
    for (std::size_t k = 0; k < 20; ++k) {
      const auto scan = scan_of(world, truth[k], 20.0);
      mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), truth[k]);
    }
    // Largest angle between a keyframe's estimated and odometry "up" (z) axes [rad].
    double worst = 0.0;
    const auto poses = mapper.keyframe_poses(), odometry = mapper.keyframe_odometry();
    for (std::size_t k = 0; k < poses.size(); ++k) {
      const Eigen::Vector3d up = poses[k].topLeftCorner<3, 3>().transpose() * Eigen::Vector3d::UnitZ();
      const Eigen::Vector3d up_odometry = odometry[k].topLeftCorner<3, 3>().transpose() * Eigen::Vector3d::UnitZ();
      worst = std::max(worst, std::acos(std::clamp(up.dot(up_odometry), -1.0, 1.0)));
    }
    return worst;
  };
  EXPECT_LT(run(true), 1e-7);   // gravity stays where odometry (the IMU) put it
  EXPECT_GT(run(false), 1e-5);  // the 6-DOF ICP tilts the frames a little
}

TEST(Mapper, OnlyTheNewestLocalMapIsKeptUnlessAsked) {
  const auto world = world_cloud(7);
  const auto truth = square_loop(1.0, 0);
  auto run = [&](bool keep) {
    MapperParams params;
    params.keep_local_maps = keep;
    Mapper mapper(params);
    for (std::size_t k = 0; k < 12; ++k) {
      const auto scan = scan_of(world, truth[k], 20.0);
      mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), truth[k]);
    }
    return mapper;
  };
  const Mapper lean = run(false), full = run(true);
  ASSERT_EQ(lean.num_keyframes(), 4u);
  EXPECT_THROW(lean.local_map(0), std::out_of_range);
  EXPECT_NO_THROW(lean.local_map(3));
  for (std::size_t k = 0; k < 4; ++k) EXPECT_NO_THROW(full.local_map(k));
  // Keeping the maps changes memory only.
  const auto a = lean.keyframe_poses(), b = full.keyframe_poses();
  for (std::size_t k = 0; k < a.size(); ++k) EXPECT_TRUE(a[k].isApprox(b[k], 1e-12));
}

TEST(Mapper, LoopClosingCutsTheErrorOfDriftingOdometry) {
  const auto world = world_cloud(4);
  const auto truth = square_loop(1.0, 12);  // one lap plus 12 m: the start is revisited
  const auto odometry = drifting_odometry(truth, 0.002, 0.01);
  auto run = [&](bool loops) {
    MapperParams params;
    params.use_registration = false;  // odometry alone between keyframes: loop closing must fix the drift
    params.loop_closing = loops;
    Mapper mapper(params);
    for (std::size_t k = 0; k < truth.size(); ++k) {
      const auto scan = scan_of(world, truth[k], 20.0);
      mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), odometry[k]);
    }
    if (mapper.pending_loops() > 0) mapper.optimize();
    EXPECT_EQ(mapper.pending_loops(), 0u);
    std::vector<Eigen::Matrix4d> truth_k;
    for (const std::size_t i : mapper.keyframe_scan_indices()) truth_k.push_back(truth[i]);
    return std::make_pair(position_rmse(mapper.keyframe_poses(), truth_k), mapper.loop_closures().size());
  };
  const auto [open_error, open_loops] = run(false);
  const auto [closed_error, loops] = run(true);
  std::cout << "odometry chaining RMSE " << open_error << " m; with " << loops << " loop closures " << closed_error
            << " m\n";
  EXPECT_EQ(open_loops, 0u);
  EXPECT_GE(loops, 1u);
  EXPECT_GT(open_error, 1.0);
  EXPECT_LT(closed_error, open_error / 3.0);
}

TEST(Mapper, GlobalMapMemoryGrowsWithTheAreaCovered) {
  MapperParams params;
  params.resolution_m = 0.2;  // 12.8 m tiles: an 8 m scan touches at most 4
  params.use_registration = false;
  params.loop_closing = false;
  params.local_map_size_m = 10.0;
  Mapper mapper(params);
  std::vector<Eigen::Vector3f> scan;
  for (float x = -4; x <= 4; x += 0.2f) {
    for (float y = -4; y <= 4; y += 0.2f) scan.emplace_back(x, y, -1.0f);
  }
  mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), pose_xyyaw(0, 0, 0, 0));
  const std::size_t one = mapper.tiles().num_tiles();
  // A straight 1 km drive: tiles along a strip, not the 1 km x 1 km square of its bounding box.
  for (int k = 1; k <= 100; ++k) {
    mapper.add_scan(PointsView<float>(scan.data()->data(), scan.size()), pose_xyyaw(10.0 * k, 10.0 * k, 0, 0));
  }
  const std::size_t tiles = mapper.tiles().num_tiles();
  EXPECT_LE(tiles, 101 * std::max<std::size_t>(one, 4));
  const double tile_m = TiledElevationMap::kTileCells * params.resolution_m;
  EXPECT_LT(static_cast<double>(tiles), 0.05 * (1000.0 / tile_m) * (1000.0 / tile_m));
}

TEST(Mapper, AnOdometryJumpIsRefusedAndLeavesTheMapperAsItWas) {
  // issue 39, item 9: one 2 km glitch must not stretch the global map over kilometres for good.
  MapperParams params;
  params.use_registration = false;
  params.loop_closing = false;
  Mapper mapper(params);
  std::vector<Eigen::Vector3f> scan;
  for (float x = -4; x <= 4; x += 0.2f) {
    for (float y = -4; y <= 4; y += 0.2f) scan.emplace_back(x, y, -1.0f);
  }
  const PointsView<float> view(scan.data()->data(), scan.size());
  mapper.add_scan(view, pose_xyyaw(0, 0, 0, 0));
  mapper.add_scan(view, pose_xyyaw(3.5, 0, 0, 0));
  const std::size_t tiles = mapper.tiles().num_tiles();
  try {
    mapper.add_scan(view, pose_xyyaw(2000.0, 0, 0, 0));
    ADD_FAILURE() << "a 2 km step was accepted";
  } catch (const std::invalid_argument& error) {
    EXPECT_NE(std::string(error.what()).find("max_odometry_step_m"), std::string::npos) << error.what();
  }
  EXPECT_EQ(mapper.num_keyframes(), 2U);
  EXPECT_EQ(mapper.tiles().num_tiles(), tiles);
  mapper.add_scan(view, pose_xyyaw(7.0, 0, 0, 0));  // the drive goes on from where it was
  EXPECT_EQ(mapper.num_keyframes(), 3U);
  EXPECT_NO_THROW(mapper.global_map());
  MapperParams bad;
  bad.max_odometry_step_m = 0.0;
  EXPECT_THROW(Mapper{bad}, std::invalid_argument);
}

TEST(Mapper, BadInputIsRejected) {
  MapperParams bad;
  bad.keyframe_distance_m = 0.0;
  EXPECT_THROW(Mapper{bad}, std::invalid_argument);
  bad = MapperParams{};
  bad.resolution_m = -1.0;
  EXPECT_THROW(Mapper{bad}, std::invalid_argument);
  bad = MapperParams{};
  bad.local_map_size_m = 1e6;
  EXPECT_THROW(Mapper{bad}, std::invalid_argument);
  bad = MapperParams{};
  bad.optimize_interval_keyframes = 0;
  EXPECT_THROW(Mapper{bad}, std::invalid_argument);
  bad = MapperParams{};
  bad.max_scans_per_local_map = 0;
  EXPECT_THROW(Mapper{bad}, std::invalid_argument);
  bad = MapperParams{};
  bad.loop_min_overlap = 1.5;
  EXPECT_THROW(Mapper{bad}, std::invalid_argument);
  for (const double max_range : {0.5, 0.1, double(NAN)}) {  // at or below min_range_m (0.5), or NaN
    bad = MapperParams{};
    bad.max_range_m = max_range;
    EXPECT_THROW(Mapper{bad}, std::invalid_argument) << max_range;
  }

  Mapper mapper;
  const std::vector<Eigen::Vector3f> scan = {{1, 2, 3}};
  const PointsView<float> view(scan.data()->data(), scan.size());
  Eigen::Matrix4d pose = Eigen::Matrix4d::Identity();
  pose(0, 3) = NAN;
  EXPECT_THROW(mapper.add_scan(view, pose), std::invalid_argument);
  pose = Eigen::Matrix4d::Identity();
  pose(0, 0) = 2.0;
  EXPECT_THROW(mapper.add_scan(view, pose), std::invalid_argument);
  const std::vector<Eigen::Vector3f> nan_scan = {{1, NAN, 3}};
  EXPECT_THROW(mapper.add_scan(PointsView<float>(nan_scan.data()->data(), 1), Eigen::Matrix4d::Identity()),
               std::invalid_argument);
  EXPECT_THROW(mapper.local_map(5), std::out_of_range);
  // An empty scan makes an empty keyframe, not a crash.
  Mapper empty;
  EXPECT_TRUE(empty.add_scan(PointsView<float>(), Eigen::Matrix4d::Identity()).keyframe);
  EXPECT_EQ(empty.global_map().geometry().num_cells(), 0u);
}

}  // namespace
}  // namespace terracube
