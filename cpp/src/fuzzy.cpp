#include "terracube/fuzzy.hpp"

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

namespace terracube {

namespace {

/// The most hybrid-learning epochs one fit runs (see check_fuzzy_params).
constexpr int kMaxEpochs = 100000;

/// MFs evaluated per coordinate: 2 for triangles, the 5 nearest for Gaussians.
constexpr int kWindow = 5;
constexpr int kGaussianHalfWindow = 2;
/// Centres stay this fraction of the initial spacing apart.
constexpr double kMinGapFraction = 0.05;
constexpr int kMaxStepTries = 4;

/// Jang (1993), section V: the step length grows by 10 % after four reductions of the error in a
/// row and shrinks by 10 % after two increase-reduction alternations in a row. `changes` holds
/// whether each earlier step raised the error; `raised` is this step's.
double jang_step_factor(bool raised, std::vector<bool>& changes) {
  changes.push_back(raised);
  const std::size_t n = changes.size();
  if (n >= 4 && !changes[n - 1] && !changes[n - 2] && !changes[n - 3] && !changes[n - 4]) {
    changes.clear();
    return 1.1;
  }
  if (n >= 4 && changes[n - 1] != changes[n - 2] && changes[n - 2] != changes[n - 3] &&
      changes[n - 3] != changes[n - 4]) {
    changes.clear();
    return 0.9;
  }
  return 1.0;
}

/// The normalised degrees of the MFs of one axis at one coordinate: MFs first..first+count-1.
struct AxisWindow {
  int first = 0;
  int count = 0;
  double degree[kWindow] = {};
  double t = 0.0;  ///< triangles: position between centres first and first + 1, in [0, 1)
  double h = 0.0;  ///< triangles: their distance [m]
};

AxisWindow axis_window(const Eigen::VectorXd& centers, MembershipFamily family, double sigma, double u) {
  AxisWindow w;
  const auto m = static_cast<int>(centers.size());
  const double* c = centers.data();
  // upper: the first centre above u.
  const auto upper = static_cast<int>(std::upper_bound(c, c + m, u) - c);
  if (family == MembershipFamily::kTriangularPartition) {
    if (upper == 0 || upper == m) {  // beyond the outer centres: the outer MF alone (degree 1)
      w.first = upper == 0 ? 0 : m - 1;
      w.count = 1;
      w.degree[0] = 1.0;
      return w;
    }
    w.first = upper - 1;
    w.count = 2;
    w.h = c[upper] - c[upper - 1];
    w.t = (u - c[upper - 1]) / w.h;
    w.degree[0] = 1.0 - w.t;
    w.degree[1] = w.t;
    return w;
  }
  int nearest = upper == 0 ? 0 : upper - 1;
  if (upper < m && c[upper] - u < u - c[nearest]) nearest = upper;
  w.first = std::max(0, nearest - kGaussianHalfWindow);
  const int last = std::min(m - 1, nearest + kGaussianHalfWindow);
  w.count = last - w.first + 1;
  double sum = 0.0;
  const double inverse = 1.0 / (2.0 * sigma * sigma);
  for (int k = 0; k < w.count; ++k) {
    const double d = u - c[w.first + k];
    w.degree[k] = std::exp(-d * d * inverse);
    sum += w.degree[k];
  }
  for (int k = 0; k < w.count; ++k) w.degree[k] /= sum;  // the nearest MF has degree 1: sum >= 1
  return w;
}

/// Adds weight * d f / d centre_k for the MFs of one axis to grad, where f = sum_k degree_k G_k
/// (G_k: the other axis already summed out) and z = f.
void add_axis_gradient(const AxisWindow& w, const Eigen::VectorXd& centers, MembershipFamily family, double sigma,
                       double u, const double* g, double z, double weight, double* grad) {
  if (family == MembershipFamily::kTriangularPartition) {
    if (w.count < 2) return;                            // clamped beyond the outer centres: f does not depend on them
    const double slope = (g[1] - g[0]) * weight / w.h;  // d f / d t, t = (u - c_k) / (c_k+1 - c_k)
    grad[w.first] += slope * (w.t - 1.0);
    grad[w.first + 1] += slope * -w.t;
    return;
  }
  // Normalised Gaussians: d a_k / d c_m = a_k (delta_km - a_m) (u - c_m) / s^2, so
  // d f / d c_m = a_m (u - c_m) / s^2 (G_m - f).
  const double inverse = 1.0 / (sigma * sigma);
  for (int k = 0; k < w.count; ++k) {
    grad[w.first + k] += weight * w.degree[k] * (u - centers[w.first + k]) * inverse * (g[k] - z);
  }
}

/// Keeps centres inside [lo, hi], increasing and at least `gap` apart.
void project_centers(Eigen::VectorXd& c, double lo, double hi, double gap) {
  const Eigen::Index m = c.size();
  c[0] = std::max(c[0], lo);
  for (Eigen::Index k = 1; k < m; ++k) c[k] = std::max(c[k], c[k - 1] + gap);
  c[m - 1] = std::min(c[m - 1], hi);
  for (Eigen::Index k = m - 2; k >= 0; --k) c[k] = std::min(c[k], c[k + 1] - gap);
}

}  // namespace

void check_fuzzy_params(const FuzzyParams& p) {
  if (p.rules_x < 2 || p.rules_y < 2) {
    throw std::invalid_argument("a fuzzy elevation map needs at least 2 x 2 rules, got " + std::to_string(p.rules_x) +
                                " x " + std::to_string(p.rules_y));
  }
  if (static_cast<double>(p.rules_x) * p.rules_y > 1e7) {
    throw std::invalid_argument("too many rules: " + std::to_string(p.rules_x) + " x " + std::to_string(p.rules_y));
  }
  if (p.membership != MembershipFamily::kTriangularPartition && p.membership != MembershipFamily::kGaussian) {
    throw std::invalid_argument("unknown membership family");
  }
  if (!(p.gaussian_width > 0.0) || !std::isfinite(p.gaussian_width)) {
    throw std::invalid_argument("gaussian_width must be a positive fraction of the centre spacing");
  }
  // Every epoch is run (no early stop) and keeps its RMSE: 10^9 epochs ran for days and grew the
  // history without bound. Hybrid learning settles within tens to hundreds of epochs.
  if (p.epochs < 0 || p.epochs > kMaxEpochs) {
    throw std::invalid_argument("epochs must be 0.." + std::to_string(kMaxEpochs) + ", got " +
                                std::to_string(p.epochs));
  }
  if (!(p.learning_rate > 0.0) || !std::isfinite(p.learning_rate)) {
    throw std::invalid_argument("learning_rate must be a positive finite fraction of the centre spacing");
  }
  if (!(p.ridge >= 0.0) || !std::isfinite(p.ridge)) throw std::invalid_argument("ridge must be finite and >= 0");
  if (!(p.smoothness >= 0.0) || !std::isfinite(p.smoothness)) {
    throw std::invalid_argument("smoothness must be finite and >= 0");
  }
  if (!(p.min_points_per_rule >= 0.0) || !std::isfinite(p.min_points_per_rule)) {
    throw std::invalid_argument("min_points_per_rule must be finite and >= 0");
  }
  if (!(p.min_confidence >= 0.0) || !std::isfinite(p.min_confidence)) {
    throw std::invalid_argument("min_confidence must be finite and >= 0 [points]");
  }
  if (p.extent) {
    const Extent2d& e = *p.extent;
    if (!e.min_m.allFinite() || !e.max_m.allFinite() || !(e.max_m.x() > e.min_m.x()) || !(e.max_m.y() > e.min_m.y())) {
      throw std::invalid_argument("extent must be finite with max > min along x and y");
    }
  }
}

namespace {

using RowsXY = Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::RowMajor>>;

}  // namespace

/// The training points and one pass over them per quantity the hybrid learning needs.
struct FuzzyFitter {
  FuzzyElevationMap& model;
  std::vector<double> x, y, z;

  double sigma_x() const { return model.sigma_m_.x(); }
  double sigma_y() const { return model.sigma_m_.y(); }
  MembershipFamily family() const { return model.params_.membership; }

  /// Sum of squared errors with the model's current parameters.
  double squared_error() const {
    double sse = 0.0;
    for (std::size_t p = 0; p < z.size(); ++p) {
      const double e = model.evaluate(x[p], y[p]) - z[p];
      sse += e * e;
    }
    return sse;
  }

  /// Gradient of the squared error with respect to the centres (consequents fixed).
  void centre_gradient(Eigen::VectorXd& grad_x, Eigen::VectorXd& grad_y) const {
    grad_x.setZero(model.centers_x_.size());
    grad_y.setZero(model.centers_y_.size());
    const Eigen::MatrixXd& c = model.consequents_;
    for (std::size_t p = 0; p < z.size(); ++p) {
      const AxisWindow wx = axis_window(model.centers_x_, family(), sigma_x(), x[p]);
      const AxisWindow wy = axis_window(model.centers_y_, family(), sigma_y(), y[p]);
      double g[kWindow] = {};  // G_a = sum_b b_b c_ab: f as a function of the x MFs
      double h[kWindow] = {};  // H_b = sum_a a_a c_ab
      double f = 0.0;
      for (int a = 0; a < wx.count; ++a) {
        for (int b = 0; b < wy.count; ++b) {
          const double rule = c(wx.first + a, wy.first + b);
          g[a] += wy.degree[b] * rule;
          h[b] += wx.degree[a] * rule;
        }
        f += wx.degree[a] * g[a];
      }
      const double weight = 2.0 * (f - z[p]);
      add_axis_gradient(wx, model.centers_x_, family(), sigma_x(), x[p], g, f, weight, grad_x.data());
      add_axis_gradient(wy, model.centers_y_, family(), sigma_y(), y[p], h, f, weight, grad_y.data());
    }
  }

  /// Reorders the points by the cell of the initial centre grid (a counting sort): the searches
  /// for each point's MFs then branch predictably, which makes every pass several times faster.
  void sort_by_rule_cell(const FuzzyParams& params, const Extent2d& extent) {
    const int cells_x = params.rules_x - 1;
    const int cells_y = params.rules_y - 1;
    const auto bin = [](double u, double lo, double hi, int cells) {
      const double f = std::floor((u - lo) / (hi - lo) * cells);
      return static_cast<std::size_t>(std::clamp(f, 0.0, static_cast<double>(cells - 1)));
    };
    std::vector<std::size_t> key(z.size());
    std::vector<std::size_t> start(static_cast<std::size_t>(cells_x) * cells_y + 1, 0);
    for (std::size_t p = 0; p < z.size(); ++p) {
      key[p] = bin(x[p], extent.min_m.x(), extent.max_m.x(), cells_x) * cells_y +
               bin(y[p], extent.min_m.y(), extent.max_m.y(), cells_y);
      ++start[key[p] + 1];
    }
    for (std::size_t k = 1; k < start.size(); ++k) start[k] += start[k - 1];
    std::vector<double> sx(z.size()), sy(z.size()), sz(z.size());
    for (std::size_t p = 0; p < z.size(); ++p) {
      const std::size_t to = start[key[p]]++;
      sx[to] = x[p];
      sy[to] = y[p];
      sz[to] = z[p];
    }
    x.swap(sx);
    y.swap(sy);
    z.swap(sz);
  }

  /// Hybrid learning over `extent` (see the header) on the collected points.
  void train(const FuzzyParams& params, const Extent2d& extent) {
    model.params_ = params;
    model.params_.extent = extent;
    model.extent_ = extent;
    model.centers_x_ = Eigen::VectorXd::LinSpaced(params.rules_x, extent.min_m.x(), extent.max_m.x());
    model.centers_y_ = Eigen::VectorXd::LinSpaced(params.rules_y, extent.min_m.y(), extent.max_m.y());
    model.set_gaussian_sigma();
    model.num_training_points_ = z.size();
    sort_by_rule_cell(params, extent);
    const double n = static_cast<double>(z.size());
    double mean_z = 0.0;
    for (const double v : z) mean_z += v;
    mean_z /= n;
    const double ridge_weight = params.ridge * n / (params.rules_x * params.rules_y);
    const double smoothness_weight = params.smoothness * n / (params.rules_x * params.rules_y);

    model.consequents_ = least_squares(ridge_weight, smoothness_weight, mean_z);
    double sse = squared_error();
    model.rmse_history_.push_back(std::sqrt(sse / n));

    const Eigen::Vector2d spacing((extent.max_m.x() - extent.min_m.x()) / (params.rules_x - 1),
                                  (extent.max_m.y() - extent.min_m.y()) / (params.rules_y - 1));
    double kappa = params.learning_rate * spacing.minCoeff();  // step length [m] (Jang's k)
    Eigen::VectorXd grad_x, grad_y;
    std::vector<bool> changes;  // StepRule::kJang: whether each step raised the error, oldest first
    for (int epoch = 0; epoch < params.epochs; ++epoch) {
      // Backward pass: a normalised gradient step on the centres, consequents fixed.
      centre_gradient(grad_x, grad_y);
      const double norm = std::sqrt(grad_x.squaredNorm() + grad_y.squaredNorm());
      if (norm > 0.0 && std::isfinite(norm)) {
        const Eigen::VectorXd old_x = model.centers_x_;
        const Eigen::VectorXd old_y = model.centers_y_;
        bool accepted = false;
        if (params.step_rule == StepRule::kJang) {
          model.centers_x_ = old_x - (kappa / norm) * grad_x;
          model.centers_y_ = old_y - (kappa / norm) * grad_y;
          project_centers(model.centers_x_, extent.min_m.x(), extent.max_m.x(), kMinGapFraction * spacing.x());
          project_centers(model.centers_y_, extent.min_m.y(), extent.max_m.y(), kMinGapFraction * spacing.y());
          const double trial = squared_error();
          kappa *= jang_step_factor(trial > sse, changes);
          sse = trial;
          accepted = true;
        }
        for (int attempt = 0; attempt < kMaxStepTries && !accepted; ++attempt) {
          model.centers_x_ = old_x - (kappa / norm) * grad_x;
          model.centers_y_ = old_y - (kappa / norm) * grad_y;
          project_centers(model.centers_x_, extent.min_m.x(), extent.max_m.x(), kMinGapFraction * spacing.x());
          project_centers(model.centers_y_, extent.min_m.y(), extent.max_m.y(), kMinGapFraction * spacing.y());
          const double trial = squared_error();
          if (trial <= sse) {
            sse = trial;
            kappa *= 1.1;
            accepted = true;
          } else {
            kappa *= 0.5;
          }
        }
        if (!accepted) {
          model.centers_x_ = old_x;
          model.centers_y_ = old_y;
        }
      }
      // Forward pass: least-squares consequents for the new centres (and their rule support), kept
      // unless the ridge term made the training error worse.
      const Eigen::MatrixXd old_consequents = model.consequents_;
      model.consequents_ = least_squares(ridge_weight, smoothness_weight, mean_z);
      const double refit = squared_error();
      if (refit <= sse) {
        sse = refit;
      } else {
        model.consequents_ = old_consequents;
      }
      model.rmse_history_.push_back(std::sqrt(sse / n));
    }
  }

  /// Rule support and the ridge least-squares consequents for the current centres.
  Eigen::MatrixXd least_squares(double ridge_weight, double smoothness_weight, double mean_z) {
    const auto rx = static_cast<int>(model.centers_x_.size());
    const auto ry = static_cast<int>(model.centers_y_.size());
    const int rules = rx * ry;
    // Two rules fired by one point lie at most `band` MFs apart along each axis.
    const int band = family() == MembershipFamily::kTriangularPartition ? 1 : 2 * kGaussianHalfWindow;
    const int side = 2 * band + 1;
    std::vector<double> normal(static_cast<std::size_t>(rules) * side * side, 0.0);
    Eigen::VectorXd rhs = Eigen::VectorXd::Zero(rules);
    Eigen::MatrixXd support = Eigen::MatrixXd::Zero(rx, ry);
    double w[kWindow * kWindow];
    int index[kWindow * kWindow];
    int rule_i[kWindow * kWindow];
    int rule_j[kWindow * kWindow];
    for (std::size_t p = 0; p < z.size(); ++p) {
      const AxisWindow wx = axis_window(model.centers_x_, family(), sigma_x(), x[p]);
      const AxisWindow wy = axis_window(model.centers_y_, family(), sigma_y(), y[p]);
      int n = 0;
      for (int a = 0; a < wx.count; ++a) {
        for (int b = 0; b < wy.count; ++b, ++n) {
          w[n] = wx.degree[a] * wy.degree[b];
          rule_i[n] = wx.first + a;
          rule_j[n] = wy.first + b;
          index[n] = rule_i[n] * ry + rule_j[n];
          support(wx.first + a, wy.first + b) += w[n];
          rhs[index[n]] += w[n] * z[p];
        }
      }
      for (int k = 0; k < n; ++k) {
        double* row = normal.data() + static_cast<std::size_t>(index[k]) * side * side;
        for (int l = 0; l < n; ++l) {
          row[(rule_i[l] - rule_i[k] + band) * side + rule_j[l] - rule_j[k] + band] += w[k] * w[l];
        }
      }
    }
    std::vector<Eigen::Triplet<double>> entries;
    entries.reserve(static_cast<std::size_t>(rules) * side * side);
    for (int r = 0; r < rules; ++r) {
      const int i = r / ry;
      const int j = r % ry;
      const double* row = normal.data() + static_cast<std::size_t>(r) * side * side;
      for (int di = -band; di <= band; ++di) {
        for (int dj = -band; dj <= band; ++dj) {
          const double value = row[(di + band) * side + dj + band];
          if (value != 0.0) entries.emplace_back(r, (i + di) * ry + j + dj, value);
        }
      }
      entries.emplace_back(r, r, ridge_weight);
      rhs[r] += ridge_weight * mean_z;
      // Smoothness: smoothness_weight * (c_r - c_s)^2 for the neighbours s of r along x and y.
      if (smoothness_weight > 0.0) {
        const int neighbours[4][2] = {{i - 1, j}, {i + 1, j}, {i, j - 1}, {i, j + 1}};
        for (const auto& [a, b] : neighbours) {
          if (a < 0 || b < 0 || a >= rx || b >= ry) continue;
          entries.emplace_back(r, r, smoothness_weight);
          entries.emplace_back(r, a * ry + b, -smoothness_weight);
        }
      }
    }
    Eigen::SparseMatrix<double> matrix(rules, rules);
    matrix.setFromTriplets(entries.begin(), entries.end());
    Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> solver(matrix);
    Eigen::VectorXd solution;
    if (solver.info() == Eigen::Success) solution = solver.solve(rhs);
    if (solver.info() != Eigen::Success || !solution.allFinite()) {
      throw std::invalid_argument(
          "the least-squares problem for the consequents is singular: some rules have no data; "
          "set ridge or smoothness > 0, or use fewer rules");
    }
    model.rule_support_ = std::move(support);
    return Eigen::Map<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>(solution.data(), rx,
                                                                                                    ry);
  }
};

void FuzzyElevationMap::set_gaussian_sigma() {
  sigma_m_.setZero();
  if (params_.membership != MembershipFamily::kGaussian) return;
  const Eigen::Vector2d length = extent_.max_m - extent_.min_m;
  sigma_m_.x() = params_.gaussian_width * length.x() / (params_.rules_x - 1);
  sigma_m_.y() = params_.gaussian_width * length.y() / (params_.rules_y - 1);
}

FuzzyElevationMap::FuzzyElevationMap(const FuzzyParams& params, Eigen::VectorXd centers_x, Eigen::VectorXd centers_y,
                                     Eigen::MatrixXd consequents, Eigen::MatrixXd rule_support,
                                     std::vector<double> rmse_history, std::size_t num_training_points)
    : params_(params),
      centers_x_(std::move(centers_x)),
      centers_y_(std::move(centers_y)),
      consequents_(std::move(consequents)),
      rule_support_(std::move(rule_support)),
      rmse_history_(std::move(rmse_history)),
      num_training_points_(num_training_points) {
  if (!params_.extent) throw std::invalid_argument("a fuzzy elevation map from parameters needs params.extent");
  params_.rules_x = static_cast<int>(centers_x_.size());
  params_.rules_y = static_cast<int>(centers_y_.size());
  check_fuzzy_params(params_);
  extent_ = *params_.extent;
  const auto check_axis = [](const Eigen::VectorXd& c, double lo, double hi, const char* axis) {
    for (Eigen::Index k = 0; k < c.size(); ++k) {
      if (!std::isfinite(c[k]) || c[k] < lo || c[k] > hi || (k > 0 && !(c[k] > c[k - 1]))) {
        throw std::invalid_argument(std::string("centres along ") + axis +
                                    " must be finite, strictly increasing and inside the extent");
      }
    }
  };
  check_axis(centers_x_, extent_.min_m.x(), extent_.max_m.x(), "x");
  check_axis(centers_y_, extent_.min_m.y(), extent_.max_m.y(), "y");
  if (consequents_.rows() != centers_x_.size() || consequents_.cols() != centers_y_.size() ||
      !consequents_.allFinite()) {
    throw std::invalid_argument("consequents must be a finite (" + std::to_string(centers_x_.size()) + ", " +
                                std::to_string(centers_y_.size()) + ") matrix, one per rule");
  }
  if (rule_support_.size() == 0) {
    rule_support_ = Eigen::MatrixXd::Zero(consequents_.rows(), consequents_.cols());
  } else if (rule_support_.rows() != consequents_.rows() || rule_support_.cols() != consequents_.cols()) {
    throw std::invalid_argument("rule_support must have the shape of the consequents");
  }
  set_gaussian_sigma();
}

double FuzzyElevationMap::evaluate(double x, double y) const {
  if (consequents_.size() == 0) return std::numeric_limits<double>::quiet_NaN();  // default-constructed
  const AxisWindow wx = axis_window(centers_x_, params_.membership, sigma_m_.x(), x);
  const AxisWindow wy = axis_window(centers_y_, params_.membership, sigma_m_.y(), y);
  double f = 0.0;
  for (int a = 0; a < wx.count; ++a) {
    double g = 0.0;
    for (int b = 0; b < wy.count; ++b) g += wy.degree[b] * consequents_(wx.first + a, wy.first + b);
    f += wx.degree[a] * g;
  }
  return f;
}

double FuzzyElevationMap::confidence(double x, double y) const {
  if (consequents_.size() == 0) return 0.0;
  if (!(x >= extent_.min_m.x() && x <= extent_.max_m.x() && y >= extent_.min_m.y() && y <= extent_.max_m.y())) {
    return 0.0;
  }
  const AxisWindow wx = axis_window(centers_x_, params_.membership, sigma_m_.x(), x);
  const AxisWindow wy = axis_window(centers_y_, params_.membership, sigma_m_.y(), y);
  double total = 0.0;
  for (int a = 0; a < wx.count; ++a) {
    for (int b = 0; b < wy.count; ++b) {
      total += wx.degree[a] * wy.degree[b] * rule_support_(wx.first + a, wy.first + b);
    }
  }
  return total;
}

Eigen::VectorXd FuzzyElevationMap::evaluate(const RowsXY& xy) const {
  Eigen::VectorXd out(xy.rows());
  for (Eigen::Index r = 0; r < xy.rows(); ++r) out[r] = evaluate(xy(r, 0), xy(r, 1));
  return out;
}

Eigen::VectorXd FuzzyElevationMap::confidence(const RowsXY& xy) const {
  Eigen::VectorXd out(xy.rows());
  for (Eigen::Index r = 0; r < xy.rows(); ++r) out[r] = confidence(xy(r, 0), xy(r, 1));
  return out;
}

void FuzzyElevationMap::to_layer(ElevationMap& map, double min_confidence, const std::string& name) const {
  if (consequents_.size() == 0) throw std::invalid_argument("the fuzzy elevation map has no rules");
  if (!std::isfinite(min_confidence)) throw std::invalid_argument("min_confidence must be finite");
  const double threshold = min_confidence < 0.0 ? params_.min_confidence : min_confidence;
  const MapGeometry& g = map.geometry();
  Layer height(g.size.x(), g.size.y());
  Layer confidence_layer(g.size.x(), g.size.y());
  for (int i = 0; i < g.size.x(); ++i) {
    for (int j = 0; j < g.size.y(); ++j) {
      const Eigen::Vector2d p = g.position_of({i, j});
      const double support = confidence(p.x(), p.y());
      confidence_layer(i, j) = static_cast<float>(support);
      height(i, j) = support >= threshold && support > 0.0 ? static_cast<float>(evaluate(p.x(), p.y()))
                                                           : std::numeric_limits<float>::quiet_NaN();
    }
  }
  map.add(name, std::move(height));
  map.add(name + "_confidence", std::move(confidence_layer));
}

namespace {

template <typename Scalar>
FuzzyElevationMap fit_impl(const PointsView<Scalar>& points, const FuzzyParams& params,
                           const std::vector<std::uint8_t>* use) {
  check_fuzzy_params(params);
  if (points.size > 0 && points.data == nullptr) throw std::invalid_argument("points view has no data");
  if (use && use->size() != points.size) {
    throw std::invalid_argument("the point selection has " + std::to_string(use->size()) + " flags for " +
                                std::to_string(points.size) + " points");
  }
  FuzzyElevationMap model;
  FuzzyFitter fit{model, {}, {}, {}};
  // Selected rows inside the extent; NaN/Inf rows are an error.
  std::size_t non_finite = 0;
  std::size_t first_non_finite = 0;
  Extent2d box{Eigen::Vector2d::Constant(std::numeric_limits<double>::infinity()),
               Eigen::Vector2d::Constant(-std::numeric_limits<double>::infinity())};
  for (std::size_t row = 0; row < points.size; ++row) {
    if (use && (*use)[row] == 0) continue;
    const Eigen::Vector3d p = points.point(row);
    if (!p.allFinite()) {
      if (non_finite++ == 0) first_non_finite = row;
      continue;
    }
    if (params.extent && !(p.x() >= params.extent->min_m.x() && p.x() <= params.extent->max_m.x() &&
                           p.y() >= params.extent->min_m.y() && p.y() <= params.extent->max_m.y())) {
      continue;
    }
    box.min_m = box.min_m.cwiseMin(p.head<2>());
    box.max_m = box.max_m.cwiseMax(p.head<2>());
    fit.x.push_back(p.x());
    fit.y.push_back(p.y());
    fit.z.push_back(p.z());
  }
  if (non_finite > 0) {
    throw std::invalid_argument(std::to_string(non_finite) + " of " + std::to_string(points.size) +
                                " point rows contain NaN or Inf (first at row " + std::to_string(first_non_finite) +
                                "); clean the cloud first");
  }
  const int rules = params.rules_x * params.rules_y;
  const double needed = std::max(static_cast<double>(rules), params.min_points_per_rule * rules);
  if (static_cast<double>(fit.z.size()) < needed) {
    throw std::invalid_argument(
        "too few points for the rule grid: " + std::to_string(fit.z.size()) + " points inside the extent for " +
        std::to_string(params.rules_x) + " x " + std::to_string(params.rules_y) + " = " + std::to_string(rules) +
        " rules; need at least " + std::to_string(static_cast<long long>(std::ceil(needed))) +
        " (min_points_per_rule = " + std::to_string(params.min_points_per_rule) + "); use fewer rules or more points");
  }
  const Extent2d extent = params.extent ? *params.extent : box;
  if (!(extent.max_m.x() > extent.min_m.x()) || !(extent.max_m.y() > extent.min_m.y())) {
    throw std::invalid_argument("the points span no area (all x or all y equal); give an extent");
  }
  fit.train(params, extent);
  return model;  // rule_support_ is that of the final centres: least_squares ran on them last
}

}  // namespace

FuzzyElevationMap fit_fuzzy_elevation_map(const PointsView<float>& points, const FuzzyParams& params,
                                          const std::vector<std::uint8_t>* use) {
  return fit_impl(points, params, use);
}

FuzzyElevationMap fit_fuzzy_elevation_map(const PointsView<double>& points, const FuzzyParams& params,
                                          const std::vector<std::uint8_t>* use) {
  return fit_impl(points, params, use);
}

}  // namespace terracube
