// collapse_overhangs with CollapseMethod::kShadowAware on hand-made columns. The naive reference of
// the whole rule is tests/python/test_shadow_aware.py; these cases keep the C++ core covered alone.
#include <gtest/gtest.h>
#include <terracube/collapse.hpp>
#include <terracube/elevation_map.hpp>

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <random>
#include <stdexcept>
#include <string>

namespace terracube {
namespace {

using Points = std::vector<Eigen::Vector3d>;

void add_grid(Points& points, double x0, double x1, double y0, double y1, double z, double step = 0.25) {
  for (double x = x0; x < x1 - 1e-9; x += step) {
    for (double y = y0; y < y1 - 1e-9; y += step) points.emplace_back(x, y, z);
  }
}

void add_face_x(Points& points, double x, double y0, double y1, double z0, double z1, double step = 0.2) {
  for (double y = y0; y < y1 - 1e-9; y += step) {
    for (double z = z0; z < z1 - 1e-9; z += step) points.emplace_back(x, y, z);
  }
}

CollapseParams shadow_aware_params(int sigma = 4) {
  CollapseParams params;
  params.edge_m = 0.5;
  params.sigma = sigma;
  params.method = CollapseMethod::kShadowAware;
  return params;
}

/// The reason of the cube holding `point`.
CubeReason reason_at(const CollapseResult& result, const Eigen::Vector3d& point) {
  const CubeGrid& grid = result.grid;
  std::int64_t i[3];
  for (int a = 0; a < 3; ++a) i[a] = quantize(point[a], grid.min_corner[a], 1.0 / grid.edge_m);
  const std::int64_t cube = grid.index(i[0], i[1], i[2]);
  const auto at = std::lower_bound(result.occupied_cubes.begin(), result.occupied_cubes.end(), cube);
  EXPECT_TRUE(at != result.occupied_cubes.end() && *at == cube);
  return result.cube_reasons[static_cast<std::size_t>(at - result.occupied_cubes.begin())];
}

TEST(ShadowAware, AMultipathPointBelowTheRoadIsKeptAndDecidesNothing) {
  Points points;
  add_grid(points, 1, 12, -3, 3, -1.7);
  const Eigen::Vector3d ghost(6.1, 0.1, -7.7);
  points.push_back(ghost);
  CollapseParams paper = shadow_aware_params();
  paper.method = CollapseMethod::kPaper;
  EXPECT_GT(collapse_overhangs(points, paper).num_overhang, 0U);  // the road above the ghost
  const CollapseResult result = collapse_overhangs(points, shadow_aware_params());
  EXPECT_EQ(result.num_overhang, 0U);
  EXPECT_EQ(reason_at(result, ghost), CubeReason::kBelowGround);
  EXPECT_EQ(reason_at(result, {6.0, 0.0, -1.7}), CubeReason::kSupported);
}

TEST(ShadowAware, AMultipathPatchUnderTheRoadIsNoGround) {
  Points points;
  add_grid(points, 1, 12, -3, 3, -1.7);
  // Four returns 2.5 m under the road in a 2 x 2 block of columns (a reflection of a car or a
  // window): together they pass the 4-of-9 support test, but the road lies over them.
  const Points ghosts = {{6.0, 0.0, -4.2}, {6.5, 0.0, -4.2}, {6.0, 0.5, -4.2}, {6.5, 0.5, -4.2}};
  points.insert(points.end(), ghosts.begin(), ghosts.end());
  const CollapseResult result = collapse_overhangs(points, shadow_aware_params());
  EXPECT_EQ(result.num_overhang, 0U);
  for (const Eigen::Vector3d& ghost : ghosts) EXPECT_EQ(reason_at(result, ghost), CubeReason::kBelowGround);
  EXPECT_EQ(reason_at(result, {6.0, 0.0, -1.7}), CubeReason::kSupported);
  EXPECT_EQ(reason_at(result, {9.0, 2.0, -1.7}), CubeReason::kSupported);
}

TEST(ShadowAware, ADeepReflectionBehindTheRoadIsNoGround) {
  // Twelve returns 8 m under the road, 20 m out, in a 2 x 2 block of columns with no return around
  // them (a reflection, as on the Ouster scan 000000): they pass the support test, but the line of
  // sight to them runs 8 m under the road nearer the sensor.
  Points points;
  add_grid(points, 1, 24, -4, 4, -1.7);
  points.erase(
      std::remove_if(points.begin(), points.end(),
                     [](const Eigen::Vector3d& p) { return std::abs(p.x() - 20.25) <= 1.0 && std::abs(p.y()) <= 1.0; }),
      points.end());
  const std::size_t road = points.size();
  Points ghosts;
  for (int k = 0; k < 12; ++k)
    ghosts.emplace_back(20.0 + 0.5 * (k % 2) + 0.05 * (k / 4), -0.5 + 0.5 * (k / 2 % 2), -9.7);
  points.insert(points.end(), ghosts.begin(), ghosts.end());
  CollapseParams params = shadow_aware_params(2);
  const CollapseResult result = collapse_overhangs(points, params);
  EXPECT_EQ(result.num_overhang, 0U);
  for (const Eigen::Vector3d& ghost : ghosts) EXPECT_EQ(reason_at(result, ghost), CubeReason::kBelowGround);
  // Without the test the ghosts are the ground of the road around them, and their rays clear it.
  params.shadow_aware.hidden_ground_margin_m = 100.0;
  const CollapseResult off = collapse_overhangs(points, params);
  EXPECT_GT(std::count(off.overhang.begin(), off.overhang.begin() + static_cast<std::ptrdiff_t>(road), 1), 0);
  // Seen from above them, with nothing in between, the same returns are ground.
  params.shadow_aware.sensor_origin = Eigen::Vector3d(20.0, 0.0, -8.0);
  const CollapseResult above = collapse_overhangs(ghosts, params);
  for (const Eigen::Vector3d& ghost : ghosts) EXPECT_EQ(reason_at(above, ghost), CubeReason::kSupported);
}

TEST(ShadowAware, AWallWhoseFootIsHiddenBehindACarStays) {
  Points points;
  add_grid(points, 1, 6, -4, 4, -1.7);
  add_face_x(points, 6.0, -2, 2, -1.7, -0.2);  // car front and roof
  add_grid(points, 6, 8, -2, 2, -0.2);
  add_face_x(points, 8.5, -2, 2, -0.2, 3.0);  // wall seen from 1.5 m above the road (σ = 2: floating)
  const CollapseResult result = collapse_overhangs(points, shadow_aware_params(2));
  EXPECT_EQ(result.num_overhang, 0U);
  EXPECT_EQ(reason_at(result, {8.5, 0.0, -0.2}), CubeReason::kShadowed);
  EXPECT_EQ(reason_at(result, {8.5, 0.0, 2.8}), CubeReason::kShadowed);
}

TEST(ShadowAware, ACrownOverACurbGoesWhileTheTrunkAndCurbStay) {
  Points points;
  add_grid(points, 1, 5, -5, 5, -1.7);
  add_grid(points, 14, 20, -5, 5, -1.7, 0.1);  // ground beyond, lit under the crown
  add_face_x(points, 5.0, -5, 5, -1.7, -1.4);  // 0.3 m curb
  add_grid(points, 5, 5.5, -5, 5, -1.4);
  add_face_x(points, 9.0, -0.2, 0.2, -1.4, 1.5, 0.1);  // trunk
  for (const double z : {1.6, 2.4, 3.2, 3.8}) add_grid(points, 7.75, 10.25, -1.25, 1.25, z);
  const CollapseResult result = collapse_overhangs(points, shadow_aware_params());
  EXPECT_EQ(reason_at(result, {8.5, 0.5, 1.6}), CubeReason::kRemovedFreeBelow);
  EXPECT_EQ(reason_at(result, {9.5, -0.5, 3.8}), CubeReason::kRemovedFreeBelow);
  // A corner of the crown: 3 of its 8 neighbours hold its bottom, 4 floating ones of the 5 x 5 do.
  EXPECT_EQ(reason_at(result, {7.75, -1.25, 1.6}), CubeReason::kRemovedFreeBelow);
  EXPECT_EQ(reason_at(result, {9.0, 0.0, 3.2}), CubeReason::kSupported);  // the trunk's column
  EXPECT_EQ(reason_at(result, {5.0, 0.0, -1.4}), CubeReason::kSupported);
  // Counted over its 8 neighbours alone the corner is thin; it is the rim of the removed crown.
  CollapseParams narrow = shadow_aware_params();
  narrow.shadow_aware.bottom_window = 1;
  EXPECT_EQ(reason_at(collapse_overhangs(points, narrow), {7.75, -1.25, 1.6}), CubeReason::kRemovedRim);
  narrow.shadow_aware.remove_rims = false;
  EXPECT_EQ(reason_at(collapse_overhangs(points, narrow), {7.75, -1.25, 1.6}), CubeReason::kThin);
  CollapseParams paper = shadow_aware_params();
  paper.method = CollapseMethod::kPaper;
  EXPECT_EQ(collapse_overhangs(points, paper).num_overhang, 0U);
}

TEST(ShadowAware, SparseScanRingsUnderACeilingGo) {
  Points points;
  add_grid(points, 1, 6, -4, 4, -1.7);  // the floor, seen before the rings and beyond them, not under them
  add_grid(points, 16, 20, -4, 4, -1.7);
  for (const double x : {8.0, 11.0, 14.0}) {
    for (double y = -3.0; y < 3.0; y += 0.1) points.emplace_back(x, y, 2.3);  // one ring each, a column wide
  }
  const CollapseResult result = collapse_overhangs(points, shadow_aware_params());
  // Only 2 of a ring cube's 8 neighbours hold a cube; 4 floating ones of its 5 x 5 square do.
  for (const double x : {8.0, 11.0, 14.0}) {
    EXPECT_EQ(reason_at(result, {x, 0.0, 2.3}), CubeReason::kRemovedFreeBelow) << x;
  }
  CollapseParams narrow = shadow_aware_params();
  narrow.shadow_aware.bottom_window = 1;  // every ring thin, none removed: no rim either
  EXPECT_EQ(reason_at(collapse_overhangs(points, narrow), {11.0, 0.0, 2.3}), CubeReason::kThin);
}

TEST(ShadowAware, APoleBesideAFloatingSignStaysWhileTheSignGoes) {
  Points points;
  add_grid(points, 1, 7.5, -4, 4, -1.7);  // no ground seen next to the pole (a car hides it)
  add_grid(points, 10, 14, -4, 4, -1.7);
  for (double z = -1.7; z < 1.05; z += 0.1) points.emplace_back(8.0, 0.0, z);  // the pole's column
  points.emplace_back(8.3, 0.0, 1.0);                                          // the sign's arm beside its top
  for (const double x : {8.5, 9.0}) {
    for (const double y : {0.5, 1.0, 1.5}) points.emplace_back(x, y, 1.0);  // the sign, floating
  }
  const CollapseResult result = collapse_overhangs(points, shadow_aware_params());
  EXPECT_EQ(reason_at(result, {8.0, 0.0, 1.0}), CubeReason::kSupported);
  EXPECT_EQ(reason_at(result, {9.0, 1.0, 1.0}), CubeReason::kRemovedFreeBelow);  // 5 of 8 beside it
  // The arm's 8 neighbours: the pole (grounded) and two sign cubes; the 4 floating sign cubes of
  // its 5 x 5 square do not count beside a grounded chain: thin. Two removed columns beside it
  // against one grounded make it the sign's rim.
  EXPECT_EQ(reason_at(result, {8.3, 0.0, 1.0}), CubeReason::kRemovedRim);
  CollapseParams no_rims = shadow_aware_params();
  no_rims.shadow_aware.remove_rims = false;
  EXPECT_EQ(reason_at(collapse_overhangs(points, no_rims), {8.3, 0.0, 1.0}), CubeReason::kThin);
}

TEST(ShadowAware, ACrownsRimBesideItsTrunkGoesThatOfAWiderPostStays) {
  Points points;
  add_grid(points, 1, 5, -5, 5, -1.7);
  add_grid(points, 14, 20, -5, 5, -1.7);       // ground beyond, lit under the crown
  add_face_x(points, 5.0, -5, 5, -1.7, -1.4);  // 0.3 m curb
  add_grid(points, 5, 5.5, -5, 5, -1.4);
  add_face_x(points, 9.0, -0.2, 0.2, -1.4, 1.5, 0.1);  // trunk
  add_grid(points, 7.5, 9.25, 1.0, 2.0, 1.6);          // crown
  const Eigen::Vector3d rim(9.5, 0.5, 1.6);            // beside the trunk's top and the crown's corner
  points.push_back(rim);
  EXPECT_EQ(reason_at(collapse_overhangs(points, shadow_aware_params()), rim), CubeReason::kRemovedRim);
  // A second post column beside it: two grounded columns against one removed.
  add_face_x(points, 9.5, -0.2, 0.2, -1.4, 1.5, 0.1);
  EXPECT_EQ(reason_at(collapse_overhangs(points, shadow_aware_params()), rim), CubeReason::kThin);
}

TEST(ShadowAware, ATrunksTopRemovedAboveABushMakesNoRimOfTheTrunkBesideIt) {
  Points points;
  add_grid(points, 1, 5, -5, 5, -1.7);
  add_grid(points, 14, 20, -5, 5, -1.7);
  add_face_x(points, 5.0, -5, 5, -1.7, -1.4);  // 0.3 m curb
  add_grid(points, 5, 5.5, -5, 5, -1.4);
  add_face_x(points, 8.0, -0.2, 0.2, -1.6, -0.6, 0.1);                    // bush
  const Eigen::Vector3d over_bush(8.0, 0.0, 1.9), beside(8.5, 0.0, 1.9);  // a trunk's top, its middle unseen
  for (const Eigen::Vector3d& top : {over_bush, beside}) add_face_x(points, top.x(), -0.2, 0.2, 1.9, 2.1, 0.1);
  const CollapseResult result = collapse_overhangs(points, shadow_aware_params());
  EXPECT_EQ(reason_at(result, over_bush), CubeReason::kRemovedAboveKept);  // [CBC]'s case: never judged wide
  EXPECT_EQ(reason_at(result, beside), CubeReason::kThin);                 // so no rim
}

/// A crown 11-14 m out behind a 1.2 m hedge: nothing the sensor saw lies beyond the hedge under it.
Points crown_behind_a_hedge() {
  Points points;
  add_grid(points, 1, 8, -5, 5, -1.7);
  add_face_x(points, 8.0, -5, 5, -1.7, -0.5);
  add_grid(points, 8, 8.5, -5, 5, -0.5);
  for (const double z : {1.6, 2.4}) add_grid(points, 11, 14, -1.5, 1.5, z);
  return points;
}

/// Beams from the sensor fanned over azimuths -20..20 degrees at `elevation` [rad].
std::vector<Eigen::Vector3d> fan_of_beams(double elevation) {
  std::vector<Eigen::Vector3d> beams;
  for (double azimuth = -20.0; azimuth <= 20.0; azimuth += 0.1) {
    const double a = azimuth * M_PI / 180.0;
    beams.emplace_back(std::cos(elevation) * std::cos(a), std::cos(elevation) * std::sin(a), std::sin(elevation));
  }
  return beams;
}

TEST(ShadowAware, BeamsWithoutAReturnUnderACrownShowItsColumnsEmpty) {
  const Points points = crown_behind_a_hedge();
  const Eigen::Vector3d crown(12.0, 0.5, 1.6);
  CollapseParams params = shadow_aware_params();
  const auto reason_with = [&](const std::vector<Eigen::Vector3d>& beams) {
    return reason_at(collapse_overhangs(points, params, PointsView<double>(beams)), crown);
  };
  EXPECT_EQ(reason_with({}), CubeReason::kShadowed);             // no ray under it
  const std::vector<Eigen::Vector3d> level = fan_of_beams(0.0);  // they pass 1.35 m under it
  const CollapseResult seen = collapse_overhangs(points, params, PointsView<double>(level));
  EXPECT_EQ(reason_at(seen, crown), CubeReason::kRemovedFreeBelow);
  EXPECT_EQ(reason_at(seen, {12.5, -1.5, 2.4}), CubeReason::kRemovedFreeBelow);
  EXPECT_EQ(reason_at(seen, {8.0, 0.0, -0.5}), CubeReason::kSupported);  // the hedge stays
  std::vector<Eigen::Vector3d> scaled;                                   // any length, 1e-310 (subnormal) to 1e300
  for (std::size_t k = 0; k < level.size(); ++k) scaled.push_back(level[k] * (k % 2 == 0 ? 1e-310 : 1e300));
  EXPECT_EQ(collapse_overhangs(points, params, PointsView<double>(scaled)).overhang, seen.overhang);
  params.shadow_aware.no_return_range_m = 10.0;  // they end before the crown
  EXPECT_EQ(reason_with(level), CubeReason::kShadowed);
  params.shadow_aware.no_return_range_m = 30.0;
  EXPECT_EQ(reason_with(fan_of_beams(-0.01)), CubeReason::kShadowed);  // below the horizon: a dark road
  EXPECT_EQ(reason_with(fan_of_beams(0.15)), CubeReason::kShadowed);   // 1.8 m up at 12 m: through the crown
  EXPECT_EQ(reason_with({Eigen::Vector3d(0.0, 0.0, 1.0)}), CubeReason::kShadowed);  // straight up: no column
  params.method = CollapseMethod::kPaper;
  EXPECT_EQ(collapse_overhangs(points, params, PointsView<double>(level)).num_overhang, 0U);  // ignored
}

TEST(ShadowAware, TheDemWithoutOverhangsTakesTheBeamsToo) {
  const Points points = crown_behind_a_hedge();
  const std::vector<Eigen::Vector3d> level = fan_of_beams(0.0);
  const CollapseParams params = shadow_aware_params();
  ElevationParams elevation;
  elevation.resolution_m = 0.5;
  const OverhangFreeMap alone = build_overhang_free_map(PointsView<double>(points), params, elevation);
  const OverhangFreeMap seen =
      build_overhang_free_map(PointsView<double>(points), params, elevation, PointsView<double>(level));
  EXPECT_EQ(seen.collapse.overhang, collapse_overhangs(points, params, PointsView<double>(level)).overhang);
  EXPECT_GT(seen.collapse.num_overhang, alone.collapse.num_overhang);
  // The crown's cells: a height without the beams, none with them (nothing under it was seen).
  const auto cell = seen.map.geometry().index_of(Eigen::Vector2d(12.0, 0.6));
  ASSERT_TRUE(cell.has_value());
  EXPECT_GT(alone.map.get("max")((*cell).x(), (*cell).y()), 1.0F);
  EXPECT_TRUE(std::isnan(seen.map.get("max")((*cell).x(), (*cell).y())));
}

TEST(ShadowAware, BeamsWithoutAReturnAreRotatedByTheLevelingTransform) {
  // The scene and its beams seen from a sensor yawed 90 degrees and rolled 5: the transform levels
  // both, so the reasons are those of the level scene.
  const Eigen::Matrix3d rotation =
      (Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(0.087, Eigen::Vector3d::UnitX()))
          .toRotationMatrix();
  Points tilted;
  for (const Eigen::Vector3d& p : crown_behind_a_hedge()) tilted.push_back(rotation.transpose() * p);
  CollapseParams params = shadow_aware_params();
  params.transform.topLeftCorner<3, 3>() = rotation;
  std::vector<Eigen::Vector3d> beams;
  for (const Eigen::Vector3d& beam : fan_of_beams(0.0)) beams.push_back(rotation.transpose() * beam);
  const CollapseResult result = collapse_overhangs(tilted, params, PointsView<double>(beams));
  EXPECT_EQ(reason_at(result, {12.0, 0.5, 1.6}), CubeReason::kRemovedFreeBelow);
  EXPECT_EQ(reason_at(result, {8.0, 0.0, -0.5}), CubeReason::kSupported);
}

TEST(ShadowAware, TheResultIsTheSameForAnyThreadCountAndStorage) {
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> across(-20.0, 20.0), up(1.0, 4.0);
  std::normal_distribution<double> noise(0.0, 0.05);
  Points points;
  for (int i = 0; i < 20000; ++i) points.emplace_back(across(rng), across(rng), -1.7 + noise(rng));
  for (int i = 0; i < 3000; ++i) points.emplace_back(across(rng) * 0.3 + 5.0, across(rng) * 0.3, up(rng));
  CollapseParams params = shadow_aware_params(3);
  const CollapseResult one = collapse_overhangs(points, params);
  ASSERT_GT(one.num_overhang, 0U);
  for (const auto& [storage, threads] :
       {std::pair{CubeStorage::kSparse, 1}, std::pair{CubeStorage::kDense, 0}, std::pair{CubeStorage::kAuto, 3}}) {
    params.storage = storage;
    params.num_threads = threads;
    const CollapseResult other = collapse_overhangs(points, params);
    EXPECT_EQ(other.overhang, one.overhang);
    EXPECT_EQ(other.cube_reasons, one.cube_reasons);
  }
}

TEST(ShadowAware, BadParametersThrowInvalidArgumentNamingThem) {
  const Points points = {{0, 0, 0}, {1, 1, 1}};
  CollapseParams params = shadow_aware_params();
  params.shadow_aware.ground_radius_m = -1.0;
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
  params = shadow_aware_params();
  params.shadow_aware.ground_support = 10;
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
  params = shadow_aware_params();
  params.shadow_aware.hidden_ground_margin_m = -0.5;
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
  params = shadow_aware_params();
  params.shadow_aware.azimuth_bins = 0;
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
  params = shadow_aware_params();
  params.shadow_aware.sensor_origin = Eigen::Vector3d(0.0, std::nan(""), 0.0);
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
  for (const double range : {0.0, -1.0, std::nan(""), HUGE_VAL}) {
    params = shadow_aware_params();
    params.shadow_aware.no_return_range_m = range;
    EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument) << range;
  }
  for (const Eigen::Vector3d& beam :
       {Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(1, std::nan(""), 0), Eigen::Vector3d(HUGE_VAL, 0, 0)}) {
    const std::vector<Eigen::Vector3d> beams = {Eigen::Vector3d(1, 0, 0), beam};
    try {
      collapse_overhangs(points, shadow_aware_params(), PointsView<double>(beams));
      FAIL() << "a beam of " << beam.transpose() << " was accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("no_return_directions row 1"), std::string::npos) << e.what();
    }
  }
  EXPECT_THROW(collapse_overhangs(points, shadow_aware_params(), PointsView<double>(nullptr, 4)),
               std::invalid_argument);
  // A survey in its own coordinates (the ground 49 m up) with the default origin at 0.
  Points survey;
  add_grid(survey, 0, 10, 0, 10, 49.0);
  add_grid(survey, 2, 6, 2, 6, 55.0);
  params = shadow_aware_params();
  try {
    collapse_overhangs(survey, params);
    FAIL() << "an origin 49 m under the cloud was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("49 m below the lowest point"), std::string::npos) << e.what();
  }
  params.shadow_aware.sensor_origin = Eigen::Vector3d(5.0, 5.0, 50.5);
  EXPECT_GT(collapse_overhangs(survey, params).num_overhang, 0U);
  params.shadow_aware.sensor_origin = Eigen::Vector3d(5.0, 5.0, 40.0);  // a slope's foot, 9 m down
  EXPECT_NO_THROW(collapse_overhangs(survey, params));
  // A tile in map coordinates (an airborne survey 5,000 km east) with the default origin: the
  // message names the distance to the origin, not the cloud's size.
  Points tile;
  add_grid(tile, 5e6, 5e6 + 10, 0, 10, 1.0);
  try {
    collapse_overhangs(tile, shadow_aware_params());
    FAIL() << "an origin 5,000 km from the cloud was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("reaches 5.00001e+06 m from the sensor origin"), std::string::npos)
        << e.what();
  }
}

TEST(ShadowAware, HostileCloudsAndParametersGiveAResultOrAStandardException) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  const double lengths[] = {0.0, 1e-300, 1e-6, 0.5, 40.0, 1e12, 1e300};
  int returned = 0;
  for (int trial = 0; trial < 200; ++trial) {
    Points points(static_cast<std::size_t>(rng() % 300));
    const double spread = lengths[rng() % 7];
    for (auto& p : points) p = {unit(rng) * spread, unit(rng) * spread, unit(rng) * spread * 0.1};
    CollapseParams params = shadow_aware_params(1 + static_cast<int>(rng() % 6));
    params.edge_m = rng() % 4 == 0 ? lengths[rng() % 7] : 0.5;
    params.storage = static_cast<CubeStorage>(rng() % 3);
    params.dense_budget_bytes = std::size_t{16} << 20;
    params.shadow_aware.ground_radius_m = rng() % 4 == 0 ? lengths[rng() % 7] : 5.0;
    params.shadow_aware.ground_support = static_cast<int>(rng() % 11);
    params.shadow_aware.min_bottom_neighbours = static_cast<int>(rng() % 10) - 1;
    params.shadow_aware.free_margin_m = rng() % 4 == 0 ? -1.0 : 0.25;
    params.shadow_aware.hidden_ground_margin_m = rng() % 4 == 0 ? lengths[rng() % 7] - 1.0 : 2.0;
    params.shadow_aware.azimuth_bins = rng() % 4 == 0 ? static_cast<int>(rng()) : 512;
    if (rng() % 3 == 0) params.shadow_aware.sensor_origin = Eigen::Vector3d(lengths[rng() % 7], 0.0, 1.0);
    try {
      const CollapseResult result = collapse_overhangs(points, params);
      EXPECT_EQ(result.cube_reasons.size(), result.occupied_cubes.size());
      ++returned;
    } catch (const std::invalid_argument&) {
    } catch (const std::length_error&) {
    } catch (const std::bad_alloc&) {
    }
  }
  EXPECT_GT(returned, 20);
}

TEST(ShadowAware, AGroundWindowWiderThanTheCloudIsTheWholeCloud) {
  // A 200 km long, one column wide cloud with a ground radius of 1e9 m: the window's minima padded
  // each column by 2 x 400,000 empty cubes, band after band (hours; found by fuzzing). A window
  // past both ends of a line is the whole line: the same result as a radius just covering it.
  Points points;
  for (int k = 0; k <= 400; ++k) {
    points.push_back({500.0 * k, 0.0, 0.0});
    if (k % 2 == 0) points.push_back({500.0 * k, 0.0, 6.0});  // something overhead in half the columns
  }
  CollapseParams params = shadow_aware_params(2);
  params.shadow_aware.sensor_origin = Eigen::Vector3d(0.0, 0.0, 1.7);
  params.shadow_aware.azimuth_bins = 1;
  params.shadow_aware.ground_radius_m = 1e9;
  const CollapseResult wide = collapse_overhangs(points, params);
  params.shadow_aware.ground_radius_m = 2.1e5;  // just over the cloud's length
  const CollapseResult covering = collapse_overhangs(points, params);
  EXPECT_EQ(wide.overhang, covering.overhang);
  EXPECT_EQ(wide.cube_reasons, covering.cube_reasons);
}

TEST(ShadowAware, PointReasonsAreTheReasonsOfEachRowsCube) {
  // The crown over a curb, tilted and cropped, as float32 rows with a NaN row (dropped).
  Points scene;
  add_grid(scene, 1, 5, -5, 5, -1.7);
  add_grid(scene, 14, 20, -5, 5, -1.7, 0.1);
  add_face_x(scene, 5.0, -5, 5, -1.7, -1.4);
  add_face_x(scene, 9.0, -0.2, 0.2, -1.4, 1.5, 0.1);
  for (const double z : {1.6, 2.4, 3.2, 3.8}) add_grid(scene, 7.75, 10.25, -1.25, 1.25, z);
  std::vector<float> rows;
  for (const Eigen::Vector3d& p : scene) rows.insert(rows.end(), {float(p.x()), float(p.y()), float(p.z())});
  rows.insert(rows.end(), {std::nanf(""), 1.0F, 1.0F});
  const PointsView<float> view(rows.data(), scene.size() + 1);
  CollapseParams params = shadow_aware_params();
  params.transform = leveling_transform(0.02, -0.03);
  params.crop = CropBox{Eigen::Vector3d(-100, -100, -100), Eigen::Vector3d(100, 4.0, 100)};  // y > 4 m out
  params.drop_non_finite = true;
  const CollapseResult result = collapse_overhangs(view, params);
  const std::vector<CubeReason> reasons = point_reasons(view, params, result);
  ASSERT_EQ(reasons.size(), view.size);
  std::size_t not_used = 0, removed = 0;
  for (std::size_t row = 0; row < view.size; ++row) {
    const Eigen::Vector3d p = view.point(row);
    Eigen::Vector3d q;  // [CBC]'s leveled point, as the library computes it
    for (int i = 0; i < 3; ++i) {
      q[i] = params.transform(i, 0) * p.x() + params.transform(i, 1) * p.y() + params.transform(i, 2) * p.z() +
             params.transform(i, 3);
    }
    if (!q.allFinite() || q.y() > 4.0) {
      EXPECT_EQ(reasons[row], CubeReason::kNotUsed) << row;
      ++not_used;
      continue;
    }
    EXPECT_EQ(reasons[row], reason_at(result, q)) << row;
    const bool is_removed =
        reasons[row] == CubeReason::kRemovedFreeBelow || reasons[row] == CubeReason::kRemovedAboveKept;
    EXPECT_EQ(is_removed, result.overhang[row] == 1) << row;
    removed += is_removed ? 1 : 0;
  }
  EXPECT_EQ(not_used, result.num_cropped + result.num_dropped_non_finite);
  EXPECT_GT(not_used, 1U);
  EXPECT_GT(removed, 0U);
  EXPECT_STREQ(cube_reason_name(CubeReason::kNotUsed), "not_used");

  // Another result, other rows or a paper result: refused, never a wrong lookup.
  CollapseParams paper = params;
  paper.method = CollapseMethod::kPaper;
  EXPECT_THROW(point_reasons(view, paper, collapse_overhangs(view, paper)), std::invalid_argument);
  EXPECT_THROW(point_reasons(PointsView<float>(rows.data(), view.size - 1), params, result), std::invalid_argument);
  std::vector<float> moved = rows;
  moved[0] += 50.0F;  // the first row now lies outside every occupied cube
  EXPECT_THROW(point_reasons(PointsView<float>(moved.data(), view.size), params, result), std::invalid_argument);
}

TEST(ShadowAware, ThePaperMethodLeavesNoReasons) {
  Points points;
  add_grid(points, 0, 4, 0, 4, 0.0);
  add_grid(points, 0, 2, 0, 2, 3.0);
  CollapseParams params = shadow_aware_params(2);
  params.method = CollapseMethod::kPaper;
  const CollapseResult result = collapse_overhangs(points, params);
  EXPECT_GT(result.num_overhang, 0U);
  EXPECT_TRUE(result.cube_reasons.empty());
  EXPECT_STREQ(cube_reason_name(CubeReason::kRemovedFreeBelow), "removed_free_below");
}

}  // namespace
}  // namespace terracube
