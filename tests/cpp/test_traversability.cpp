// add_traversability_layers on an ElevationMap: closed forms of a tilted plane and a step, the
// clearance veto, unknown cells, and the errors.
#include <gtest/gtest.h>
#include <terracube/traversability.hpp>

#include <Eigen/QR>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <vector>

namespace terracube {
namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

/// A 20 x 12 map at 0.1 m whose "mean" is height(i, j).
template <typename Height>
ElevationMap map_of(Height&& height) {
  MapGeometry geometry;
  geometry.resolution_m = 0.1;
  geometry.size = CellIndex(20, 12);
  ElevationMap map(geometry);
  Layer mean(20, 12);
  for (int i = 0; i < 20; ++i) {
    for (int j = 0; j < 12; ++j) mean(i, j) = static_cast<float>(height(i, j));
  }
  map.add("mean", mean);
  return map;
}

TEST(Traversability, ATiltedPlaneHasItsSlopeNoRoughnessAndTheFormulasCost) {
  const double slope = 0.1;  // rad, rising along y
  ElevationMap map = map_of([&](int, int j) { return std::tan(slope) * 0.1 * j; });
  TraversabilityParams params;  // 7 x 7 windows, no clearance layer: nothing overhangs
  add_traversability_layers(map, params);
  for (const auto& [i, j] : {std::pair{0, 0}, std::pair{10, 6}, std::pair{19, 11}}) {
    EXPECT_NEAR(map.get("slope")(i, j), slope, 1e-5);
    EXPECT_NEAR(map.get("roughness")(i, j), 0.0, 1e-5);
    // The window spans 3 rows of y beside a border cell, 7 inside.
    const int columns = std::min(j + 3, 11) - std::max(j - 3, 0);
    const double step = std::tan(slope) * 0.1 * columns;
    EXPECT_NEAR(map.get("step")(i, j), step, 1e-6);
    const double cost = (slope / params.max_slope_rad + step / params.max_step_m) / 3.0;
    EXPECT_NEAR(map.get("traversability")(i, j), 1.0 - cost, 1e-5);
  }
}

TEST(Traversability, AStepBlocksItsNeighbourhoodAndALowClearanceItsCell) {
  ElevationMap map = map_of([](int i, int) { return i >= 10 ? 0.3 : 0.0; });
  map.get("mean")(2, 2) = kNaN;
  map.get("mean")(3, 9) = std::numeric_limits<float>::infinity();  // unknown too, not a step
  Layer clearance = Layer::Constant(20, 12, std::numeric_limits<float>::infinity());
  clearance(15, 6) = 0.5F;  // under a 0.7 m robot's height
  map.add("clearance", clearance);
  add_traversability_layers(map);
  EXPECT_FLOAT_EQ(map.get("step")(9, 6), 0.3F);
  EXPECT_EQ(map.get("traversability")(9, 6), 0.0F);  // the step is over max_step_m
  EXPECT_EQ(map.get("traversability")(15, 6), 0.0F);
  EXPECT_EQ(map.get("step")(15, 6), 0.0F);
  EXPECT_GT(map.get("traversability")(15, 3), 0.99F);  // flat, open
  for (const char* name : {"step", "slope", "roughness", "traversability"}) {
    EXPECT_TRUE(std::isnan(map.get(name)(2, 2))) << name;
    EXPECT_TRUE(std::isnan(map.get(name)(3, 9))) << name;
  }
  EXPECT_EQ(map.get("step")(3, 8), 0.0F);
  EXPECT_GT(map.get("traversability")(3, 8), 0.99F);
}

TEST(Traversability, AWindowWithTooFewKnownCellsHasNoSlope) {
  ElevationMap map = map_of([](int i, int j) { return (i == 5 && j < 3) || (i == 6 && j == 0) ? 0.0 : kNaN; });
  TraversabilityParams params;
  params.min_window_cells = 5;
  add_traversability_layers(map, params);
  EXPECT_EQ(map.get("step")(5, 0), 0.0F);
  EXPECT_TRUE(std::isnan(map.get("slope")(5, 0)));  // 4 known cells
  params.min_window_cells = 4;
  add_traversability_layers(map, params);
  EXPECT_NEAR(map.get("slope")(5, 0), 0.0, 1e-6);
}

TEST(Traversability, PartsAndThreadsGiveTheNaiveFitOfEveryWindowBitForBitAlike) {
  // 240 x 150 cells: the rows are cut into two parts whose windows start afresh; every cell's slope
  // and roughness against a plain least-squares solve over its window, its step and traversability
  // against a plain loop and the formula, on 1, 2 and all threads.
  MapGeometry geometry;
  geometry.size = CellIndex(240, 150);
  ElevationMap map(geometry);
  Layer height(240, 150);
  for (int i = 0; i < 240; ++i) {
    for (int j = 0; j < 150; ++j) {
      height(i, j) = (i * 7 + j * 3) % 11 == 0 ? kNaN : static_cast<float>(0.3 * std::sin(0.07 * i) + 0.01 * (j % 5));
    }
  }
  map.add("mean", height);
  TraversabilityParams params;
  params.footprint_radius_m = 0.2;  // 5 x 5 windows
  add_traversability_layers(map, params);
  for (const int threads : {2, 0}) {
    ElevationMap again = map;
    add_traversability_layers(again, params, "mean", CellIndex(0, 0), threads);
    for (const char* name : {"step", "slope", "roughness", "traversability"}) {
      const Layer& a = map.get(name);
      const Layer& b = again.get(name);
      for (Eigen::Index k = 0; k < a.size(); ++k) {
        ASSERT_TRUE(a.data()[k] == b.data()[k] || (std::isnan(a.data()[k]) && std::isnan(b.data()[k]))) << name;
      }
    }
  }
  for (int i = 0; i < 240; ++i) {
    for (int j = 0; j < 150; ++j) {
      if (std::isnan(height(i, j))) continue;
      std::vector<Eigen::Vector3d> cells;
      float lowest = height(i, j), highest = height(i, j);
      for (int a = std::max(i - 2, 0); a <= std::min(i + 2, 239); ++a) {
        for (int b = std::max(j - 2, 0); b <= std::min(j + 2, 149); ++b) {
          if (std::isnan(height(a, b))) continue;
          cells.emplace_back(a, b, height(a, b));
          lowest = std::min(lowest, height(a, b));
          highest = std::max(highest, height(a, b));
        }
      }
      Eigen::MatrixXd design(cells.size(), 3);
      Eigen::VectorXd z(cells.size());
      for (std::size_t k = 0; k < cells.size(); ++k) {
        design.row(static_cast<Eigen::Index>(k)) << cells[k].x(), cells[k].y(), 1.0;
        z(static_cast<Eigen::Index>(k)) = cells[k].z();
      }
      const Eigen::Vector3d plane = design.colPivHouseholderQr().solve(z);
      const double roughness = std::sqrt((design * plane - z).squaredNorm() / static_cast<double>(cells.size()));
      const double slope = std::atan(plane.head<2>().norm() / 0.1);
      ASSERT_NEAR(map.get("slope")(i, j), slope, 1e-5) << i << " " << j;
      ASSERT_NEAR(map.get("roughness")(i, j), roughness, 1e-5) << i << " " << j;
      ASSERT_EQ(map.get("step")(i, j), highest - lowest) << i << " " << j;
      // The formula of traversability.hpp, its three weights 1 (no clearance layer).
      const double step = highest - lowest;
      const bool blocked =
          slope > params.max_slope_rad || step > params.max_step_m || roughness > params.max_roughness_m;
      const double cost =
          (slope / params.max_slope_rad + step / params.max_step_m + roughness / params.max_roughness_m) / 3;
      ASSERT_NEAR(map.get("traversability")(i, j), blocked ? 0.0 : 1.0 - cost, 1e-4) << i << " " << j;
    }
  }
}

TEST(Traversability, BadCallsThrowNamingTheProblem) {
  ElevationMap map = map_of([](int, int) { return 0.0; });
  EXPECT_THROW(add_traversability_layers(map, {}, "elevation"), std::out_of_range);
  TraversabilityParams bad;
  bad.max_step_m = 0.0;
  try {
    add_traversability_layers(map, bad);
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("max_step_m"), std::string::npos);
  }
  EXPECT_THROW(add_traversability_layers(map, {}, "mean", CellIndex(20, 0)), std::invalid_argument);
  EXPECT_THROW(add_traversability_layers(map, {}, "mean", CellIndex(0, 0), -1), std::invalid_argument);
  TraversabilityParams huge;
  huge.footprint_radius_m = 1e300;  // a window over the whole map
  add_traversability_layers(map, huge);
  EXPECT_EQ(map.get("step")(0, 0), 0.0F);
  // A window of more than 511 cells a side would cost over 2000 reads a cell: refused, named.
  ElevationMap fine(MapGeometry{0.001, Eigen::Vector2d::Zero(), CellIndex(600, 3)});
  fine.add("mean", 0.0F);
  try {
    add_traversability_layers(fine);  // 0.3 m at 1 mm: 601 cells a side
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("601 cells a side, over 511"), std::string::npos) << e.what();
  }
  huge.footprint_radius_m = 0.255;  // 511 cells: the widest window taken
  add_traversability_layers(fine, huge);
  EXPECT_EQ(fine.get("step")(0, 0), 0.0F);
  // A window's rows of two million cells each would need 7 x 2e6 x 80 bytes of sums: refused.
  ElevationMap wide(MapGeometry{0.1, Eigen::Vector2d::Zero(), CellIndex(7, 2000000)});
  wide.add("mean", 0.0F);
  try {
    add_traversability_layers(wide);
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("would need over 1 GB"), std::string::npos) << e.what();
  }
  EXPECT_FALSE(wide.exists("step"));  // refused before any layer is added
}

}  // namespace
}  // namespace terracube
