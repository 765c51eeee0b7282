#include <gtest/gtest.h>
#include <terracube/baselines.hpp>
#include <terracube/collapse.hpp>

#include <algorithm>
#include <cmath>
#include <map>

#include "test_support.hpp"

namespace terracube {
namespace {

TEST(OctomapBaseline, AgreesWithCollapsePointForPointOnRandomScenes) {
  for (std::uint32_t seed = 1; seed <= 8; ++seed) {
    const auto points = test::random_scene(seed, 5000, 8.0 + seed);
    CollapseParams params;
    params.edge_m = 0.1 + 0.07 * seed;
    params.sigma = 1 + static_cast<int>(seed % 3);
    const auto expected = collapse_overhangs(points, params).overhang;
    ASSERT_GT(std::count(expected.begin(), expected.end(), 1), 0) << "the scene must contain overhangs";
    EXPECT_EQ(octomap_column_overhangs(PointsView<double>(points), params), expected) << "seed " << seed;
  }
}

TEST(OctomapBaseline, AgreesWithCollapseOnRealScansWithLevelingAndCrop) {
  const auto data = test::shared_data_dir();
  if (!data) GTEST_SKIP() << "../shared/data not found (set TERRACUBE_DATA_DIR)";
  for (const std::string file : {"/kitti_seq00/velodyne/000001.bin", "/ouster128/ouster128_000002_xyzi_valid.bin"}) {
    const test::XyziScan scan = test::read_xyzi_bin(*data + file);
    CollapseParams params;
    params.edge_m = 0.25;
    params.sigma = 3;
    EXPECT_EQ(octomap_column_overhangs(scan.xyz(), params), collapse_overhangs(scan.xyz(), params).overhang) << file;
    params.transform = leveling_transform(0.02, -0.03);
    params.crop = CropBox{{-30, -30, -3}, {30, 30, 10}};
    EXPECT_EQ(octomap_column_overhangs(scan.xyz(), params), collapse_overhangs(scan.xyz(), params).overhang) << file;
  }
}

TEST(OctomapBaseline, RejectsGridsBeyondSixteenBitKeys) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}, {70000, 0, 0}};
  CollapseParams params;
  params.edge_m = 1.0;
  EXPECT_THROW(octomap_column_overhangs(PointsView<double>(points), params), std::invalid_argument);
}

TEST(OctomapBaseline, RejectsAnEdgeWhoseTreeOverflowsFloat) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}, {1, 2, 3}};
  CollapseParams params;
  params.edge_m = 1e300;  // one cube holds everything, but OctoMap's float coordinates cannot
  EXPECT_THROW(octomap_column_overhangs(PointsView<double>(points), params), std::invalid_argument);
  params.edge_m = 1e30;  // 65536 keys of 1e30 m still fit a float
  EXPECT_EQ(octomap_column_overhangs(PointsView<double>(points), params), std::vector<std::uint8_t>(2, 0));
}

TEST(OctomapBaseline, EmptyCloudGivesEmptyMask) {
  EXPECT_TRUE(octomap_column_overhangs(PointsView<double>(), CollapseParams{}).empty());
}

TEST(PointBasedBaseline, PointsAboveTheFirstGapOfSigmaEmptyStepsAreOverhang) {
  // One cell, E = 0.5, the lowest point z = 0 sets the steps: heights 0.0, 0.3, 1.7, 1.9, 4.0 are
  // steps 0, 1, 3, 4, 8. sigma = 2: 1 -> 3 leaves one empty step (no gap), 4 -> 8 three (a gap).
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0.3}, {0, 0, 1.7}, {0, 0, 0.0}, {0, 0, 4.0}, {0, 0, 1.9}};
  PointBasedParams params;
  params.edge_m = 0.5;
  params.sigma = 2;
  EXPECT_EQ(point_based_overhangs(PointsView<double>(points), params), (std::vector<std::uint8_t>{0, 0, 0, 1, 0}));
  params.sigma = 1;  // 1 -> 3 is now a gap: everything from 1.7 up
  EXPECT_EQ(point_based_overhangs(PointsView<double>(points), params), (std::vector<std::uint8_t>{0, 1, 0, 1, 1}));
  params.variance_threshold_m2 = 10.0;  // the cell's variance (about 2.0 m^2) is below: not searched
  EXPECT_EQ(point_based_overhangs(PointsView<double>(points), params), (std::vector<std::uint8_t>{0, 0, 0, 0, 0}));
}

TEST(PointBasedBaseline, WithoutTheVarianceTestEqualsCollapsibleCubesOnRandomScenes) {
  for (std::uint32_t seed = 1; seed <= 6; ++seed) {
    const auto points = test::random_scene(seed, 4000, 6.0 + seed);
    CollapseParams cubes;
    cubes.edge_m = 0.1 + 0.07 * seed;
    cubes.sigma = 1 + static_cast<int>(seed % 3);
    PointBasedParams params;
    params.edge_m = cubes.edge_m;
    params.sigma = cubes.sigma;
    params.variance_threshold_m2 = 0.0;
    const auto expected = collapse_overhangs(points, cubes).overhang;
    ASSERT_GT(std::count(expected.begin(), expected.end(), 1), 0);
    EXPECT_EQ(point_based_overhangs(PointsView<double>(points), params), expected) << "seed " << seed;
  }
}

TEST(PointBasedBaseline, TheVarianceTestOnlyEverKeepsPoints) {
  // Skipping low-variance cells can only miss overhangs, never add one.
  const auto points = test::random_scene(3, 4000, 6.0);
  PointBasedParams all, screened;
  all.variance_threshold_m2 = 0.0;
  screened.variance_threshold_m2 = 0.3;
  const auto a = point_based_overhangs(PointsView<double>(points), all);
  const auto b = point_based_overhangs(PointsView<double>(points), screened);
  std::size_t fewer = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    EXPECT_LE(b[i], a[i]) << "point " << i;
    fewer += a[i] > b[i] ? 1 : 0;
  }
  EXPECT_GT(fewer, 0U) << "a 0.3 m^2 threshold should skip some cells of this scene";
}

TEST(PointBasedBaseline, RejectsBadParameters) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}};
  PointBasedParams params;
  params.edge_m = 0.0;
  EXPECT_THROW(point_based_overhangs(PointsView<double>(points), params), std::invalid_argument);
  params.edge_m = 1.0;
  params.sigma = 0;
  EXPECT_THROW(point_based_overhangs(PointsView<double>(points), params), std::invalid_argument);
  params.sigma = 2;
  params.variance_threshold_m2 = -1.0;
  EXPECT_THROW(point_based_overhangs(PointsView<double>(points), params), std::invalid_argument);
  params.variance_threshold_m2 = std::nan("");
  EXPECT_THROW(point_based_overhangs(PointsView<double>(points), params), std::invalid_argument);
}

TEST(PointBasedBaseline, AgreementWithCollapsibleCubesOnKittiIsHigh) {
  const auto data = test::shared_data_dir();
  if (!data) GTEST_SKIP() << "../shared/data not found (set TERRACUBE_DATA_DIR)";
  const test::XyziScan scan = test::read_xyzi_bin(*data + "/kitti_seq00/velodyne/000000.bin");
  CollapseParams cubes;  // E = 0.5 m, sigma = 2
  const PointBasedParams points;
  const auto a = collapse_overhangs(scan.xyz(), cubes).overhang;
  const auto b = point_based_overhangs(scan.xyz(), points);
  std::size_t same = 0;
  for (std::size_t i = 0; i < a.size(); ++i) same += a[i] == b[i] ? 1 : 0;
  const double agreement = static_cast<double>(same) / static_cast<double>(a.size());
  RecordProperty("point_based_agreement", std::to_string(agreement));
  EXPECT_GT(agreement, 0.99);
}

}  // namespace
}  // namespace terracube
