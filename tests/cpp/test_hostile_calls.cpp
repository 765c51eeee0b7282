// A seeded mutator over the core's entry points (issue 39): hostile clouds (NaN, Inf, huge and
// tiny coordinates, empty, one point) and hostile parameters (zero, negative, NaN, huge, subnormal)
// in random combinations. Every call must return or throw a standard exception naming the problem:
// never crash, hang or write out of bounds (run under ASan and UBSan in CI).
#include <gtest/gtest.h>
#include <terracube/collapse.hpp>
#include <terracube/elevation_map.hpp>
#include <terracube/icp.hpp>
#include <terracube/terrain.hpp>

#include <cmath>
#include <cstdint>
#include <limits>
#include <new>
#include <random>
#include <stdexcept>
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

}  // namespace
}  // namespace terracube
