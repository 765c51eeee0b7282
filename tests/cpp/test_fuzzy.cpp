#include <gtest/gtest.h>
#include <terracube/collapse.hpp>
#include <terracube/elevation_map.hpp>
#include <terracube/fuzzy.hpp>

#include <cmath>
#include <fstream>
#include <functional>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "test_support.hpp"

namespace terracube {
namespace {

using test::expect_throw_with;

FuzzyParams params_over(double x0, double y0, double x1, double y1, int rules_x, int rules_y) {
  FuzzyParams params;
  params.rules_x = rules_x;
  params.rules_y = rules_y;
  params.extent = Extent2d{{x0, y0}, {x1, y1}};
  return params;
}

/// The naive formula from the header, summing over every MF: triangles reaching zero at the
/// neighbouring centres (the outer ones held at 1 beyond the outer centres), or Gaussians.
double naive_degree(const Eigen::VectorXd& c, int k, double u, MembershipFamily family, double sigma) {
  const auto m = static_cast<int>(c.size());
  if (family == MembershipFamily::kGaussian) return std::exp(-(u - c[k]) * (u - c[k]) / (2 * sigma * sigma));
  if (u <= c[k]) {
    if (k == 0) return 1.0;
    return u <= c[k - 1] ? 0.0 : (u - c[k - 1]) / (c[k] - c[k - 1]);
  }
  if (k == m - 1) return 1.0;
  return u >= c[k + 1] ? 0.0 : (c[k + 1] - u) / (c[k + 1] - c[k]);
}

double naive_surface(const FuzzyElevationMap& model, double x, double y) {
  const MembershipFamily family = model.params().membership;
  const Eigen::VectorXd& cx = model.centers_x();
  const Eigen::VectorXd& cy = model.centers_y();
  double sum_a = 0.0;
  double sum_b = 0.0;
  for (int i = 0; i < cx.size(); ++i) sum_a += naive_degree(cx, i, x, family, model.gaussian_sigma_m().x());
  for (int j = 0; j < cy.size(); ++j) sum_b += naive_degree(cy, j, y, family, model.gaussian_sigma_m().y());
  double f = 0.0;
  for (int i = 0; i < cx.size(); ++i) {
    for (int j = 0; j < cy.size(); ++j) {
      f += naive_degree(cx, i, x, family, model.gaussian_sigma_m().x()) / sum_a *
           naive_degree(cy, j, y, family, model.gaussian_sigma_m().y()) / sum_b * model.consequents()(i, j);
    }
  }
  return f;
}

/// A known surface: 6 x 4 rules over [0, 10] x [0, 5] with uneven centres and seeded consequents.
FuzzyElevationMap known_surface(MembershipFamily family) {
  FuzzyParams params = params_over(0, 0, 10, 5, 6, 4);
  params.membership = family;
  Eigen::VectorXd cx(6), cy(4);
  cx << 0.0, 1.5, 4.5, 5.5, 8.0, 10.0;
  cy << 0.0, 2.0, 3.0, 5.0;
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> height(-1.0, 1.0);
  Eigen::MatrixXd c(6, 4);
  for (Eigen::Index k = 0; k < c.size(); ++k) c.data()[k] = height(rng);
  return FuzzyElevationMap(params, cx, cy, c);
}

std::vector<Eigen::Vector3d> sample(const FuzzyElevationMap& model, std::size_t n, std::uint32_t seed,
                                    double noise_m = 0.0) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> ux(model.extent().min_m.x(), model.extent().max_m.x());
  std::uniform_real_distribution<double> uy(model.extent().min_m.y(), model.extent().max_m.y());
  std::normal_distribution<double> noise(0.0, noise_m > 0 ? noise_m : 1.0);
  std::vector<Eigen::Vector3d> points;
  for (std::size_t k = 0; k < n; ++k) {
    const double x = ux(rng);
    const double y = uy(rng);
    points.emplace_back(x, y, model.evaluate(x, y) + (noise_m > 0 ? noise(rng) : 0.0));
  }
  return points;
}

// --- model and evaluation ---------------------------------------------------------------------

TEST(FuzzyElevationMap, PaperModelHas190RulesAnd219Parameters) {
  const FuzzyParams params = params_over(0, 0, 20, 10, 19, 10);
  const FuzzyElevationMap model(params, Eigen::VectorXd::LinSpaced(19, 0, 20), Eigen::VectorXd::LinSpaced(10, 0, 10),
                                Eigen::MatrixXd::Zero(19, 10));
  EXPECT_EQ(model.num_rules(), 190);
  EXPECT_EQ(model.num_parameters(), 219);
  EXPECT_EQ(FuzzyParams{}.rules_x, 19);
  EXPECT_EQ(FuzzyParams{}.rules_y, 10);
}

TEST(FuzzyElevationMap, EvaluateMatchesTheNaiveFormula) {
  for (const auto family : {MembershipFamily::kTriangularPartition, MembershipFamily::kGaussian}) {
    const FuzzyElevationMap model = known_surface(family);
    std::mt19937 rng(3);
    std::uniform_real_distribution<double> ux(-1.0, 11.0);  // also beyond the extent
    std::uniform_real_distribution<double> uy(-1.0, 6.0);
    // Gaussians: the library sums the 5 nearest MFs only; the rest weigh < 1e-5 here.
    const double tolerance = family == MembershipFamily::kGaussian ? 1e-4 : 1e-12;
    for (int k = 0; k < 500; ++k) {
      const double x = ux(rng);
      const double y = uy(rng);
      ASSERT_NEAR(model.evaluate(x, y), naive_surface(model, x, y), tolerance) << "at " << x << ", " << y;
    }
  }
}

TEST(FuzzyElevationMap, TriangularPartitionInterpolatesConsequentsAtCentres) {
  const FuzzyElevationMap model = known_surface(MembershipFamily::kTriangularPartition);
  for (int i = 0; i < 6; ++i) {
    for (int j = 0; j < 4; ++j) {
      EXPECT_DOUBLE_EQ(model.evaluate(model.centers_x()[i], model.centers_y()[j]), model.consequents()(i, j));
    }
  }
}

// --- identification ---------------------------------------------------------------------------

TEST(FitFuzzyElevationMap, LeastSquaresRecoversAKnownSurfaceOnItsOwnCentres) {
  // The truth uses the uniform centres the fit starts from, so least squares alone recovers it.
  FuzzyParams params = params_over(0, 0, 10, 5, 6, 4);
  params.epochs = 0;
  params.ridge = 1e-12;
  params.smoothness = 0.0;
  const FuzzyElevationMap truth(params, Eigen::VectorXd::LinSpaced(6, 0, 10), Eigen::VectorXd::LinSpaced(4, 0, 5),
                                known_surface(MembershipFamily::kTriangularPartition).consequents());
  const std::vector<Eigen::Vector3d> points = sample(truth, 3000, 12);
  const FuzzyElevationMap fitted = fit_fuzzy_elevation_map(PointsView<double>(points), params);
  EXPECT_LT((fitted.consequents() - truth.consequents()).cwiseAbs().maxCoeff(), 1e-6);
  EXPECT_LT(fitted.rmse_history().back(), 1e-8);
  EXPECT_EQ(fitted.num_training_points(), 3000U);
}

TEST(FitFuzzyElevationMap, HybridLearningMovesCentresTowardsAKnownSurface) {
  for (const auto family : {MembershipFamily::kTriangularPartition, MembershipFamily::kGaussian}) {
    SCOPED_TRACE(family == MembershipFamily::kGaussian ? "gaussian" : "triangular");
    const FuzzyElevationMap truth = known_surface(family);
    const std::vector<Eigen::Vector3d> points = sample(truth, 4000, 5);
    FuzzyParams params = truth.params();
    params.epochs = 40;
    params.ridge = 1e-9;
    params.smoothness = 0.0;
    const FuzzyElevationMap fitted = fit_fuzzy_elevation_map(PointsView<double>(points), params);
    const std::vector<double>& rmse = fitted.rmse_history();
    ASSERT_EQ(rmse.size(), 41U);
    EXPECT_LT(rmse.back(), 0.5 * rmse.front()) << "first " << rmse.front() << ", last " << rmse.back();
    // The fitted surface agrees with the truth away from the samples too.
    const std::vector<Eigen::Vector3d> check = sample(truth, 500, 99);
    double sse = 0.0;
    for (const auto& p : check) sse += std::pow(fitted.evaluate(p.x(), p.y()) - p.z(), 2);
    EXPECT_LT(std::sqrt(sse / 500), 2.0 * rmse.back() + 1e-3);
  }
}

TEST(FitFuzzyElevationMap, TrainingErrorNeverIncreasesAcrossEpochs) {
  for (const auto family : {MembershipFamily::kTriangularPartition, MembershipFamily::kGaussian}) {
    const FuzzyElevationMap truth = known_surface(family);
    const std::vector<Eigen::Vector3d> points = sample(truth, 2000, 21, 0.05);
    FuzzyParams params = params_over(0, 0, 10, 5, 8, 5);
    params.membership = family;
    params.epochs = 25;
    params.learning_rate = 0.5;  // large steps: some get rejected
    const FuzzyElevationMap fitted = fit_fuzzy_elevation_map(PointsView<double>(points), params);
    const std::vector<double>& rmse = fitted.rmse_history();
    ASSERT_EQ(rmse.size(), 26U);
    for (std::size_t e = 1; e < rmse.size(); ++e) EXPECT_LE(rmse[e], rmse[e - 1]) << "epoch " << e;
    for (int k = 1; k < fitted.centers_x().size(); ++k) EXPECT_GT(fitted.centers_x()[k], fitted.centers_x()[k - 1]);
    EXPECT_GE(fitted.centers_x()[0], 0.0);
    EXPECT_LE(fitted.centers_x()[fitted.centers_x().size() - 1], 10.0);
  }
}

TEST(FitFuzzyElevationMap, JangStepRuleIsPlainAnfisTakingEveryStep) {
  // Plain ANFIS (no regularisation, Jang's step-size heuristic) learns a known surface.
  const FuzzyElevationMap truth = known_surface(MembershipFamily::kTriangularPartition);
  const std::vector<Eigen::Vector3d> points = sample(truth, 4000, 5);
  FuzzyParams params = truth.params();
  params.epochs = 40;
  params.ridge = 0.0;
  params.smoothness = 0.0;
  params.step_rule = StepRule::kJang;
  const FuzzyElevationMap learned = fit_fuzzy_elevation_map(PointsView<double>(points), params);
  ASSERT_EQ(learned.rmse_history().size(), 41U);
  EXPECT_LT(learned.rmse_history().back(), 0.5 * learned.rmse_history().front());
  // One epoch takes the first step whatever it does to the error: the centres move by exactly
  // kappa = learning_rate x the smaller spacing along the normalised gradient (no clipping here).
  const std::vector<Eigen::Vector3d> noisy = sample(truth, 2000, 21, 0.05);
  FuzzyParams one = params_over(0, 0, 10, 5, 8, 5);
  one.epochs = 1;
  one.learning_rate = 0.05;
  one.ridge = 0.0;
  one.smoothness = 0.0;
  one.step_rule = StepRule::kJang;
  const FuzzyElevationMap stepped = fit_fuzzy_elevation_map(PointsView<double>(noisy), one);
  const Eigen::VectorXd start_x = Eigen::VectorXd::LinSpaced(8, 0.0, 10.0);
  const Eigen::VectorXd start_y = Eigen::VectorXd::LinSpaced(5, 0.0, 5.0);
  const double moved =
      std::sqrt((stepped.centers_x() - start_x).squaredNorm() + (stepped.centers_y() - start_y).squaredNorm());
  EXPECT_NEAR(moved, 0.05 * std::min(10.0 / 7.0, 5.0 / 4.0), 1e-9);
}

TEST(FitFuzzyElevationMap, IsDeterministicAndFloatAgreesWithDouble) {
  const std::vector<Eigen::Vector3d> points = test::random_scene(4, 5000, 20.0);
  FuzzyParams params;
  params.rules_x = 8;
  params.rules_y = 6;
  params.epochs = 5;
  const FuzzyElevationMap a = fit_fuzzy_elevation_map(PointsView<double>(points), params);
  const FuzzyElevationMap b = fit_fuzzy_elevation_map(PointsView<double>(points), params);
  EXPECT_EQ(a.consequents(), b.consequents());
  EXPECT_EQ(a.centers_x(), b.centers_x());
  EXPECT_EQ(a.rmse_history(), b.rmse_history());
  std::vector<Eigen::Vector3f> floats;
  for (const auto& p : points) floats.push_back(p.cast<float>());
  const FuzzyElevationMap c = fit_fuzzy_elevation_map(PointsView<float>(floats), params);
  EXPECT_NEAR(c.rmse_history().back(), a.rmse_history().back(), 1e-4);
}

TEST(FitFuzzyElevationMap, AFittedMapRebuiltFromItsPartsIsTheSame) {
  const std::vector<Eigen::Vector3d> points = test::random_scene(5, 4000, 20.0);
  for (const MembershipFamily membership : {MembershipFamily::kTriangularPartition, MembershipFamily::kGaussian}) {
    FuzzyParams params;
    params.rules_x = 7;
    params.rules_y = 5;
    params.epochs = 3;
    params.membership = membership;
    const FuzzyElevationMap fitted = fit_fuzzy_elevation_map(PointsView<double>(points), params);
    FuzzyParams parts = fitted.params();
    parts.extent = fitted.extent();  // derived from the points when fitting
    const FuzzyElevationMap rebuilt(parts, fitted.centers_x(), fitted.centers_y(), fitted.consequents(),
                                    fitted.rule_support(), fitted.rmse_history(), fitted.num_training_points());
    EXPECT_EQ(rebuilt.rmse_history(), fitted.rmse_history());
    EXPECT_EQ(rebuilt.num_training_points(), fitted.num_training_points());
    EXPECT_EQ(rebuilt.gaussian_sigma_m(), fitted.gaussian_sigma_m());
    for (double x = -1.0; x <= 21.0; x += 0.37) {
      for (double y = -1.0; y <= 21.0; y += 0.41) {
        EXPECT_EQ(rebuilt.evaluate(x, y), fitted.evaluate(x, y));
        EXPECT_EQ(rebuilt.confidence(x, y), fitted.confidence(x, y));
      }
    }
  }
}

TEST(FitFuzzyElevationMap, UseFlagsAndExtentSelectTheTrainingPoints) {
  const FuzzyElevationMap truth = known_surface(MembershipFamily::kTriangularPartition);
  std::vector<Eigen::Vector3d> points = sample(truth, 1000, 8);
  FuzzyParams params = truth.params();
  params.epochs = 3;
  const FuzzyElevationMap alone = fit_fuzzy_elevation_map(PointsView<double>(points), params);
  std::vector<std::uint8_t> use(points.size() + 2, 1);
  points.emplace_back(5.0, 2.0, 100.0);  // an overhang point, deselected
  points.emplace_back(50.0, 2.0, 0.0);   // outside the extent
  use[1000] = 0;
  const FuzzyElevationMap fitted = fit_fuzzy_elevation_map(PointsView<double>(points), params, &use);
  EXPECT_EQ(fitted.num_training_points(), 1000U);
  EXPECT_EQ(fitted.consequents(), alone.consequents());
  EXPECT_EQ(fitted.centers_x(), alone.centers_x());
  EXPECT_NEAR(fitted.rule_support().sum(), 1000.0, 1e-6);  // partition of unity
}

// --- layers -----------------------------------------------------------------------------------

TEST(FuzzyElevationMap, ToLayerFillsSmallHolesButNotOutsideTheData) {
  // A tilted plane over [0, 10] x [0, 5] with a 1 m hole in the middle.
  std::vector<Eigen::Vector3d> points;
  for (double x = 0.025; x < 10.0; x += 0.05) {
    for (double y = 0.025; y < 5.0; y += 0.05) {
      if (std::abs(x - 5.0) < 0.5 && std::abs(y - 2.5) < 0.5) continue;
      points.emplace_back(x, y, 0.1 * x - 0.2 * y);
    }
  }
  const FuzzyParams params = params_over(0, 0, 10, 5, 11, 6);
  const FuzzyElevationMap model = fit_fuzzy_elevation_map(PointsView<double>(points), params);
  MapGeometry geometry;
  geometry.resolution_m = 0.1;
  geometry.origin_m = {-1.0, 0.0};  // ten columns of cells left of the data
  geometry.size = {110, 50};
  ElevationMap map(geometry);
  model.to_layer(map);
  const Layer& fem = map.get("fem");
  const Layer& confidence = map.get("fem_confidence");
  const auto hole = geometry.index_of({5.0, 2.5});
  ASSERT_TRUE(hole.has_value());
  const Eigen::Vector2d centre = geometry.position_of(*hole);
  EXPECT_NEAR(fem((*hole)(0), (*hole)(1)), 0.1 * centre.x() - 0.2 * centre.y(), 1e-3);
  EXPECT_GT(confidence((*hole)(0), (*hole)(1)), 3.0);
  EXPECT_TRUE(std::isnan(fem(0, 10)));  // x = -0.95: outside the extent
  EXPECT_EQ(confidence(0, 10), 0.0F);
  expect_throw_with<std::invalid_argument>([&] { model.to_layer(map, std::nan("")); }, {"min_confidence"});
}

// --- bad input --------------------------------------------------------------------------------

TEST(FitFuzzyElevationMap, TooFewPointsForTheRuleGridIsAClearError) {
  const std::vector<Eigen::Vector3d> points = test::random_scene(1, 300, 20.0);
  FuzzyParams params;  // 190 rules, 2 points per rule -> 380 needed
  expect_throw_with<std::invalid_argument>(
      [&] { fit_fuzzy_elevation_map(PointsView<double>(points), params); },
      {"too few points for the rule grid", "300 points", "19 x 10 = 190 rules", "at least 380"});
  params.min_points_per_rule = 0.0;  // still one per rule
  EXPECT_NO_THROW(fit_fuzzy_elevation_map(PointsView<double>(points), params));
  expect_throw_with<std::invalid_argument>(
      [&] { fit_fuzzy_elevation_map(PointsView<double>(std::vector<Eigen::Vector3d>{}), params); },
      {"too few points", "0 points"});
}

TEST(FitFuzzyElevationMap, RejectsNanRowsAndBadParameters) {
  std::vector<Eigen::Vector3d> points = test::random_scene(2, 2000, 20.0);
  points[17].z() = std::numeric_limits<double>::quiet_NaN();
  FuzzyParams params;
  expect_throw_with<std::invalid_argument>([&] { fit_fuzzy_elevation_map(PointsView<double>(points), params); },
                                           {"1 of 2000", "NaN or Inf", "row 17"});
  points[17].z() = 0.0;
  const auto expect_bad = [&](const std::function<void(FuzzyParams&)>& change, const std::string& part) {
    FuzzyParams bad;
    change(bad);
    expect_throw_with<std::invalid_argument>([&] { fit_fuzzy_elevation_map(PointsView<double>(points), bad); }, {part});
  };
  expect_bad([](FuzzyParams& p) { p.rules_x = 1; }, "at least 2 x 2 rules");
  expect_bad([](FuzzyParams& p) { p.epochs = -1; }, "epochs");
  expect_bad([](FuzzyParams& p) { p.epochs = 1000000000; }, "epochs must be 0..100000");  // days, and its history
  expect_bad([](FuzzyParams& p) { p.learning_rate = 0.0; }, "learning_rate");
  expect_bad([](FuzzyParams& p) { p.ridge = -1.0; }, "ridge");
  expect_bad([](FuzzyParams& p) { p.smoothness = std::nan(""); }, "smoothness");
  expect_bad([](FuzzyParams& p) { p.gaussian_width = 0.0; }, "gaussian_width");
  expect_bad([](FuzzyParams& p) { p.extent = Extent2d{{0, 0}, {0, 5}}; }, "extent");
  std::vector<Eigen::Vector3d> line;
  for (int k = 0; k < 1000; ++k) line.emplace_back(0.01 * k, 1.0, 0.0);
  expect_throw_with<std::invalid_argument>([&] { fit_fuzzy_elevation_map(PointsView<double>(line), params); },
                                           {"span no area"});
  FuzzyParams unsupported = params_over(0, 0, 10, 10, 4, 4);
  unsupported.ridge = 0.0;
  unsupported.smoothness = 0.0;
  unsupported.min_points_per_rule = 0.0;
  std::vector<Eigen::Vector3d> corner;
  for (int k = 0; k < 100; ++k) corner.emplace_back(0.01 * k, 0.01 * (k % 10), 0.0);
  expect_throw_with<std::invalid_argument>([&] { fit_fuzzy_elevation_map(PointsView<double>(corner), unsupported); },
                                           {"singular", "ridge or smoothness"});
}

// --- real data --------------------------------------------------------------------------------

TEST(FitFuzzyElevationMap, KittiWindowOfKeptPointsSmoke) {
  const auto dir = test::shared_data_dir();
  if (!dir) GTEST_SKIP() << "shared data not found";
  const std::string path = *dir + "/kitti_seq00/velodyne/000000.bin";
  if (!std::ifstream(path)) GTEST_SKIP() << path << " not found";
  const test::XyziScan scan = test::read_xyzi_bin(path);
  CollapseParams collapse;
  collapse.sigma = 5;
  const CollapseResult result = collapse_overhangs(scan.xyz(), collapse);
  std::vector<std::uint8_t> kept(result.overhang.size());
  for (std::size_t k = 0; k < kept.size(); ++k) kept[k] = result.overhang[k] ? 0 : 1;
  const FuzzyParams params = params_over(0, -5, 20, 5, 19, 10);
  const FuzzyElevationMap model = fit_fuzzy_elevation_map(scan.xyz(), params, &kept);
  EXPECT_GT(model.num_training_points(), 5000U);
  EXPECT_EQ(model.num_parameters(), 219);
  EXPECT_LT(model.rmse_history().back(), 0.5);
  EXPECT_LE(model.rmse_history().back(), model.rmse_history().front());
}

}  // namespace
}  // namespace terracube
