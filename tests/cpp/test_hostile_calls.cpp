// A seeded mutator over the core's entry points (issue 39): hostile clouds (NaN, Inf, huge and
// tiny coordinates, empty, one point) and hostile parameters (zero, negative, NaN, huge, subnormal)
// in random combinations. Every call must return or throw a standard exception naming the problem:
// never crash, hang or write out of bounds (run under ASan and UBSan in CI).
#include <gtest/gtest.h>
#include <terracube/collapse.hpp>
#include <terracube/elevation_map.hpp>
#include <terracube/fuzzy.hpp>
#include <terracube/icp.hpp>
#include <terracube/local_map.hpp>
#include <terracube/mapper.hpp>
#include <terracube/terrain.hpp>

#include <cmath>
#include <cstdint>
#include <limits>
#include <new>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

namespace terracube {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

/// A value drawn mostly from a plain range, sometimes from the hostile ones.
double hostile_value(std::mt19937& rng, double plain) {
  static const double kWild[] = {kNaN, kInf, -kInf, 1e300, -1e300, 1e-300, 5e-324, 1e15, -1e15, 0.0};
  if (rng() % 8 != 0) return std::uniform_real_distribution<double>(-plain, plain)(rng);
  return kWild[rng() % (sizeof(kWild) / sizeof(kWild[0]))];
}

/// A length parameter: usually sensible, sometimes hostile.
double hostile_length(std::mt19937& rng, double sensible) {
  static const double kWild[] = {0.0, -1.0, kNaN, kInf, 1e-300, 5e-324, 1e-9, 1e9};
  return rng() % 3 != 0 ? sensible : kWild[rng() % (sizeof(kWild) / sizeof(kWild[0]))];
}

std::vector<double> hostile_cloud(std::mt19937& rng) {
  static const std::size_t kSizes[] = {0, 1, 2, 17, 300, 3000};
  const std::size_t n = kSizes[rng() % 6];
  std::vector<double> values(3 * n);
  const double extent = rng() % 4 == 0 ? 1e4 : 20.0;
  for (double& v : values) v = hostile_value(rng, extent);
  return values;
}

/// Runs `call`; a standard exception is a fine answer, anything else fails the test. Counts the
/// calls that answered and those that returned a result.
template <typename Call>
void returns_or_throws(const Call& call, int& answered, int& returned) {
  try {
    call();
    ++returned;
  } catch (const std::invalid_argument&) {
  } catch (const std::out_of_range&) {
  } catch (const std::length_error&) {
  } catch (const std::bad_alloc&) {
  }
  ++answered;
}

TEST(HostileCalls, SeededMutationsOfCloudsAndParametersEndInAResultOrAnException) {
  std::mt19937 rng(20261202);
  int answered = 0, returned = 0;
  for (int round = 0; round < 400; ++round) {
    const std::vector<double> cloud = hostile_cloud(rng);
    const PointsView<double> view(cloud.empty() ? nullptr : cloud.data(), cloud.size() / 3);
    CollapseParams collapse;
    collapse.edge_m = hostile_length(rng, 0.5);
    collapse.sigma = rng() % 4 == 0 ? static_cast<int>(rng()) : 1 + static_cast<int>(rng() % 5);
    collapse.drop_non_finite = rng() % 2 == 0;
    collapse.storage = static_cast<CubeStorage>(rng() % 3);
    collapse.dense_budget_bytes = std::size_t{16} << 20;
    if (rng() % 4 == 0) collapse.crop = CropBox{{-5.0, -5.0, -hostile_length(rng, 2.0)}, {5.0, 5.0, 3.0}};
    ElevationParams map;
    map.resolution_m = hostile_length(rng, 0.2);
    map.discontinuity_m = hostile_length(rng, 1.0);
    map.drop_non_finite = collapse.drop_non_finite;
    map.max_cells = std::size_t{1} << 20;  // bounds the memory of a fuzz case, not the check
    if (rng() % 3 == 0) {
      map.origin_m = Eigen::Vector2d(hostile_value(rng, 20.0), hostile_value(rng, 20.0));
      map.size = CellIndex(static_cast<int>(rng() % 300) - 5, static_cast<int>(rng() % 300) - 5);
    }
    TerrainParams terrain;
    terrain.sensor_height_m = hostile_value(rng, 2.0);
    terrain.robot_height_m = hostile_length(rng, 0.7);
    terrain.reference = static_cast<GroundReference>(rng() % 2);
    terrain.local_ground_radius_cells = rng() % 5 == 0 ? -1 : static_cast<int>(rng() % 20);

    returns_or_throws([&] { collapse_overhangs(view, collapse); }, answered, returned);
    returns_or_throws([&] { build_overhang_free_map(view, collapse, map); }, answered, returned);
    returns_or_throws(
        [&] {
          ElevationMap built = build_elevation_map(view, map);
          classify_terrain(built, terrain);
          ClassifiedPoints points = points_of_map(built);
          RegistrationParams registration;
          registration.max_iterations = 5;
          registration.max_correspondence_distance_m = hostile_length(rng, 1.5);
          Eigen::Matrix4d guess = Eigen::Matrix4d::Identity();
          guess(0, 3) = hostile_value(rng, 1.0);
          register_points(points, points, guess, registration);
        },
        answered, returned);
  }
  EXPECT_EQ(answered, 3 * 400);
  // Enough cases pass the checks to reach the algorithms, or the fuzzing proves little.
  EXPECT_GT(returned, 3 * 400 / 5) << returned << " of " << answered << " calls returned a result";
}

/// What `call` throws as std::invalid_argument ("" when it returns).
template <typename Call>
std::string refusal_of(const Call& call) {
  try {
    call();
  } catch (const std::invalid_argument& error) {
    return error.what();
  }
  return "";
}

// Each parameter struct's public check accepts its defaults and refuses a bad field with the
// message that the call taking the struct gives, so a configuration can be checked before a scan.
TEST(ParameterChecks, EachCheckAcceptsTheDefaultsAndRefusesWhatItsCallRefuses) {
  const std::vector<double> rows = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 3};
  const PointsView<double> cloud(rows.data(), 4);
  EXPECT_EQ(refusal_of([] { check_collapse_params({}); }), "");
  for (int field = 0; field < 3; ++field) {
    CollapseParams bad;
    if (field == 0) bad.edge_m = -1.0;
    if (field == 1) bad.shadow_aware.ground_support = 12;
    if (field == 2) bad.shadow_aware.free_margin_m = kNaN;
    const std::string refusal = refusal_of([&] { check_collapse_params(bad); });
    EXPECT_NE(refusal, "") << "field " << field;
    EXPECT_EQ(refusal, refusal_of([&] { collapse_overhangs(cloud, bad); }));
  }
  EXPECT_EQ(refusal_of([] { check_elevation_params({}); }), "");
  ElevationParams coarse;
  coarse.resolution_m = 0.0;
  EXPECT_NE(refusal_of([&] { check_elevation_params(coarse); }), "");
  EXPECT_EQ(refusal_of([&] { check_elevation_params(coarse); }),
            refusal_of([&] { build_elevation_map(cloud, coarse); }));
  EXPECT_EQ(refusal_of([] { check_terrain_params({}); }), "");
  TerrainParams flat;
  flat.std_dev_m = -1.0;
  ElevationMap map = build_elevation_map(cloud, {});
  EXPECT_NE(refusal_of([&] { check_terrain_params(flat); }), "");
  EXPECT_EQ(refusal_of([&] { check_terrain_params(flat); }), refusal_of([&] { classify_terrain(map, flat); }));
  EXPECT_EQ(refusal_of([] { check_registration_params({}); }), "");
  RegistrationParams searching;
  searching.search.window_m = -1.0;  // checked even when the search is off
  searching.correlative_search = false;
  EXPECT_NE(refusal_of([&] { check_registration_params(searching); }).find("window_m"), std::string::npos);
  EXPECT_EQ(refusal_of([] { check_fuzzy_params({}); }), "");
  FuzzyParams one_rule;
  one_rule.rules_x = 1;
  EXPECT_EQ(refusal_of([&] { check_fuzzy_params(one_rule); }),
            refusal_of([&] { fit_fuzzy_elevation_map(cloud, one_rule); }));
  EXPECT_EQ(refusal_of([] { check_mapper_params({}); }), "");
  MapperParams mapper;
  mapper.registration.max_iterations = 0;  // the mapper's own registration is checked with it
  EXPECT_NE(refusal_of([&] { check_mapper_params(mapper); }), "");
  EXPECT_EQ(refusal_of([&] { check_mapper_params(mapper); }), refusal_of([&] { Mapper{mapper}; }));
  EXPECT_EQ(refusal_of([] { check_local_map_params({}); }), "");
  LocalMapParams local;
  local.collapse.shadow_aware.bottom_window = 0;
  EXPECT_NE(refusal_of([&] { check_local_map_params(local); }), "");
  EXPECT_EQ(refusal_of([&] { check_local_map_params(local); }), refusal_of([&] { LocalMap{local}; }));
}

}  // namespace
}  // namespace terracube
