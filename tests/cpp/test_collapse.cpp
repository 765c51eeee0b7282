#include <gtest/gtest.h>
#include <terracube/collapse.hpp>
#include <terracube/elevation_map.hpp>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <functional>
#include <limits>
#include <random>
#include <set>
#include <thread>

#include "test_support.hpp"

namespace terracube {
namespace {

// [CBC] Algorithm 1 written out loop by loop, as the paper states it: V as a
// std::vector<bool>, the unsorted list L, std::sort, M holding the ground cube's index I.
struct NaiveResult {
  std::vector<std::uint8_t> overhang;
  std::vector<std::int64_t> occupied;
  std::vector<std::int64_t> removed;
};

NaiveResult naive_algorithm1(const std::vector<Eigen::Vector3d>& points, double edge, int sigma) {
  NaiveResult out;
  out.overhang.assign(points.size(), 0);
  if (points.empty()) return out;
  double min[3] = {1e300, 1e300, 1e300};
  double max[3] = {-1e300, -1e300, -1e300};
  for (const auto& p : points) {
    for (int a = 0; a < 3; ++a) {
      min[a] = std::min(min[a], p[a]);
      max[a] = std::max(max[a], p[a]);
    }
  }
  const double inv = 1.0 / edge;
  const auto round_half_up = [&](double v, int a) {
    return static_cast<std::int64_t>(std::floor((v - min[a]) * inv + 0.5));
  };
  const std::int64_t ixmax = round_half_up(max[0], 0) + 1;
  const std::int64_t iymax = round_half_up(max[1], 1) + 1;
  const std::int64_t izmax = round_half_up(max[2], 2) + 1;
  std::vector<bool> V(static_cast<std::size_t>(ixmax * iymax * izmax), false);
  std::vector<std::int64_t> L;
  std::vector<std::int64_t> index_of_point(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) {
    const std::int64_t I = round_half_up(points[i].x(), 0) + round_half_up(points[i].y(), 1) * ixmax +
                           round_half_up(points[i].z(), 2) * ixmax * iymax;
    index_of_point[i] = I;
    if (!V[static_cast<std::size_t>(I)]) {
      V[static_cast<std::size_t>(I)] = true;
      L.push_back(I);
    }
  }
  std::sort(L.begin(), L.end());
  const std::int64_t columns = ixmax * iymax;
  std::vector<std::int64_t> M(static_cast<std::size_t>(columns), -1);
  std::set<std::int64_t> R;
  for (const std::int64_t I : L) {
    auto& ground = M[static_cast<std::size_t>(I % columns)];
    if (ground == -1) {
      ground = I;
    } else {
      const std::int64_t empty_cubes = (I - ground) / columns - 1;
      if (empty_cubes < sigma) {
        ground = I;
      } else {
        R.insert(I);
      }
    }
  }
  for (std::size_t i = 0; i < points.size(); ++i) out.overhang[i] = R.count(index_of_point[i]) ? 1 : 0;
  out.occupied = L;
  out.removed.assign(R.begin(), R.end());
  return out;
}

void expect_same_as_naive(const std::vector<Eigen::Vector3d>& points, double edge, int sigma) {
  const NaiveResult expected = naive_algorithm1(points, edge, sigma);
  for (const CubeStorage storage : {CubeStorage::kDense, CubeStorage::kSparse, CubeStorage::kAuto}) {
    CollapseParams params;
    params.edge_m = edge;
    params.sigma = sigma;
    params.storage = storage;
    const CollapseResult result = collapse_overhangs(points, params);
    ASSERT_EQ(result.overhang, expected.overhang) << "storage " << static_cast<int>(storage);
    ASSERT_EQ(result.occupied_cubes, expected.occupied);
    ASSERT_EQ(result.removed_cubes, expected.removed);
    ASSERT_EQ(result.num_overhang,
              static_cast<std::size_t>(std::count(expected.overhang.begin(), expected.overhang.end(), 1)));
  }
}

// --- hand-made columns ------------------------------------------------------------------------

/// One column at x = y = 0 with a point at the centre of each listed layer (E = 1, z = layer).
std::vector<Eigen::Vector3d> column(const std::vector<int>& layers) {
  std::vector<Eigen::Vector3d> points;
  for (const int layer : layers) points.emplace_back(0.0, 0.0, static_cast<double>(layer));
  return points;
}

std::vector<std::uint8_t> collapse_mask(const std::vector<Eigen::Vector3d>& points, int sigma,
                                        CubeStorage storage = CubeStorage::kAuto) {
  CollapseParams params;
  params.edge_m = 1.0;
  params.sigma = sigma;
  params.storage = storage;
  return collapse_overhangs(points, params).overhang;
}

TEST(CollapseColumns, GapOfSigmaMinusOneEmptyCubesKeepsTheCubeAsGround) {
  // σ = 3: layers 0 and 3 are separated by 2 = σ - 1 empty cubes.
  EXPECT_EQ(collapse_mask(column({0, 3}), 3), (std::vector<std::uint8_t>{0, 0}));
}

TEST(CollapseColumns, GapOfExactlySigmaEmptyCubesCollapses) {
  EXPECT_EQ(collapse_mask(column({0, 4}), 3), (std::vector<std::uint8_t>{0, 1}));
}

TEST(CollapseColumns, GapOfSigmaPlusOneEmptyCubesCollapses) {
  EXPECT_EQ(collapse_mask(column({0, 5}), 3), (std::vector<std::uint8_t>{0, 1}));
}

TEST(CollapseColumns, SigmaOneCollapsesAnySingleEmptyCube) {
  EXPECT_EQ(collapse_mask(column({0, 1, 3}), 1), (std::vector<std::uint8_t>{0, 0, 1}));
}

TEST(CollapseColumns, GroundClimbsThroughSmallGapsLikeAStaircase) {
  // Each step leaves 1 empty cube (< σ = 2): every cube becomes the ground in turn.
  EXPECT_EQ(collapse_mask(column({0, 2, 4, 6, 8}), 2), (std::vector<std::uint8_t>{0, 0, 0, 0, 0}));
}

TEST(CollapseColumns, SeveralOverhangLayersAreMeasuredFromTheGroundNotFromEachOther) {
  // Ground 0-1, a bridge deck at 5-6, a canopy at 8 and a wire at 12: all collapse, because the
  // collapsed cubes count as empty: the gaps are measured from the ground at layer 1.
  EXPECT_EQ(collapse_mask(column({0, 1, 5, 6, 8, 12}), 2), (std::vector<std::uint8_t>{0, 0, 1, 1, 1, 1}));
}

TEST(CollapseColumns, WallsAndTrunksStay) {
  std::vector<int> trunk;
  for (int layer = 0; layer < 20; ++layer) trunk.push_back(layer);
  EXPECT_EQ(collapse_mask(column(trunk), 2), std::vector<std::uint8_t>(20, 0));
}

TEST(CollapseColumns, SingleCubeColumnsAreGround) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}, {1, 0, 7}, {2, 3, 4}, {5, 5, 5}};
  EXPECT_EQ(collapse_mask(points, 1), std::vector<std::uint8_t>(4, 0));
}

TEST(CollapseColumns, ColumnsAreIndependent) {
  // A column whose lowest cube is high up keeps it as ground even when its neighbour has ground
  // at layer 0: the paper's rule looks at one column at a time.
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}, {0, 0, 5}, {1, 0, 5}, {1, 0, 9}};
  EXPECT_EQ(collapse_mask(points, 2), (std::vector<std::uint8_t>{0, 1, 0, 1}));
}

TEST(CollapseColumns, ExactRemovedCubeIndices) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}, {0, 0, 5}, {1, 1, 0}, {1, 1, 1}, {1, 1, 4}};
  CollapseParams params;
  params.edge_m = 1.0;
  params.sigma = 2;
  const CollapseResult result = collapse_overhangs(points, params);
  ASSERT_EQ(result.grid.ixmax, 2);
  ASSERT_EQ(result.grid.iymax, 2);
  ASSERT_EQ(result.grid.izmax, 6);
  EXPECT_EQ(result.occupied_cubes, (std::vector<std::int64_t>{0, 3, 7, 19, 20}));
  EXPECT_EQ(result.removed_cubes, (std::vector<std::int64_t>{19, 20}));
  EXPECT_EQ(result.overhang, (std::vector<std::uint8_t>{0, 1, 0, 0, 1}));
}

TEST(CollapseColumns, MultiplePointsInOneCubeShareItsFate) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}, {0.1, 0.1, 4.1}, {-0.1, 0.2, 3.8}, {0.2, -0.1, 0.2}};
  EXPECT_EQ(collapse_mask(points, 2), (std::vector<std::uint8_t>{0, 1, 1, 0}));
}

// --- against the naive Algorithm 1 -------------------------------------------------------------

TEST(CollapseVsNaive, RandomScenesAreIdenticalForEveryStorage) {
  for (std::uint32_t seed = 1; seed <= 12; ++seed) {
    const auto points = test::random_scene(seed, 3000 + 500 * seed, 5.0 + seed);
    const double edge = 0.1 + 0.05 * (seed % 7);
    const int sigma = 1 + static_cast<int>(seed % 4);
    SCOPED_TRACE("seed " + std::to_string(seed));
    expect_same_as_naive(points, edge, sigma);
  }
}

TEST(CollapseVsNaive, ConsecutiveCallsOnGridsOfEverySizeShareNoState) {
  // The dense path keeps V, its summary and M per thread and restores them after each call:
  // alternate sparse-looking grids (V has more words than the cloud has rows: the summary path),
  // small grids holding many points (every word of V read) and an empty-looking tall grid, each
  // checked against the naive Algorithm 1.
  for (std::uint32_t round = 0; round < 6; ++round) {
    SCOPED_TRACE("round " + std::to_string(round));
    auto spread = test::random_scene(100 + round, 400, 40.0);  // ~160^3 cubes at 0.25 m: 64k words
    expect_same_as_naive(spread, 0.25, 1 + static_cast<int>(round % 3));
    expect_same_as_naive(test::random_scene(200 + round, 5000, 3.0), 0.5, 2);  // few cubes, many points
    spread.push_back({0.0, 0.0, 500.0});                                       // a tall, almost empty grid
    expect_same_as_naive(spread, 0.5, 2);
  }
}

TEST(CollapseVsNaive, LargeGridsWithManyPointsPerCubeMatchTheNaiveAlgorithm) {
  // Over 2^16 cubes (V stays a bit vector) with at least half as many points (52 x 52 m by about
  // 21 m at 0.5 m: some 470,000 cubes for 240,000 points); small grids of this density keep V as
  // bytes and are checked in ConsecutiveCallsOnGridsOfEverySizeShareNoState and the leveled tests.
  const auto points = test::random_scene(404, 240000, 52.0);
  expect_same_as_naive(points, 0.5, 2);
  // With rows that take no part (a crop of the highest outliers): their cube is the byte past the
  // last cube.
  CollapseParams params;
  params.edge_m = 0.5;
  params.sigma = 3;
  params.crop = CropBox{{-1.0, -1.0, -1.5}, {53.0, 53.0, 12.0}};
  std::vector<Eigen::Vector3d> inside;
  std::vector<std::size_t> rows_inside;
  for (std::size_t row = 0; row < points.size(); ++row) {
    if ((points[row].array() >= params.crop->min.array()).all() &&
        (points[row].array() <= params.crop->max.array()).all()) {
      inside.push_back(points[row]);
      rows_inside.push_back(row);
    }
  }
  ASSERT_GT(points.size() - inside.size(), 1000U) << "the box must cut the scene";
  const NaiveResult expected = naive_algorithm1(inside, 0.5, 3);
  ASSERT_GT(expected.occupied.back() + 1, std::int64_t{1} << 16) << "the grid must exceed 2^16 cubes";
  const CollapseResult result = collapse_overhangs(points, params);
  std::vector<std::uint8_t> mask(points.size(), 0);
  for (std::size_t k = 0; k < inside.size(); ++k) mask[rows_inside[k]] = expected.overhang[k];
  EXPECT_EQ(result.overhang, mask);
  EXPECT_EQ(result.occupied_cubes, expected.occupied);
  EXPECT_EQ(result.removed_cubes, expected.removed);
}

TEST(CollapseVsNaive, TinyAndDegenerateClouds) {
  expect_same_as_naive({{1, 2, 3}}, 0.5, 2);
  expect_same_as_naive({{1, 2, 3}, {1, 2, 3}, {1, 2, 3}}, 0.5, 2);                   // duplicates
  expect_same_as_naive({{0, 0, 0}, {0, 0, 10}}, 0.5, 2);                             // one column
  expect_same_as_naive({{0, 0, 0}, {10, 0, 0}, {20, 0, 0}}, 0.5, 2);                 // one layer
  expect_same_as_naive({{-5, -5, -5}, {-5, -5, 5}, {5, 5, -5}, {5, 5, 5}}, 1.0, 1);  // negatives
}

TEST(CollapseVsNaive, RealKittiAndOusterScans) {
  const auto data = test::shared_data_dir();
  if (!data) GTEST_SKIP() << "../shared/data not found (set TERRACUBE_DATA_DIR)";
  for (const std::string file : {"/kitti_seq00/velodyne/000000.bin", "/ouster128/ouster128_000000_xyzi_valid.bin"}) {
    SCOPED_TRACE(file);
    const test::XyziScan scan = test::read_xyzi_bin(*data + file);
    const auto points = scan.as_vectors();
    expect_same_as_naive(points, 0.5, 2);
    expect_same_as_naive(points, 0.2, 4);
    // The float32 strided view of the same values gives the same answer as the doubles.
    CollapseParams params;
    params.edge_m = 0.2;
    params.sigma = 4;
    EXPECT_EQ(collapse_overhangs(scan.xyz(), params).overhang, collapse_overhangs(points, params).overhang);
  }
}

// --- leveling and cropping --------------------------------------------------------------------

TEST(CollapsePreprocessing, LevelingATiltedScanRecoversTheLevelResult) {
  // A level scene on cube-centre positions, then seen by a sensor pitched 20 degrees.
  std::vector<Eigen::Vector3d> level;
  for (int i = 0; i < 30; ++i) {
    for (int j = 0; j < 10; ++j) {
      level.emplace_back(0.5 * i, 0.5 * j, 0.0);                        // ground
      if (i > 10 && i < 20) level.emplace_back(0.5 * i, 0.5 * j, 3.0);  // a bridge deck
    }
  }
  const Eigen::Matrix4d leveling = leveling_transform(0.05, 0.35);
  std::vector<Eigen::Vector3d> tilted;
  for (const auto& p : level) tilted.push_back(leveling.topLeftCorner<3, 3>().transpose() * p);
  CollapseParams params;
  params.edge_m = 0.5;
  params.sigma = 2;
  const CollapseResult reference = collapse_overhangs(level, params);
  EXPECT_EQ(reference.num_overhang, 90U);
  params.transform = leveling;
  const CollapseResult leveled = collapse_overhangs(tilted, params);
  EXPECT_EQ(leveled.overhang, reference.overhang);
  params.transform = Eigen::Matrix4d::Identity();
  EXPECT_NE(collapse_overhangs(tilted, params).overhang, reference.overhang);
}

TEST(CollapsePreprocessing, CropBoxExcludesPointsAndTheyAreNeverOverhang) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}, {0, 0, 5}, {50, 0, 0}, {50, 0, 5}};
  CollapseParams params;
  params.edge_m = 1.0;
  params.crop = CropBox{{-1, -1, -1}, {10, 10, 10}};
  const CollapseResult result = collapse_overhangs(points, params);
  EXPECT_EQ(result.overhang, (std::vector<std::uint8_t>{0, 1, 0, 0}));
  EXPECT_EQ(result.num_cropped, 2U);
  EXPECT_EQ(result.num_used, 2U);
  EXPECT_EQ(result.grid.ixmax, 1);  // the grid covers only the cropped cloud

  // The same with a cube far up the crop box: 1,000 cubes for 5 points (V's bits, not a byte per
  // cube, decide the mask; the tiny grid above took the byte map).
  const std::vector<Eigen::Vector3d> spread = {{0, 0, 0}, {0, 0, 5}, {50, 0, 0}, {50, 0, 5}, {9, 9, 9}};
  const CollapseResult spread_result = collapse_overhangs(spread, params);
  EXPECT_EQ(spread_result.grid.num_cubes(), 1000);
  EXPECT_EQ(spread_result.overhang, (std::vector<std::uint8_t>{0, 1, 0, 0, 0}));
  EXPECT_EQ(spread_result.num_cropped, 2U);
}

/// The rows of `points` that are finite and, leveled by `transform` (R p + t, computed here point
/// by point), inside `crop`: the leveled points and their input rows.
struct LeveledByHand {
  std::vector<Eigen::Vector3d> points;
  std::vector<std::size_t> rows;
};
LeveledByHand level_by_hand(const std::vector<Eigen::Vector3d>& points, const Eigen::Matrix4d& transform,
                            const CropBox& crop) {
  LeveledByHand out;
  for (std::size_t row = 0; row < points.size(); ++row) {
    if (!points[row].allFinite()) continue;
    const Eigen::Vector3d p = transform.topLeftCorner<3, 3>() * points[row] + transform.topRightCorner<3, 1>();
    if ((p.array() < crop.min.array()).any() || (p.array() > crop.max.array()).any()) continue;
    out.points.push_back(p);
    out.rows.push_back(row);
  }
  return out;
}

/// Collapse parameters (σ = 2) that level by `transform`, crop to `crop` and drop NaN/Inf rows.
CollapseParams leveling_params(double edge_m, const Eigen::Matrix4d& transform, const CropBox& crop) {
  CollapseParams params;
  params.edge_m = edge_m;
  params.sigma = 2;
  params.transform = transform;
  params.crop = crop;
  params.drop_non_finite = true;
  return params;
}

/// The naive Algorithm 1's mask of the leveled rows, scattered back to all `num_rows` rows.
std::vector<std::uint8_t> scattered(const LeveledByHand& leveled, const NaiveResult& naive, std::size_t num_rows) {
  std::vector<std::uint8_t> mask(num_rows, 0);
  for (std::size_t k = 0; k < leveled.rows.size(); ++k) mask[leveled.rows[k]] = naive.overhang[k];
  return mask;
}

TEST(CollapsePreprocessing, LeveledCroppedCloudsWithDroppedRowsMatchTheNaiveAlgorithmOnTheLeveledPoints) {
  // The transform and the crop, applied here point by point (R p + t in doubles, as documented),
  // then the naive Algorithm 1 on the points inside the box: every storage, float and double
  // views, NaN/Inf rows dropped. Their mask, scattered back to the input rows, is the answer.
  for (std::uint32_t seed = 301; seed <= 306; ++seed) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    auto points = test::random_scene(seed, 4000, 6.0 + seed % 4);
    points[17] = Eigen::Vector3d(std::numeric_limits<double>::quiet_NaN(), 0.0, 0.0);
    points[500] = Eigen::Vector3d(0.0, std::numeric_limits<double>::infinity(), 0.0);
    Eigen::Matrix4d transform = leveling_transform(0.01 * (seed % 5), -0.02 * (seed % 3));
    transform.topRightCorner<3, 1>() = Eigen::Vector3d(0.3 * seed, -1.25, 0.5);
    const CropBox crop{{-2.0 + 0.3 * seed, -4.0, -1.0}, {0.3 * seed + 5.0, 3.0, 4.0}};
    const LeveledByHand leveled = level_by_hand(points, transform, crop);
    const std::vector<Eigen::Vector3d>& inside = leveled.points;
    const std::size_t cropped = points.size() - 2 - inside.size();  // two rows are NaN/Inf
    ASSERT_GT(cropped, 100U) << "the box must cut the scene";
    const NaiveResult naive = naive_algorithm1(inside, 0.5, 2);
    const std::vector<std::uint8_t> expected = scattered(leveled, naive, points.size());
    ASSERT_GT(std::count(expected.begin(), expected.end(), 1), 0) << "the scene must keep overhangs";
    const std::vector<float> floats = [&] {
      std::vector<float> packed;
      for (const auto& p : points) packed.insert(packed.end(), {float(p.x()), float(p.y()), float(p.z())});
      return packed;
    }();
    for (const CubeStorage storage : {CubeStorage::kDense, CubeStorage::kSparse}) {
      CollapseParams params = leveling_params(0.5, transform, crop);
      params.storage = storage;
      const CollapseResult result = collapse_overhangs(points, params);
      EXPECT_EQ(result.overhang, expected);
      EXPECT_EQ(result.occupied_cubes, naive.occupied);
      EXPECT_EQ(result.removed_cubes, naive.removed);
      EXPECT_EQ(result.num_points, points.size());
      EXPECT_EQ(result.num_used, inside.size());
      EXPECT_EQ(result.num_cropped, cropped);
      EXPECT_EQ(result.num_dropped_non_finite, 2U);
      EXPECT_EQ(result.num_overhang, static_cast<std::size_t>(std::count(expected.begin(), expected.end(), 1)));
      EXPECT_EQ(result.storage_used, storage);
      // float rows: the naive reference on the float coordinates gives the same masks.
      const CollapseResult from_floats = collapse_overhangs(PointsView<float>(floats.data(), points.size()), params);
      std::vector<Eigen::Vector3d> rounded(points.size());
      for (std::size_t row = 0; row < points.size(); ++row) rounded[row] = test::rounded_to<float>(points[row]);
      const LeveledByHand float_leveled = level_by_hand(rounded, transform, crop);
      const NaiveResult float_naive = naive_algorithm1(float_leveled.points, 0.5, 2);
      EXPECT_EQ(from_floats.overhang, scattered(float_leveled, float_naive, points.size()));
      EXPECT_EQ(from_floats.removed_cubes, float_naive.removed);
    }
    // Without dropping, the NaN/Inf rows are named, whatever the transform and crop.
    CollapseParams strict;
    strict.transform = transform;
    strict.crop = crop;
    try {
      collapse_overhangs(points, strict);
      ADD_FAILURE() << "expected std::invalid_argument";
    } catch (const std::invalid_argument& error) {
      EXPECT_NE(std::string(error.what()).find("2 of 4000 point rows contain NaN or Inf (first at row 17)"),
                std::string::npos)
          << error.what();
    }
  }
}

TEST(CollapsePreprocessing, LeveledCloudsThroughEveryViewLayoutAndLengthMatchTheNaiveAlgorithm) {
  // Leveled rows read through any strides (packed, x y z i, column-major, reversed rows) and
  // clouds of every small length.
  Eigen::Matrix4d transform = leveling_transform(0.04, -0.03);
  transform.topRightCorner<3, 1>() = Eigen::Vector3d(0.5, -0.25, 1.0);
  const CropBox crop{{-3.0, -3.0, -1.0}, {3.0, 2.5, 6.0}};
  for (const std::size_t n : {1U, 2U, 3U, 4U, 5U, 7U, 9U, 2003U}) {
    SCOPED_TRACE("n " + std::to_string(n));
    auto points = test::random_scene(400 + static_cast<std::uint32_t>(n), n, 4.0);
    points = std::vector<Eigen::Vector3d>(points.begin(), points.begin() + static_cast<std::ptrdiff_t>(n));
    if (n > 5) points[5] = Eigen::Vector3d(1.0, std::numeric_limits<double>::quiet_NaN(), 0.0);
    for (auto& p : points) p = test::rounded_to<float>(p);  // exact in float rows too
    // Expected: the naive Algorithm 1 on the rows leveled and cropped here.
    const LeveledByHand leveled = level_by_hand(points, transform, crop);
    const std::vector<Eigen::Vector3d>& inside = leveled.points;
    const NaiveResult naive = naive_algorithm1(inside, 0.25, 2);
    if (n > 1000) {
      ASSERT_GT(naive.removed.size(), 0U) << "the scene must keep overhangs";
    }
    const std::vector<std::uint8_t> expected = scattered(leveled, naive, n);
    const CollapseParams params = leveling_params(0.25, transform, crop);
    const auto check = [&](const auto& view, const std::vector<std::uint8_t>& mask, const char* what) {
      const CollapseResult result = collapse_overhangs(view, params);
      EXPECT_EQ(result.overhang, mask) << what;
      EXPECT_EQ(result.removed_cubes, naive.removed) << what;
      EXPECT_EQ(result.num_used, inside.size()) << what;
      EXPECT_EQ(result.num_dropped_non_finite, n > 5 ? 1U : 0U) << what;
    };
    std::vector<double> packed, xyzi, columns(3 * n);
    std::vector<float> packed_float, xyzi_float;
    for (std::size_t row = 0; row < n; ++row) {
      for (int a = 0; a < 3; ++a) {
        packed.push_back(points[row][a]);
        xyzi.push_back(points[row][a]);
        packed_float.push_back(static_cast<float>(points[row][a]));
        xyzi_float.push_back(static_cast<float>(points[row][a]));
        columns[static_cast<std::size_t>(a) * n + row] = points[row][a];
      }
      xyzi.push_back(7.0);
      xyzi_float.push_back(7.0F);
    }
    check(PointsView<double>(packed.data(), n), expected, "double x y z");
    check(PointsView<double>(xyzi.data(), n, 4, 1), expected, "double x y z i");
    check(PointsView<float>(packed_float.data(), n), expected, "float x y z");
    check(PointsView<float>(xyzi_float.data(), n, 4, 1), expected, "float x y z i");
    check(PointsView<double>(columns.data(), n, 1, static_cast<std::ptrdiff_t>(n)), expected, "column-major");
    // Rows reversed: a negative row stride from the last row; the mask comes out reversed.
    const std::vector<std::uint8_t> reversed(expected.rbegin(), expected.rend());
    check(PointsView<double>(packed.data() + 3 * (n - 1), n, -3, 1), reversed, "reversed rows");
  }
}

/// Rows of `stride` scalars (x y z, then extra columns holding NaN): `points` written out.
template <typename Scalar>
std::vector<Scalar> rows_with_extra_columns(const std::vector<Eigen::Vector3d>& points, int stride) {
  std::vector<Scalar> rows(points.size() * static_cast<std::size_t>(stride), std::numeric_limits<Scalar>::quiet_NaN());
  for (std::size_t r = 0; r < points.size(); ++r) {
    for (int a = 0; a < 3; ++a) rows[r * static_cast<std::size_t>(stride) + a] = static_cast<Scalar>(points[r][a]);
  }
  return rows;
}

template <typename Scalar>
void check_leveled_non_finite_rows() {
  // NaN/Inf rows at every position of small clouds, several next to each other, extra columns of
  // NaN that are no coordinates, rows of 3, 4 and 6 scalars. Dropped, the rest must match the
  // naive Algorithm 1 on the rows leveled by hand; kept, the error must count them and name the
  // first.
  Eigen::Matrix4d transform = leveling_transform(0.05, 0.02);
  transform.topRightCorner<3, 1>() = Eigen::Vector3d(-0.5, 0.75, 1.5);
  const CropBox crop{{-3.5, -3.0, -1.0}, {3.0, 3.5, 6.5}};
  const Scalar bad_values[] = {std::numeric_limits<Scalar>::quiet_NaN(), std::numeric_limits<Scalar>::infinity(),
                               -std::numeric_limits<Scalar>::infinity()};
  for (const int stride : {3, 4, 6}) {
    for (const std::size_t n : {1U, 2U, 3U, 4U, 5U, 6U, 7U, 8U, 9U, 12U, 13U, 37U}) {
      auto points = test::random_scene(700 + static_cast<std::uint32_t>(n), n, 4.0);
      points.resize(n);
      for (auto& p : points) p = test::rounded_to<Scalar>(p);  // exact in the rows
      // Bad rows: spread over the cloud, two close together when it has room.
      std::vector<std::size_t> bad_rows;
      for (std::size_t row = n / 3; row < n; row += 5) bad_rows.push_back(row);
      if (n >= 8) bad_rows.push_back(4 + (n % 4 == 0 ? 3 : 2));
      std::sort(bad_rows.begin(), bad_rows.end());
      bad_rows.erase(std::unique(bad_rows.begin(), bad_rows.end()), bad_rows.end());
      std::vector<Scalar> rows = rows_with_extra_columns<Scalar>(points, stride);
      for (std::size_t k = 0; k < bad_rows.size(); ++k) {
        const std::size_t row = bad_rows[k];
        rows[row * static_cast<std::size_t>(stride) + k % 3] = bad_values[k % 3];
        points[row][static_cast<int>(k % 3)] = std::numeric_limits<double>::quiet_NaN();
      }
      const std::string where = std::string(sizeof(Scalar) == 4 ? "float" : "double") + " stride " +
                                std::to_string(stride) + " n " + std::to_string(n);
      const PointsView<Scalar> view(rows.data(), n, stride);
      const LeveledByHand leveled = level_by_hand(points, transform, crop);
      const NaiveResult naive = naive_algorithm1(leveled.points, 0.25, 2);
      const CollapseResult result = collapse_overhangs(view, leveling_params(0.25, transform, crop));
      EXPECT_EQ(result.overhang, scattered(leveled, naive, n)) << where;
      EXPECT_EQ(result.occupied_cubes, naive.occupied) << where;
      EXPECT_EQ(result.num_used, leveled.points.size()) << where;
      EXPECT_EQ(result.num_dropped_non_finite, bad_rows.size()) << where;
      EXPECT_EQ(result.num_cropped, n - bad_rows.size() - leveled.points.size()) << where;
      // The min corner to the last bit: the documented q_i = ((r_i0 x + r_i1 y) + r_i2 z) + t_i.
      for (int a = 0; a < 3 && !leveled.rows.empty(); ++a) {
        double lo = std::numeric_limits<double>::infinity();
        for (const std::size_t row : leveled.rows) {
          const Eigen::Vector3d& p = points[row];
          lo = std::min(
              lo, ((transform(a, 0) * p.x() + transform(a, 1) * p.y()) + transform(a, 2) * p.z()) + transform(a, 3));
        }
        EXPECT_EQ(result.grid.min_corner[a], lo) << where << " axis " << a;
      }
      if (bad_rows.empty()) continue;
      CollapseParams strict = leveling_params(0.25, transform, crop);
      strict.drop_non_finite = false;
      try {
        collapse_overhangs(view, strict);
        ADD_FAILURE() << "expected std::invalid_argument, " << where;
      } catch (const std::invalid_argument& error) {
        const std::string expected = std::to_string(bad_rows.size()) + " of " + std::to_string(n) +
                                     " point rows contain NaN or Inf (first at row " + std::to_string(bad_rows[0]) +
                                     ")";
        EXPECT_NE(std::string(error.what()).find(expected), std::string::npos) << error.what() << ", " << where;
      }
    }
  }
}

TEST(CollapsePreprocessing, LeveledNonFiniteRowsAnywhereAndExtraColumnsAreHandledAsTheNaiveAlgorithm) {
  check_leveled_non_finite_rows<float>();
  check_leveled_non_finite_rows<double>();
}

// --- storage ----------------------------------------------------------------------------------

TEST(CollapseVsNaive, FloatRowsAreQuantisedByTheDoubleFormulaForEdgesCornersAndExtentsOfEveryScale) {
  // Plain float rows are quantised eight at a time in float arithmetic where the float estimate's
  // error bound allows (a margin of 2^-12 to 2^-7 cubes), else in doubles; rows whose estimate
  // lies within the margin of a cube border take the double formula. Either way every cube index
  // must be [CBC] eqs. (4)-(6)'s in doubles: random rows, and rows on and up to 16 float ulps either
  // side of cube borders, for grids whose margin ranges over the whole span and past it (a corner
  // 3e5 m away, the 20,000-cube axis), on rows of 3 and 4 scalars and lengths that end inside and
  // after an 8-row block.
  struct Case {
    double edge;
    Eigen::Vector3d corner;
    Eigen::Vector3i cubes;
  };
  const std::vector<Case> cases = {
      {0.5, {-80.0, -60.0, -3.0}, {320, 240, 20}},      {0.07, {123.456, -987.65, 0.7}, {300, 150, 40}},
      {0.35, {5000.3, -4000.1, 100.2}, {200, 100, 40}}, {0.045, {-1.3, 2.9, -0.4}, {2000, 10, 30}},
      {0.013, {0.01, -0.03, 0.0}, {8000, 4, 4}},        {0.1, {300000.3, -200000.7, 10.2}, {50, 50, 20}},
      {0.003, {-0.7, 0.4, 0.0}, {20000, 2, 2}},         {3.0, {-1234.5, 987.6, -50.0}, {64, 64, 10}},
  };
  std::mt19937 random(2026);
  int float_differs = 0;  // border rows that float arithmetic alone would put in another cube
  for (const Case& c : cases) {
    SCOPED_TRACE("edge " + std::to_string(c.edge) + ", corner " + std::to_string(c.corner.x()) + ", " +
                 std::to_string(c.corner.y()) + ", " + std::to_string(c.corner.z()));
    const Eigen::Vector3d low = test::rounded_to<float>(c.corner);
    const Eigen::Vector3d high =
        test::rounded_to<float>(Eigen::Vector3d(low + c.edge * (c.cubes.cast<double>() - Eigen::Vector3d::Ones())));
    std::vector<Eigen::Vector3d> points = {low, high};
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    for (int k = 0; k < 1500; ++k) {
      Eigen::Vector3d p;
      for (int a = 0; a < 3; ++a) p[a] = low[a] + unit(random) * (high[a] - low[a]);
      points.push_back(test::rounded_to<float>(p));
    }
    for (int axis = 0; axis < 3; ++axis) {
      std::uniform_int_distribution<int> border_index(0, c.cubes[axis] - 2);
      const double inverse = 1.0 / c.edge;
      for (int k = 0; k < 660; ++k) {
        // The border between cubes b and b + 1 lies where (x - xmin) / E + 0.5 = b + 1.
        auto x = static_cast<float>(low[axis] + (border_index(random) + 0.5) * c.edge);
        const int ulps = k % 33 - 16;  // -16 .. 16 float ulps from the border
        for (int step = 0; step < std::abs(ulps); ++step) x = std::nextafter(x, ulps > 0 ? 1e30F : -1e30F);
        Eigen::Vector3d p = points[static_cast<std::size_t>(k)];
        p[axis] = std::clamp(static_cast<double>(x), low[axis], high[axis]);
        points.push_back(p);
        const float estimate =
            (static_cast<float>(p[axis]) - static_cast<float>(low[axis])) * static_cast<float>(inverse) + 0.5F;
        if (std::floor(static_cast<double>(estimate)) != std::floor((p[axis] - low[axis]) * inverse + 0.5)) {
          ++float_differs;
        }
      }
    }
    std::shuffle(points.begin(), points.end(), random);
    for (const std::size_t length : {points.size(), std::size_t{8}, std::size_t{15}, std::size_t{17}}) {
      std::vector<Eigen::Vector3d> slice(points.begin(), points.begin() + static_cast<std::ptrdiff_t>(length));
      if (length < points.size()) slice.insert(slice.end(), {low, high});  // the same grid
      const NaiveResult expected = naive_algorithm1(slice, c.edge, 2);
      for (const int stride : {3, 4}) {
        SCOPED_TRACE("length " + std::to_string(slice.size()) + ", stride " + std::to_string(stride));
        const std::vector<float> rows = rows_with_extra_columns<float>(slice, stride);
        CollapseParams params;
        params.edge_m = c.edge;
        params.sigma = 2;
        params.storage = CubeStorage::kDense;
        const CollapseResult result =
            collapse_overhangs(PointsView<float>(rows.data(), slice.size(), stride, 1), params);
        ASSERT_EQ(result.occupied_cubes, expected.occupied);
        ASSERT_EQ(result.removed_cubes, expected.removed);
        ASSERT_EQ(result.overhang, expected.overhang);
      }
    }
  }
  EXPECT_GT(float_differs, 0) << "the border rows must include some that only the double formula quantises right";
}

TEST(CollapseVsNaive, LatticeFloatRowsOnCubeBordersStayExact) {
  // Coordinates on a 1 cm lattice (as laser-scanner exports often are) put 2 % of the rows of each
  // axis exactly on a border of 0.5 m cubes, where a float quantisation would round them into the
  // wrong cube. Lattice rows first, then random rows, and the other way round.
  std::mt19937 random(7);
  std::uniform_int_distribution<int> step(0, 1500);
  std::uniform_real_distribution<double> coordinate(0.0, 15.0);
  std::vector<Eigen::Vector3d> lattice, scattered;
  for (int k = 0; k < 5000; ++k) {
    lattice.push_back(test::rounded_to<float>(Eigen::Vector3d(step(random), step(random), step(random)) * 0.01));
    scattered.push_back(
        test::rounded_to<float>(Eigen::Vector3d(coordinate(random), coordinate(random), coordinate(random))));
  }
  for (const bool lattice_first : {true, false}) {
    SCOPED_TRACE(lattice_first ? "lattice first" : "lattice last");
    std::vector<Eigen::Vector3d> points = lattice_first ? lattice : scattered;
    points.insert(points.end(), (lattice_first ? scattered : lattice).begin(),
                  (lattice_first ? scattered : lattice).end());
    const NaiveResult expected = naive_algorithm1(points, 0.5, 2);
    for (const int stride : {3, 4}) {
      const std::vector<float> rows = rows_with_extra_columns<float>(points, stride);
      CollapseParams params;
      params.edge_m = 0.5;
      params.sigma = 2;
      const CollapseResult result =
          collapse_overhangs(PointsView<float>(rows.data(), points.size(), stride, 1), params);
      ASSERT_EQ(result.occupied_cubes, expected.occupied) << "stride " << stride;
      ASSERT_EQ(result.removed_cubes, expected.removed);
      ASSERT_EQ(result.overhang, expected.overhang);
    }
  }
}

TEST(CollapseStorage, TenKilometreCloudAtFiveCentimetresStaysSparseAndExact) {
  // 200,000 x 200,000 x 2,000 cubes would be 10 TB of bits: the sparse path must be chosen.
  auto points = test::random_scene(7, 2000, 20.0);
  const std::size_t n = points.size();
  for (std::size_t i = 0; i < n; ++i) points.push_back(points[i] + Eigen::Vector3d(10000.0, 10000.0, 95.0));
  CollapseParams params;
  params.edge_m = 0.05;
  params.sigma = 20;
  const CollapseResult result = collapse_overhangs(points, params);
  EXPECT_EQ(result.storage_used, CubeStorage::kSparse);
  EXPECT_GT(result.grid.num_cubes(), std::int64_t{1} << 40);
  // Far-apart halves do not interact: each matches the result of its own half.
  const std::vector<Eigen::Vector3d> near(points.begin(), points.begin() + static_cast<std::ptrdiff_t>(n));
  const CollapseResult near_only = collapse_overhangs(near, params);
  EXPECT_TRUE(std::equal(near_only.overhang.begin(), near_only.overhang.end(), result.overhang.begin()));
  EXPECT_TRUE(std::equal(near_only.overhang.begin(), near_only.overhang.end(), result.overhang.begin() + n));
  params.storage = CubeStorage::kDense;
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
}

// --- several threads (CollapseParams::num_threads) -----------------------------------------------

/// collapse_overhangs with `threads` threads.
CollapseResult collapse_on_threads(const std::function<CollapseResult(const CollapseParams&)>& collapse,
                                   CollapseParams params, int threads) {
  params.num_threads = threads;
  CollapseResult result = collapse(params);
  return result;
}

void expect_same_result(const CollapseResult& actual, const CollapseResult& expected) {
  EXPECT_EQ(actual.overhang, expected.overhang);
  EXPECT_EQ(actual.occupied_cubes, expected.occupied_cubes);
  EXPECT_EQ(actual.removed_cubes, expected.removed_cubes);
  EXPECT_EQ(actual.num_overhang, expected.num_overhang);
  EXPECT_EQ(actual.num_used, expected.num_used);
  EXPECT_EQ(actual.num_cropped, expected.num_cropped);
  EXPECT_EQ(actual.num_dropped_non_finite, expected.num_dropped_non_finite);
  EXPECT_EQ(actual.grid.min_corner, expected.grid.min_corner);
  EXPECT_EQ(actual.grid.ixmax, expected.grid.ixmax);
  EXPECT_EQ(actual.grid.iymax, expected.grid.iymax);
  EXPECT_EQ(actual.grid.izmax, expected.grid.izmax);
}

TEST(CollapseThreads, RandomScenesOnAnyNumberOfThreadsMatchTheNaiveAlgorithm) {
  // V as bits (a 52 m scene at 0.5 m: 7,400 words; at 28 m and 0.1 m: 260,000 words, more than
  // the points, so with V's summary; at 30 m and 0.05 m: 2.4 M words) and as bytes (a 6 m scene at
  // 0.5 m: under 2^16 cubes). Float rows strided and double rows, against the naive Algorithm 1.
  struct Case {
    std::uint32_t seed;
    double extent_m, edge_m;
  };
  for (const Case c : {Case{81, 52.0, 0.5}, Case{82, 28.0, 0.1}, Case{85, 30.0, 0.05}, Case{83, 6.0, 0.5}}) {
    SCOPED_TRACE("seed " + std::to_string(c.seed));
    const auto points = test::random_scene(c.seed, 150000, c.extent_m);
    const NaiveResult expected = naive_algorithm1(points, c.edge_m, 2);
    std::vector<float> strided(points.size() * 4);
    for (std::size_t row = 0; row < points.size(); ++row) {
      for (int axis = 0; axis < 3; ++axis) strided[row * 4 + axis] = static_cast<float>(points[row][axis]);
    }
    const PointsView<float> floats(strided.data(), points.size(), 4, 1);
    CollapseParams params;
    params.edge_m = c.edge_m;
    params.storage = CubeStorage::kDense;
    const CollapseResult float_serial = collapse_overhangs(floats, params);
    for (const int threads : {2, 3, 0}) {
      SCOPED_TRACE(std::to_string(threads) + " threads");
      const CollapseResult result =
          collapse_on_threads([&](const CollapseParams& p) { return collapse_overhangs(points, p); }, params, threads);
      EXPECT_EQ(result.overhang, expected.overhang);
      EXPECT_EQ(result.occupied_cubes, expected.occupied);
      EXPECT_EQ(result.removed_cubes, expected.removed);
      expect_same_result(
          collapse_on_threads([&](const CollapseParams& p) { return collapse_overhangs(floats, p); }, params, threads),
          float_serial);
    }
  }
}

TEST(CollapseThreads, RealScansLatticeRowsTransformsCropsAndNaNRowsGiveTheOneThreadResult) {
  const auto data = test::shared_data_dir();
  if (!data) GTEST_SKIP() << "../shared/data not found (set TERRACUBE_DATA_DIR)";
  const test::XyziScan scan = test::read_xyzi_bin(*data + "/kitti_seq00/velodyne/000000.bin");
  CollapseParams params;
  const auto kitti = [&](const CollapseParams& p) { return collapse_overhangs(scan.xyz(), p); };
  expect_same_result(collapse_on_threads(kitti, params, 2), kitti(params));
  // Leveled and cropped.
  params.transform = leveling_transform(0.03, -0.02);
  params.crop = CropBox{{-40.0, -40.0, -3.0}, {40.0, 40.0, 20.0}};
  expect_same_result(collapse_on_threads(kitti, params, 3), kitti(params));
  // A 1 cm lattice: many rows on cube borders.
  std::vector<Eigen::Vector3d> lattice;
  for (const Eigen::Vector3d& p : scan.as_vectors()) lattice.push_back((p * 100.0).array().round() / 100.0);
  params = CollapseParams{};
  const auto on_lattice = [&](const CollapseParams& p) { return collapse_overhangs(lattice, p); };
  expect_same_result(collapse_on_threads(on_lattice, params, 2), on_lattice(params));
  // NaN rows in both halves: counted once each, the first one named; dropped on request.
  std::vector<Eigen::Vector3d> poisoned = lattice;
  for (const std::size_t row : {std::size_t{120000}, std::size_t{70}, std::size_t{71}}) poisoned[row].z() = NAN;
  params.num_threads = 2;
  try {
    collapse_overhangs(poisoned, params);
    ADD_FAILURE() << "expected std::invalid_argument";
  } catch (const std::invalid_argument& error) {
    EXPECT_NE(std::string(error.what()).find("3 of 124668 point rows contain NaN or Inf (first at row 70)"),
              std::string::npos)
        << error.what();
  }
  params.drop_non_finite = true;
  const auto dropping = [&](const CollapseParams& p) { return collapse_overhangs(poisoned, p); };
  const CollapseResult dropped = collapse_on_threads(dropping, params, 2);
  params.num_threads = 1;
  expect_same_result(dropped, dropping(params));
  EXPECT_EQ(dropped.num_dropped_non_finite, 3U);
}

TEST(CollapseThreads, SmallCloudsOnSeveralThreadsGiveTheOneThreadResultAndNegativeCountsAreRejected) {
  const auto points = test::random_scene(84, 20000, 8.0);
  CollapseParams params;
  params.num_threads = 8;
  const CollapseResult result = collapse_overhangs(points, params);
  params.num_threads = 1;
  expect_same_result(result, collapse_overhangs(points, params));
  params.num_threads = -3;
  try {
    collapse_overhangs(points, params);
    ADD_FAILURE() << "expected std::invalid_argument";
  } catch (const std::invalid_argument& error) {
    EXPECT_NE(std::string(error.what()).find("CollapseParams.num_threads must be >= 0"), std::string::npos)
        << error.what();
  }
}

// --- bad input --------------------------------------------------------------------------------

TEST(CollapseBadInput, EmptyCloudGivesAValidEmptyResult) {
  const CollapseResult result = collapse_overhangs(std::vector<Eigen::Vector3d>{}, CollapseParams{});
  EXPECT_TRUE(result.overhang.empty());
  EXPECT_TRUE(result.occupied_cubes.empty());
  EXPECT_TRUE(result.removed_cubes.empty());
  EXPECT_EQ(result.grid.num_cubes(), 0);
}

TEST(CollapseBadInput, NanAndInfRowsAreCountedInTheError) {
  std::vector<Eigen::Vector3d> points = {
      {0, 0, 0}, {NAN, 0, 0}, {0, 0, 5}, {0, std::numeric_limits<double>::infinity(), 0}};
  try {
    collapse_overhangs(points, CollapseParams{});
    FAIL() << "expected std::invalid_argument";
  } catch (const std::invalid_argument& error) {
    EXPECT_NE(std::string(error.what()).find("2 of 4 point rows contain NaN or Inf (first at row 1)"),
              std::string::npos)
        << error.what();
  }
}

// The bounding box and the non-finite check over rows of 3 or 4 float/double scalars: every
// layout, small sizes, and a NaN/Inf in every row and axis position of small clouds. Compared with
// the naive box (the grid's min corner and counts) and the row count of the error.
template <typename Scalar>
void check_packed_extent_layouts() {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> coordinate(-30.0, 30.0);
  const Scalar bad_values[] = {std::numeric_limits<Scalar>::quiet_NaN(), std::numeric_limits<Scalar>::infinity(),
                               -std::numeric_limits<Scalar>::infinity()};
  for (const int stride : {3, 4}) {
    for (const std::size_t n : {1, 2, 3, 5, 7, 8, 9, 15, 16, 17, 23, 24, 25, 31, 33, 47, 48, 49, 97, 1001}) {
      // Rows of 4 end after the last row's z, as a view of x, y, z of a longer row can: no pass
      // may read past it (ASan's build would see it).
      std::vector<Scalar> rows(n * static_cast<std::size_t>(stride) - (stride == 4 ? 1 : 0));
      for (Scalar& v : rows) v = static_cast<Scalar>(coordinate(rng));
      if (stride == 4) {
        for (std::size_t r = 0; r + 1 < n; r += 3) rows[4 * r + 3] = std::numeric_limits<Scalar>::quiet_NaN();
      }
      std::vector<Eigen::Vector3d> points(n);
      for (std::size_t r = 0; r < n; ++r) {
        for (int a = 0; a < 3; ++a) points[r][a] = static_cast<double>(rows[r * static_cast<std::size_t>(stride) + a]);
      }
      CollapseParams params;
      params.edge_m = 0.25;
      const PointsView<Scalar> view(rows.data(), n, stride);
      // An intensity column full of NaN is not a coordinate: no error, the naive box.
      const CollapseResult result = collapse_overhangs(view, params);
      const NaiveResult naive = naive_algorithm1(points, params.edge_m, params.sigma);
      EXPECT_EQ(result.overhang, naive.overhang) << "stride " << stride << " n " << n;
      EXPECT_EQ(result.occupied_cubes, naive.occupied) << "stride " << stride << " n " << n;
      for (int a = 0; a < 3; ++a) {
        double lo = points[0][a];
        for (const auto& p : points) lo = std::min(lo, p[a]);
        EXPECT_EQ(result.grid.min_corner[a], lo) << "stride " << stride << " n " << n << " axis " << a;
      }
      const std::size_t positions = n <= 49 ? n : 3;
      for (std::size_t k = 0; k < positions; ++k) {
        const std::size_t row = n <= 49 ? k : (k == 0 ? 0 : k == 1 ? n / 2 : n - 1);
        for (int axis = 0; axis < 3; ++axis) {
          for (const Scalar bad : bad_values) {
            std::vector<Scalar> broken = rows;
            broken[row * static_cast<std::size_t>(stride) + static_cast<std::size_t>(axis)] = bad;
            const PointsView<Scalar> broken_view(broken.data(), n, stride);
            try {
              collapse_overhangs(broken_view, params);
              ADD_FAILURE() << "no error for " << bad << " at row " << row << " axis " << axis << ", stride " << stride
                            << ", n " << n;
            } catch (const std::invalid_argument& error) {
              const std::string expected = "1 of " + std::to_string(n) +
                                           " point rows contain NaN or Inf (first at row " + std::to_string(row) + ")";
              EXPECT_NE(std::string(error.what()).find(expected), std::string::npos) << error.what();
            }
          }
        }
      }
    }
  }
}

TEST(CollapseBadInput, TheExtentFindsEveryNonFiniteCoordinateAndTheNaiveBox) {
  check_packed_extent_layouts<float>();
  check_packed_extent_layouts<double>();
}

TEST(CollapseBadInput, NanRowsCanBeDroppedAndReported) {
  std::vector<Eigen::Vector3d> points = {
      {0, 0, 0}, {NAN, 0, 0}, {0, 0, 5}, {0, 0, -std::numeric_limits<double>::infinity()}};
  CollapseParams params;
  params.drop_non_finite = true;
  const CollapseResult result = collapse_overhangs(points, params);
  EXPECT_EQ(result.num_dropped_non_finite, 2U);
  EXPECT_EQ(result.overhang, (std::vector<std::uint8_t>{0, 0, 1, 0}));
}

TEST(CollapseBadInput, NonPositiveEdgeAndSigmaBelowOneAreRejected) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}};
  for (const double edge :
       {0.0, -1.0, std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity()}) {
    CollapseParams params;
    params.edge_m = edge;
    EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument) << edge;
  }
  CollapseParams params;
  params.sigma = 0;
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
}

TEST(CollapseBadInput, ExtentThatOverflowsTheIndexIsRejected) {
  const std::vector<Eigen::Vector3d> points = {{-1e300, 0, 0}, {1e300, 1e300, 1e300}};
  try {
    collapse_overhangs(points, CollapseParams{});
    FAIL() << "expected std::invalid_argument";
  } catch (const std::invalid_argument& error) {
    EXPECT_NE(std::string(error.what()).find("overflows a 64-bit cube index"), std::string::npos) << error.what();
  }
  // 2^21 cubes per axis: each count fits but the product (2^63) does not.
  const std::vector<Eigen::Vector3d> cube = {{0, 0, 0}, {2097152.0, 2097152.0, 2097152.0}};
  CollapseParams params;
  params.edge_m = 1.0;
  EXPECT_THROW(collapse_overhangs(cube, params), std::invalid_argument);
}

TEST(CollapseBadInput, NonRigidTransformsAndBadCropsAreRejected) {
  const std::vector<Eigen::Vector3d> points = {{0, 0, 0}};
  CollapseParams params;
  params.transform(0, 0) = 2.0;
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
  params.transform = Eigen::Matrix4d::Identity();
  params.transform(2, 2) = -1.0;  // a reflection
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
  params.transform = Eigen::Matrix4d::Identity();
  params.transform(0, 3) = NAN;
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
  params.transform = Eigen::Matrix4d::Identity();
  params.crop = CropBox{{1, 1, 1}, {0, 0, 0}};
  EXPECT_THROW(collapse_overhangs(points, params), std::invalid_argument);
}

TEST(CollapseBadInput, ViewWithoutDataIsRejected) {
  EXPECT_THROW(collapse_overhangs(PointsView<float>(nullptr, 3), CollapseParams{}), std::invalid_argument);
}

}  // namespace
}  // namespace terracube

namespace terracube {
namespace {

// issue 39, item 2: the caller's array may change while a call reads it (another thread, a
// recycled driver buffer, a memory map another process writes). Whatever it holds by then, no call
// may write out of bounds or crash (run under ASan in CI), with several callers at once; a row that
// moved takes no part.
TEST(ConcurrentInput, AWriterRewritingRowsDuringTheCallsNeverBreaksThem) {
  const auto scene = test::random_scene(91, 6000, 12.0);
  std::vector<double> values;
  for (const Eigen::Vector3d& p : scene) values.insert(values.end(), {p.x(), p.y(), p.z()});
  std::atomic<bool> stop{false};
  std::thread writer([&] {  // keeps 64 rows moved far out (or to NaN), moving others back in turn
    std::mt19937 rng(5);
    const double wild[] = {100.0, -100.0, 60.0, -60.0, std::numeric_limits<double>::quiet_NaN()};
    std::vector<std::size_t> moved(64, 0);
    for (std::size_t turn = 0; !stop.load(std::memory_order_relaxed); ++turn) {
      volatile double* slots = values.data();  // plain stores another thread races with
      std::size_t& k = moved[turn % moved.size()];
      slots[k] = scene[k / 3][static_cast<int>(k % 3)];
      k = rng() % values.size();
      slots[k] = wild[rng() % 5];
    }
  });
  const PointsView<double> view(values.data(), scene.size());
  std::atomic<std::size_t> calls{0};
  const auto caller = [&] {  // two of them, concurrently
    CollapseParams params;
    params.drop_non_finite = true;
    ElevationParams map;
    map.resolution_m = 0.5;
    map.drop_non_finite = true;
    for (int round = 0; round < 30; ++round) {
      for (const CubeStorage storage : {CubeStorage::kDense, CubeStorage::kSparse}) {
        params.storage = storage;
        try {  // a clear exception (an extent too large for the grid, say) is fine; a crash is not
          const CollapseResult result = collapse_overhangs(view, params);
          EXPECT_EQ(result.overhang.size(), scene.size());
          for (const std::int64_t cube : result.occupied_cubes) {
            ASSERT_TRUE(cube >= 0 && cube < result.grid.num_cubes()) << "cube " << cube << " outside the grid";
          }
          ++calls;
        } catch (const std::invalid_argument&) {
        }
      }
      try {
        build_overhang_free_map(view, params, map);
        ++calls;
      } catch (const std::invalid_argument&) {
      }
    }
  };
  std::thread first(caller), second(caller);
  first.join();
  second.join();
  stop = true;
  writer.join();
  EXPECT_GT(calls.load(), 0U);
}

}  // namespace
}  // namespace terracube
