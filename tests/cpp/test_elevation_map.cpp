#include <gtest/gtest.h>
#include <Eigen/Geometry>
#include <terracube/collapse.hpp>
#include <terracube/elevation_map.hpp>

#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <csignal>
#include <functional>
#include <limits>
#include <map>
#include <optional>
#include <random>
#include <stdexcept>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "test_support.hpp"

namespace terracube {
namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();
const std::vector<std::string> kStatisticLayers = {"count", "min", "max", "mean", "std_dev", "discontinuity"};

// --- helpers ----------------------------------------------------------------------------------

using test::expect_throw_with;

/// NaN-aware exact equality of two layers (NaN == NaN, +inf == +inf).
void expect_same_layer(const Layer& actual, const Layer& expected, const std::string& what) {
  ASSERT_EQ(actual.rows(), expected.rows()) << what;
  ASSERT_EQ(actual.cols(), expected.cols()) << what;
  int mismatches = 0;
  for (Eigen::Index i = 0; i < actual.rows(); ++i) {
    for (Eigen::Index j = 0; j < actual.cols(); ++j) {
      const float a = actual(i, j);
      const float e = expected(i, j);
      if ((std::isnan(a) && std::isnan(e)) || a == e) continue;
      ADD_FAILURE() << what << " at (" << i << ", " << j << "): " << a << " != " << e;
      if (++mismatches == 5) return;
    }
  }
}

/// NaN in exactly the same cells, the other values within `tolerance`.
void expect_near_layer(const Layer& actual, const Layer& expected, float tolerance, const std::string& what) {
  ASSERT_EQ(actual.rows(), expected.rows()) << what;
  ASSERT_EQ(actual.cols(), expected.cols()) << what;
  int mismatches = 0;
  for (Eigen::Index i = 0; i < actual.rows(); ++i) {
    for (Eigen::Index j = 0; j < actual.cols(); ++j) {
      const float a = actual(i, j);
      const float e = expected(i, j);
      if (std::isnan(a) && std::isnan(e)) continue;
      if (!std::isnan(a) && !std::isnan(e) && std::abs(a - e) <= tolerance) continue;
      ADD_FAILURE() << what << " at (" << i << ", " << j << "): " << a << " vs " << e;
      if (++mismatches == 5) return;
    }
  }
}

void expect_same_statistics(const ElevationMap& actual, const ElevationMap& expected) {
  EXPECT_EQ(actual.geometry().resolution_m, expected.geometry().resolution_m);
  EXPECT_EQ(actual.geometry().origin_m, expected.geometry().origin_m);
  EXPECT_EQ(actual.geometry().size.matrix(), expected.geometry().size.matrix());
  for (const std::string& name : kStatisticLayers) expect_same_layer(actual.get(name), expected.get(name), name);
}

/// The naive reference: the elevations of each cell, binned as the documented convention says,
/// cell = floor((p - origin) / resolution), points outside ignored.
using NaiveCells = std::map<std::pair<int, int>, std::vector<double>>;

NaiveCells naive_cells(const std::vector<Eigen::Vector3d>& points, const MapGeometry& geometry) {
  NaiveCells cells;
  for (const Eigen::Vector3d& p : points) {
    const double fx = std::floor((p.x() - geometry.origin_m.x()) / geometry.resolution_m);
    const double fy = std::floor((p.y() - geometry.origin_m.y()) / geometry.resolution_m);
    if (fx < 0 || fy < 0 || fx >= geometry.size.x() || fy >= geometry.size.y()) continue;
    cells[{static_cast<int>(fx), static_cast<int>(fy)}].push_back(p.z());
  }
  return cells;
}

/// |actual - expected| <= relative |expected|, plus the rounding noise of a double computation on
/// values of magnitude `scale` (the reference's own: its two-pass std-dev of equal values can be
/// 1e-18 where the exact answer, 0, is what the map reports).
bool within_relative(float actual, double expected, double relative, double scale = 0.0) {
  return std::abs(static_cast<double>(actual) - expected) <= relative * std::abs(expected) + 1e-12 * scale;
}

/// Every layer of `map` against the naive per-cell lists of elevations.
void expect_matches_naive(const ElevationMap& map, const std::vector<Eigen::Vector3d>& points, double discontinuity_m) {
  ASSERT_EQ(map.layers(), kStatisticLayers);
  const MapGeometry& geometry = map.geometry();
  const NaiveCells cells = naive_cells(points, geometry);
  const Layer& count = map.get("count");
  const Layer& min = map.get("min");
  const Layer& max = map.get("max");
  const Layer& mean = map.get("mean");
  const Layer& std_dev = map.get("std_dev");
  const Layer& discontinuity = map.get("discontinuity");
  for (const std::string& name : kStatisticLayers) {
    ASSERT_EQ(map.get(name).rows(), geometry.size.x()) << name;
    ASSERT_EQ(map.get(name).cols(), geometry.size.y()) << name;
  }
  for (int i = 0; i < geometry.size.x(); ++i) {
    for (int j = 0; j < geometry.size.y(); ++j) {
      SCOPED_TRACE("cell (" + std::to_string(i) + ", " + std::to_string(j) + ")");
      const auto found = cells.find({i, j});
      if (found == cells.end()) {
        ASSERT_EQ(count(i, j), 0.0F);
        ASSERT_TRUE(std::isnan(min(i, j)));
        ASSERT_TRUE(std::isnan(max(i, j)));
        ASSERT_TRUE(std::isnan(mean(i, j)));
        ASSERT_TRUE(std::isnan(std_dev(i, j)));
        ASSERT_TRUE(std::isnan(discontinuity(i, j)));
        continue;
      }
      std::vector<double> z = found->second;
      std::sort(z.begin(), z.end());
      const double n = static_cast<double>(z.size());
      double sum = 0.0;
      for (const double v : z) sum += v;
      const double average = sum / n;
      double squares = 0.0;
      for (const double v : z) squares += (v - average) * (v - average);
      const double population_std = std::sqrt(squares / n);
      bool gap = false;
      for (std::size_t k = 1; k < z.size(); ++k) gap = gap || z[k] - z[k - 1] > discontinuity_m;

      ASSERT_EQ(count(i, j), static_cast<float>(z.size()));
      ASSERT_EQ(min(i, j), static_cast<float>(z.front()));
      ASSERT_EQ(max(i, j), static_cast<float>(z.back()));
      ASSERT_TRUE(within_relative(mean(i, j), average, 1e-5)) << mean(i, j) << " vs " << average;
      const double scale = std::max(std::abs(z.front()), std::abs(z.back()));
      ASSERT_TRUE(within_relative(std_dev(i, j), population_std, 1e-5, scale))
          << std_dev(i, j) << " vs " << population_std;
      ASSERT_EQ(discontinuity(i, j), gap ? 1.0F : 0.0F);
    }
  }
}

std::vector<float> as_floats(const std::vector<Eigen::Vector3d>& points, int stride) {
  std::vector<float> values(points.size() * static_cast<std::size_t>(stride), -7.0F);  // padding is never read
  for (std::size_t row = 0; row < points.size(); ++row) {
    for (int axis = 0; axis < 3; ++axis) {
      values[row * static_cast<std::size_t>(stride) + static_cast<std::size_t>(axis)] =
          static_cast<float>(points[row][axis]);
    }
  }
  return values;
}

/// The points as the float view sees them.
std::vector<Eigen::Vector3d> rounded_to_float(const std::vector<Eigen::Vector3d>& points) {
  std::vector<Eigen::Vector3d> out;
  for (const Eigen::Vector3d& p : points) out.push_back(test::rounded_to<float>(p));
  return out;
}

ElevationParams fixed_extent(double resolution_m, Eigen::Vector2d origin_m, CellIndex size) {
  ElevationParams params;
  params.resolution_m = resolution_m;
  params.origin_m = origin_m;
  params.size = size;
  return params;
}

/// Auto extent: origin a multiple of the resolution, within one cell below the smallest point,
/// and the last cell holding the largest one.
void expect_snapped_extent(const MapGeometry& geometry, const std::vector<Eigen::Vector3d>& points) {
  Eigen::Vector2d lo = Eigen::Vector2d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector2d hi = -lo;
  for (const Eigen::Vector3d& p : points) {
    lo = lo.cwiseMin(p.head<2>());
    hi = hi.cwiseMax(p.head<2>());
  }
  for (int axis = 0; axis < 2; ++axis) {
    const double res = geometry.resolution_m;
    const double origin = geometry.origin_m[axis];
    EXPECT_NEAR(origin / res, std::round(origin / res), 1e-9) << "axis " << axis;
    EXPECT_LE(origin, lo[axis]) << "axis " << axis;
    EXPECT_GT(origin, lo[axis] - res) << "axis " << axis;
    EXPECT_LE(origin + (geometry.size[axis] - 1) * res, hi[axis]) << "axis " << axis;
    EXPECT_GT(origin + geometry.size[axis] * res, hi[axis]) << "axis " << axis;
  }
}

/// "(i, j)" or "outside": index_of results compared as text, safe when there is no cell.
std::string cell(const std::optional<CellIndex>& index) {
  return index ? "(" + std::to_string((*index)(0)) + ", " + std::to_string((*index)(1)) + ")" : "outside";
}

// --- MapGeometry --------------------------------------------------------------------------------

MapGeometry example_geometry() {
  MapGeometry geometry;
  geometry.resolution_m = 0.5;
  geometry.origin_m = {-1.0, 2.0};
  geometry.size = {4, 3};  // x in [-1, 1), y in [2, 3.5)
  return geometry;
}

TEST(MapGeometry, CountsLengthAndCellCentres) {
  const MapGeometry geometry = example_geometry();
  EXPECT_EQ(geometry.num_cells(), 12U);
  EXPECT_EQ(geometry.length_m(), Eigen::Vector2d(2.0, 1.5));
  EXPECT_EQ(geometry.position_of({0, 0}), Eigen::Vector2d(-0.75, 2.25));
  EXPECT_EQ(geometry.position_of({3, 2}), Eigen::Vector2d(0.75, 3.25));
  EXPECT_EQ(geometry.position_of({1, 2}), Eigen::Vector2d(-0.25, 3.25));
}

TEST(MapGeometry, IndexOfCellCentreIsTheCell) {
  const MapGeometry geometry = example_geometry();
  for (int i = 0; i < 4; ++i) {
    for (int j = 0; j < 3; ++j) {
      EXPECT_EQ(cell(geometry.index_of(geometry.position_of({i, j}))), cell(CellIndex(i, j)));
    }
  }
}

TEST(MapGeometry, LowerCellBoundaryIsInsideTheCellAndUpperBoundaryIsTheNextCell) {
  const MapGeometry geometry = example_geometry();
  EXPECT_EQ(cell(geometry.index_of({-1.0, 2.0})), "(0, 0)");  // the map's corner
  EXPECT_EQ(cell(geometry.index_of({-0.5, 2.5})), "(1, 1)");  // shared corner of 4 cells
  EXPECT_EQ(cell(geometry.index_of({0.0, 3.0})), "(2, 2)");
  EXPECT_EQ(cell(geometry.index_of({std::nextafter(-0.5, -1.0), std::nextafter(2.5, 0.0)})), "(0, 0)");
  // Just below the map's upper boundaries (1e-9 m: x - origin must not round onto the boundary).
  EXPECT_EQ(cell(geometry.index_of({1.0 - 1e-9, 3.5 - 1e-9})), "(3, 2)");
}

TEST(MapGeometry, UpperBoundaryOfTheLastCellIsOutside) {
  const MapGeometry geometry = example_geometry();
  EXPECT_FALSE(geometry.index_of({1.0, 2.25}).has_value());
  EXPECT_FALSE(geometry.index_of({0.0, 3.5}).has_value());
  EXPECT_FALSE(geometry.index_of({1.0, 3.5}).has_value());
}

TEST(MapGeometry, NegativeCoordinatesFloorTowardsMinusInfinity) {
  MapGeometry geometry;
  geometry.resolution_m = 0.25;
  geometry.origin_m = {-2.0, -1.0};
  geometry.size = {8, 8};
  EXPECT_EQ(cell(geometry.index_of({-1.9, -0.9})), "(0, 0)");
  EXPECT_EQ(cell(geometry.index_of({-0.1, -0.01})), "(7, 3)");
  EXPECT_EQ(cell(geometry.index_of({-1.75, -0.75})), "(1, 1)");
  EXPECT_EQ(cell(geometry.index_of({-0.25, 0.0})), "(7, 4)");
  EXPECT_FALSE(geometry.index_of({0.0, 0.0}).has_value()) << "x = 0 is the upper boundary of the last column";
  EXPECT_FALSE(geometry.index_of({-2.01, 0.0}).has_value());
}

TEST(MapGeometry, PointsOutsideGiveNothing) {
  const MapGeometry geometry = example_geometry();
  EXPECT_FALSE(geometry.index_of({std::nextafter(-1.0, -2.0), 2.5}).has_value());
  EXPECT_FALSE(geometry.index_of({0.0, std::nextafter(2.0, 0.0)}).has_value());
  EXPECT_FALSE(geometry.index_of({-50.0, -50.0}).has_value());
  EXPECT_FALSE(geometry.index_of({50.0, 2.5}).has_value());
  EXPECT_FALSE(geometry.index_of({std::numeric_limits<double>::quiet_NaN(), 2.5}).has_value());
  MapGeometry empty;
  EXPECT_FALSE(empty.index_of({0.0, 0.0}).has_value());
}

// --- ElevationMap -----------------------------------------------------------------------------

TEST(ElevationMapLayers, AddGetExistsAndLayersInInsertionOrder) {
  ElevationMap map(example_geometry());
  EXPECT_TRUE(map.layers().empty());
  map.add("zeta", 2.5F);
  map.add("alpha");
  Layer data(4, 3);
  for (int k = 0; k < 12; ++k) data.data()[k] = static_cast<float>(k);
  map.add("mid", data);
  EXPECT_EQ(map.layers(), (std::vector<std::string>{"zeta", "alpha", "mid"}));
  EXPECT_TRUE(map.exists("alpha"));
  EXPECT_FALSE(map.exists("beta"));
  EXPECT_EQ(map.get("zeta"), Layer::Constant(4, 3, 2.5F));
  EXPECT_TRUE(map.get("alpha").array().isNaN().all()) << "the default fill is NaN (no data)";
  EXPECT_EQ(map.get("mid"), data);
  EXPECT_EQ(map.get("mid")(1, 2), 5.0F) << "row-major: (i, j) is element i * size_y + j";
  const ElevationMap& const_map = map;
  EXPECT_EQ(const_map.get("mid"), data);
  map.get("mid")(0, 0) = 42.0F;  // the non-const accessor writes through
  EXPECT_EQ(const_map.get("mid")(0, 0), 42.0F);
}

TEST(ElevationMapLayers, ReferencesStayValidWhenLayersAreAdded) {
  // Like grid_map: a layer reference taken before more layers are added still reads (and writes)
  // that layer (under ASan a moved-from layer would be a use after free).
  MapGeometry geometry;
  geometry.size = {3, 2};
  ElevationMap map(geometry);
  map.add("first", 1.5F);
  Layer& first = map.get("first");
  const float* data = first.data();
  for (int k = 0; k < 40; ++k) map.add("extra_" + std::to_string(k), static_cast<float>(k));
  EXPECT_EQ(&first, &map.get("first"));
  EXPECT_EQ(first.data(), data);
  first(2, 1) = -4.0F;
  EXPECT_EQ(map.get("first")(2, 1), -4.0F);
  EXPECT_EQ(map.get("first")(0, 0), 1.5F);
  EXPECT_EQ(map.get("extra_39")(1, 1), 39.0F);
}

TEST(ElevationMapLayers, OverwritingKeepsThePlaceInTheOrder) {
  ElevationMap map(example_geometry());
  map.add("a", 1.0F);
  map.add("b", 2.0F);
  map.add("c", 3.0F);
  map.add("a", 10.0F);
  map.add("b", Layer::Constant(4, 3, 20.0F));
  EXPECT_EQ(map.layers(), (std::vector<std::string>{"a", "b", "c"}));
  EXPECT_EQ(map.get("a"), Layer::Constant(4, 3, 10.0F));
  EXPECT_EQ(map.get("b"), Layer::Constant(4, 3, 20.0F));
}

TEST(ElevationMapLayers, GettingAnUnknownLayerThrowsOutOfRangeNamingIt) {
  ElevationMap map(example_geometry());
  map.add("max");
  map.add("mean");
  expect_throw_with<std::out_of_range>([&] { map.get("std_dev"); }, {"'std_dev'", "max, mean"});
  const ElevationMap& const_map = map;
  expect_throw_with<std::out_of_range>([&] { const_map.get("relative_height"); }, {"'relative_height'"});
}

TEST(ElevationMapLayers, AddingALayerOfTheWrongSizeThrowsInvalidArgument) {
  ElevationMap map(example_geometry());
  expect_throw_with<std::invalid_argument>([&] { map.add("bad", Layer::Zero(3, 4)); }, {"'bad'", "3 x 4", "4 x 3"});
  EXPECT_THROW(map.add("bad", Layer::Zero(4, 4)), std::invalid_argument);
  EXPECT_THROW(map.add("bad", Layer()), std::invalid_argument);
  EXPECT_FALSE(map.exists("bad"));
}

TEST(ElevationMapLayers, BadGeometryIsRejected) {
  MapGeometry geometry = example_geometry();
  geometry.resolution_m = 0.0;
  EXPECT_THROW(ElevationMap{geometry}, std::invalid_argument);
  geometry.resolution_m = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(ElevationMap{geometry}, std::invalid_argument);
  geometry = example_geometry();
  geometry.size = {-1, 3};
  EXPECT_THROW(ElevationMap{geometry}, std::invalid_argument);
}

// --- build_elevation_map: hand-made cells -------------------------------------------------------

TEST(BuildElevationMap, HandMadeCellsGiveExactStatistics) {
  // res 1: cell (0, 0) holds 1, 2, 4, 5 (mean 3, population std sqrt(2.5)), cell (1, 0) one point.
  const std::vector<Eigen::Vector3d> points = {
      {0.5, 0.5, 1.0}, {0.1, 0.9, 5.0}, {0.9, 0.1, 2.0}, {0.0, 0.0, 4.0}, {1.5, 0.5, -3.0}};
  const ElevationMap map = build_elevation_map(PointsView<double>(points), fixed_extent(1.0, {0.0, 0.0}, {2, 2}));
  EXPECT_EQ(map.layers(), kStatisticLayers);
  expect_same_layer(map.get("count"), (Layer(2, 2) << 4, 0, 1, 0).finished(), "count");
  expect_same_layer(map.get("min"), (Layer(2, 2) << 1, kNaN, -3, kNaN).finished(), "min");
  expect_same_layer(map.get("max"), (Layer(2, 2) << 5, kNaN, -3, kNaN).finished(), "max");
  expect_same_layer(map.get("mean"), (Layer(2, 2) << 3, kNaN, -3, kNaN).finished(), "mean");
  expect_same_layer(map.get("std_dev"), (Layer(2, 2) << static_cast<float>(std::sqrt(2.5)), kNaN, 0, kNaN).finished(),
                    "std_dev");
  expect_same_layer(map.get("discontinuity"), (Layer(2, 2) << 1, kNaN, 0, kNaN).finished(), "discontinuity");
}

TEST(BuildElevationMap, GapExactlyEqualToTheThresholdIsNotADiscontinuity) {
  // Unsorted on purpose: the gap is between sorted neighbours 0.0 and 1.0.
  const std::vector<Eigen::Vector3d> points = {{0.5, 0.5, 1.0}, {0.5, 0.5, 0.0}};
  ElevationParams params = fixed_extent(1.0, {0.0, 0.0}, {1, 1});
  params.discontinuity_m = 1.0;
  EXPECT_EQ(build_elevation_map(PointsView<double>(points), params).get("discontinuity")(0, 0), 0.0F);
  params.discontinuity_m = std::nextafter(1.0, 0.0);  // the 1.0 m gap is now strictly greater
  EXPECT_EQ(build_elevation_map(PointsView<double>(points), params).get("discontinuity")(0, 0), 1.0F);
}

TEST(BuildElevationMap, GapJustAboveTheThresholdIsADiscontinuity) {
  const std::vector<Eigen::Vector3d> points = {{0.5, 0.5, 0.0}, {0.5, 0.5, std::nextafter(1.0, 2.0)}};
  ElevationParams params = fixed_extent(1.0, {0.0, 0.0}, {1, 1});
  params.discontinuity_m = 1.0;
  EXPECT_EQ(build_elevation_map(PointsView<double>(points), params).get("discontinuity")(0, 0), 1.0F);
}

TEST(BuildElevationMap, OnlyGapsBetweenSortedNeighboursCount) {
  // 0, 0.75, 1.5, 2.25: the range is 2.25 but no gap between sorted neighbours exceeds 1.
  const std::vector<Eigen::Vector3d> points = {{0.5, 0.5, 2.25}, {0.5, 0.5, 0.0}, {0.5, 0.5, 1.5}, {0.5, 0.5, 0.75}};
  const ElevationMap map = build_elevation_map(PointsView<double>(points), fixed_extent(1.0, {0.0, 0.0}, {1, 1}));
  EXPECT_EQ(map.get("discontinuity")(0, 0), 0.0F);
}

TEST(BuildElevationMap, PointsOutsideAFixedExtentAreIgnored) {
  const std::vector<Eigen::Vector3d> points = {{-0.01, 0.5, 9.0}, {0.5, 0.5, 1.0},  {2.0, 0.5, 9.0},
                                               {1.99, 0.5, 2.0},  {0.5, -3.0, 9.0}, {0.5, 1.0, 9.0}};
  const ElevationMap map = build_elevation_map(PointsView<double>(points), fixed_extent(1.0, {0.0, 0.0}, {2, 1}));
  expect_same_layer(map.get("count"), (Layer(2, 1) << 1, 1).finished(), "count");
  expect_same_layer(map.get("max"), (Layer(2, 1) << 1, 2).finished(), "max");
}

TEST(BuildElevationMap, AutoExtentSnapsTheOriginDownToTheResolutionAndIncludesTheMaxPoint) {
  // x in [-0.7, 1.5], y in [0.2, 0.9] at 0.5 m: origin (-1, 0); x = 1.5 (the max) opens a 6th column.
  const std::vector<Eigen::Vector3d> points = {{-0.7, 0.2, 0.0}, {1.5, 0.9, 1.0}, {0.3, 0.5, 2.0}};
  ElevationParams params;
  params.resolution_m = 0.5;
  const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
  EXPECT_EQ(map.geometry().origin_m, Eigen::Vector2d(-1.0, 0.0));
  EXPECT_EQ(map.geometry().size.matrix(), CellIndex(6, 2).matrix());
  EXPECT_EQ(map.geometry().resolution_m, 0.5);
  // (-0.7, 0.2) -> (0, 0); (0.3, 0.5) -> (2, 1); (1.5, 0.9) -> (5, 1).
  expect_same_layer(map.get("count"), (Layer(6, 2) << 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 1).finished(), "count");
  // The same max at x = 1.49 stays in the 5th column.
  const std::vector<Eigen::Vector3d> inside = {{-0.7, 0.2, 0.0}, {1.49, 0.9, 1.0}};
  EXPECT_EQ(build_elevation_map(PointsView<double>(inside), params).geometry().size.matrix(), CellIndex(5, 2).matrix());
  // A negative origin that is already a multiple stays.
  const std::vector<Eigen::Vector3d> on_grid = {{-1.5, -2.0, 0.0}, {-1.4, -1.9, 0.0}};
  EXPECT_EQ(build_elevation_map(PointsView<double>(on_grid), params).geometry().origin_m, Eigen::Vector2d(-1.5, -2.0));
}

TEST(BuildElevationMap, AutoExtentKeepsEveryPointOfCloudsOnDecimalCoordinates) {
  // Coordinates such as 0.3 or 57.9 at 0.1 m lie within a rounding error of a cell boundary.
  // Whatever side they fall on, the auto extent must hold every point of the cloud.
  ElevationParams params;
  params.resolution_m = 0.1;
  int dropped = 0;
  for (int k = 0; k < 1000; ++k) {
    const double a = k / 10.0;
    const double b = (k + 3) / 10.0;
    const std::vector<Eigen::Vector3d> points = {{a, a, 0.0}, {b, b, 1.0}};
    const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
    if (map.get("count").sum() != 2.0F && ++dropped <= 3) {
      ADD_FAILURE() << "points at " << a << " and " << b << ": map origin " << map.geometry().origin_m.transpose()
                    << ", size " << map.geometry().size.transpose() << ", counted " << map.get("count").sum();
    }
  }
  EXPECT_EQ(dropped, 0) << "of 1000 two-point clouds lost a point";
}

TEST(BuildElevationMap, PointsAreBinnedIntoTheCellThatIndexOfNames) {
  // The map must agree with its own geometry: each point is counted in geometry.index_of(point).
  const ElevationParams params = fixed_extent(0.1, {0.0, -5.0}, {100, 100});
  std::vector<Eigen::Vector3d> points;
  for (int k = 0; k < 100; ++k) points.emplace_back(k / 10.0, -5.0 + k / 10.0, 0.0);
  const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
  Layer expected = Layer::Zero(100, 100);
  for (const Eigen::Vector3d& p : points) {
    const auto index = map.geometry().index_of(p.head<2>());
    ASSERT_TRUE(index.has_value());
    expected((*index)(0), (*index)(1)) += 1.0F;
  }
  expect_same_layer(map.get("count"), expected, "count");
}

// --- fast paths: binning by multiplication, the wide-cell filter of the gap test, scratch reuse ----

TEST(BuildElevationMapEdgeCases, PointsOnAndWithinRoundingOfCellBordersAreBinnedByTheDivisionFormula) {
  // The binning estimates (p - origin) / res by a multiplication and divides only near whole
  // numbers; points on borders and a few ulps either side must land where the division puts them.
  for (const double resolution : {0.1, 0.05, 0.3, 1.0 / 3.0, 0.7, 0.25}) {
    for (const Eigen::Vector2d& origin : {Eigen::Vector2d(0.0, 0.0), Eigen::Vector2d(-20.0, -10.0),
                                          Eigen::Vector2d(3.7, -0.1), Eigen::Vector2d(1e4 + 0.3, -2e4)}) {
      SCOPED_TRACE("resolution " + std::to_string(resolution) + ", origin " + std::to_string(origin.x()));
      const CellIndex size(37, 23);
      std::vector<Eigen::Vector3d> points;
      for (int k = -2; k <= 39; ++k) {
        const double border_x = origin.x() + k * resolution;
        const double border_y = origin.y() + (k % 25) * resolution;
        for (const double dx : {-2e-9, 0.0, 2e-9}) {
          for (int ulps = -3; ulps <= 3; ++ulps) {
            double x = border_x + dx;
            double y = border_y - dx;
            for (int u = 0; u < std::abs(ulps); ++u) {
              x = std::nextafter(x, ulps > 0 ? 1e300 : -1e300);
              y = std::nextafter(y, ulps > 0 ? -1e300 : 1e300);
            }
            points.emplace_back(x, y, 0.01 * k);
          }
        }
      }
      const ElevationParams params = fixed_extent(resolution, origin, size);
      const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
      expect_matches_naive(map, points, params.discontinuity_m);
    }
  }
}

TEST(BuildElevationMapEdgeCases, DiscontinuityOfManyElevationsWithGapsAtTheThresholdMatchesTheSortedScan) {
  // The gap test of wide cells buckets the elevations (width threshold / 2) instead of sorting
  // them. Cells of 2 to 60 elevations built from runs of close values separated by gaps of exactly
  // the threshold, one ulp less or more, or random, at random offsets (so gaps straddle bucket
  // borders every way), a cell with an outlier far above the rest (the sorted fallback), for a
  // representable and a non-representable threshold, and one of a few ulps of heights 300 km up
  // (rounding as large as the buckets), against the naive sorted scan.
  std::mt19937 random(5);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (const auto& [threshold, base] : {std::pair{1.0, 0.0}, std::pair{0.3, 0.0}, std::pair{3e-10, 3e5}}) {
    SCOPED_TRACE("threshold " + std::to_string(threshold) + " at " + std::to_string(base));
    std::vector<Eigen::Vector3d> points;
    const CellIndex size(20, 20);
    for (int cell = 0; cell < 400; ++cell) {
      const double x = 0.05 + 0.1 * (cell / 20);
      const double y = 0.05 + 0.1 * (cell % 20);
      double z = base + (-5.0 + 10.0 * unit(random)) * threshold;
      const int count = 2 + static_cast<int>(59 * unit(random));
      for (int k = 0; k < count; ++k) {
        points.emplace_back(x, y, z);
        const double choice = unit(random);
        if (choice < 0.15) {
          z += threshold;
        } else if (choice < 0.25) {
          z = std::nextafter(z + threshold, -1e300);
        } else if (choice < 0.35) {
          z = std::nextafter(z + threshold, 1e300);
        } else if (choice < 0.4) {
          z += threshold * (1.0 + unit(random));
        } else {
          z += threshold * 0.6 * unit(random);
        }
      }
      if (cell % 50 == 7) points.emplace_back(x, y, 1e6);  // an outlier: sorted instead
    }
    std::shuffle(points.begin(), points.end(), random);
    ElevationParams params = fixed_extent(0.1, {0.0, 0.0}, size);
    params.discontinuity_m = threshold;
    expect_matches_naive(build_elevation_map(PointsView<double>(points), params), points, threshold);
  }
}

TEST(BuildElevationMapEdgeCases, LowestHeightGapIsTheSortedScansFirstGap) {
  // The pair itself (not only whether there is one), against sorting and scanning: random sets of
  // runs, gaps at the threshold and one ulp either side, an outlier now and then (the sorted path).
  std::mt19937 random(11);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  std::vector<double> scratch;
  for (int trial = 0; trial < 2000; ++trial) {
    const double threshold = trial % 2 == 0 ? 0.5 : 0.3;
    std::vector<double> heights;
    double z = -3.0 + 6.0 * unit(random);
    const int count = 1 + static_cast<int>(40 * unit(random));
    for (int k = 0; k < count; ++k) {
      heights.push_back(z);
      const double choice = unit(random);
      z += choice < 0.1    ? threshold
           : choice < 0.2  ? std::nextafter(threshold, 1.0)
           : choice < 0.25 ? threshold * (1.0 + unit(random))
                           : threshold * 0.7 * unit(random);
    }
    if (trial % 37 == 0) heights.push_back(1e5);
    std::shuffle(heights.begin(), heights.end(), random);
    std::vector<double> sorted = heights;
    std::sort(sorted.begin(), sorted.end());
    std::optional<HeightGap> expected;
    for (std::size_t k = 1; k < sorted.size() && !expected; ++k) {
      if (sorted[k] - sorted[k - 1] > threshold) expected = HeightGap{sorted[k - 1], sorted[k]};
    }
    const std::optional<HeightGap> got = lowest_height_gap(heights.data(), heights.size(), threshold, scratch);
    ASSERT_EQ(got.has_value(), expected.has_value()) << "trial " << trial;
    if (got) {
      EXPECT_EQ(got->below_m, expected->below_m);
      EXPECT_EQ(got->above_m, expected->above_m);
    }
  }
  const double bad[] = {0.0, std::nan(""), 2.0};
  EXPECT_THROW(lowest_height_gap(bad, 3, 0.5, scratch), std::invalid_argument);
  EXPECT_THROW(lowest_height_gap(bad, 1, 0.0, scratch), std::invalid_argument);
  EXPECT_FALSE(lowest_height_gap(bad, 0, 0.5, scratch).has_value());
}

TEST(BuildElevationMapEdgeCases, WideCellFilterAtTheThresholdAgreesWithHandComputedFlags) {
  // One cell per case (threshold 1 m, all values exact in binary). Only cells whose range exceeds
  // the threshold are sorted; the rest are 0 without looking for gaps.
  struct Case {
    std::vector<double> z;
    float flag;
    const char* what;
  };
  const std::vector<Case> cases = {
      {{0.0, 0.5, 0.25}, 0.0F, "narrow cell"},
      {{0.0, 1.0}, 0.0F, "range exactly the threshold: not wide, and its gap is not longer"},
      {{1.0, 0.5, 0.0}, 0.0F, "range exactly the threshold, three values"},
      {{0.0, 0.5, 1.5}, 0.0F, "wide (range 1.5) without a gap over 1"},
      {{1.5, 0.0, 0.5, 1.0}, 0.0F, "wide, steps of 0.5"},
      {{0.0, 1.0, 1.5}, 0.0F, "wide, a gap exactly the threshold"},
      {{2.0, 0.0, 1.0}, 0.0F, "wide, two gaps exactly the threshold"},
      {{0.0, static_cast<double>(std::nextafter(1.0F, 2.0F)), 1.5}, 1.0F, "wide, a gap one float ulp over"},
      {{5.0, 0.0, 0.25, 0.5}, 1.0F, "wide, the gap at the top"},
      {{-3.0, 0.0, 0.25, 0.5}, 1.0F, "wide, the gap at the bottom"},
      {{7.0}, 0.0F, "one point"},
  };
  std::vector<Eigen::Vector3d> points;
  for (std::size_t c = 0; c < cases.size(); ++c) {
    for (const double z : cases[c].z) points.emplace_back(c + 0.5, 0.5, z);
  }
  const ElevationParams params = fixed_extent(1.0, {0.0, 0.0}, CellIndex(static_cast<int>(cases.size()) + 1, 1));
  for (const bool as_float : {false, true}) {
    const std::vector<float> floats = as_floats(points, 3);
    const ElevationMap map = as_float ? build_elevation_map(PointsView<float>(floats.data(), points.size()), params)
                                      : build_elevation_map(PointsView<double>(points), params);
    for (std::size_t c = 0; c < cases.size(); ++c) {
      EXPECT_EQ(map.get("discontinuity")(static_cast<int>(c), 0), cases[c].flag)
          << cases[c].what << (as_float ? " (float view)" : " (double view)");
    }
    EXPECT_TRUE(std::isnan(map.get("discontinuity")(static_cast<int>(cases.size()), 0))) << "the empty cell";
    expect_matches_naive(map, as_float ? rounded_to_float(points) : points, params.discontinuity_m);
  }
}

TEST(BuildElevationMapEdgeCases, TransformedCloudsKeepDoubleHeightsForTheWideCellFilter) {
  // With a transform the heights are doubles: a range of 1 + 1e-12 m is wide and holds a gap just
  // over 1 m that float heights would round away.
  const std::vector<Eigen::Vector3d> points = {
      {0.5, 0.5, 10.0}, {0.5, 0.5, 11.0 + 1e-12}, {1.5, 0.5, 10.0}, {1.5, 0.5, 11.0}};
  ElevationParams params = fixed_extent(1.0, {0.0, 0.0}, {2, 1});
  params.transform.topRightCorner<3, 1>() = Eigen::Vector3d(0.0, 0.0, -10.0);
  std::vector<Eigen::Vector3d> moved;
  for (const Eigen::Vector3d& p : points) moved.push_back(p + Eigen::Vector3d(0.0, 0.0, -10.0));
  const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
  EXPECT_EQ(map.get("discontinuity")(0, 0), 1.0F);
  EXPECT_EQ(map.get("discontinuity")(1, 0), 0.0F);
  expect_matches_naive(map, moved, params.discontinuity_m);
}

TEST(BuildElevationMapEdgeCases, ScratchBuffersReusedAcrossCallsOfDifferentSizesLeaveNoTrace) {
  // build_elevation_map keeps per-thread scratch buffers: a large map, a small one and the large
  // one again must each equal a build on a fresh thread.
  const auto large = test::random_scene(41, 8000, 9.0);
  const auto small = test::random_scene(42, 300, 2.0);
  ElevationParams large_params;
  large_params.resolution_m = 0.1;
  ElevationParams small_params = fixed_extent(0.5, {-1.0, -1.0}, {3, 5});
  const ElevationMap first = build_elevation_map(PointsView<double>(large), large_params);
  const ElevationMap second = build_elevation_map(PointsView<double>(small), small_params);
  const ElevationMap third = build_elevation_map(PointsView<double>(large), large_params);
  expect_same_statistics(first, third);
  expect_matches_naive(second, small, small_params.discontinuity_m);
  std::optional<ElevationMap> on_fresh_thread;
  std::thread([&] { on_fresh_thread = build_elevation_map(PointsView<double>(large), large_params); }).join();
  expect_same_statistics(*on_fresh_thread, first);
  expect_matches_naive(first, large, large_params.discontinuity_m);
}

/// Drops a map of `layers` layers of `size`, every cell `poison`; returns their buffers.
std::vector<const float*> drop_poisoned_map(const MapGeometry& geometry, int layers, float poison) {
  std::vector<const float*> buffers;
  ElevationMap poisoned(geometry);
  for (int k = 0; k < layers; ++k) {
    poisoned.add("poison " + std::to_string(k), poison);
    buffers.push_back(poisoned.get("poison " + std::to_string(k)).data());
  }
  return buffers;
}

TEST(BuildElevationMapEdgeCases, MapsBuiltAfterDroppedMapsShowNoTraceOfThem) {
  // The memory of a dropped map may well be the next map's: the next map must still equal the
  // naive layers, its own and the overhang pipeline's derived ones alike (a build on another
  // thread is the reference there).
  const auto points = test::random_scene(61, 3000, 6.0);
  const ElevationParams params = fixed_extent(0.25, {-6.0, -6.0}, {48, 40});
  constexpr float kPoison = 12345.0F;
  MapGeometry geometry;
  geometry.resolution_m = 0.25;
  geometry.origin_m = Eigen::Vector2d(-6.0, -6.0);
  geometry.size = CellIndex(48, 40);
  const std::vector<const float*> dropped = drop_poisoned_map(geometry, 12, kPoison);
  // Buffers of the same size from the allocator in between: had the dropped layers gone back to
  // it, these would likely take them, and the map would not.
  std::vector<std::vector<float>> others(12, std::vector<float>(geometry.num_cells()));
  const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
  for (const std::string& name : map.layers()) {
    EXPECT_EQ((map.get(name).array() == kPoison).count(), 0) << name;
    // This thread kept the dropped map's buffers: the new map's layers are them, no fresh memory.
    EXPECT_NE(std::find(dropped.begin(), dropped.end(), map.get(name).data()), dropped.end()) << name;
  }
  expect_matches_naive(map, points, params.discontinuity_m);

  CollapseParams collapse;
  collapse.edge_m = 0.5;
  collapse.sigma = 2;
  drop_poisoned_map(geometry, 20, kPoison);
  const OverhangFreeMap again = build_overhang_free_map(PointsView<double>(points), collapse, params);
  std::optional<OverhangFreeMap> fresh;
  std::thread([&] { fresh = build_overhang_free_map(PointsView<double>(points), collapse, params); }).join();
  ASSERT_EQ(again.map.layers(), fresh->map.layers());
  for (const std::string& name : again.map.layers()) {
    expect_same_layer(again.map.get(name), fresh->map.get(name), name);
  }
}

TEST(BuildElevationMapEdgeCases, AMapDroppedAtThreadExitAfterTheKeptLayersOfItsThreadFreesItsLayers) {
  // `held` is made before the thread keeps any layer, so it is destroyed after the kept layers
  // are: its layers are then freed (ASan and LSan watch), not kept by a destroyed keeper.
  MapGeometry geometry;
  geometry.size = CellIndex(30, 20);
  std::thread([&] {
    thread_local std::optional<ElevationMap> held;
    held.emplace(geometry);
    held->add("height", 1.0F);
    ElevationMap(geometry).add("dropped", 2.0F);  // dropped now: its layer is kept until thread exit
  }).join();
  SUCCEED();
}

TEST(BuildElevationMapEdgeCases, ConcurrentCallsOnTwoThreadsGiveTheSerialResults) {
  const auto a = test::random_scene(51, 6000, 8.0);
  const auto b = test::random_scene(52, 5000, 6.0);
  ElevationParams params;
  params.resolution_m = 0.2;
  const ElevationMap serial_a = build_elevation_map(PointsView<double>(a), params);
  const ElevationMap serial_b = build_elevation_map(PointsView<double>(b), params);
  std::vector<ElevationMap> from_a(20), from_b(20);
  std::thread first([&] {
    for (auto& map : from_a) map = build_elevation_map(PointsView<double>(a), params);
  });
  std::thread second([&] {
    for (auto& map : from_b) map = build_elevation_map(PointsView<double>(b), params);
  });
  first.join();
  second.join();
  for (const auto& map : from_a) expect_same_statistics(map, serial_a);
  for (const auto& map : from_b) expect_same_statistics(map, serial_b);
}

TEST(BuildElevationMapEdgeCases, FloatRowsOnAndNearCellBordersOfEveryTailLengthAreBinnedByTheDivisionFormula) {
  // Float rows of 3 and 4 scalars on every cell border along x or y and a float ulp either side
  // (among them rows where multiplying by 1 / resolution floors differently from dividing), rows
  // outside by less than a cell, NaN/Inf rows (dropped on request), and every cloud length from 1
  // to 13 rows, against the naive reference.
  const double resolution = 0.1;
  const CellIndex size(40, 20);
  int multiplication_differs = 0;  // rows the estimate alone would bin wrongly (origin 3.7 has some)
  for (const Eigen::Vector2d& origin : {Eigen::Vector2d(-2.0, -1.0), Eigen::Vector2d(3.7, 3.7)}) {
    SCOPED_TRACE("origin " + std::to_string(origin.x()));
    std::mt19937 random(7);
    std::uniform_real_distribution<double> unit(0.0, 1.0), height(-1.0, 3.0);
    std::vector<Eigen::Vector3d> pool;
    for (int axis = 0; axis < 2; ++axis) {
      for (int k = -1; k <= size[axis] + 1; ++k) {
        const auto border = static_cast<float>(origin[axis] + k * resolution);
        for (const float v : {std::nextafter(border, -1e30F), border, std::nextafter(border, 1e30F)}) {
          Eigen::Vector3d p(origin.x() + unit(random) * size.x() * resolution,
                            origin.y() + unit(random) * size.y() * resolution, height(random));
          p = test::rounded_to<float>(p);
          p[axis] = v;
          const double offset = p[axis] - origin[axis];
          multiplication_differs += std::floor(offset / resolution) != std::floor(offset * (1.0 / resolution));
          pool.push_back(p);
        }
      }
    }
    ElevationParams params = fixed_extent(resolution, origin, size);
    params.drop_non_finite = true;
    constexpr double kNaNd = std::numeric_limits<double>::quiet_NaN();
    std::vector<std::pair<std::size_t, std::size_t>> slices = {{0, pool.size()}};  // (start, length)
    for (std::size_t length = 1; length <= 13; ++length) {
      for (std::size_t start = length; start + length <= pool.size(); start += 41) slices.emplace_back(start, length);
    }
    for (const auto& [start, length] : slices) {
      std::vector<Eigen::Vector3d> points(pool.begin() + static_cast<std::ptrdiff_t>(start),
                                          pool.begin() + static_cast<std::ptrdiff_t>(start + length));
      std::vector<Eigen::Vector3d> with_bad = points;
      with_bad[length / 2].y() = length % 2 ? kNaNd : std::numeric_limits<double>::infinity();
      std::vector<Eigen::Vector3d> finite = points;
      finite.erase(finite.begin() + static_cast<std::ptrdiff_t>(length / 2));
      for (const int stride : {3, 4}) {
        SCOPED_TRACE("length " + std::to_string(length) + ", start " + std::to_string(start) + ", stride " +
                     std::to_string(stride));
        const std::vector<float> rows = as_floats(points, stride);
        expect_matches_naive(build_elevation_map(PointsView<float>(rows.data(), points.size(), stride, 1), params),
                             points, 1.0);
        const std::vector<float> bad_rows = as_floats(with_bad, stride);
        expect_matches_naive(
            build_elevation_map(PointsView<float>(bad_rows.data(), with_bad.size(), stride, 1), params), finite, 1.0);
      }
    }
  }
  EXPECT_GT(multiplication_differs, 0) << "the rows must include some that only the division bins right";
}

TEST(BuildElevationMapEdgeCases, FloatRowsAreBinnedByTheDivisionFormulaForOriginsResolutionsAndWidthsOfEveryScale) {
  // Every float row must land in the cell of the division formula (in doubles): random rows and
  // rows on, and a float ulp either side of, cell borders, for origins, resolutions and widths of
  // every scale (an origin 3e5 m away that a float does not hold, a 20,000-cell map), on rows of 3
  // and 4 scalars and lengths around multiples of 8.
  struct Case {
    double resolution;
    Eigen::Vector2d origin;
    CellIndex size;
  };
  const std::vector<Case> cases = {
      {0.1, {-20.0, -10.0}, {400, 200}},      {0.07, {123.456, -987.65}, {300, 150}},
      {0.25, {5000.3, -4000.1}, {200, 100}},  {0.05, {-1.3, 2.9}, {2000, 10}},
      {0.02, {0.01, -0.03}, {8000, 4}},       {0.1, {300000.0, -200000.0}, {50, 50}},
      {0.1, {300000.3, -200000.7}, {50, 50}}, {0.003, {-0.7, 0.4}, {20000, 2}},
      {3.0, {-1234.5, 987.6}, {64, 64}},
  };
  std::mt19937 random(2024);
  for (const Case& c : cases) {
    SCOPED_TRACE("resolution " + std::to_string(c.resolution) + ", origin " + std::to_string(c.origin.x()) + ", " +
                 std::to_string(c.origin.y()) + ", size " + std::to_string(c.size.x()) + " x " +
                 std::to_string(c.size.y()));
    std::uniform_real_distribution<double> unit(-0.05, 1.05), height(-2.0, 5.0);
    std::vector<Eigen::Vector3d> points;
    for (int k = 0; k < 1500; ++k) {
      points.push_back(test::rounded_to<float>(Eigen::Vector3d(
          c.origin.x() + unit(random) * static_cast<double>(c.size.x()) * c.resolution,
          c.origin.y() + unit(random) * static_cast<double>(c.size.y()) * c.resolution, height(random))));
    }
    for (int axis = 0; axis < 2; ++axis) {
      std::uniform_int_distribution<int> border_index(-1, static_cast<int>(c.size[axis]) + 1);
      for (int k = 0; k < 300; ++k) {
        const auto border = static_cast<float>(c.origin[axis] + border_index(random) * c.resolution);
        Eigen::Vector3d p = points[static_cast<std::size_t>(k)];
        p[axis] = static_cast<double>(k % 3 == 0 ? std::nextafter(border, -1e30F)
                                                 : (k % 3 == 1 ? border : std::nextafter(border, 1e30F)));
        points.push_back(p);
      }
    }
    std::shuffle(points.begin(), points.end(), random);
    const ElevationParams params = fixed_extent(c.resolution, c.origin, c.size);
    for (const std::size_t length : {points.size(), std::size_t{8}, std::size_t{15}, std::size_t{17}}) {
      const std::vector<Eigen::Vector3d> slice(points.begin(), points.begin() + static_cast<std::ptrdiff_t>(length));
      for (const int stride : {3, 4}) {
        SCOPED_TRACE("length " + std::to_string(length) + ", stride " + std::to_string(stride));
        const std::vector<float> rows = as_floats(slice, stride);
        expect_matches_naive(build_elevation_map(PointsView<float>(rows.data(), slice.size(), stride, 1), params),
                             slice, 1.0);
      }
    }
  }
}

TEST(BuildElevationMapEdgeCases, LatticeRowsOnCellBordersAreBinnedByTheDivisionFormula) {
  // Coordinates on a 1 cm lattice (as laser-scanner exports often are) put a tenth of the rows of
  // each axis on 0.1 m cell borders, with NaN/Inf rows among them. Every row must land where the
  // division puts it, on float and double views, rows of 3 and 4 scalars, with and without a
  // selection, fixed and automatic extents.
  std::mt19937 random(11);
  std::uniform_int_distribution<int> step_x(-150, 250), step_y(-80, 300), step_z(-50, 400);
  std::vector<Eigen::Vector3d> lattice;
  for (int k = 0; k < 3001; ++k) {
    lattice.push_back(Eigen::Vector3d(step_x(random), step_y(random), step_z(random)) * 0.01);
  }
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  std::vector<Eigen::Vector3d> points = lattice;
  for (std::size_t row : {0, 5, 10, 15, 17, 18, 19, 300, 301, 2000}) {  // alone and in runs
    points[row][static_cast<int>(row % 3)] = row % 2 == 0 ? nan : inf;
  }
  std::vector<std::uint8_t> use(points.size());
  for (std::size_t row = 0; row < use.size(); ++row) use[row] = row % 3 == 0 ? 0 : 1;
  for (const bool fixed : {true, false}) {
    ElevationParams params = fixed ? fixed_extent(0.1, {-1.0, -0.5}, {30, 40}) : ElevationParams{};
    params.resolution_m = 0.1;
    params.drop_non_finite = true;
    for (const bool selection : {false, true}) {
      std::vector<Eigen::Vector3d> finite, finite_float;
      for (std::size_t row = 0; row < points.size(); ++row) {
        if (!points[row].allFinite() || (selection && use[row] == 0)) continue;
        finite.push_back(points[row]);
        finite_float.push_back(test::rounded_to<float>(points[row]));
      }
      const std::vector<std::uint8_t>* chosen = selection ? &use : nullptr;
      SCOPED_TRACE(std::string(fixed ? "fixed extent" : "automatic extent") + (selection ? ", selection" : ""));
      {
        SCOPED_TRACE("double view");
        expect_matches_naive(build_elevation_map(PointsView<double>(points), params, chosen), finite, 1.0);
      }
      for (const int stride : {3, 4}) {
        SCOPED_TRACE("float view, stride " + std::to_string(stride));
        const std::vector<float> rows = as_floats(points, stride);
        expect_matches_naive(
            build_elevation_map(PointsView<float>(rows.data(), points.size(), stride, 1), params, chosen), finite_float,
            1.0);
      }
    }
  }
}

TEST(BuildElevationMapEdgeCases, RunsOfACellBrokenByOutsideRowsAndOtherCellsKeepEveryElevation) {
  // Consecutive rows of one cell are summed as a run, and the gap test gathers elevations run by
  // run: rows outside the map inside a run, a cell that comes back after another, and a gap that
  // only appears with the rows of a later run.
  const std::vector<Eigen::Vector3d> points = {{0.5, 0.5, 0.0}, {9.0, 9.0, 50.0}, {0.5, 0.5, 0.25}, {1.5, 0.5, 4.0},
                                               {0.5, 0.5, 0.5}, {-3.0, 0.5, 9.0}, {0.5, 0.5, 2.0},  {1.5, 0.5, 4.5},
                                               {9.0, 0.5, 1.0}, {1.5, 0.5, 5.0},  {0.5, 0.5, 2.25}, {1.5, 0.5, 3.0}};
  const ElevationParams params = fixed_extent(1.0, {0.0, 0.0}, {2, 1});
  for (const bool as_float : {false, true}) {
    SCOPED_TRACE(as_float ? "float view" : "double view");
    const std::vector<float> floats = as_floats(points, 4);
    const ElevationMap map = as_float
                                 ? build_elevation_map(PointsView<float>(floats.data(), points.size(), 4, 1), params)
                                 : build_elevation_map(PointsView<double>(points), params);
    // Cell (0, 0): 0, 0.25, 0.5, 2, 2.25 -> a gap of 1.5 m; cell (1, 0): 3, 4, 4.5, 5 -> none.
    EXPECT_EQ(map.get("count")(0, 0), 5.0F);
    EXPECT_EQ(map.get("discontinuity")(0, 0), 1.0F);
    EXPECT_EQ(map.get("count")(1, 0), 4.0F);
    EXPECT_EQ(map.get("discontinuity")(1, 0), 0.0F);
    expect_matches_naive(map, points, params.discontinuity_m);
  }
}

TEST(BuildElevationMapEdgeCases, ACallThatThrowsOnNaNRowsLeavesNoTraceForTheNextCall) {
  // With a fixed extent the NaN check ends the pass that has already summed the finite rows: the
  // per-thread statistics must be cleaned all the same.
  const auto points = test::random_scene(61, 3000, 4.0);
  std::vector<Eigen::Vector3d> with_nan = points;
  with_nan[1500].z() = std::numeric_limits<double>::quiet_NaN();
  const ElevationParams params = fixed_extent(0.2, {-4.0, -4.0}, {40, 40});
  for (const int stride : {3, 4}) {
    const std::vector<float> rows = as_floats(with_nan, stride);
    EXPECT_THROW(build_elevation_map(PointsView<float>(rows.data(), with_nan.size(), stride, 1), params),
                 std::invalid_argument);
    EXPECT_THROW(build_elevation_map(PointsView<double>(with_nan), params), std::invalid_argument);
    expect_matches_naive(build_elevation_map(PointsView<double>(points), params), points, params.discontinuity_m);
    const std::vector<float> clean = as_floats(points, stride);
    expect_matches_naive(build_elevation_map(PointsView<float>(clean.data(), points.size(), stride, 1), params),
                         rounded_to_float(points), params.discontinuity_m);
  }
}

TEST(BuildElevationMapEdgeCases, ShiftedOnePassVarianceIsAccurateFarFromZeroAndAfterAnOutlyingFirstPoint) {
  // The std-dev is accumulated relative to each cell's first elevation. Large absolute heights
  // (1e7 m, spread 1 mm) and a first elevation 100 m from the other 2000 (spread 1 mm) must still
  // give the two-pass value of the naive reference to 1e-5 relative.
  std::vector<Eigen::Vector3d> points;
  for (int k = 0; k < 500; ++k) points.emplace_back(0.5, 0.5, 1e7 + 1e-3 * (k % 7));
  points.emplace_back(1.5, 0.5, 100.0);
  for (int k = 0; k < 2000; ++k) points.emplace_back(1.5, 0.5, 1e-3 * (k % 5));
  const ElevationParams params = fixed_extent(1.0, {0.0, 0.0}, {2, 1});
  const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
  expect_matches_naive(map, points, params.discontinuity_m);
  EXPECT_GT(map.get("std_dev")(0, 0), 0.0F);
}

/// A cell's mean and std-dev as build_elevation_map documents them: elevations relative to the
/// first, added one after the other in row order.
std::pair<float, float> documented_mean_and_std(const std::vector<double>& z) {
  double sum = 0.0, squares = 0.0;
  for (const double v : z) {
    sum += v - z[0];
    squares += (v - z[0]) * (v - z[0]);
  }
  const auto n = static_cast<double>(z.size());
  const double offset = sum / n;
  const double variance = std::max((squares - sum * offset) / n, 0.0);
  return {static_cast<float>(z[0] + offset), static_cast<float>(std::sqrt(variance))};
}

/// Cells of 1 to 40 elevations: pairs of +-`magnitude` and small elevations, shuffled, so that the
/// order of the additions shows in the float mean (a small elevation added next to an uncancelled
/// large one is lost); rows of the cells interleaved. The map must give the row order's bits.
template <typename Scalar>
void expect_documented_order(double magnitude) {
  std::mt19937 rng(97);
  std::uniform_real_distribution<double> small(0.0, 1.0);
  constexpr int kCells = 320;
  const auto count_of = [](int k) { return k % 40 + 1; };
  const auto large = static_cast<double>(static_cast<Scalar>(magnitude));
  std::vector<std::vector<double>> heights(kCells);  // the cloud's values (float clouds: rounded)
  std::vector<Scalar> rows;
  for (int k = 0; k < kCells; ++k) {
    std::vector<double>& z = heights[k];
    for (int pair = 0; pair < count_of(k) / 3; ++pair) z.insert(z.end(), {large, -large});
    while (static_cast<int>(z.size()) < count_of(k)) z.push_back(static_cast<double>(static_cast<Scalar>(small(rng))));
    std::shuffle(z.begin(), z.end(), rng);
  }
  for (int m = 0; m < 40; ++m) {  // row m of every cell that has one, cells in turn
    for (int k = 0; k < kCells; ++k) {
      if (m < count_of(k)) {
        rows.insert(rows.end(), {static_cast<Scalar>(k + 0.5), Scalar(0.5), static_cast<Scalar>(heights[k][m])});
      }
    }
  }
  const ElevationParams params = fixed_extent(1.0, {0.0, 0.0}, {kCells, 1});
  for (const int threads : {1, 2}) {
    ElevationParams threaded = params;
    threaded.num_threads = threads;
    const ElevationMap map = build_elevation_map(PointsView<Scalar>(rows.data(), rows.size() / 3), threaded);
    for (int k = 0; k < kCells; ++k) {
      SCOPED_TRACE("cell " + std::to_string(k) + " of " + std::to_string(count_of(k)) + " elevations");
      const auto [mean, std_dev] = documented_mean_and_std(heights[k]);
      EXPECT_EQ(map.get("count")(k, 0), static_cast<float>(count_of(k)));
      EXPECT_EQ(map.get("mean")(k, 0), mean);
      EXPECT_EQ(map.get("std_dev")(k, 0), std_dev);
    }
  }
}

TEST(BuildElevationMapEdgeCases, CellSumsAddTheElevationsInRowOrderBitForBit) { expect_documented_order<double>(1e10); }

TEST(BuildElevationMapEdgeCases, FloatCellSumsAddTheElevationsInRowOrderBitForBit) {
  expect_documented_order<float>(1e30);
}

// --- build_elevation_map against the naive reference ----------------------------------------------

TEST(BuildElevationMapVsNaive, RandomScenesDoubleViewAutoExtent) {
  for (std::uint32_t seed = 1; seed <= 5; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    const auto points = test::random_scene(seed, 6000, 6.0 + seed);
    ElevationParams params;
    params.resolution_m = 0.1 + 0.07 * seed;
    params.discontinuity_m = 0.25 * seed;
    const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
    expect_snapped_extent(map.geometry(), points);
    EXPECT_EQ(map.get("count").sum(), static_cast<float>(points.size()));
    expect_matches_naive(map, points, params.discontinuity_m);
    EXPECT_GT(map.get("discontinuity").array().isNaN().count(), 0) << "the scene must leave empty cells";
    EXPECT_GT((map.get("discontinuity").array() == 1.0F).count(), 0) << "the scene must have gaps";
  }
}

TEST(BuildElevationMapVsNaive, RandomScenesFloatViewsContiguousAndStrided) {
  for (std::uint32_t seed = 11; seed <= 14; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    const auto points = rounded_to_float(test::random_scene(seed, 6000, 9.0));
    const ElevationParams params = fixed_extent(0.25, {2.0, -1.0}, {20, 30});  // covers part of the scene
    const std::vector<float> packed = as_floats(points, 3);
    const std::vector<float> strided = as_floats(points, 4);
    const ElevationMap from_packed = build_elevation_map(PointsView<float>(packed.data(), points.size()), params);
    const ElevationMap from_strided =
        build_elevation_map(PointsView<float>(strided.data(), points.size(), 4, 1), params);
    expect_matches_naive(from_packed, points, params.discontinuity_m);
    expect_matches_naive(from_strided, points, params.discontinuity_m);
    EXPECT_LT(from_packed.get("count").sum(), static_cast<float>(points.size())) << "some points must be outside";
    // Auto extent from the float views.
    ElevationParams automatic;
    automatic.resolution_m = 0.2;
    const ElevationMap auto_strided =
        build_elevation_map(PointsView<float>(strided.data(), points.size(), 4, 1), automatic);
    expect_snapped_extent(auto_strided.geometry(), points);
    expect_matches_naive(auto_strided, points, automatic.discontinuity_m);
  }
}

TEST(BuildElevationMapVsNaive, ColumnMajorDoubleView) {
  const auto points = test::random_scene(21, 4000, 7.0);
  std::vector<double> columns(3 * points.size());
  for (std::size_t row = 0; row < points.size(); ++row) {
    for (int axis = 0; axis < 3; ++axis)
      columns[static_cast<std::size_t>(axis) * points.size() + row] = points[row][axis];
  }
  ElevationParams params;
  params.resolution_m = 0.3;
  const PointsView<double> view(columns.data(), points.size(), 1, static_cast<std::ptrdiff_t>(points.size()));
  const ElevationMap map = build_elevation_map(view, params);
  expect_matches_naive(map, points, params.discontinuity_m);
  expect_same_statistics(map, build_elevation_map(PointsView<double>(points), params));
}

TEST(BuildElevationMapVsNaive, RealKittiScanOnAFixedExtent) {
  const auto data = test::shared_data_dir();
  if (!data) GTEST_SKIP() << "../shared/data not found (set TERRACUBE_DATA_DIR)";
  const test::XyziScan scan = test::read_xyzi_bin(*data + "/kitti_seq00/velodyne/000000.bin");
  const auto points = scan.as_vectors();
  const ElevationParams params = fixed_extent(0.1, {-20.0, -10.0}, {400, 200});
  const ElevationMap map = build_elevation_map(scan.xyz(), params);
  expect_matches_naive(map, points, params.discontinuity_m);
  const float counted = map.get("count").sum();
  EXPECT_GT(counted, 0.3F * static_cast<float>(points.size()));
  EXPECT_LT(counted, static_cast<float>(points.size())) << "points beyond the 40 m x 20 m extent are ignored";
  expect_same_statistics(build_elevation_map(PointsView<double>(points), params), map);
}

// --- several threads (ElevationParams::num_threads) ----------------------------------------------

/// Builds with `threads` threads.
ElevationMap build_on_threads(const std::function<ElevationMap(const ElevationParams&)>& build, ElevationParams params,
                              int threads) {
  params.num_threads = threads;
  ElevationMap map = build(params);
  return map;
}

TEST(BuildElevationMapThreads, RandomScenesGiveTheOneThreadMapBitForBitOnAnyNumberOfThreads) {
  // Random point order: consecutive rows fall in cells of different threads' ranges all the time,
  // so runs of a cell are cut by other ranges' rows everywhere.
  for (std::uint32_t seed = 61; seed <= 62; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    const auto points = rounded_to_float(test::random_scene(seed, 140000, 12.0 + seed));
    const std::vector<float> strided = as_floats(points, 4);
    const PointsView<float> floats(strided.data(), points.size(), 4, 1);
    ElevationParams automatic;
    automatic.resolution_m = 0.05 * (seed - 60);
    automatic.discontinuity_m = 0.4;
    const ElevationParams fixed = fixed_extent(0.1, {-3.0, -2.0}, {150, 170});  // part of the scene
    for (const ElevationParams& params : {automatic, fixed}) {
      const ElevationMap serial = build_elevation_map(PointsView<double>(points), params);
      expect_matches_naive(serial, points, params.discontinuity_m);
      EXPECT_GT((serial.get("discontinuity").array() == 1.0F).count(), 0) << "the scene must have gaps";
      for (const int threads : {2, 3, 4, 0}) {
        SCOPED_TRACE(std::to_string(threads) + " threads");
        expect_same_statistics(
            build_on_threads(
                [&](const ElevationParams& p) { return build_elevation_map(PointsView<double>(points), p); }, params,
                threads == 0 ? 0 : threads),
            serial);
        expect_same_statistics(
            build_on_threads([&](const ElevationParams& p) { return build_elevation_map(floats, p); }, params,
                             threads == 0 ? 0 : threads),
            serial);
      }
    }
  }
}

TEST(BuildElevationMapThreads, RunsCutByRowsOfAnotherThreadsCellsAreSummedAsOnOneThread) {
  // Each cell on the left (x < 0) gets three rows, a row of a cell on the right, three more rows.
  // The thread building the left cells must add the six heights in the one-thread order whatever
  // the rows of the other thread's cells between them; heights of +-1e6 m that cancel make the
  // order show in the float mean and std-dev of many cells.
  std::mt19937 rng(76);
  std::uniform_real_distribution<double> small(0.0, 1.0);
  std::uniform_int_distribution<int> column(0, 99);
  std::vector<Eigen::Vector3d> points;
  for (int group = 0; group < 12000; ++group) {
    const double x = -9.95 + 0.1 * (group % 90), y = -9.95 + 0.1 * (group / 90 % 100);
    const double right_x = 0.05 + 0.1 * column(rng), right_y = -9.95 + 0.1 * column(rng);
    for (const double big : {1e6, 0.0, -1e6 + 0.25, 0.0}) {
      points.emplace_back(x, y, big + small(rng));
      if (big == 0.0 && points.size() % 2 == 0) points.emplace_back(right_x, right_y, small(rng));
    }
    points.emplace_back(right_x, right_y, small(rng));
  }
  ElevationParams params = fixed_extent(0.1, {-10.0, -10.0}, {200, 200});
  params.discontinuity_m = 5e6;
  const ElevationMap serial = build_elevation_map(PointsView<double>(points), params);
  for (const int threads : {2, 3}) {
    expect_same_statistics(
        build_on_threads([&](const ElevationParams& p) { return build_elevation_map(PointsView<double>(points), p); },
                         params, threads),
        serial);
  }
}

TEST(BuildElevationMapThreads, RealKittiScanGivesTheOneThreadMapBitForBit) {
  const auto data = test::shared_data_dir();
  if (!data) GTEST_SKIP() << "../shared/data not found (set TERRACUBE_DATA_DIR)";
  const test::XyziScan scan = test::read_xyzi_bin(*data + "/kitti_seq00/velodyne/000000.bin");
  const ElevationParams params = fixed_extent(0.1, {-20.0, -10.0}, {400, 200});
  const ElevationMap serial = build_elevation_map(scan.xyz(), params);
  for (const int threads : {2, 3}) {
    const ElevationMap threaded =
        build_on_threads([&](const ElevationParams& p) { return build_elevation_map(scan.xyz(), p); }, params, threads);
    expect_same_statistics(threaded, serial);
    expect_matches_naive(threaded, scan.as_vectors(), params.discontinuity_m);
  }
}

TEST(BuildElevationMapThreads, LatticeRowsSelectionsTransformsAndRefillsGiveTheOneThreadMaps) {
  // A 1 cm lattice puts many rows on 0.1 m cell borders (the exact-formula path of the binning),
  // every third row is left out by a selection, and a leveling transform packs the rows first.
  std::mt19937 rng(71);
  std::uniform_int_distribution<int> lattice(-900, 900);
  std::uniform_int_distribution<int> heights(-50, 300);
  std::vector<Eigen::Vector3d> points(120000);
  for (auto& p : points) p = Eigen::Vector3d(0.01 * lattice(rng), 0.01 * lattice(rng), 0.01 * heights(rng));
  std::vector<std::uint8_t> use(points.size());
  for (std::size_t row = 0; row < use.size(); ++row) use[row] = row % 3 != 0 ? 1 : 0;
  ElevationParams params = fixed_extent(0.1, {-8.0, -9.0}, {170, 160});
  const auto build = [&](const ElevationParams& p) { return build_elevation_map(PointsView<double>(points), p, &use); };
  expect_same_statistics(build_on_threads(build, params, 2), build(params));
  ElevationParams leveled = params;
  leveled.transform.topLeftCorner<3, 3>() = Eigen::AngleAxisd(0.05, Eigen::Vector3d::UnitX()).toRotationMatrix();
  expect_same_statistics(build_on_threads(build, leveled, 3), build(leveled));
  // Refilling one map alternately on one and several threads leaves no trace of the other calls.
  ElevationMap reused;
  const auto other = test::random_scene(72, 90000, 8.0);
  for (const int threads : {2, 1, 3, 1}) {
    params.num_threads = threads;
    build_elevation_map_into(reused, PointsView<double>(threads == 3 ? other : points), params,
                             threads == 3 ? nullptr : &use);
    params.num_threads = 1;
    const ElevationMap fresh = threads == 3 ? build_elevation_map(PointsView<double>(other), params) : build(params);
    expect_same_statistics(reused, fresh);
  }
}

TEST(BuildElevationMapThreads, NaNRowsInSeveralThreadsBlocksAreCountedOnceAndTheFirstIsNamed) {
  auto points = test::random_scene(73, 100000, 10.0);
  for (const std::size_t row : {99990, 70000, 5000, 5001}) points[row].y() = std::nan("");
  ElevationParams params = fixed_extent(0.1, {-10.0, -10.0}, {200, 200});
  params.num_threads = 3;
  ElevationMap untouched;
  build_elevation_map_into(untouched, PointsView<double>(test::random_scene(74, 1000, 5.0)), params);
  const ElevationMap before = untouched;
  expect_throw_with<std::invalid_argument>(
      [&] { build_elevation_map_into(untouched, PointsView<double>(points), params); },
      {"4 of 100000", "first at row 5000", "drop_non_finite"});
  expect_same_statistics(untouched, before);  // a call that throws leaves the map unchanged
  params.drop_non_finite = true;
  const ElevationMap dropped = build_elevation_map(PointsView<double>(points), params);
  params.num_threads = 1;
  expect_same_statistics(dropped, build_elevation_map(PointsView<double>(points), params));
  EXPECT_EQ(dropped.get("count").sum(), static_cast<float>(points.size() - 4));
}

TEST(BuildElevationMapThreads, RefillingOnThreadsGivesTheFreshMapAndResetsOtherLayersInEveryRange) {
  // Each thread's range of cells sets its part of the layers the build does not write to NaN.
  const ElevationParams params = fixed_extent(0.1, {-6.0, -5.0}, {130, 110});
  ElevationMap map = build_elevation_map(PointsView<double>(test::random_scene(81, 2000, 5.0)), params);
  map.add("extra", 3.0F);  // a layer of an earlier use (classify_terrain's, say)
  map.add("more", -1.0F);
  const float* extra = map.get("extra").data();
  for (const int threads : {2, 3}) {
    SCOPED_TRACE(std::to_string(threads) + " threads");
    map.get("extra").setConstant(3.0F);
    map.get("more").setConstant(-1.0F);
    const auto points = test::random_scene(82 + static_cast<std::uint32_t>(threads), 120000, 7.0);
    build_on_threads(
        [&](const ElevationParams& p) {
          build_elevation_map_into(map, PointsView<double>(points), p);
          return ElevationMap();
        },
        params, threads);
    expect_same_statistics(map, build_elevation_map(PointsView<double>(points), params));
    EXPECT_EQ(map.get("extra").data(), extra) << "refilled in place";
    EXPECT_TRUE(map.get("extra").array().isNaN().all()) << "a layer the build does not write holds no data";
    EXPECT_TRUE(map.get("more").array().isNaN().all()) << "a layer the build does not write holds no data";
  }
}

TEST(BuildElevationMapThreads, AForkedChildOfAProcessThatUsedThreadsBuildsOnOneInsteadOfHanging) {
  // The threads of a process that used them do not exist in its forked child (with GCC's libgomp,
  // which the library once used, the child hung): the child's calls must still finish.
  const auto points = test::random_scene(77, 100000, 10.0);
  ElevationParams params;
  params.num_threads = 2;
  const ElevationMap parent = build_elevation_map(PointsView<double>(points), params);  // starts TBB's workers
  const float expected = parent.get("count").sum();
  const pid_t child = fork();
  ASSERT_GE(child, 0) << "fork failed";
  if (child == 0) {
    const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
    _exit(map.get("count").sum() == expected ? 0 : 1);
  }
  int status = 0;
  pid_t done = 0;
  for (int tick = 0; tick < 600 && done == 0; ++tick) {  // up to 60 s
    done = waitpid(child, &status, WNOHANG);
    if (done == 0) std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  if (done == 0) {
    kill(child, SIGKILL);
    waitpid(child, &status, 0);
    FAIL() << "the forked child hung in its first threaded build";
  }
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0) << "the child's map differs from the parent's";
}

TEST(BuildElevationMapThreads, SmallCloudsOnSeveralThreadsGiveTheOneThreadMapAndNegativeCountsAreRejected) {
  const auto points = test::random_scene(75, 5000, 6.0);
  ElevationParams params;
  params.num_threads = 4;
  const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
  params.num_threads = 1;
  expect_same_statistics(map, build_elevation_map(PointsView<double>(points), params));
  params.num_threads = -1;
  expect_throw_with<std::invalid_argument>([&] { build_elevation_map(PointsView<double>(points), params); },
                                           {"num_threads", ">= 0", "-1"});
}

// --- selection, transform, crop ----------------------------------------------------------------

TEST(BuildElevationMapSelection, UseSelectsThePointsThatTakePart) {
  const auto points = test::random_scene(31, 5000, 8.0);
  std::vector<std::uint8_t> use(points.size());
  std::vector<Eigen::Vector3d> selected;
  for (std::size_t row = 0; row < points.size(); ++row) {
    use[row] = static_cast<std::uint8_t>(row % 3 == 0 ? 0 : 7);  // any non-zero flag selects
    if (use[row] != 0) selected.push_back(points[row]);
  }
  for (const bool fixed : {false, true}) {
    SCOPED_TRACE(fixed ? "fixed extent" : "auto extent");
    ElevationParams params = fixed ? fixed_extent(0.2, {1.0, 1.0}, {25, 25}) : ElevationParams{};
    params.resolution_m = 0.2;
    const ElevationMap map = build_elevation_map(PointsView<double>(points), params, &use);
    expect_same_statistics(map, build_elevation_map(PointsView<double>(selected), params));
    expect_matches_naive(map, selected, params.discontinuity_m);
  }
}

TEST(BuildElevationMapSelection, FloatRowsWithASelectionSkipUnselectedNaNRows) {
  // Float rows of 3 and 4 scalars with a selection: unselected rows, NaN ones among them, take no
  // part; a selected NaN row is still an error.
  auto points = rounded_to_float(test::random_scene(33, 6000, 8.0));
  for (std::size_t row = 0; row < 40; ++row) {  // rows on cell borders (x = 0.25 k) and just beside
    points[row].x() = 0.25 * static_cast<double>(row % 20) + (row < 20 ? 0.0 : 1e-7);
  }
  points[77] = Eigen::Vector3d(std::numeric_limits<double>::quiet_NaN(), 1.0, 1.0);
  std::vector<std::uint8_t> use(points.size());
  std::vector<Eigen::Vector3d> selected;
  for (std::size_t row = 0; row < points.size(); ++row) {
    use[row] = static_cast<std::uint8_t>(row % 7 != 3 && row != 77);
    if (use[row] != 0) selected.push_back(points[row]);
  }
  for (const int stride : {3, 4}) {
    SCOPED_TRACE("stride " + std::to_string(stride));
    const std::vector<float> rows = as_floats(points, stride);
    const PointsView<float> view(rows.data(), points.size(), stride, 1);
    for (const bool fixed : {false, true}) {
      ElevationParams params = fixed ? fixed_extent(0.25, {0.5, -1.0}, {20, 24}) : ElevationParams{};
      params.resolution_m = 0.25;
      const ElevationMap map = build_elevation_map(view, params, &use);
      expect_matches_naive(map, selected, params.discontinuity_m);
      expect_same_statistics(map, build_elevation_map(PointsView<double>(selected), params));
    }
    use[77] = 1;
    expect_throw_with<std::invalid_argument>(
        [&] { build_elevation_map(view, fixed_extent(0.25, {0, 0}, {4, 4}), &use); },
        {"1 of 6000 point rows contain NaN or Inf (first at row 77)"});
    use[77] = 0;
  }
}

TEST(BuildElevationMapSelection, DoubleRowsWithASelectionSkipUnselectedNaNRows) {
  // The same for double rows of 3 and 4 scalars.
  auto points = test::random_scene(34, 6001, 8.0);
  for (std::size_t row = 0; row < 40; ++row) {  // rows on cell borders (x = 0.25 k) and just beside
    points[row].x() = 0.25 * static_cast<double>(row % 20) + (row < 20 ? 0.0 : 1e-12);
  }
  points[78] = Eigen::Vector3d(1.0, std::numeric_limits<double>::infinity(), 1.0);
  std::vector<std::uint8_t> use(points.size());
  std::vector<Eigen::Vector3d> selected;
  for (std::size_t row = 0; row < points.size(); ++row) {
    use[row] = static_cast<std::uint8_t>(row % 5 != 2 && row != 78);
    if (use[row] != 0) selected.push_back(points[row]);
  }
  for (const int stride : {3, 4}) {
    SCOPED_TRACE("stride " + std::to_string(stride));
    std::vector<double> rows(points.size() * static_cast<std::size_t>(stride), -7.0);
    for (std::size_t row = 0; row < points.size(); ++row) {
      for (int axis = 0; axis < 3; ++axis) rows[row * static_cast<std::size_t>(stride) + axis] = points[row][axis];
    }
    const PointsView<double> view(rows.data(), points.size(), stride, 1);
    for (const bool fixed : {false, true}) {
      ElevationParams params = fixed ? fixed_extent(0.25, {0.5, -1.0}, {20, 24}) : ElevationParams{};
      params.resolution_m = 0.25;
      const ElevationMap map = build_elevation_map(view, params, &use);
      expect_matches_naive(map, selected, params.discontinuity_m);
      expect_same_statistics(map, build_elevation_map(PointsView<double>(selected), params));
    }
    use[78] = 1;
    expect_throw_with<std::invalid_argument>(
        [&] { build_elevation_map(view, fixed_extent(0.25, {0, 0}, {4, 4}), &use); },
        {"1 of 6001 point rows contain NaN or Inf (first at row 78)"});
    use[78] = 0;
  }
}

TEST(BuildElevationMapSelection, AutoExtentFollowsOnlyTheSelectedPoints) {
  const std::vector<Eigen::Vector3d> points = {{0.25, 0.25, 0.0}, {10.0, 10.0, 0.0}, {0.75, 0.25, 1.0}};
  const std::vector<std::uint8_t> use = {1, 0, 1};
  ElevationParams params;
  params.resolution_m = 0.5;
  const ElevationMap map = build_elevation_map(PointsView<double>(points), params, &use);
  EXPECT_EQ(map.geometry().origin_m, Eigen::Vector2d(0.0, 0.0));
  EXPECT_EQ(map.geometry().size.matrix(), CellIndex(2, 1).matrix());
  expect_same_layer(map.get("max"), (Layer(2, 1) << 0, 1).finished(), "max");
}

TEST(BuildElevationMapSelection, UseOfTheWrongLengthIsRejected) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}, {1, 1, 1}};
  const std::vector<std::uint8_t> use = {1, 1, 1};
  expect_throw_with<std::invalid_argument>(
      [&] { build_elevation_map(PointsView<double>(points), ElevationParams{}, &use); }, {"3 flags for 2 points"});
}

TEST(BuildElevationMapTransform, LevelingATiltedSceneGivesTheLevelScenesLayers) {
  // Ground, steps and a deck 3 m up, with points kept well inside their 0.5 m cells.
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> inside(0.05, 0.45);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  std::vector<Eigen::Vector3d> level;
  for (int i = 0; i < 24; ++i) {
    for (int j = 0; j < 12; ++j) {
      for (int k = 0; k < 6; ++k) {
        const double x = 0.5 * i + inside(rng);
        const double y = 0.5 * j + inside(rng);
        level.emplace_back(x, y, 0.1 * (i / 6) + 0.05 * unit(rng));
        if (i > 8 && i < 16 && k < 2) level.emplace_back(x, y, 3.0 + 0.2 * unit(rng));
      }
    }
  }
  const Eigen::Matrix4d leveling = leveling_transform(0.05, 0.35);
  std::vector<Eigen::Vector3d> tilted;
  for (const auto& p : level) tilted.push_back(leveling.topLeftCorner<3, 3>().transpose() * p);
  ElevationParams params;
  params.resolution_m = 0.5;
  const ElevationMap reference = build_elevation_map(PointsView<double>(level), params);
  params.transform = leveling;
  const ElevationMap leveled = build_elevation_map(PointsView<double>(tilted), params);
  EXPECT_EQ(leveled.geometry().origin_m, reference.geometry().origin_m);
  ASSERT_EQ(leveled.geometry().size.matrix(), reference.geometry().size.matrix());
  expect_same_layer(leveled.get("count"), reference.get("count"), "count");
  expect_same_layer(leveled.get("discontinuity"), reference.get("discontinuity"), "discontinuity");
  for (const std::string name : {"min", "max", "mean", "std_dev"}) {
    expect_near_layer(leveled.get(name), reference.get(name), 1e-4F, name);
  }
  EXPECT_GT((reference.get("discontinuity").array() == 1.0F).count(), 0);
  params.transform = Eigen::Matrix4d::Identity();
  const ElevationMap unleveled = build_elevation_map(PointsView<double>(tilted), params);
  EXPECT_FALSE(unleveled.geometry().size.matrix() == reference.geometry().size.matrix() &&
               unleveled.get("max").isApprox(reference.get("max")));
}

TEST(BuildElevationMapTransform, TranslationMovesPointsBeforeBinning) {
  const std::vector<Eigen::Vector3d> points = {{0.25, 0.25, 0.0}};
  ElevationParams params = fixed_extent(0.5, {0.0, 0.0}, {3, 2});
  params.transform(0, 3) = 1.0;
  params.transform(1, 3) = 0.5;
  params.transform(2, 3) = 1.75;
  const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
  expect_same_layer(map.get("max"), (Layer(3, 2) << kNaN, kNaN, kNaN, kNaN, kNaN, 1.75).finished(), "max");
}

TEST(BuildElevationMapTransform, CropBoxInTheTransformedFrameExcludesPoints) {
  const std::vector<Eigen::Vector3d> points = {{0.2, 0.2, 0.0}, {0.2, 0.2, 5.0}, {8.0, 8.0, 0.0}, {0.7, 0.2, 1.0}};
  ElevationParams params;
  params.resolution_m = 0.5;
  params.crop = CropBox{{-1.0, -1.0, -1.0}, {1.0, 1.0, 3.0}};
  const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
  EXPECT_EQ(map.geometry().size.matrix(), CellIndex(2, 1).matrix()) << "the auto extent follows the cropped cloud";
  expect_same_layer(map.get("max"), (Layer(2, 1) << 0, 1).finished(), "max");
  expect_same_layer(map.get("discontinuity"), (Layer(2, 1) << 0, 0).finished(), "discontinuity");
  // The crop applies after the transform: lifting everything by 2.5 m pushes z = 1 out of it.
  params.transform(2, 3) = 2.5;
  const ElevationMap lifted = build_elevation_map(PointsView<double>(points), params);
  EXPECT_EQ(lifted.geometry().size.matrix(), CellIndex(1, 1).matrix());
  expect_same_layer(lifted.get("max"), (Layer(1, 1) << 2.5).finished(), "max");
}

// --- refilling a map (build_elevation_map_into) --------------------------------------------------

/// Every layer of `actual` equals that of `expected`, in the same order.
void expect_same_layers(const ElevationMap& actual, const ElevationMap& expected) {
  ASSERT_EQ(actual.layers(), expected.layers());
  EXPECT_EQ(actual.geometry().origin_m, expected.geometry().origin_m);
  EXPECT_EQ(actual.geometry().size.matrix(), expected.geometry().size.matrix());
  for (const std::string& name : expected.layers()) expect_same_layer(actual.get(name), expected.get(name), name);
}

TEST(BuildElevationMapInto, RefillingGivesTheFreshBuildInTheSameBuffersAndResetsOtherLayers) {
  const ElevationParams params = fixed_extent(0.25, {-2.0, -3.0}, {40, 36});
  ElevationMap map = build_elevation_map(PointsView<double>(test::random_scene(61, 3000, 8.0)), params);
  map.add("extra", 3.0F);  // a layer of an earlier use (classify_terrain's, say)
  std::map<std::string, const float*> buffers;
  for (const std::string& name : map.layers()) buffers[name] = map.get(name).data();
  const Layer& mean = map.get("mean");
  const std::vector<std::string> order = map.layers();
  for (std::uint32_t seed = 62; seed <= 65; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    // Denser and sparser scenes than the first, through every kind of view and a selection.
    const auto points = rounded_to_float(test::random_scene(seed, 1000 * (seed - 60), 4.0 + seed - 60));
    std::vector<std::uint8_t> use(points.size());
    std::vector<Eigen::Vector3d> selected;
    for (std::size_t row = 0; row < points.size(); ++row) {
      use[row] = static_cast<std::uint8_t>(row % 4 != 1);
      if (use[row] != 0) selected.push_back(points[row]);
    }
    const std::vector<float> strided = as_floats(points, 4);
    switch (seed % 3) {
      case 0:
        build_elevation_map_into(map, PointsView<double>(points), params);
        break;
      case 1:
        build_elevation_map_into(map, PointsView<float>(strided.data(), points.size(), 4, 1), params);
        break;
      default:
        build_elevation_map_into(map, PointsView<double>(points), params, &use);
    }
    const auto& expected_points = seed % 3 == 2 ? selected : points;
    const ElevationMap fresh = build_elevation_map(PointsView<double>(expected_points), params);
    expect_same_statistics(map, fresh);
    ElevationMap statistics(map.geometry());  // the six layers alone, for the naive check
    for (const std::string& name : kStatisticLayers) statistics.add(name, map.get(name));
    expect_matches_naive(statistics, expected_points, params.discontinuity_m);
    EXPECT_EQ(map.layers(), order);
    for (const std::string& name : map.layers()) EXPECT_EQ(map.get(name).data(), buffers[name]) << name;
    EXPECT_TRUE(map.get("extra").array().isNaN().all()) << "a layer the build does not write holds no data";
    expect_same_layer(mean, fresh.get("mean"), "a reference taken before the refill");
  }
}

TEST(BuildElevationMapInto, AMapWithoutLayersTakesAnyGeometryThenKeepsItsSize) {
  const auto first = test::random_scene(71, 2000, 6.0);
  const auto wider = test::random_scene(72, 2000, 9.0);
  ElevationParams automatic;
  automatic.resolution_m = 0.2;
  ElevationMap map;
  build_elevation_map_into(map, PointsView<double>(first), automatic);
  expect_same_layers(map, build_elevation_map(PointsView<double>(first), automatic));
  // Another auto extent of another size would need new layers: refused, the map unchanged.
  const ElevationMap before = map;
  ASSERT_NE(build_elevation_map(PointsView<double>(wider), automatic).geometry().size.matrix(),
            map.geometry().size.matrix());
  expect_throw_with<std::invalid_argument>([&] { build_elevation_map_into(map, PointsView<double>(wider), automatic); },
                                           {"cannot refill a map of", "fixed extent"});
  expect_same_layers(map, before);
  // The same size elsewhere moves the map.
  const ElevationParams moved = fixed_extent(0.2, {-5.5, 2.25}, before.geometry().size);
  build_elevation_map_into(map, PointsView<double>(wider), moved);
  expect_same_layers(map, build_elevation_map(PointsView<double>(wider), moved));
}

TEST(BuildElevationMapInto, AFailedRefillLeavesTheMapUnchanged) {
  const ElevationParams params = fixed_extent(0.5, {0.0, 0.0}, {4, 4});
  ElevationMap map = build_elevation_map(PointsView<double>(test::random_scene(81, 500, 2.0)), params);
  const ElevationMap before = map;
  const std::vector<Eigen::Vector3d> with_nan = {{0.5, 0.5, 1.0}, {NAN, 0.5, 0.0}};
  expect_throw_with<std::invalid_argument>([&] { build_elevation_map_into(map, PointsView<double>(with_nan), params); },
                                           {"1 of 2 point rows contain NaN or Inf"});
  expect_same_layers(map, before);
  const std::vector<std::uint8_t> short_use = {1};
  EXPECT_THROW(build_elevation_map_into(map, PointsView<double>(with_nan), params, &short_use), std::invalid_argument);
  expect_same_layers(map, before);
}

TEST(ElevationMapLayers, SetGeometryMovesTheMapAndKeepsItsLayers) {
  MapGeometry geometry;
  geometry.resolution_m = 0.5;
  geometry.size = CellIndex(3, 2);
  ElevationMap map(geometry);
  map.add("z", 1.5F);
  const float* buffer = map.get("z").data();
  geometry.origin_m = Eigen::Vector2d(10.0, -4.0);
  geometry.resolution_m = 0.25;
  map.set_geometry(geometry);
  EXPECT_EQ(map.geometry().origin_m, Eigen::Vector2d(10.0, -4.0));
  EXPECT_EQ(map.geometry().resolution_m, 0.25);
  EXPECT_EQ(map.get("z").data(), buffer);
  EXPECT_TRUE((map.get("z").array() == 1.5F).all());
  geometry.size = CellIndex(2, 3);
  expect_throw_with<std::invalid_argument>([&] { map.set_geometry(geometry); }, {"3 x 2 cells", "2 x 3 cells"});
  geometry.size = CellIndex(3, 2);
  geometry.resolution_m = 0.0;
  EXPECT_THROW(map.set_geometry(geometry), std::invalid_argument);
  geometry.resolution_m = 1.0;
  geometry.origin_m.x() = std::numeric_limits<double>::infinity();
  EXPECT_THROW(map.set_geometry(geometry), std::invalid_argument);
  EXPECT_EQ(map.geometry().resolution_m, 0.25) << "a refused geometry leaves the map as it was";
  ElevationMap empty;
  geometry.origin_m.x() = 0.0;
  geometry.size = CellIndex(7, 7);
  empty.set_geometry(geometry);  // no layers: any size
  EXPECT_EQ(empty.geometry().size.matrix(), CellIndex(7, 7).matrix());
}

/// The rows of `points` that are finite and, leveled by `transform` (R p + t), inside `crop`:
/// the leveled points and their input rows, computed here point by point.
struct LeveledByHand {
  std::vector<Eigen::Vector3d> points;
  std::vector<std::size_t> rows;
};
LeveledByHand level_by_hand(const std::vector<Eigen::Vector3d>& points, const Eigen::Matrix4d& transform,
                            const CropBox& crop, const std::vector<std::uint8_t>* use = nullptr) {
  LeveledByHand out;
  for (std::size_t row = 0; row < points.size(); ++row) {
    if ((use != nullptr && (*use)[row] == 0) || !points[row].allFinite()) continue;
    const Eigen::Vector3d p = transform.topLeftCorner<3, 3>() * points[row] + transform.topRightCorner<3, 1>();
    if ((p.array() < crop.min.array()).any() || (p.array() > crop.max.array()).any()) continue;
    out.points.push_back(p);
    out.rows.push_back(row);
  }
  return out;
}

TEST(BuildElevationMapTransform, LeveledCroppedSelectedCloudsMatchTheNaiveLayersOfTheLeveledPoints) {
  for (std::uint32_t seed = 91; seed <= 95; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    auto points = test::random_scene(seed, 5000, 7.0);
    points[3] = Eigen::Vector3d(0.0, std::numeric_limits<double>::quiet_NaN(), 1.0);
    Eigen::Matrix4d transform = leveling_transform(0.02 * (seed % 3), -0.015 * (seed % 4));
    transform.topRightCorner<3, 1>() = Eigen::Vector3d(-0.7, 0.2 * seed - 18.0, 1.5);
    const CropBox crop{{-1.0, -2.0, 0.0}, {5.0, 4.0, 6.0}};
    std::vector<std::uint8_t> use(points.size());
    for (std::size_t row = 0; row < points.size(); ++row) use[row] = static_cast<std::uint8_t>(row % 5 != 2);
    const LeveledByHand by_hand = level_by_hand(points, transform, crop, &use);
    ASSERT_GT(by_hand.points.size(), 1000U);
    ASSERT_LT(by_hand.points.size(), 3500U) << "the crop must cut the scene";
    for (const bool fixed : {false, true}) {
      SCOPED_TRACE(fixed ? "fixed extent" : "auto extent");
      ElevationParams params = fixed ? fixed_extent(0.2, {-0.5, -1.5}, {25, 30}) : ElevationParams{};
      params.resolution_m = 0.2;
      params.discontinuity_m = 0.5;
      params.transform = transform;
      params.crop = crop;
      params.drop_non_finite = true;
      const ElevationMap map = build_elevation_map(PointsView<double>(points), params, &use);
      if (!fixed) expect_snapped_extent(map.geometry(), by_hand.points);
      expect_matches_naive(map, by_hand.points, params.discontinuity_m);
      if (!fixed) {
        EXPECT_EQ(map.get("count").sum(), static_cast<float>(by_hand.points.size()));
      }
      // float rows: the same against the float coordinates.
      const std::vector<float> strided = as_floats(points, 4);
      const auto rounded = rounded_to_float(points);
      const LeveledByHand float_by_hand = level_by_hand(rounded, transform, crop, &use);
      expect_matches_naive(build_elevation_map(PointsView<float>(strided.data(), points.size(), 4, 1), params, &use),
                           float_by_hand.points, params.discontinuity_m);
      params.drop_non_finite = false;
      expect_throw_with<std::invalid_argument>([&] { build_elevation_map(PointsView<double>(points), params, &use); },
                                               {"1 of 5000 point rows contain NaN or Inf (first at row 3)"});
      use[3] = 0;  // an unselected NaN row is no error
      expect_matches_naive(build_elevation_map(PointsView<double>(points), params, &use), by_hand.points,
                           params.discontinuity_m);
      use[3] = 1;
    }
  }
}

TEST(BuildElevationMapTransform, CroppedFloatCloudsGiveTheDoubleViewsLayers) {
  // A float cloud that is cropped but not transformed: the layers must equal the naive ones of the
  // points that take part, and those of a double view of the same values bit for bit, for row
  // counts of every remainder and a view with column stride 2.
  for (std::uint32_t seed = 96; seed <= 98; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    auto points = rounded_to_float(test::random_scene(seed, 4997 + seed % 3, 7.0));
    points[5] = Eigen::Vector3d(0.0, 0.0, std::numeric_limits<double>::quiet_NaN());
    points[points.size() - 1] = Eigen::Vector3d(std::numeric_limits<double>::infinity(), 0.0, 0.0);  // in the tail
    const CropBox crop{{-1.0, -2.0, 0.0}, {5.0, 4.0, 6.0}};
    std::vector<std::uint8_t> use(points.size());
    for (std::size_t row = 0; row < points.size(); ++row) use[row] = static_cast<std::uint8_t>(row % 7 != 3);
    const std::vector<float> strided = as_floats(points, 4);
    std::vector<float> interleaved(2 * 3 * points.size(), -9.0F);  // x ? y ? z ? per row: column stride 2
    for (std::size_t row = 0; row < points.size(); ++row) {
      for (int axis = 0; axis < 3; ++axis) interleaved[6 * row + 2 * axis] = strided[4 * row + axis];
    }
    const PointsView<float> views[] = {PointsView<float>(strided.data(), points.size(), 4, 1),
                                       PointsView<float>(interleaved.data(), points.size(), 6, 2)};
    for (const bool selected : {false, true}) {
      SCOPED_TRACE(selected ? "with a selection" : "every row");
      const std::vector<std::uint8_t>* selection = selected ? &use : nullptr;
      const LeveledByHand by_hand = level_by_hand(points, Eigen::Matrix4d::Identity(), crop, selection);
      ASSERT_LT(by_hand.points.size(), points.size() * 3 / 4) << "the crop must cut the scene";
      for (const bool fixed : {false, true}) {
        SCOPED_TRACE(fixed ? "fixed extent" : "auto extent");
        ElevationParams params = fixed ? fixed_extent(0.2, {-0.5, -1.5}, {25, 30}) : ElevationParams{};
        params.resolution_m = 0.2;
        params.discontinuity_m = 0.5;
        params.crop = crop;
        params.drop_non_finite = true;
        const ElevationMap from_doubles = build_elevation_map(PointsView<double>(points), params, selection);
        expect_matches_naive(from_doubles, by_hand.points, params.discontinuity_m);
        for (const PointsView<float>& view : views) {
          SCOPED_TRACE("column stride " + std::to_string(view.column_stride));
          expect_same_statistics(build_elevation_map(view, params, selection), from_doubles);
        }
        params.drop_non_finite = false;
        expect_throw_with<std::invalid_argument>(
            [&] { build_elevation_map(views[0], params, selection); },
            {"2 of " + std::to_string(points.size()) + " point rows", "(first at row 5)"});
      }
    }
  }
}

// --- bad input ----------------------------------------------------------------------------------

TEST(BuildElevationMapBadInput, NanAndInfRowsThrowWithTheirCount) {
  const std::vector<Eigen::Vector3d> points = {
      {0, 0, 0}, {NAN, 0, 0}, {1, 1, 1}, {0, 0, std::numeric_limits<double>::infinity()}, {2, 2, 2}};
  expect_throw_with<std::invalid_argument>([&] { build_elevation_map(PointsView<double>(points), ElevationParams{}); },
                                           {"2 of 5 point rows contain NaN or Inf (first at row 1)"});
  // A fixed extent does not skip the check.
  expect_throw_with<std::invalid_argument>(
      [&] { build_elevation_map(PointsView<double>(points), fixed_extent(1.0, {0, 0}, {3, 3})); },
      {"2 of 5 point rows contain NaN or Inf (first at row 1)", "drop_non_finite"});
  const std::vector<float> floats = as_floats(points, 4);
  EXPECT_THROW(build_elevation_map(PointsView<float>(floats.data(), points.size(), 4, 1), ElevationParams{}),
               std::invalid_argument);
}

TEST(BuildElevationMapBadInput, NanAndInfRowsAreDroppedOnRequest) {
  const std::vector<Eigen::Vector3d> points = {
      {0, 0, 0}, {NAN, 0, 0}, {1, 1, 1}, {0, 0, -std::numeric_limits<double>::infinity()}, {2, 2, 2}};
  const std::vector<Eigen::Vector3d> finite = {{0, 0, 0}, {1, 1, 1}, {2, 2, 2}};
  ElevationParams params;
  params.resolution_m = 0.5;
  params.drop_non_finite = true;
  const ElevationMap map = build_elevation_map(PointsView<double>(points), params);
  expect_same_statistics(map, build_elevation_map(PointsView<double>(finite), params));
  EXPECT_EQ(map.get("count").sum(), 3.0F);
  ElevationParams fixed = fixed_extent(1.0, {0, 0}, {3, 3});
  fixed.drop_non_finite = true;
  const std::vector<float> floats = as_floats(points, 4);
  const ElevationMap from_floats = build_elevation_map(PointsView<float>(floats.data(), points.size(), 4, 1), fixed);
  expect_same_statistics(from_floats, build_elevation_map(PointsView<double>(finite), fixed));
  EXPECT_EQ(from_floats.get("count"), Layer::Identity(3, 3));
}

TEST(BuildElevationMapBadInput, EmptyCloudGivesAnEmptyMapWithEveryLayer) {
  const ElevationMap map = build_elevation_map(PointsView<double>(), ElevationParams{});
  EXPECT_EQ(map.geometry().size.matrix(), CellIndex(0, 0).matrix());
  EXPECT_EQ(map.geometry().num_cells(), 0U);
  ASSERT_EQ(map.layers(), kStatisticLayers);
  for (const std::string& name : kStatisticLayers) EXPECT_EQ(map.get(name).size(), 0) << name;
  // Nothing selected is the same as nothing at all.
  const std::vector<Eigen::Vector3d> points = {{1, 1, 1}};
  const std::vector<std::uint8_t> none = {0};
  EXPECT_EQ(build_elevation_map(PointsView<double>(points), ElevationParams{}, &none).geometry().num_cells(), 0U);
  // An empty cloud on a fixed extent is a map of empty cells.
  const ElevationMap fixed = build_elevation_map(PointsView<float>(), fixed_extent(0.5, {1.0, 2.0}, {3, 4}));
  EXPECT_EQ(fixed.get("count"), Layer::Zero(3, 4));
  for (const std::string name : {"min", "max", "mean", "std_dev", "discontinuity"}) {
    EXPECT_TRUE(fixed.get(name).array().isNaN().all()) << name;
  }
}

TEST(BuildElevationMapBadInput, NonPositiveResolutionIsRejected) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}};
  for (const double resolution :
       {0.0, -0.1, std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity(), 1e-320}) {
    ElevationParams params;
    params.resolution_m = resolution;
    expect_throw_with<std::invalid_argument>([&] { build_elevation_map(PointsView<double>(points), params); },
                                             {"resolution"});
  }
}

TEST(BuildElevationMapBadInput, ResolutionsBelowTheSpacingOfDoublesEndWithAnErrorNotALoop) {
  // The auto extent's origin is snapped in closed form: a step below the spacing of doubles near
  // the minimum (5 - 1e-20 == 5) cannot loop, and the cell count check refuses the map.
  const std::vector<Eigen::Vector3d> points = {{5.0, 5.0, 0.0}, {7.0, 6.0, 1.0}};
  for (const double resolution : {1e-20, 1e-300}) {
    ElevationParams params;
    params.resolution_m = resolution;
    expect_throw_with<std::invalid_argument>([&] { build_elevation_map(PointsView<double>(points), params); },
                                             {"cells", "max_cells"});
  }
}

TEST(BuildOverhangFreeMapBadInput, ElevationParamsAreCheckedBeforeTheGeometry) {
  const std::vector<Eigen::Vector3d> points = {{5.0, 5.0, 0.0}, {7.0, 6.0, 1.0}};
  ElevationParams params;
  params.resolution_m = -0.5;  // derived into a geometry first, this looped for ever
  expect_throw_with<std::invalid_argument>(
      [&] { build_overhang_free_map(PointsView<double>(points), CollapseParams{}, params); }, {"resolution"});
}

TEST(BuildElevationMapBadInput, OriginWithoutSizeOrSizeWithoutOriginIsRejected) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}};
  ElevationParams params;
  params.origin_m = Eigen::Vector2d(0.0, 0.0);
  expect_throw_with<std::invalid_argument>([&] { build_elevation_map(PointsView<double>(points), params); },
                                           {"both origin and size"});
  params.origin_m.reset();
  params.size = CellIndex(4, 4);
  expect_throw_with<std::invalid_argument>([&] { build_elevation_map(PointsView<double>(points), params); },
                                           {"both origin and size"});
}

TEST(BuildElevationMapBadInput, ZeroOrNegativeSizeIsRejected) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}};
  for (const CellIndex& size : {CellIndex(0, 4), CellIndex(4, 0), CellIndex(-1, 4)}) {
    expect_throw_with<std::invalid_argument>(
        [&] { build_elevation_map(PointsView<double>(points), fixed_extent(0.1, {0, 0}, size)); }, {"at least 1 x 1"});
  }
  ElevationParams params = fixed_extent(0.1, {std::numeric_limits<double>::quiet_NaN(), 0}, {4, 4});
  EXPECT_THROW(build_elevation_map(PointsView<double>(points), params), std::invalid_argument);
}

TEST(BuildElevationMapBadInput, MapsOverMaxCellsAreRejected) {
  // A 1 km x 1 km cloud at 1 cm needs 10^10 cells, over the default 2^26.
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}, {1000, 1000, 0}};
  ElevationParams params;
  params.resolution_m = 0.01;
  expect_throw_with<std::invalid_argument>([&] { build_elevation_map(PointsView<double>(points), params); },
                                           {"max_cells = 67108864", "coarser resolution"});
  // The guard applies to fixed extents too, and exactly at the limit the map is built.
  params = fixed_extent(1.0, {0, 0}, {10, 10});
  params.max_cells = 99;
  EXPECT_THROW(build_elevation_map(PointsView<double>(points), params), std::invalid_argument);
  params.max_cells = 100;
  EXPECT_EQ(build_elevation_map(PointsView<double>(points), params).geometry().num_cells(), 100U);
}

TEST(BuildElevationMapBadInput, NonRigidTransformsBadCropsAndBadThresholdsAreRejected) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}};
  ElevationParams params;
  params.transform(0, 0) = 2.0;  // a scaling
  expect_throw_with<std::invalid_argument>([&] { build_elevation_map(PointsView<double>(points), params); }, {"rigid"});
  params.transform = Eigen::Matrix4d::Identity();
  params.transform(1, 1) = -1.0;  // a reflection
  EXPECT_THROW(build_elevation_map(PointsView<double>(points), params), std::invalid_argument);
  params.transform = Eigen::Matrix4d::Identity();
  params.transform(3, 0) = 0.5;  // a projective last row
  EXPECT_THROW(build_elevation_map(PointsView<double>(points), params), std::invalid_argument);
  params.transform = Eigen::Matrix4d::Identity();
  params.transform(2, 3) = std::numeric_limits<double>::infinity();
  EXPECT_THROW(build_elevation_map(PointsView<double>(points), params), std::invalid_argument);
  params.transform = Eigen::Matrix4d::Identity();
  params.crop = CropBox{{1, 1, 1}, {0, 0, 0}};
  EXPECT_THROW(build_elevation_map(PointsView<double>(points), params), std::invalid_argument);
  params.crop.reset();
  for (const double gap : {0.0, -1.0, std::numeric_limits<double>::quiet_NaN()}) {
    params.discontinuity_m = gap;
    EXPECT_THROW(build_elevation_map(PointsView<double>(points), params), std::invalid_argument) << gap;
  }
}

TEST(BuildElevationMapBadInput, ViewWithoutDataIsRejected) {
  EXPECT_THROW(build_elevation_map(PointsView<float>(nullptr, 3), ElevationParams{}), std::invalid_argument);
}

// --- step_layer ---------------------------------------------------------------------------------

TEST(StepLayer, LargestDifferenceToNeighboursWithDataZeroWhenIsolatedNaNWhenEmpty) {
  const Layer height = (Layer(3, 3) << -0.5F, 1.0F, kNaN,  //
                        2.5F, kNaN, kNaN,                  //
                        kNaN, kNaN, 4.0F)
                           .finished();
  // (0,0): |1 - -0.5| = 1.5, |2.5 - -0.5| = 3 (diagonal (1,1) empty). (0,1): 1.5 and |2.5 - 1| = 1.5
  // (diagonal). (1,0): 3 and 1.5. (2,2): no neighbour with data.
  const Layer expected = (Layer(3, 3) << 3.0F, 1.5F, kNaN,  //
                          3.0F, kNaN, kNaN,                 //
                          kNaN, kNaN, 0.0F)
                             .finished();
  expect_same_layer(step_layer(height), expected, "step");
}

TEST(StepLayer, RandomLayersWithEmptyCellsMatchANeighbourByNeighbourLoop) {
  // Every shape from 1 x 1 to 6 x 7 and a 40 x 53 layer, a third to two thirds of the cells empty,
  // against the definition written out: the largest |difference| to the up to eight neighbours
  // that have data, 0 without one, NaN where the cell has no data.
  std::mt19937 random(11);
  std::uniform_real_distribution<float> value(-3.0F, 3.0F), unit(0.0F, 1.0F);
  std::vector<std::pair<int, int>> shapes = {{40, 53}};
  for (int rows = 1; rows <= 6; ++rows) {
    for (int cols = 1; cols <= 7; ++cols) shapes.emplace_back(rows, cols);
  }
  for (const auto& [rows, cols] : shapes) {
    for (const float empty : {0.33F, 0.67F}) {
      Layer height(rows, cols);
      for (Eigen::Index k = 0; k < height.size(); ++k) height.data()[k] = unit(random) < empty ? kNaN : value(random);
      Layer expected(rows, cols);
      for (int i = 0; i < rows; ++i) {
        for (int j = 0; j < cols; ++j) {
          float largest = 0.0F;
          for (int a = i - 1; a <= i + 1; ++a) {
            for (int b = j - 1; b <= j + 1; ++b) {
              if ((a == i && b == j) || a < 0 || b < 0 || a >= rows || b >= cols || std::isnan(height(a, b))) continue;
              largest = std::max(largest, std::abs(height(a, b) - height(i, j)));
            }
          }
          expected(i, j) = std::isnan(height(i, j)) ? kNaN : largest;
        }
      }
      expect_same_layer(step_layer(height), expected, std::to_string(rows) + " x " + std::to_string(cols));
    }
  }
}

TEST(StepLayer, RectangularLayersUseAllEightNeighbours) {
  const Layer height = (Layer(2, 4) << 0, 0, 0, 0,  //
                        0, 0, 0, 2)
                           .finished();
  const Layer expected = (Layer(2, 4) << 0, 0, 2, 2,  //
                          0, 0, 2, 2)
                             .finished();
  expect_same_layer(step_layer(height), expected, "step");
  EXPECT_EQ(step_layer(Layer(0, 0)).size(), 0);
  expect_same_layer(step_layer((Layer(1, 1) << 7).finished()), (Layer(1, 1) << 0).finished(), "single cell");
}

// --- build_overhang_free_map --------------------------------------------------------------------

TEST(OverhangFreeMap, LayersAreTheElevationMapOfTheKeptPointsOnTheSameGeometry) {
  for (std::uint32_t seed = 41; seed <= 44; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    const auto points = test::random_scene(seed, 6000, 10.0);
    CollapseParams collapse;
    collapse.edge_m = 0.4;
    collapse.sigma = 2;
    ElevationParams elevation;
    elevation.resolution_m = 0.25;
    const OverhangFreeMap result = build_overhang_free_map(PointsView<double>(points), collapse, elevation);
    EXPECT_EQ(result.collapse.overhang, collapse_overhangs(points, collapse).overhang);
    ASSERT_GT(result.collapse.num_overhang, 0U);
    EXPECT_EQ(result.map.layers(), (std::vector<std::string>{"count", "min", "max", "mean", "std_dev", "discontinuity",
                                                             "overhang_min", "clearance", "step"}));
    // The geometry follows all points, as the raw DEM's does.
    const ElevationMap raw = build_elevation_map(PointsView<double>(points), elevation);
    EXPECT_EQ(result.map.geometry().origin_m, raw.geometry().origin_m);
    EXPECT_EQ(result.map.geometry().size.matrix(), raw.geometry().size.matrix());

    std::vector<std::uint8_t> kept(points.size());
    std::vector<Eigen::Vector3d> kept_points, overhang_points;
    for (std::size_t row = 0; row < points.size(); ++row) {
      kept[row] = result.collapse.overhang[row] ? 0 : 1;
      (kept[row] ? kept_points : overhang_points).push_back(points[row]);
    }
    ElevationParams same_geometry = elevation;
    same_geometry.origin_m = raw.geometry().origin_m;
    same_geometry.size = raw.geometry().size;
    expect_same_statistics(result.map, build_elevation_map(PointsView<double>(points), same_geometry, &kept));
    expect_same_statistics(result.map, build_elevation_map(PointsView<double>(kept_points), same_geometry));

    // overhang_min and clearance from the naive per-cell lists.
    const NaiveCells kept_cells = naive_cells(kept_points, result.map.geometry());
    const NaiveCells overhang_cells = naive_cells(overhang_points, result.map.geometry());
    Layer overhang_min = Layer::Constant(raw.geometry().size.x(), raw.geometry().size.y(), kNaN);
    Layer clearance = overhang_min;
    for (const auto& [cell, z] : overhang_cells) {
      overhang_min(cell.first, cell.second) = static_cast<float>(*std::min_element(z.begin(), z.end()));
    }
    int finite = 0, infinite = 0;
    for (const auto& [cell, z] : kept_cells) {
      const float lowest_overhang = overhang_min(cell.first, cell.second);
      if (std::isnan(lowest_overhang)) {
        clearance(cell.first, cell.second) = kInf;
        ++infinite;
        continue;
      }
      // The ground under the overhang: the highest kept point below the lowest overhang point.
      double under = -std::numeric_limits<double>::infinity();
      for (const double height : z) {
        if (height < lowest_overhang) under = std::max(under, height);
      }
      if (std::isfinite(under)) {
        clearance(cell.first, cell.second) = lowest_overhang - static_cast<float>(under);
        EXPECT_GT(clearance(cell.first, cell.second), 0.0F);
        ++finite;
      }
    }
    EXPECT_GT(finite, 0);
    EXPECT_GT(infinite, 0);
    expect_same_layer(result.map.get("overhang_min"), overhang_min, "overhang_min");
    expect_same_layer(result.map.get("clearance"), clearance, "clearance");
    expect_same_layer(result.map.get("step"), step_layer(result.map.get("max")), "step");
  }
}

TEST(OverhangFreeMap, ClearanceIsNeverNegativeWhenAMapCellStraddlesTwoCubeColumns) {
  // One 1 m map cell over two 0.5 m cube columns: column A has ground at 0 and a collapsed canopy
  // at 3; column B is a wall from 0 to 3.5 (kept). The free height under the canopy is measured
  // from the highest kept point below it (the wall at 2.75), not from the wall's top (3.5).
  std::vector<Eigen::Vector3d> points = {{0.0, 0.0, 0.0}, {0.0, 0.0, 3.0}};
  for (int k = 0; k <= 14; ++k) points.emplace_back(0.6, 0.0, 0.25 * k);
  CollapseParams collapse;
  collapse.edge_m = 0.5;
  collapse.sigma = 2;
  ElevationParams elevation;
  elevation.resolution_m = 1.0;
  const OverhangFreeMap result = build_overhang_free_map(PointsView<double>(points), collapse, elevation);
  ASSERT_EQ(result.collapse.num_overhang, 1U);
  ASSERT_EQ(result.map.geometry().size.x(), 1);
  EXPECT_FLOAT_EQ(result.map.get("max")(0, 0), 3.5F);
  EXPECT_FLOAT_EQ(result.map.get("clearance")(0, 0), 0.25F);
}

TEST(OverhangFreeMap, GroundAndCanopyInOneCellGiveTheirVerticalDistanceAsClearance) {
  // Cell (0, 0): ground at z = 0 and a canopy at z = 3 (5 empty 0.5 m cubes >= sigma 2: collapsed).
  // Cell (1, 0): ground only.
  const std::vector<Eigen::Vector3d> points = {{0.1, 0.1, 0.0}, {0.3, 0.2, 0.0}, {0.2, 0.3, 3.0}, {1.6, 0.2, 0.5}};
  CollapseParams collapse;
  collapse.edge_m = 0.5;
  collapse.sigma = 2;
  const OverhangFreeMap result =
      build_overhang_free_map(PointsView<double>(points), collapse, fixed_extent(1.0, {0.0, 0.0}, {2, 1}));
  EXPECT_EQ(result.collapse.overhang, (std::vector<std::uint8_t>{0, 0, 1, 0}));
  expect_same_layer(result.map.get("max"), (Layer(2, 1) << 0.0F, 0.5F).finished(), "max");
  expect_same_layer(result.map.get("discontinuity"), (Layer(2, 1) << 0, 0).finished(), "discontinuity");
  expect_same_layer(result.map.get("overhang_min"), (Layer(2, 1) << 3.0F, kNaN).finished(), "overhang_min");
  expect_same_layer(result.map.get("clearance"), (Layer(2, 1) << 3.0F, kInf).finished(), "clearance");
  expect_same_layer(result.map.get("step"), (Layer(2, 1) << 0.5F, 0.5F).finished(), "step");
}

TEST(OverhangFreeMap, CellWithOnlyOverhangPointsHasNaNClearance) {
  // One 1 m cube column spans both 0.2 m cells: the canopy over cell 1 is collapsed by the ground
  // in cell 0, so cell 1 has an overhang but no kept point.
  const std::vector<Eigen::Vector3d> points = {{0.1, 0.1, 0.0}, {0.3, 0.1, 5.0}};
  CollapseParams collapse;
  collapse.edge_m = 1.0;
  collapse.sigma = 2;
  const OverhangFreeMap result =
      build_overhang_free_map(PointsView<double>(points), collapse, fixed_extent(0.2, {0.0, 0.0}, {2, 1}));
  ASSERT_EQ(result.collapse.overhang, (std::vector<std::uint8_t>{0, 1}));
  expect_same_layer(result.map.get("count"), (Layer(2, 1) << 1, 0).finished(), "count");
  expect_same_layer(result.map.get("overhang_min"), (Layer(2, 1) << kNaN, 5.0F).finished(), "overhang_min");
  expect_same_layer(result.map.get("clearance"), (Layer(2, 1) << kInf, kNaN).finished(), "clearance");
}

TEST(OverhangFreeMap, CollapseTransformAndCropReplaceTheElevationOnes) {
  const auto points = test::random_scene(45, 4000, 8.0);
  CollapseParams collapse;
  collapse.transform = leveling_transform(0.03, -0.04);
  collapse.crop = CropBox{{1.0, 1.0, -5.0}, {7.0, 7.0, 20.0}};
  ElevationParams elevation;
  elevation.resolution_m = 0.25;
  elevation.transform = leveling_transform(0.4, 0.0);          // ignored
  elevation.crop = CropBox{{0.0, 0.0, 0.0}, {0.1, 0.1, 0.1}};  // ignored
  const OverhangFreeMap result = build_overhang_free_map(PointsView<double>(points), collapse, elevation);
  ElevationParams expected_params = elevation;
  expected_params.transform = collapse.transform;
  expected_params.crop = collapse.crop;
  const ElevationMap raw = build_elevation_map(PointsView<double>(points), expected_params);
  EXPECT_EQ(result.map.geometry().origin_m, raw.geometry().origin_m);
  EXPECT_EQ(result.map.geometry().size.matrix(), raw.geometry().size.matrix());
  std::vector<std::uint8_t> kept(points.size());
  for (std::size_t row = 0; row < points.size(); ++row) kept[row] = result.collapse.overhang[row] ? 0 : 1;
  expected_params.origin_m = raw.geometry().origin_m;
  expected_params.size = raw.geometry().size;
  expect_same_statistics(result.map, build_elevation_map(PointsView<double>(points), expected_params, &kept));
}

TEST(OverhangFreeMap, ALeveledCroppedCloudGivesTheMapAndMaskOfItsPointsLeveledByHand) {
  // The pipeline with collapse's transform and crop against the pipeline without them on the
  // points leveled and cropped here: the same layers, and the same mask back on the input rows.
  for (std::uint32_t seed = 47; seed <= 49; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    auto points = test::random_scene(seed, 6000, 9.0);
    points[11] = Eigen::Vector3d(std::numeric_limits<double>::infinity(), 0.0, 0.0);
    CollapseParams collapse;
    collapse.edge_m = 0.5;
    collapse.sigma = 2;
    collapse.transform = leveling_transform(-0.03, 0.02);
    collapse.transform.topRightCorner<3, 1>() = Eigen::Vector3d(1.0, -2.0, 0.25 * seed - 10.0);
    collapse.crop = CropBox{{0.0, -3.0, -20.0}, {9.0, 5.0, 20.0}};
    collapse.drop_non_finite = true;
    ElevationParams elevation;
    elevation.resolution_m = 0.25;
    const OverhangFreeMap result = build_overhang_free_map(PointsView<double>(points), collapse, elevation);
    const LeveledByHand by_hand = level_by_hand(points, collapse.transform, *collapse.crop);
    CollapseParams plain = collapse;
    plain.transform = Eigen::Matrix4d::Identity();
    plain.crop.reset();
    const OverhangFreeMap expected = build_overhang_free_map(PointsView<double>(by_hand.points), plain, elevation);
    ASSERT_GT(expected.collapse.num_overhang, 0U) << "the scene must keep overhangs";
    std::vector<std::uint8_t> mask(points.size(), 0);
    for (std::size_t k = 0; k < by_hand.rows.size(); ++k) mask[by_hand.rows[k]] = expected.collapse.overhang[k];
    EXPECT_EQ(result.collapse.overhang, mask);
    EXPECT_EQ(result.collapse.removed_cubes, expected.collapse.removed_cubes);
    EXPECT_EQ(result.collapse.num_points, points.size());
    EXPECT_EQ(result.collapse.num_used, by_hand.points.size());
    EXPECT_EQ(result.collapse.num_cropped, points.size() - 1 - by_hand.points.size());
    EXPECT_EQ(result.collapse.num_dropped_non_finite, 1U);
    ASSERT_EQ(result.map.layers(), expected.map.layers());
    EXPECT_EQ(result.map.geometry().origin_m, expected.map.geometry().origin_m);
    for (const std::string& name : expected.map.layers()) {
      expect_same_layer(result.map.get(name), expected.map.get(name), name);
    }
  }
}

TEST(OverhangFreeMap, FloatAndDoubleViewsOfTheSameValuesAgree) {
  const auto points = rounded_to_float(test::random_scene(46, 5000, 9.0));
  const std::vector<float> strided = as_floats(points, 4);
  CollapseParams collapse;
  collapse.edge_m = 0.3;
  collapse.sigma = 3;
  ElevationParams elevation;
  elevation.resolution_m = 0.2;
  const OverhangFreeMap from_float =
      build_overhang_free_map(PointsView<float>(strided.data(), points.size(), 4, 1), collapse, elevation);
  const OverhangFreeMap from_double = build_overhang_free_map(PointsView<double>(points), collapse, elevation);
  EXPECT_EQ(from_float.collapse.overhang, from_double.collapse.overhang);
  ASSERT_EQ(from_float.map.layers(), from_double.map.layers());
  for (const std::string& name : from_double.map.layers()) {
    expect_same_layer(from_float.map.get(name), from_double.map.get(name), name);
  }
}

TEST(OverhangFreeMap, ACroppedFloatCloudGivesTheMapAndMaskOfItsDoubleView) {
  // Only cropped, a float cloud is packed in floats; a double view of the same values is packed
  // in doubles. Both must give the same mask, cube lists, counts and layers.
  for (std::uint32_t seed = 50; seed <= 51; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    auto points = rounded_to_float(test::random_scene(seed, 6001, 9.0));
    points[7] = Eigen::Vector3d(0.0, std::numeric_limits<double>::quiet_NaN(), 0.0);
    const std::vector<float> strided = as_floats(points, 4);
    CollapseParams collapse;
    collapse.edge_m = 0.5;
    collapse.sigma = 2;
    collapse.crop = CropBox{{0.0, -3.0, -20.0}, {9.0, 5.0, 20.0}};
    collapse.drop_non_finite = true;
    ElevationParams elevation;
    elevation.resolution_m = 0.25;
    const OverhangFreeMap from_float =
        build_overhang_free_map(PointsView<float>(strided.data(), points.size(), 4, 1), collapse, elevation);
    const OverhangFreeMap from_double = build_overhang_free_map(PointsView<double>(points), collapse, elevation);
    ASSERT_GT(from_double.collapse.num_overhang, 0U) << "the scene must keep overhangs";
    ASSERT_GT(from_double.collapse.num_cropped, 0U) << "the crop must cut the scene";
    EXPECT_EQ(from_float.collapse.overhang, from_double.collapse.overhang);
    EXPECT_EQ(from_float.collapse.occupied_cubes, from_double.collapse.occupied_cubes);
    EXPECT_EQ(from_float.collapse.removed_cubes, from_double.collapse.removed_cubes);
    EXPECT_EQ(from_float.collapse.num_used, from_double.collapse.num_used);
    EXPECT_EQ(from_float.collapse.num_cropped, from_double.collapse.num_cropped);
    EXPECT_EQ(from_float.collapse.num_dropped_non_finite, 1U);
    ASSERT_EQ(from_float.map.layers(), from_double.map.layers());
    for (const std::string& name : from_double.map.layers()) {
      expect_same_layer(from_float.map.get(name), from_double.map.get(name), name);
    }
  }
}

TEST(OverhangFreeMap, EmptyCloudGivesAnEmptyMapLikeBuildElevationMap) {
  // build_elevation_map returns a 0 x 0 map with every layer for an empty cloud (or one whose
  // points are all cropped); the overhang-free map must do the same rather than throw.
  OverhangFreeMap result;
  ASSERT_NO_THROW(result = build_overhang_free_map(PointsView<double>(), CollapseParams{}, ElevationParams{}));
  EXPECT_EQ(result.map.geometry().num_cells(), 0U);
  EXPECT_TRUE(result.map.exists("clearance"));
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}, {0, 0, 5}};
  CollapseParams cropped;
  cropped.crop = CropBox{{10, 10, 10}, {11, 11, 11}};
  ASSERT_NO_THROW(result = build_overhang_free_map(PointsView<double>(points), cropped, ElevationParams{}));
  EXPECT_EQ(result.map.geometry().num_cells(), 0U);
  EXPECT_EQ(result.collapse.overhang, (std::vector<std::uint8_t>{0, 0}));
}

}  // namespace
}  // namespace terracube
