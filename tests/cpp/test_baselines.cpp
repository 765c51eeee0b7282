#include <gtest/gtest.h>
#include <terracube/baselines.hpp>
#include <terracube/collapse.hpp>

#include <algorithm>
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

TEST(OctomapBaseline, EmptyCloudGivesEmptyMask) {
  EXPECT_TRUE(octomap_column_overhangs(PointsView<double>(), CollapseParams{}).empty());
}

TEST(PointGapBaseline, PointsAboveTheFirstLargeGapAreOverhang) {
  // One cell: ground 0.0-0.3, a gap of 1.2 m, canopy 1.5-1.7, another gap, 4.0.
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0.3}, {0, 0, 1.5}, {0, 0, 0.0}, {0, 0, 4.0}, {0, 0, 1.7}};
  PointGapParams params;
  params.cell_m = 1.0;
  params.min_gap_m = 1.0;
  EXPECT_EQ(point_gap_overhangs(PointsView<double>(points), params), (std::vector<std::uint8_t>{0, 1, 0, 1, 1}));
  params.min_gap_m = 1.2;  // strictly larger: the 1.2 m gap no longer counts, the 2.3 m one does
  EXPECT_EQ(point_gap_overhangs(PointsView<double>(points), params), (std::vector<std::uint8_t>{0, 0, 0, 1, 0}));
}

TEST(PointGapBaseline, MatchesAPerCellMapReference) {
  const auto points = test::random_scene(3, 4000, 6.0);
  PointGapParams params;
  params.cell_m = 0.4;
  params.min_gap_m = 0.8;
  const auto mask = point_gap_overhangs(PointsView<double>(points), params);
  // Reference: a std::map from (ix, iy) to the sorted heights in the cell.
  double xmin = 1e300, ymin = 1e300;
  for (const auto& p : points) {
    xmin = std::min(xmin, p.x());
    ymin = std::min(ymin, p.y());
  }
  const auto cell_of = [&](const Eigen::Vector3d& p) {
    return std::make_pair(static_cast<long>(std::floor((p.x() - xmin) * (1.0 / 0.4) + 0.5)),
                          static_cast<long>(std::floor((p.y() - ymin) * (1.0 / 0.4) + 0.5)));
  };
  std::map<std::pair<long, long>, std::vector<double>> cells;
  for (const auto& p : points) cells[cell_of(p)].push_back(p.z());
  std::map<std::pair<long, long>, double> threshold;  // lowest overhang height per cell
  for (auto& [cell, heights] : cells) {
    std::sort(heights.begin(), heights.end());
    threshold[cell] = 1e300;
    for (std::size_t i = 1; i < heights.size(); ++i) {
      if (heights[i] - heights[i - 1] > 0.8) {
        threshold[cell] = heights[i];
        break;
      }
    }
  }
  std::size_t overhangs = 0;
  for (std::size_t i = 0; i < points.size(); ++i) {
    const bool expected = points[i].z() >= threshold[cell_of(points[i])];
    EXPECT_EQ(mask[i] == 1, expected) << "point " << i;
    overhangs += expected ? 1 : 0;
  }
  EXPECT_GT(overhangs, 100U);
}

TEST(PointGapBaseline, RejectsBadParameters) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}};
  PointGapParams params;
  params.cell_m = 0.0;
  EXPECT_THROW(point_gap_overhangs(PointsView<double>(points), params), std::invalid_argument);
  params.cell_m = 1.0;
  params.min_gap_m = -1.0;
  EXPECT_THROW(point_gap_overhangs(PointsView<double>(points), params), std::invalid_argument);
}

TEST(PointGapBaseline, AgreementWithCollapsibleCubesOnKittiIsHigh) {
  const auto data = test::shared_data_dir();
  if (!data) GTEST_SKIP() << "../shared/data not found (set TERRACUBE_DATA_DIR)";
  const test::XyziScan scan = test::read_xyzi_bin(*data + "/kitti_seq00/velodyne/000000.bin");
  CollapseParams cubes;
  cubes.edge_m = 0.5;
  cubes.sigma = 2;
  PointGapParams gaps;
  gaps.cell_m = 0.5;
  gaps.min_gap_m = 1.0;  // σ E: the same clearance in metres
  const auto a = collapse_overhangs(scan.xyz(), cubes).overhang;
  const auto b = point_gap_overhangs(scan.xyz(), gaps);
  std::size_t same = 0;
  for (std::size_t i = 0; i < a.size(); ++i) same += a[i] == b[i] ? 1 : 0;
  const double agreement = static_cast<double>(same) / static_cast<double>(a.size());
  RecordProperty("point_gap_agreement", std::to_string(agreement));
  EXPECT_GT(agreement, 0.97);
}

}  // namespace
}  // namespace terracube
