// Fuzzy elevation maps (FEM): [CBC] section IV-C. The
// terrain is a zero-order Takagi-Sugeno fuzzy surface z = f(x, y), identified from the points that
// collapse_overhangs kept by ANFIS hybrid learning (Jang 1993): least squares for the consequents,
// gradient steps for the membership functions. The surface filters sensor noise and interpolates
// small shadowed areas that the DEM leaves empty.
//
// Model. Membership functions (MFs) A_1..A_nx on x and B_1..B_ny on y; one rule per pair,
//   rule (i, j): IF x is A_i AND y is B_j THEN z = c_ij                   (zero-order consequent)
//   f(x, y) = sum_ij a_i(x) b_j(y) c_ij,  a_i = A_i / sum_k A_k,  b_j = B_j / sum_k B_k
// (product t-norm; the normalised firing strength of rule (i, j) is a_i(x) b_j(y)).
//
// Parameter count. Each MF has one free parameter, its centre; the width is not identified:
//  - kTriangularPartition: triangles peaking at their centre and reaching zero at the neighbouring
//    centres, so the degrees already sum to one (a partition of unity) and f is the bilinear
//    interpolation of the consequents over the (movable) centre grid; every point fires at most
//    2 x 2 rules.
//  - kGaussian: exp(-(u - centre)^2 / (2 s^2)) with a fixed width s = gaussian_width * the initial
//    centre spacing, normalised; degrees are taken over the 5 MFs nearest each coordinate (with
//    evenly spaced centres the others weigh below 1e-5 at the default width), so a point fires at
//    most 5 x 5 rules.
// The paper's model, 19 x 10 = 190 rules over a 20 x 10 m area, thus has 190 consequents plus
// 19 + 10 = 29 centres = 219 parameters, the count the paper reports (rules_x = 19, rules_y = 10
// are the defaults).
//
// Hybrid learning, one epoch: (1) a gradient step on the centres with the consequents fixed, step
// length kappa along the normalised gradient of the squared error, by default kept when the
// training error does not increase (then kappa grows by 10 %), rejected with kappa halved
// otherwise (up to 4 tries) (StepRule::kJang: Jang's heuristic, every step taken); centres stay
// ordered inside the extent; (2) the consequents by
// regularised linear least squares,
//   min sum_p (f(p) - z_p)^2 + lambda sum_r (c_r - mean z)^2 + mu sum_{r~s} (c_r - c_s)^2
// (r~s: rules adjacent along x or y; the mu term is a membrane that keeps rules with little data,
// at the edge of a shadow or between sparse scan rings, from overshooting), solved by sparse LDLT
// on the normal equations (banded: at most 9 or 81 non-zeros per row, so 120k points take
// milliseconds), and kept unless they raise the training error (which only the regularisation
// can do). Epoch 0 is the least-squares fit on uniformly spaced centres; the training RMSE is
// non-increasing from there on.
//
// Confidence. The support of rule r is the sum of its firing strengths over the training points;
// the confidence at (x, y) is the support of the rules firing there, weighted by their strengths:
// high inside the data and across small holes, falling to zero away from it.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "terracube/cube_grid.hpp"
#include "terracube/elevation_map.hpp"

namespace terracube {

/// The membership-function family of a FuzzyElevationMap.
enum class MembershipFamily {
  kTriangularPartition = 0,  ///< triangles between neighbouring centres (bilinear interpolation)
  kGaussian = 1,             ///< normalised Gaussians of fixed width
};

/// How hybrid learning adapts the gradient step on the centres.
enum class StepRule {
  /// A step is kept only when the training error does not grow (kappa +10 %), else retried with
  /// kappa halved (up to 4 tries): the training error never increases.
  kGuarded = 0,
  /// Jang (1993), section V: every step is taken; kappa +10 % after four reductions of the error
  /// in a row, -10 % after two increase-reduction alternations in a row. Plain ANFIS.
  kJang = 1,
};

/// The rectangle a fuzzy surface is identified over [m].
struct Extent2d {
  Eigen::Vector2d min_m = Eigen::Vector2d::Zero();
  Eigen::Vector2d max_m = Eigen::Vector2d::Zero();
};

/// Parameters of fit_fuzzy_elevation_map. Defaults: the paper's 19 x 10 rule model.
struct FuzzyParams {
  int rules_x = 19;  ///< MFs (rule columns) along x, >= 2
  int rules_y = 10;  ///< MFs (rule rows) along y, >= 2
  MembershipFamily membership = MembershipFamily::kTriangularPartition;
  /// Gaussian width s as a fraction of the initial centre spacing, > 0 (kGaussian only).
  double gaussian_width = 0.5;
  /// Hybrid-learning epochs, 0..100000; 0 = least squares only on uniformly spaced centres.
  int epochs = 10;
  StepRule step_rule = StepRule::kGuarded;
  /// Initial gradient step kappa as a fraction of the smaller initial centre spacing, > 0.
  double learning_rate = 0.1;
  /// Ridge weight lambda = ridge * (training points / rules), >= 0: pulls rules with little data
  /// towards the mean elevation.
  double ridge = 1e-4;
  /// Smoothness weight mu = smoothness * (training points / rules), >= 0: penalises differences
  /// between the consequents of neighbouring rules, so rules with little data (at the edge of a
  /// shadow, between sparse scan rings) follow their neighbours instead of overshooting.
  /// ridge = smoothness = 0 needs data under every rule.
  double smoothness = 0.05;
  /// Area the surface is fitted over; unset: the bounding box of the points. Points outside
  /// take no part; centres are kept inside it, ordered and at least 5 % of a spacing apart.
  std::optional<Extent2d> extent;
  /// The fit needs at least this many points per rule on average, >= 0 (and at least one per rule).
  double min_points_per_rule = 2.0;
  /// to_layer leaves cells whose confidence is below this empty [points], >= 0.
  double min_confidence = 3.0;
};

/// Throws std::invalid_argument naming the first field out of range; fitting a FuzzyElevationMap calls it first, and a
/// configuration can call it before the first scan.
void check_fuzzy_params(const FuzzyParams& params);

/// A zero-order Takagi-Sugeno fuzzy surface z = f(x, y); see the top of this header.
class FuzzyElevationMap {
 public:
  FuzzyElevationMap() = default;
  /// A surface from explicit parameters: strictly increasing centres inside `params.extent`
  /// (required), consequents as a (rules_x, rules_y) matrix; `rule_support` (optional, same shape)
  /// is the confidence of each rule [points]; `rmse_history` and `num_training_points` (optional)
  /// the training record of a fitted map whose parts these are (a map read back, e.g. unpickled).
  /// Throws std::invalid_argument on inconsistent sizes.
  FuzzyElevationMap(const FuzzyParams& params, Eigen::VectorXd centers_x, Eigen::VectorXd centers_y,
                    Eigen::MatrixXd consequents, Eigen::MatrixXd rule_support = {},
                    std::vector<double> rmse_history = {}, std::size_t num_training_points = 0);

  const FuzzyParams& params() const { return params_; }
  const Extent2d& extent() const { return extent_; }
  int num_rules() const { return static_cast<int>(consequents_.size()); }
  /// Consequents plus one centre per MF: 219 for the paper's 19 x 10 model.
  int num_parameters() const { return num_rules() + static_cast<int>(centers_x_.size() + centers_y_.size()); }
  const Eigen::VectorXd& centers_x() const { return centers_x_; }  ///< MF centres along x [m]
  const Eigen::VectorXd& centers_y() const { return centers_y_; }  ///< MF centres along y [m]
  /// c_ij [m], rows i along x, columns j along y.
  const Eigen::MatrixXd& consequents() const { return consequents_; }
  /// Sum of the firing strengths of the training points per rule [points], (rules_x, rules_y).
  const Eigen::MatrixXd& rule_support() const { return rule_support_; }
  /// Training RMSE [m]: entry 0 after the initial least-squares fit, then one per epoch.
  const std::vector<double>& rmse_history() const { return rmse_history_; }
  std::size_t num_training_points() const { return num_training_points_; }
  /// Width s of the Gaussian MFs along x and y [m] (0 for triangles).
  const Eigen::Vector2d& gaussian_sigma_m() const { return sigma_m_; }

  /// f(x, y) [m]. Outside the extent the surface continues as it is at the border; NaN for a
  /// default-constructed (empty) map.
  double evaluate(double x, double y) const;
  /// f at each row (x, y) of `xy`.
  Eigen::VectorXd evaluate(const Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::RowMajor>>& xy) const;
  /// How much data supported the rules firing at (x, y): sum_ij a_i(x) b_j(y) support_ij
  /// [points]; 0 outside the extent.
  double confidence(double x, double y) const;
  Eigen::VectorXd confidence(
      const Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::RowMajor>>& xy) const;
  /// Adds `name` (f at the cell centres, NaN where the confidence is below `min_confidence`) and
  /// `name + "_confidence"` to `map`. min_confidence < 0: params().min_confidence.
  void to_layer(ElevationMap& map, double min_confidence = -1.0, const std::string& name = "fem") const;

 private:
  friend struct FuzzyFitter;
  void set_gaussian_sigma();

  FuzzyParams params_;
  Extent2d extent_;
  Eigen::VectorXd centers_x_, centers_y_;
  Eigen::MatrixXd consequents_, rule_support_;
  Eigen::Vector2d sigma_m_ = Eigen::Vector2d::Zero();
  std::vector<double> rmse_history_;
  std::size_t num_training_points_ = 0;
};

/// Identifies a fuzzy elevation map from the points (x, y, z) [m] by hybrid learning. `use`
/// (optional, one flag per point; e.g. the points collapse_overhangs kept) selects the points.
/// Deterministic: no randomness, same input -> bit-identical model. Throws std::invalid_argument
/// on invalid parameters, NaN/Inf rows, a degenerate extent or too few points for the rule grid.
FuzzyElevationMap fit_fuzzy_elevation_map(const PointsView<float>& points, const FuzzyParams& params = {},
                                          const std::vector<std::uint8_t>* use = nullptr);
FuzzyElevationMap fit_fuzzy_elevation_map(const PointsView<double>& points, const FuzzyParams& params = {},
                                          const std::vector<std::uint8_t>* use = nullptr);

}  // namespace terracube
