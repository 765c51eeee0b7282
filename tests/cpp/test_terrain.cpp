#include <gtest/gtest.h>
#include <terracube/elevation_map.hpp>
#include <terracube/terrain.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <iostream>
#include <limits>
#include <map>
#include <random>
#include <set>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "test_support.hpp"

namespace terracube {

// Readable class names in gtest failure messages.
void PrintTo(TerrainClass c, std::ostream* os) {
  static const char* const kNames[] = {"unknown", "ground", "obstacle", "overhanging", "vertical", "edge"};
  const auto value = static_cast<unsigned>(c);
  *os << (value < 6 ? kNames[value] : "invalid") << " (" << value << ")";
}

namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

// --- helpers ----------------------------------------------------------------------------------

/// A hand-made map of nx x ny cells, all holding the same statistics (min = max).
ElevationMap uniform_map(int nx, int ny, float max, float std_dev, float discontinuity = 0.0F) {
  MapGeometry geometry;
  geometry.resolution_m = 0.5;
  geometry.size = CellIndex(nx, ny);
  ElevationMap map(geometry);
  map.add("count", 3.0F);
  map.add("min", max);
  map.add("max", max);
  map.add("mean", max);
  map.add("std_dev", std_dev);
  map.add("discontinuity", discontinuity);
  return map;
}

void set_cell(ElevationMap& map, int i, int j, float max, float std_dev, float discontinuity = 0.0F) {
  map.get("count")(i, j) = 3.0F;
  map.get("min")(i, j) = max;
  map.get("max")(i, j) = max;
  map.get("mean")(i, j) = max;
  map.get("std_dev")(i, j) = std_dev;
  map.get("discontinuity")(i, j) = discontinuity;
}

void clear_cell(ElevationMap& map, int i, int j) {
  map.get("count")(i, j) = 0.0F;
  for (const std::string name : {"min", "max", "mean", "std_dev", "discontinuity"}) map.get(name)(i, j) = kNaN;
}

/// The class of a lone cell (no neighbours, so no horizontal edge).
TerrainClass classify_cell(float max, float std_dev, float discontinuity, const TerrainParams& params) {
  ElevationMap map = uniform_map(1, 1, max, std_dev, discontinuity);
  return static_cast<TerrainClass>(classify_terrain(map, params).classes(0, 0));
}

/// Thresholds exactly representable in float: low < 0.25 <= middle < 1.0 <= high, small std < 0.5.
TerrainParams exact_params(double sensor_height_m = 0.0) {
  TerrainParams params;
  params.ground_height_m = 0.25;
  params.std_dev_m = 0.5;
  params.robot_height_m = 1.0;
  params.sensor_height_m = sensor_height_m;
  return params;
}

/// Classes as rows of letters: . unknown, g ground, o obstacle, h overhanging, v vertical, e edge.
std::vector<std::string> letters(const TerrainClassification& result) {
  static const char kLetters[] = ".gohve";
  std::vector<std::string> rows;
  for (Eigen::Index i = 0; i < result.classes.rows(); ++i) {
    std::string row;
    for (Eigen::Index j = 0; j < result.classes.cols(); ++j) row += kLetters[result.classes(i, j)];
    rows.push_back(row);
  }
  return rows;
}

template <typename Error>
void expect_throw_with(const std::function<void()>& call, const std::string& part) {
  try {
    call();
    ADD_FAILURE() << "expected an exception";
  } catch (const Error& error) {
    EXPECT_NE(std::string(error.what()).find(part), std::string::npos) << error.what();
  }
}

// --- [TC] Table 1, one row at a time -----------------------------------------------------------------

// [TC] Table 1: rows "Small"/"Large" spread, columns "Low"/"Middle"/"High" highest elevation.
// With exact_params: low < 0.25 <= middle <= 1.0 < high, small std-dev < 0.5.

TEST(TerrainRule, SmallSpreadAndLowIsGround) {
  const TerrainParams params = exact_params();
  EXPECT_EQ(classify_cell(0.125F, 0.25F, 0.0F, params), TerrainClass::kGround);
  EXPECT_EQ(classify_cell(0.0F, 0.0F, 0.0F, params), TerrainClass::kGround);
  EXPECT_EQ(classify_cell(-3.0F, 0.0F, 0.0F, params), TerrainClass::kGround) << "below the ground plane is low";
}

TEST(TerrainRule, SmallSpreadAndMiddleIsObstacle) {
  const TerrainParams params = exact_params();
  EXPECT_EQ(classify_cell(0.5F, 0.0F, 0.0F, params), TerrainClass::kObstacle);
  EXPECT_EQ(classify_cell(0.75F, 0.25F, 0.0F, params), TerrainClass::kObstacle);
}

TEST(TerrainRule, SmallSpreadAndHigherThanTheRobotIsOverhanging) {
  // Eaves, crowns and car roofs seen from below: "higher than the robot" with a small spread.
  const TerrainParams params = exact_params();
  EXPECT_EQ(classify_cell(2.0F, 0.25F, 0.0F, params), TerrainClass::kOverhangingObject);
  EXPECT_EQ(classify_cell(1.5F, 0.0F, 0.0F, params), TerrainClass::kOverhangingObject);
}

TEST(TerrainRule, LargeSpreadWithoutDiscontinuityIsVerticalInEveryHeightColumn) {
  // The "Large" row's entries span the Low, Middle and High columns.
  const TerrainParams params = exact_params();
  EXPECT_EQ(classify_cell(0.125F, 0.75F, 0.0F, params), TerrainClass::kVerticalObject);  // low
  EXPECT_EQ(classify_cell(0.5F, 0.75F, 0.0F, params), TerrainClass::kVerticalObject);    // middle
  EXPECT_EQ(classify_cell(2.0F, 0.75F, 0.0F, params), TerrainClass::kVerticalObject);    // high
}

TEST(TerrainRule, LargeSpreadWithDiscontinuityIsOverhangingInEveryHeightColumn) {
  const TerrainParams params = exact_params();
  EXPECT_EQ(classify_cell(0.125F, 0.75F, 1.0F, params), TerrainClass::kOverhangingObject);  // low
  EXPECT_EQ(classify_cell(0.5F, 0.75F, 1.0F, params), TerrainClass::kOverhangingObject);    // middle
  EXPECT_EQ(classify_cell(2.0F, 0.75F, 1.0F, params), TerrainClass::kOverhangingObject);    // high
}

TEST(TerrainRule, DiscontinuityWithASmallSpreadIsStillOverhanging) {
  // Not in the table (a 1 m gap rarely leaves a small spread); class 3's text decides: a grid
  // with a discontinuity is an overhanging object.
  const TerrainParams params = exact_params();
  EXPECT_EQ(classify_cell(0.0F, 0.0F, 1.0F, params), TerrainClass::kOverhangingObject);
  EXPECT_EQ(classify_cell(0.5F, 0.0F, 1.0F, params), TerrainClass::kOverhangingObject);
  EXPECT_EQ(classify_cell(2.0F, 0.25F, 1.0F, params), TerrainClass::kOverhangingObject);
}

TEST(TerrainRule, EmptyCellIsUnknown) {
  EXPECT_EQ(classify_cell(kNaN, kNaN, kNaN, exact_params()), TerrainClass::kUnknown);
}

TEST(TerrainRule, RelativeHeightEqualToGroundHeightIsMiddleNotLow) {
  const TerrainParams params = exact_params();
  EXPECT_EQ(classify_cell(0.25F, 0.0F, 0.0F, params), TerrainClass::kObstacle);
  EXPECT_EQ(classify_cell(std::nextafter(0.25F, 0.0F), 0.0F, 0.0F, params), TerrainClass::kGround);
}

TEST(TerrainRule, HigherThanTheRobotIsStrict) {
  // Exactly the robot height is middle (obstacle); the next float up is high (overhanging).
  const TerrainParams params = exact_params();
  EXPECT_EQ(classify_cell(1.0F, 0.0F, 0.0F, params), TerrainClass::kObstacle);
  EXPECT_EQ(classify_cell(std::nextafter(1.0F, 2.0F), 0.0F, 0.0F, params), TerrainClass::kOverhangingObject);
}

TEST(TerrainRule, StdDevEqualToTheThresholdIsLarge) {
  const TerrainParams params = exact_params();
  EXPECT_EQ(classify_cell(0.125F, 0.5F, 0.0F, params), TerrainClass::kVerticalObject);  // low, large
  EXPECT_EQ(classify_cell(2.0F, 0.5F, 0.0F, params), TerrainClass::kVerticalObject);    // high, large
  EXPECT_EQ(classify_cell(0.125F, std::nextafter(0.5F, 0.0F), 0.0F, params), TerrainClass::kGround);
  EXPECT_EQ(classify_cell(2.0F, std::nextafter(0.5F, 0.0F), 0.0F, params), TerrainClass::kOverhangingObject);
}

TEST(TerrainRule, ThresholdsApplyToHeightAboveTheSensorGroundPlane) {
  // Sensor 1.5 m up: the ground plane is z = -1.5, so max = -1.25 is exactly 0.25 above it.
  const TerrainParams params = exact_params(1.5);
  EXPECT_EQ(classify_cell(-1.375F, 0.0F, 0.0F, params), TerrainClass::kGround);             // 0.125
  EXPECT_EQ(classify_cell(-1.25F, 0.0F, 0.0F, params), TerrainClass::kObstacle);            // 0.25: middle
  EXPECT_EQ(classify_cell(-0.5F, 0.0F, 0.0F, params), TerrainClass::kObstacle);             // 1.0: middle
  EXPECT_EQ(classify_cell(-0.25F, 0.25F, 0.0F, params), TerrainClass::kOverhangingObject);  // 1.25: high
  EXPECT_EQ(classify_cell(0.125F, 0.0F, 0.0F, exact_params()), TerrainClass::kGround);
  EXPECT_EQ(classify_cell(0.125F, 0.0F, 0.0F, params), TerrainClass::kOverhangingObject)  // 1.625: high
      << "the same cell is no longer low once the sensor is 1.5 m up";
}

TEST(TerrainRule, PaperDefaultsOnValuesAwayFromTheThresholds) {
  TerrainParams params;  // [TC] section 3.2: 20 cm, 10 cm, robot 70 cm
  EXPECT_EQ(params.ground_height_m, 0.2);
  EXPECT_EQ(params.std_dev_m, 0.1);
  EXPECT_EQ(params.robot_height_m, 0.7);
  EXPECT_EQ(params.reference, GroundReference::kSensorHeight);
  params.sensor_height_m = 1.73;
  const float ground = -1.73F;
  EXPECT_EQ(classify_cell(ground + 0.05F, 0.02F, 0.0F, params), TerrainClass::kGround);
  EXPECT_EQ(classify_cell(ground + 0.05F, 0.3F, 0.0F, params), TerrainClass::kVerticalObject);
  EXPECT_EQ(classify_cell(ground + 0.45F, 0.02F, 0.0F, params), TerrainClass::kObstacle);
  EXPECT_EQ(classify_cell(ground + 0.45F, 0.3F, 0.0F, params), TerrainClass::kVerticalObject);
  EXPECT_EQ(classify_cell(ground + 1.5F, 0.5F, 0.0F, params), TerrainClass::kVerticalObject);
  EXPECT_EQ(classify_cell(ground + 1.5F, 0.03F, 0.0F, params), TerrainClass::kOverhangingObject);
  EXPECT_EQ(classify_cell(ground + 1.5F, 0.5F, 1.0F, params), TerrainClass::kOverhangingObject);
  EXPECT_EQ(classify_cell(ground + 0.05F, 0.02F, 1.0F, params), TerrainClass::kOverhangingObject);
  EXPECT_EQ(classify_cell(kNaN, kNaN, kNaN, params), TerrainClass::kUnknown);
  // With the default sensor height 0 the plane is z = 0 and a cell 1.6 m below the sensor is low.
  EXPECT_EQ(classify_cell(-1.6F, 0.02F, 0.0F, TerrainParams{}), TerrainClass::kGround);
}

TEST(TerrainRule, RobotHeightEqualToGroundHeightLeavesAOnePointMiddleBand) {
  TerrainParams params = exact_params();
  params.robot_height_m = params.ground_height_m;
  EXPECT_EQ(classify_cell(0.25F, 0.0F, 0.0F, params), TerrainClass::kObstacle);
  EXPECT_EQ(classify_cell(0.5F, 0.0F, 0.0F, params), TerrainClass::kOverhangingObject);
  EXPECT_EQ(classify_cell(0.125F, 0.0F, 0.0F, params), TerrainClass::kGround);
}

// --- horizontal edges ---------------------------------------------------------------------------

TEST(TerrainEdges, GroundBesideAnObjectBecomesEdgeIncludingDiagonals) {
  struct Object {
    float max, std_dev, discontinuity;
    char letter;
  };
  for (const Object object : {Object{0.5F, 0.0F, 0.0F, 'o'}, Object{2.0F, 0.0F, 1.0F, 'h'},
                              Object{2.0F, 0.75F, 0.0F, 'v'}, Object{2.0F, 0.0F, 0.0F, 'h'}}) {
    SCOPED_TRACE(std::string("object ") + object.letter);
    ElevationMap map = uniform_map(5, 5, 0.0F, 0.0F);
    set_cell(map, 2, 2, object.max, object.std_dev, object.discontinuity);
    const std::string centre = std::string("geeeg").replace(2, 1, 1, object.letter);
    EXPECT_EQ(letters(classify_terrain(map, exact_params())),
              (std::vector<std::string>{"ggggg", "geeeg", centre, "geeeg", "ggggg"}));
  }
}

TEST(TerrainEdges, EdgesDoNotPropagate) {
  // The ground two cells from the obstacle touches only edge cells: it stays ground.
  ElevationMap map = uniform_map(1, 6, 0.0F, 0.0F);
  set_cell(map, 0, 0, 0.5F, 0.0F);
  EXPECT_EQ(letters(classify_terrain(map, exact_params())), (std::vector<std::string>{"oegggg"}));
}

TEST(TerrainEdges, GroundBesideUnknownGroundOrEdgeOnlyStaysGround) {
  ElevationMap map = uniform_map(3, 3, 0.0F, 0.0F);
  clear_cell(map, 1, 1);
  clear_cell(map, 0, 0);
  EXPECT_EQ(letters(classify_terrain(map, exact_params())), (std::vector<std::string>{".gg", "g.g", "ggg"}));
}

TEST(TerrainEdges, ObjectsInCornersAndOnBordersMarkOnlyCellsInsideTheMap) {
  ElevationMap map = uniform_map(4, 5, 0.0F, 0.0F);
  set_cell(map, 0, 0, 2.0F, 0.75F);  // vertical
  set_cell(map, 3, 2, 0.5F, 0.0F);   // obstacle
  clear_cell(map, 0, 4);
  EXPECT_EQ(letters(classify_terrain(map, exact_params())),
            (std::vector<std::string>{"vegg.", "eeggg", "geeeg", "geoeg"}));
}

TEST(TerrainEdges, OnlyGroundBecomesEdgeNeverAnotherClass) {
  // Obstacles, vertical and overhanging cells next to each other keep their classes.
  ElevationMap map = uniform_map(1, 4, 0.5F, 0.0F);  // obstacles
  set_cell(map, 0, 1, 2.0F, 0.75F);                  // vertical
  set_cell(map, 0, 2, 0.0F, 0.0F, 1.0F);             // overhanging
  EXPECT_EQ(letters(classify_terrain(map, exact_params())), (std::vector<std::string>{"ovho"}));
}

// --- the vectorised passes against a naive per-cell reference ----------------------------------

/// [TC] Table 1 and the edge rule written out cell by cell, comparing in double as the paper's
/// thresholds are given: the independent reference for the float, branch-free implementation.
Eigen::Matrix<std::uint8_t, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> naive_classes(
    const ElevationMap& map, const TerrainParams& params) {
  const Layer& max = map.get("max");
  const Layer& std_dev = map.get("std_dev");
  const Layer& gap = map.get("discontinuity");
  const float ground = static_cast<float>(-params.sensor_height_m);
  Eigen::Matrix<std::uint8_t, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> classes(max.rows(), max.cols());
  for (Eigen::Index i = 0; i < max.rows(); ++i) {
    for (Eigen::Index j = 0; j < max.cols(); ++j) {
      const float relative = max(i, j) - ground;
      TerrainClass c = TerrainClass::kUnknown;
      if (std::isnan(relative)) {
        c = TerrainClass::kUnknown;
      } else if (gap(i, j) == 1.0F) {
        c = TerrainClass::kOverhangingObject;
      } else {
        // Table 1 as printed: the "Large" row is vertical whatever the height; the "Small" row
        // reads the Low / Middle / High columns ("higher than" the robot is strict).
        const double h = relative;
        const bool small = static_cast<double>(std_dev(i, j)) < params.std_dev_m;
        if (!small) {
          c = TerrainClass::kVerticalObject;
        } else if (h < params.ground_height_m) {
          c = TerrainClass::kGround;
        } else if (h <= params.robot_height_m) {
          c = TerrainClass::kObstacle;
        } else {
          c = TerrainClass::kOverhangingObject;
        }
      }
      classes(i, j) = static_cast<std::uint8_t>(c);
    }
  }
  auto result = classes;
  for (Eigen::Index i = 0; i < max.rows(); ++i) {
    for (Eigen::Index j = 0; j < max.cols(); ++j) {
      if (classes(i, j) != static_cast<std::uint8_t>(TerrainClass::kGround)) continue;
      for (Eigen::Index di = -1; di <= 1; ++di) {
        for (Eigen::Index dj = -1; dj <= 1; ++dj) {
          const Eigen::Index a = i + di;
          const Eigen::Index b = j + dj;
          if (a < 0 || b < 0 || a >= max.rows() || b >= max.cols()) continue;
          const std::uint8_t other = classes(a, b);
          if (other == 2 || other == 3 || other == 4) {
            result(i, j) = static_cast<std::uint8_t>(TerrainClass::kHorizontalEdge);
          }
        }
      }
    }
  }
  return result;
}

/// A seeded random map whose heights and spreads sit on and next to the float neighbours of the
/// (not float-representable) thresholds, with empty and discontinuous cells.
/// `sparse`: mostly smooth ground with scattered object cells, so that edges come from single
/// neighbours on every side.
ElevationMap random_threshold_map(std::uint32_t seed, int nx, int ny, const TerrainParams& params,
                                  bool sparse = false) {
  std::mt19937 rng(seed);
  const auto near = [&](double threshold) {
    float v = static_cast<float>(threshold);
    const int steps = static_cast<int>(rng() % 7) - 3;  // -3 .. 3 floats away
    for (int k = 0; k < std::abs(steps); ++k) {
      v = std::nextafter(v,
                         steps > 0 ? std::numeric_limits<float>::infinity() : -std::numeric_limits<float>::infinity());
    }
    return v;
  };
  const float ground = static_cast<float>(-params.sensor_height_m);
  ElevationMap map = uniform_map(nx, ny, 0.0F, 0.0F);
  for (int i = 0; i < nx; ++i) {
    for (int j = 0; j < ny; ++j) {
      const unsigned kind = rng() % 10;
      if (kind == 0) {
        clear_cell(map, i, j);
        continue;
      }
      if (sparse && rng() % 8 != 0) {  // plain ground: low and smooth
        set_cell(map, i, j, ground, 0.0F);
        continue;
      }
      const double target =
          kind < 4 ? params.ground_height_m : (kind < 7 ? params.robot_height_m : 0.01 * (rng() % 300));
      // max chosen so that max - ground lands on a float near the target height
      const float max = near(target) + ground;
      const float spread = rng() % 2 ? near(params.std_dev_m) : 0.001F * static_cast<float>(rng() % 400);
      set_cell(map, i, j, max, spread, rng() % 15 == 0 ? 1.0F : 0.0F);
    }
  }
  return map;
}

TEST(TerrainVsNaive, RandomMapsWithValuesAtTheFloatNeighboursOfTheThresholds) {
  TerrainParams params;  // the paper's 0.2, 0.1 and 0.7 m: none is a float
  const std::vector<std::pair<int, int>> shapes = {{1, 1}, {1, 9}, {9, 1}, {2, 2}, {7, 13}, {40, 33}};
  std::uint32_t seed = 1;
  for (const auto& [nx, ny] : shapes) {
    for (int repeat = 0; repeat < 4; ++repeat, ++seed) {
      // Sensor height 0: relative heights are exactly the floats next to the thresholds.
      params.sensor_height_m = repeat % 2 == 0 ? 0.0 : 1.73;
      SCOPED_TRACE("map " + std::to_string(nx) + " x " + std::to_string(ny) + ", seed " + std::to_string(seed));
      ElevationMap map = random_threshold_map(seed, nx, ny, params, repeat >= 2);
      const auto expected = naive_classes(map, params);
      const TerrainClassification result = classify_terrain(map, params);
      ASSERT_EQ(result.classes.rows(), nx);
      ASSERT_EQ(result.classes.cols(), ny);
      int mismatches = 0;
      for (int i = 0; i < nx; ++i) {
        for (int j = 0; j < ny; ++j) {
          if (result.classes(i, j) != expected(i, j) && ++mismatches <= 5) {
            ADD_FAILURE() << "cell (" << i << ", " << j << "): " << int(result.classes(i, j)) << " vs naive "
                          << int(expected(i, j)) << ", max " << map.get("max")(i, j) << ", std "
                          << map.get("std_dev")(i, j);
          }
          const float layer = map.get("class")(i, j);
          if (expected(i, j) == 0) {
            EXPECT_TRUE(std::isnan(layer));
          } else {
            EXPECT_EQ(layer, static_cast<float>(expected(i, j)));
          }
        }
      }
    }
  }
}

TEST(TerrainVsNaive, SeveralThreadsGiveTheNaiveClassesAndTheOneThreadLayers) {
  // Maps large enough for two to four threads, split into row blocks whose edge tests read the
  // rows of their neighbours; both ground references.
  TerrainParams params;
  params.sensor_height_m = 1.73;
  std::uint32_t seed = 200;
  for (const auto& [nx, ny] : std::vector<std::pair<int, int>>{{800, 700}, {4000, 67}, {67, 4000}}) {
    for (const GroundReference reference : {GroundReference::kSensorHeight, GroundReference::kLocalGround}) {
      SCOPED_TRACE("map " + std::to_string(nx) + " x " + std::to_string(ny) + ", seed " + std::to_string(seed));
      params.reference = reference;
      params.local_ground_radius_cells = 3;
      ElevationMap serial_map = random_threshold_map(seed++, nx, ny, params, nx == 4000);
      ElevationMap threaded_map = serial_map;
      params.num_threads = 1;
      const TerrainClassification serial = classify_terrain(serial_map, params);
      if (reference == GroundReference::kSensorHeight) {  // (the local ground has its own tests below)
        EXPECT_EQ(serial.classes, naive_classes(serial_map, params));
      }
      for (const int threads : {2, 3, 4}) {
        params.num_threads = threads;
        const TerrainClassification threaded = classify_terrain(threaded_map, params);
        EXPECT_EQ(threaded.classes, serial.classes) << threads << " threads";
        for (const char* name : {"class", "relative_height", "ground"}) {
          const Layer& a = threaded_map.get(name);
          const Layer& b = serial_map.get(name);
          EXPECT_EQ(a.array().isNaN().matrix(), b.array().isNaN().matrix()) << name;
          EXPECT_EQ(a.array().isNaN().select(0.0F, a.array()).matrix(),
                    b.array().isNaN().select(0.0F, b.array()).matrix())
              << name;
        }
      }
    }
  }
  params.num_threads = -2;
  ElevationMap map = uniform_map(3, 3, 0.0F, 0.0F);
  expect_throw_with<std::invalid_argument>([&] { classify_terrain(map, params); }, "num_threads must be >= 0");
}

TEST(TerrainVsNaive, ClassifyingTheSameMapTwiceGivesTheSameResultAndLayers) {
  TerrainParams params;
  params.sensor_height_m = 1.73;
  ElevationMap map = random_threshold_map(99, 20, 17, params);
  const TerrainClassification first = classify_terrain(map, params);
  const Layer class_layer = map.get("class");
  const TerrainClassification second = classify_terrain(map, params);  // layers now reused in place
  EXPECT_EQ(first.classes, second.classes);
  EXPECT_EQ(map.get("class").array().isNaN().matrix(), class_layer.array().isNaN().matrix());
  EXPECT_EQ(map.get("class").array().isNaN().select(0.0F, map.get("class").array()).matrix(),
            class_layer.array().isNaN().select(0.0F, class_layer.array()).matrix());
  EXPECT_EQ(map.get("ground"), second.ground);
  EXPECT_EQ(map.layers(), (std::vector<std::string>{"count", "min", "max", "mean", "std_dev", "discontinuity", "class",
                                                    "relative_height", "ground"}));
}

TEST(TerrainVsNaive, ClassifyTerrainLayersGivesTheClassesAndLayersOfClassifyTerrain) {
  TerrainParams params;
  params.sensor_height_m = 0.4;
  for (const GroundReference reference : {GroundReference::kSensorHeight, GroundReference::kLocalGround}) {
    params.reference = reference;
    ElevationMap full = random_threshold_map(7, 23, 19, params);
    ElevationMap light = full;
    const TerrainClassification expected = classify_terrain(full, params);
    const TerrainClasses classes = classify_terrain_layers(light, params);
    EXPECT_EQ(classes, expected.classes);
    EXPECT_EQ(light.layers(), full.layers());
    EXPECT_EQ(light.get("ground"), expected.ground);
    const Layer& relative = light.get("relative_height");
    EXPECT_EQ(relative.array().isNaN().matrix(), expected.relative_height.array().isNaN().matrix());
    EXPECT_EQ(relative.array().isNaN().select(0.0F, relative.array()).matrix(),
              expected.relative_height.array().isNaN().select(0.0F, expected.relative_height.array()).matrix());
  }
}

TEST(TerrainReference, LocalGroundEqualsANaiveWindowMinimumForAnyRadiusAndShape) {
  // The O(1)-per-cell running minimum against a direct scan of every window (NaN = empty).
  const std::vector<std::pair<int, int>> shapes = {{1, 1}, {1, 12}, {12, 1}, {5, 7}, {31, 17}};
  std::mt19937 rng(5);
  for (const auto& [nx, ny] : shapes) {
    for (const int radius : {0, 1, 2, 3, 6, 40, std::numeric_limits<int>::max()}) {
      SCOPED_TRACE(std::to_string(nx) + " x " + std::to_string(ny) + ", radius " + std::to_string(radius));
      ElevationMap map = uniform_map(nx, ny, 0.0F, 0.0F);
      Layer& lowest = map.get("min");
      for (int i = 0; i < nx; ++i) {
        for (int j = 0; j < ny; ++j) {
          if (rng() % 4 == 0) {
            clear_cell(map, i, j);
          } else {
            lowest(i, j) = static_cast<float>(static_cast<int>(rng() % 2001) - 1000) / 64.0F;
            map.get("max")(i, j) = lowest(i, j) + 0.5F;
          }
        }
      }
      TerrainParams params = exact_params();
      params.reference = GroundReference::kLocalGround;
      params.local_ground_radius_cells = radius;
      const Layer ground = classify_terrain(map, params).ground;
      const Layer& minimum = map.get("min");  // classify_terrain adds layers: `lowest` may dangle
      for (int i = 0; i < nx; ++i) {
        for (int j = 0; j < ny; ++j) {
          float expected = std::numeric_limits<float>::infinity();
          for (long a = std::max<long>(0, i - static_cast<long>(radius));
               a <= std::min<long>(nx - 1, i + static_cast<long>(radius)); ++a) {
            for (long b = std::max<long>(0, j - static_cast<long>(radius));
                 b <= std::min<long>(ny - 1, j + static_cast<long>(radius)); ++b) {
              if (!std::isnan(minimum(a, b))) expected = std::min(expected, minimum(a, b));
            }
          }
          if (std::isinf(expected)) {
            EXPECT_TRUE(std::isnan(ground(i, j))) << "cell (" << i << ", " << j << ")";
          } else {
            EXPECT_EQ(ground(i, j), expected) << "cell (" << i << ", " << j << ")";
          }
        }
      }
    }
  }
}

// --- ground reference ---------------------------------------------------------------------------

TEST(TerrainReference, SensorHeightGivesAConstantGroundLayer) {
  ElevationMap map = uniform_map(2, 3, 0.0F, 0.0F);
  clear_cell(map, 1, 2);
  map.get("min")(0, 0) = -10.0F;  // not used by this reference
  const TerrainClassification result = classify_terrain(map, exact_params(1.5));
  EXPECT_EQ(result.ground, Layer::Constant(2, 3, -1.5F));
  EXPECT_EQ(result.relative_height(0, 1), 1.5F);
  EXPECT_TRUE(std::isnan(result.relative_height(1, 2)));
}

/// A planar ramp 2 m above the sensor: z = 2 + i / 16 + j / 32, each cell's max 0.125 above its min.
ElevationMap ramp_map(int nx, int ny) {
  ElevationMap map = uniform_map(nx, ny, 0.0F, 0.0625F);
  for (int i = 0; i < nx; ++i) {
    for (int j = 0; j < ny; ++j) {
      const float base = 2.0F + 0.0625F * static_cast<float>(i) + 0.03125F * static_cast<float>(j);
      set_cell(map, i, j, base + 0.125F, 0.0625F);
      map.get("min")(i, j) = base;
    }
  }
  return map;
}

TEST(TerrainReference, LocalGroundFollowsASlopeThatTheSensorPlaneCallsHigh) {
  ElevationMap map = ramp_map(8, 6);
  TerrainParams params = exact_params();
  // The sensor plane z = 0: every cell is over 2 m high with a small spread.
  const TerrainClassification flat = classify_terrain(map, params);
  EXPECT_TRUE((flat.classes.array() == static_cast<std::uint8_t>(TerrainClass::kOverhangingObject)).all());
  EXPECT_TRUE((flat.relative_height.array() >= 2.0F).all());
  // The local ground (radius 1): relative height 0.125 + i' / 16 + j' / 32 with i' = min(i, 1),
  // j' = min(j, 1), at most 0.21875 < 0.25: every cell is ground.
  params.reference = GroundReference::kLocalGround;
  params.local_ground_radius_cells = 1;
  const TerrainClassification local = classify_terrain(map, params);
  EXPECT_TRUE((local.classes.array() == static_cast<std::uint8_t>(TerrainClass::kGround)).all())
      << local.classes.cast<int>();
  for (int i = 0; i < 8; ++i) {
    for (int j = 0; j < 6; ++j) {
      const float ground =
          2.0F + 0.0625F * static_cast<float>(std::max(0, i - 1)) + 0.03125F * static_cast<float>(std::max(0, j - 1));
      EXPECT_EQ(local.ground(i, j), ground) << i << ", " << j;
      EXPECT_EQ(local.relative_height(i, j),
                0.125F + 0.0625F * static_cast<float>(std::min(i, 1)) + 0.03125F * static_cast<float>(std::min(j, 1)))
          << i << ", " << j;
    }
  }
}

TEST(TerrainReference, LocalGroundIsTheLowestMinInASquareWindow) {
  ElevationMap map = ramp_map(8, 6);
  TerrainParams params = exact_params();
  params.reference = GroundReference::kLocalGround;
  for (const int radius : {0, 2, 3, 20}) {
    SCOPED_TRACE("radius " + std::to_string(radius));
    params.local_ground_radius_cells = radius;
    const TerrainClassification result = classify_terrain(map, params);
    for (int i = 0; i < 8; ++i) {
      for (int j = 0; j < 6; ++j) {
        // The ramp rises with i and j: the window's lowest cell is its lower-left corner.
        const float ground = 2.0F + 0.0625F * static_cast<float>(std::max(0, i - radius)) +
                             0.03125F * static_cast<float>(std::max(0, j - radius));
        ASSERT_EQ(result.ground(i, j), ground) << i << ", " << j;
      }
    }
  }
  // Radius 0: the relative height is max - min of the cell itself.
  params.local_ground_radius_cells = 0;
  EXPECT_EQ(classify_terrain(map, params).relative_height, Layer::Constant(8, 6, 0.125F));
}

TEST(TerrainReference, LocalGroundSkipsEmptyCellsAndIsNaNWhereTheWindowIsEmpty) {
  ElevationMap map = uniform_map(1, 7, 0.0F, 0.0F);
  const float min[7] = {1.0F, kNaN, 0.5F, kNaN, kNaN, kNaN, 3.0F};
  for (int j = 0; j < 7; ++j) {
    if (std::isnan(min[j])) {
      clear_cell(map, 0, j);
    } else {
      set_cell(map, 0, j, min[j] + 0.125F, 0.0F);
      map.get("min")(0, j) = min[j];
    }
  }
  TerrainParams params = exact_params();
  params.reference = GroundReference::kLocalGround;
  params.local_ground_radius_cells = 1;
  const TerrainClassification result = classify_terrain(map, params);
  const Layer expected_ground = (Layer(1, 7) << 1.0F, 0.5F, 0.5F, 0.5F, kNaN, 3.0F, 3.0F).finished();
  for (int j = 0; j < 7; ++j) {
    if (std::isnan(expected_ground(0, j))) {
      EXPECT_TRUE(std::isnan(result.ground(0, j))) << j;
    } else {
      EXPECT_EQ(result.ground(0, j), expected_ground(0, j)) << j;
    }
  }
  EXPECT_EQ(letters(result), (std::vector<std::string>{"g.g...g"}));
  EXPECT_EQ(result.relative_height(0, 0), 0.125F);
  EXPECT_TRUE(std::isnan(result.relative_height(0, 3))) << "empty cells have no height even with a ground";
}

// --- output layers ------------------------------------------------------------------------------

TEST(TerrainLayers, ClassRelativeHeightAndGroundAreAddedToTheMap) {
  ElevationMap map = uniform_map(2, 3, 0.0F, 0.0F);
  set_cell(map, 0, 0, 2.0F, 0.75F);  // vertical
  set_cell(map, 1, 2, 0.5F, 0.0F);   // obstacle
  clear_cell(map, 0, 2);
  const TerrainClassification result = classify_terrain(map, exact_params(0.125));
  EXPECT_EQ(letters(result), (std::vector<std::string>{"ve.", "eeo"}));
  EXPECT_EQ(map.layers(), (std::vector<std::string>{"count", "min", "max", "mean", "std_dev", "discontinuity", "class",
                                                    "relative_height", "ground"}));
  const Layer& classes = map.get("class");
  EXPECT_EQ(classes(0, 0), 4.0F);
  EXPECT_EQ(classes(0, 1), 5.0F);
  EXPECT_TRUE(std::isnan(classes(0, 2)));
  EXPECT_EQ(classes(1, 0), 5.0F);
  EXPECT_EQ(classes(1, 1), 5.0F);
  EXPECT_EQ(classes(1, 2), 2.0F);
  const Layer& relative = map.get("relative_height");
  EXPECT_EQ(relative(0, 0), 2.125F);
  EXPECT_EQ(relative(1, 0), 0.125F);
  EXPECT_EQ(relative(1, 2), 0.625F);
  EXPECT_TRUE(std::isnan(relative(0, 2)));
  EXPECT_EQ(map.get("ground"), Layer::Constant(2, 3, -0.125F));
  EXPECT_EQ(map.get("ground"), result.ground);
  // The layers match the returned classification, NaN for NaN.
  for (Eigen::Index k = 0; k < 6; ++k) {
    EXPECT_EQ(std::isnan(relative.data()[k]), std::isnan(result.relative_height.data()[k]));
    if (!std::isnan(relative.data()[k])) {
      EXPECT_EQ(relative.data()[k], result.relative_height.data()[k]);
    }
    if (result.classes.data()[k] != 0) {
      EXPECT_EQ(classes.data()[k], static_cast<float>(result.classes.data()[k]));
    }
  }
}

TEST(TerrainLayers, ClassifyingAgainOverwritesTheLayers) {
  ElevationMap map = uniform_map(1, 2, 0.0F, 0.0F);
  classify_terrain(map, exact_params());
  classify_terrain(map, exact_params(2.0));  // the cells are now 2 m above the ground plane
  EXPECT_EQ(map.layers().size(), 9U);
  EXPECT_EQ(map.get("class"), Layer::Constant(1, 2, 3.0F));  // high, small std: overhanging
  EXPECT_EQ(map.get("ground"), Layer::Constant(1, 2, -2.0F));
}

TEST(TerrainLayers, NewLayersOnBuffersOfDroppedMapsAreWrittenInEveryCell) {
  // Every cell of the three added layers is written, in both ground references, even when the
  // memory a dropped map left holds garbage.
  for (const GroundReference reference : {GroundReference::kSensorHeight, GroundReference::kLocalGround}) {
    SCOPED_TRACE(reference == GroundReference::kSensorHeight ? "sensor height" : "local ground");
    {
      ElevationMap garbage = uniform_map(9, 11, 0.0F, 0.0F);
      for (int k = 0; k < 12; ++k) garbage.add("garbage" + std::to_string(k), 777.0F);
    }  // dropped: its 18 buffers of 9 x 11 cells are kept for the next layers of that size
    ElevationMap map = uniform_map(9, 11, 0.0F, 0.0F);
    std::mt19937 rng(17);
    for (int i = 0; i < 9; ++i) {
      for (int j = 0; j < 11; ++j) {
        if (rng() % 5 == 0) {
          clear_cell(map, i, j);
        } else {
          const float top = static_cast<float>(rng() % 300) / 100.0F;
          set_cell(map, i, j, top, static_cast<float>(rng() % 3) / 4.0F);
          map.get("min")(i, j) = top - static_cast<float>(rng() % 50) / 100.0F;
        }
      }
    }
    TerrainParams params = exact_params(0.25);
    params.reference = reference;
    params.local_ground_radius_cells = 1;
    const TerrainClassification result = classify_terrain(map, params);
    for (int i = 0; i < 9; ++i) {
      for (int j = 0; j < 11; ++j) {
        SCOPED_TRACE("cell (" + std::to_string(i) + ", " + std::to_string(j) + ")");
        float ground = -0.25F;
        if (reference == GroundReference::kLocalGround) {
          ground = std::numeric_limits<float>::infinity();
          for (int a = std::max(0, i - 1); a <= std::min(8, i + 1); ++a) {
            for (int b = std::max(0, j - 1); b <= std::min(10, j + 1); ++b) {
              if (!std::isnan(map.get("min")(a, b))) ground = std::min(ground, map.get("min")(a, b));
            }
          }
          if (std::isinf(ground)) ground = kNaN;
        }
        const float top = map.get("max")(i, j);
        const std::uint8_t c = result.classes(i, j);
        if (std::isnan(ground)) {
          EXPECT_TRUE(std::isnan(map.get("ground")(i, j)));
        } else {
          EXPECT_EQ(map.get("ground")(i, j), ground);
        }
        if (std::isnan(top) || std::isnan(ground)) {
          EXPECT_TRUE(std::isnan(map.get("relative_height")(i, j)));
          EXPECT_EQ(c, 0);
        } else {
          EXPECT_EQ(map.get("relative_height")(i, j), top - ground);
          EXPECT_NE(c, 0);
        }
        if (c == 0) {
          EXPECT_TRUE(std::isnan(map.get("class")(i, j)));
        } else {
          EXPECT_EQ(map.get("class")(i, j), static_cast<float>(c));
        }
      }
    }
  }
}

TEST(TerrainLayers, EmptyMapGivesEmptyClassification) {
  ElevationMap map = uniform_map(0, 0, 0.0F, 0.0F);
  const TerrainClassification result = classify_terrain(map, exact_params());
  EXPECT_EQ(result.classes.size(), 0);
  EXPECT_EQ(map.get("class").size(), 0);
}

// --- bad input ----------------------------------------------------------------------------------

TEST(TerrainBadInput, NonPositiveOrNonFiniteThresholdsAreRejected) {
  ElevationMap map = uniform_map(1, 1, 0.0F, 0.0F);
  for (const double bad :
       {0.0, -0.1, std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity()}) {
    SCOPED_TRACE(bad);
    TerrainParams params;
    params.ground_height_m = bad;
    EXPECT_THROW(classify_terrain(map, params), std::invalid_argument);
    params = TerrainParams{};
    params.std_dev_m = bad;
    EXPECT_THROW(classify_terrain(map, params), std::invalid_argument);
    params = TerrainParams{};
    params.robot_height_m = bad;
    EXPECT_THROW(classify_terrain(map, params), std::invalid_argument);
  }
  TerrainParams params;
  params.sensor_height_m = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(classify_terrain(map, params), std::invalid_argument);
  EXPECT_FALSE(map.exists("class")) << "a rejected call adds nothing";
}

TEST(TerrainBadInput, RobotHeightBelowGroundHeightIsRejected) {
  ElevationMap map = uniform_map(1, 1, 0.0F, 0.0F);
  TerrainParams params;
  params.ground_height_m = 0.5;
  params.robot_height_m = 0.25;
  expect_throw_with<std::invalid_argument>([&] { classify_terrain(map, params); }, "robot height");
}

TEST(TerrainBadInput, NegativeLocalGroundRadiusIsRejected) {
  ElevationMap map = uniform_map(1, 1, 0.0F, 0.0F);
  TerrainParams params;
  params.reference = GroundReference::kLocalGround;
  params.local_ground_radius_cells = -1;
  expect_throw_with<std::invalid_argument>([&] { classify_terrain(map, params); }, "radius");
}

TEST(TerrainBadInput, MissingLayerThrowsOutOfRangeNamingIt) {
  for (const std::string missing : {"max", "std_dev", "discontinuity"}) {
    SCOPED_TRACE(missing);
    MapGeometry geometry;
    geometry.size = CellIndex(2, 2);
    ElevationMap map(geometry);
    for (const std::string name : {"min", "max", "std_dev", "discontinuity"}) {
      if (name != missing) map.add(name, 0.0F);
    }
    expect_throw_with<std::out_of_range>([&] { classify_terrain(map, exact_params()); }, "'" + missing + "'");
  }
  MapGeometry geometry;
  geometry.size = CellIndex(2, 2);
  ElevationMap map(geometry);
  for (const std::string name : {"max", "std_dev", "discontinuity"}) map.add(name, 0.0F);
  TerrainParams params = exact_params();
  params.reference = GroundReference::kLocalGround;
  expect_throw_with<std::out_of_range>([&] { classify_terrain(map, params); }, "'min'");
}

// --- SemanticKITTI ------------------------------------------------------------------------------

// SemanticKITTI label ids (low 16 bits).
constexpr std::uint16_t kCar = 10, kRoad = 40, kParking = 44, kSidewalk = 48, kBuilding = 50, kFence = 51,
                        kVegetation = 70, kTrunk = 71, kPole = 80, kTrafficSign = 81;

struct Tally {
  std::size_t cells = 0;
  std::size_t hits = 0;
  std::map<int, std::size_t> by_class;
  double rate() const { return cells == 0 ? 0.0 : static_cast<double>(hits) / static_cast<double>(cells); }
};

std::string describe(const Tally& tally) {
  static const char* const kNames[] = {"unknown", "ground", "obstacle", "overhanging", "vertical", "edge"};
  char head[96];
  std::snprintf(head, sizeof head, "%.4f of %zu cells (", tally.rate(), tally.cells);
  std::string text = head;
  for (const auto& [c, n] : tally.by_class) text += std::string(kNames[c]) + " " + std::to_string(n) + " ";
  return text + ")";
}

TEST(TerrainKitti, ClassesAgreeWithTheSemanticKittiLabels) {
  const auto data = test::shared_data_dir();
  if (!data) GTEST_SKIP() << "../shared/data not found (set TERRACUBE_DATA_DIR)";
  const std::set<std::uint16_t> road_like = {kRoad, kSidewalk};
  const std::set<std::uint16_t> wall_like = {kBuilding, kFence};
  const std::set<std::uint16_t> thin = {kTrunk, kPole, kTrafficSign};
  Tally road, wall, car, parking, crown, trunk;
  for (const std::string frame : {"000000", "000001", "000002"}) {
    const test::XyziScan scan = test::read_xyzi_bin(*data + "/kitti_seq00/velodyne/" + frame + ".bin");
    const std::vector<std::uint16_t> labels =
        test::read_semantic_labels(*data + "/kitti_seq00/labels/" + frame + ".label");
    ASSERT_EQ(labels.size(), scan.values.size() / 4);
    ElevationParams elevation;
    elevation.resolution_m = 0.1;
    elevation.origin_m = Eigen::Vector2d(-20.0, -10.0);
    elevation.size = CellIndex(400, 200);
    ElevationMap map = build_elevation_map(scan.xyz(), elevation);
    TerrainParams terrain;
    terrain.sensor_height_m = 1.73;
    const TerrainClassification result = classify_terrain(map, terrain);

    // Majority label per cell (ties to the smaller id).
    std::map<std::pair<int, int>, std::map<std::uint16_t, int>> votes;
    const PointsView<float> view = scan.xyz();
    for (std::size_t row = 0; row < view.size; ++row) {
      const auto index = map.geometry().index_of(view.point(row).head<2>());
      if (index) ++votes[{(*index)(0), (*index)(1)}][labels[row]];
    }
    for (const auto& [cell, count] : votes) {
      std::uint16_t majority = 0;
      int best = 0;
      for (const auto& [label, n] : count) {
        if (n > best) {
          best = n;
          majority = label;
        }
      }
      const auto c = static_cast<TerrainClass>(result.classes(cell.first, cell.second));
      const auto tally = [&](Tally& t, bool hit) {
        ++t.cells;
        t.hits += hit ? 1 : 0;
        ++t.by_class[static_cast<int>(c)];
      };
      if (road_like.count(majority)) tally(road, c == TerrainClass::kGround || c == TerrainClass::kHorizontalEdge);
      if (wall_like.count(majority)) tally(wall, c == TerrainClass::kVerticalObject);
      if (majority == kCar) tally(car, c == TerrainClass::kObstacle);
      if (majority == kParking) tally(parking, c == TerrainClass::kGround || c == TerrainClass::kHorizontalEdge);
      // A crown: vegetation whose lowest return in the cell is over 1 m above the road (seen from below).
      const bool lifted = map.get("min")(cell.first, cell.second) > 1.0F - 1.73F;
      if (majority == kVegetation && lifted) tally(crown, c == TerrainClass::kOverhangingObject);
      if (thin.count(majority)) tally(trunk, c == TerrainClass::kVerticalObject);
    }
  }
  std::cout << "road/sidewalk -> ground or edge: " << describe(road) << "\n"
            << "building/fence -> vertical:      " << describe(wall) << "\n"
            << "car -> obstacle:                 " << describe(car) << "\n"
            << "crown -> overhanging:            " << describe(crown) << "\n"
            << "trunk/pole/sign -> vertical:     " << describe(trunk) << "\n"
            << "(info) parking -> ground/edge:   " << describe(parking) << "\n";
  RecordProperty("road_sidewalk_ground_or_edge_rate", std::to_string(road.rate()));
  RecordProperty("building_fence_vertical_rate", std::to_string(wall.rate()));
  RecordProperty("car_obstacle_rate", std::to_string(car.rate()));
  RecordProperty("crown_overhanging_rate", std::to_string(crown.rate()));
  RecordProperty("trunk_pole_vertical_rate", std::to_string(trunk.rate()));
  ASSERT_GT(road.cells, 1000U);
  ASSERT_GT(wall.cells, 100U);
  ASSERT_GT(car.cells, 100U);
  ASSERT_GT(crown.cells, 100U);
  ASSERT_GT(trunk.cells, 100U);
  // [TC] Table 1 as printed, measured on frames 000000-000002 (pooled, every cell with a labelled
  // point): road/sidewalk 0.9218, building/fence 0.6807, crowns 0.9901, trunks/poles 0.4801 (the
  // sparse beams leave many trunk cells a small spread). KITTI's cars (1.5 m) are higher than the
  // paper's 0.7 m robot: their roofs are overhanging objects and their flanks vertical, so
  // car -> obstacle is 0.0854. The floors sit 0.03 below so that a regression fails.
  EXPECT_GE(road.rate(), 0.89);
  EXPECT_GE(wall.rate(), 0.65);
  EXPECT_GE(car.rate(), 0.055);
  EXPECT_GE(crown.rate(), 0.96);
  EXPECT_GE(trunk.rate(), 0.45);
}

}  // namespace
}  // namespace terracube
