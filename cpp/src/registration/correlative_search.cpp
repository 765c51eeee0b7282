// Correlative yaw x translation search on classified points (not in [TC]): the start of the
// registration (RegistrationParams::correlative_search) and of the Mapper's loop closing.
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <utility>
#include <vector>

#include "cloud_frame.hpp"
#include "number_text.hpp"
#include "terracube/icp.hpp"

namespace terracube {

namespace {

/// The most (yaw, translation) candidates one search scores (each keeps 40 bytes: 160 MB).
constexpr double kMaxCandidates = 4e6;

}  // namespace

void check_correlative_search_params(const CorrelativeSearchParams& p) {
  const auto positive = [](double v) { return v > 0.0 && std::isfinite(v); };
  if (!positive(p.window_m)) throw std::invalid_argument("correlative search window_m must be positive and finite [m]");
  if (!positive(p.cell_m)) throw std::invalid_argument("correlative search cell_m must be positive and finite [m]");
  if (p.window_m / p.cell_m > 4096.0) {
    throw std::invalid_argument("correlative search window_m / cell_m must be at most 4096 cells");
  }
  if (p.step_cells < 1) throw std::invalid_argument("correlative search step_cells must be at least 1");
  if (!(p.yaw_window_rad >= 0.0 && p.yaw_window_rad <= 3.2)) {
    throw std::invalid_argument("correlative search yaw_window_rad must lie in [0, 3.2] [rad]");
  }
  if (p.yaw_hypotheses < 1) throw std::invalid_argument("correlative search yaw_hypotheses must be at least 1");
  // Every (yaw, translation) candidate is scored and kept: bound them (the defaults: 15 x 11^2).
  const double per_axis = 2.0 * std::floor(std::ceil(p.window_m / p.cell_m - 1e-9) / p.step_cells) + 1.0;
  const double candidates = per_axis * per_axis * p.yaw_hypotheses;
  if (candidates > kMaxCandidates) {
    throw std::invalid_argument(
        "correlative search: " + std::to_string(p.yaw_hypotheses) + " yaw hypotheses x " +
        detail::number_text(per_axis) + "^2 translations is " + detail::number_text(candidates) + " candidates, over " +
        detail::number_text(kMaxCandidates) + "; use fewer yaw hypotheses, a larger cell or step, or a smaller window");
  }
  if (!(p.tie_tolerance >= 0.0 && p.tie_tolerance < 1.0)) {
    throw std::invalid_argument("correlative search tie_tolerance must lie in [0, 1)");
  }
}

namespace {

// The occupancy grid's size limit (bytes): beyond it the search returns the guess.
constexpr double kMaxGridCells = 2.5e8;

bool takes_part(std::uint8_t terrain_class) {
  return terrain_class >= static_cast<std::uint8_t>(TerrainClass::kObstacle);
}

}  // namespace

namespace {

/// The target's non-ground cells, each with its eight neighbours, on a grid of `cell` with a margin
/// of 2 * window + 2 cells: a source point whose cell lies within `window` of the grid's edge can
/// never reach an occupied cell, and the others never leave the grid, so scoring needs no bounds
/// checks.
struct OccupancyGrid {
  double cell = 0.0;
  int window = 0;
  Eigen::Vector2d origin;
  std::int64_t nx = 0, ny = 0;
  std::vector<std::uint8_t> occupied;  ///< cell (a, b) at a * ny + b

  /// Empty (nx = 0) when the grid would exceed kMaxGridCells.
  OccupancyGrid(const std::vector<Eigen::Vector2d>& fixed, const Eigen::Vector2d& low, const Eigen::Vector2d& high,
                const CorrelativeSearchParams& params)
      : cell(params.cell_m), window(static_cast<int>(std::ceil(params.window_m / params.cell_m - 1e-9))) {
    const int margin = 2 * window + 2;
    origin = ((low / cell).array().floor() - margin).matrix() * cell;
    const auto extent = [&](double lo, double hi) {  // in cells, as a double (checked before any cast)
      return std::floor(hi / cell) - std::floor(lo / cell) + 1.0 + 2.0 * margin;
    };
    const double cells_x = extent(low.x(), high.x()), cells_y = extent(low.y(), high.y());
    if (!(cells_x * cells_y <= kMaxGridCells)) return;  // too large to search
    nx = static_cast<std::int64_t>(cells_x);
    ny = static_cast<std::int64_t>(cells_y);
    occupied.assign(static_cast<std::size_t>(nx * ny), 0);
    for (const Eigen::Vector2d& q : fixed) {
      // Inside by construction, up to rounding: at 1e300 m the margin is lost in (low / cell) - margin,
      // and a target point could land on the grid's border (its neighbours beyond it). Such a point
      // is left out rather than written out of bounds.
      const double fa = std::floor((q.x() - origin.x()) / cell), fb = std::floor((q.y() - origin.y()) / cell);
      if (!(fa >= 1.0 && fa < cells_x - 1.0 && fb >= 1.0 && fb < cells_y - 1.0)) continue;
      const auto a = static_cast<std::int64_t>(fa), b = static_cast<std::int64_t>(fb);
      for (std::int64_t da = -1; da <= 1; ++da) {
        for (std::int64_t db = -1; db <= 1; ++db) occupied[static_cast<std::size_t>((a + da) * ny + b + db)] = 1;
      }
    }
  }
};

/// One hypothesis of the search and its score.
struct Hypothesis {
  std::size_t score;
  double distance;  // from the guess, in cells (a yaw step counting as one)
  double yaw;
  int dx, dy;
};

/// The cells of the source points (moved by r, t) that can score, each once with its points: points
/// in one cell score alike at every translation.
std::vector<std::pair<std::int64_t, std::uint32_t>> source_cells(const std::vector<Eigen::Vector2d>& moving,
                                                                 const Eigen::Matrix2d& r, const Eigen::Vector2d& t,
                                                                 const OccupancyGrid& grid) {
  std::vector<std::int64_t> base;  // per source point that can score: its cell's index
  base.reserve(moving.size());
  for (const Eigen::Vector2d& p : moving) {
    // In cells as doubles first: a point far outside the grid (a wild guess) must not overflow.
    const Eigen::Vector2d q = r * p + t;
    const double fa = std::floor((q.x() - grid.origin.x()) / grid.cell);
    const double fb = std::floor((q.y() - grid.origin.y()) / grid.cell);
    if (!(fa >= grid.window && fa < static_cast<double>(grid.nx - grid.window) && fb >= grid.window &&
          fb < static_cast<double>(grid.ny - grid.window))) {
      continue;
    }
    base.push_back(static_cast<std::int64_t>(fa) * grid.ny + static_cast<std::int64_t>(fb));
  }
  std::sort(base.begin(), base.end());
  std::vector<std::pair<std::int64_t, std::uint32_t>> cells;  // (cell index, points in it)
  for (std::size_t k = 0; k < base.size();) {
    std::size_t end = k + 1;
    while (end < base.size() && base[end] == base[k]) ++end;
    cells.push_back({base[k], static_cast<std::uint32_t>(end - k)});
    k = end;
  }
  return cells;
}

/// The hypothesis whose score lies within tie_tolerance of the best and nearest the guess (the
/// search moves a good guess only for a clearly better match); null when nothing scores.
const Hypothesis* choose(const std::vector<Hypothesis>& scored, double tie_tolerance) {
  std::size_t best_score = 0;
  for (const Hypothesis& h : scored) best_score = std::max(best_score, h.score);
  if (best_score == 0) return nullptr;
  const double floor = (1.0 - tie_tolerance) * static_cast<double>(best_score);
  const Hypothesis* chosen = nullptr;
  for (const Hypothesis& h : scored) {
    if (static_cast<double>(h.score) >= floor && (chosen == nullptr || h.distance < chosen->distance)) chosen = &h;
  }
  return chosen;
}

/// One level of the search: `hypotheses` yaws over +-yaw_window_rad about the source origin, then
/// translations of step_cells cells within +-window_m, scored on an occupancy grid of cell_m.
CorrelativeSearchResult search_level(const std::vector<Eigen::Vector2d>& moving,
                                     const std::vector<Eigen::Vector2d>& fixed, const Eigen::Vector2d& low,
                                     const Eigen::Vector2d& high, const Eigen::Matrix4d& guess,
                                     const CorrelativeSearchParams& params) {
  CorrelativeSearchResult result;
  result.transform = guess;
  result.points = moving.size();
  const OccupancyGrid grid(fixed, low, high, params);
  if (grid.nx == 0) return result;  // too large to search: the guess, score 0
  const int hypotheses = params.yaw_hypotheses;
  const int window = grid.window;
  std::vector<Hypothesis> scored;
  for (int h = 0; h < hypotheses; ++h) {
    const double fraction = hypotheses == 1 ? 0.0 : 2.0 * h / (hypotheses - 1) - 1.0;
    const double yaw = params.yaw_window_rad * fraction;
    Eigen::Matrix4d turned = guess;
    turned.topLeftCorner<3, 3>() =
        guess.topLeftCorner<3, 3>() * Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    const auto cells = source_cells(moving, turned.topLeftCorner<2, 2>(), turned.topRightCorner<2, 1>(), grid);
    const double steps = hypotheses == 1 ? 0.0 : fraction * (hypotheses - 1) / 2.0;
    for (int dx = -window; dx <= window; dx += params.step_cells) {
      for (int dy = -window; dy <= window; dy += params.step_cells) {
        const std::int64_t shift = static_cast<std::int64_t>(dx) * grid.ny + dy;
        std::size_t score = 0;
        for (const auto& [k, count] : cells) score += grid.occupied[static_cast<std::size_t>(k + shift)] * count;
        scored.push_back(
            {score, static_cast<double>(dx) * dx + static_cast<double>(dy) * dy + steps * steps, yaw, dx, dy});
      }
    }
  }
  const Hypothesis* chosen = choose(scored, params.tie_tolerance);
  if (chosen == nullptr) return result;
  result.transform.topLeftCorner<3, 3>() =
      guess.topLeftCorner<3, 3>() * Eigen::AngleAxisd(chosen->yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  result.transform(0, 3) += chosen->dx * grid.cell;
  result.transform(1, 3) += chosen->dy * grid.cell;
  result.score = chosen->score;
  return result;
}

}  // namespace

CorrelativeSearchResult correlative_search(const ClassifiedPoints& source, const ClassifiedPoints& target,
                                           const Eigen::Matrix4d& guess, const CorrelativeSearchParams& params) {
  check_correlative_search_params(params);
  detail::check_rigid_transform(guess, "correlative search guess");
  if (source.classes.size() != source.points.size() || target.classes.size() != target.points.size()) {
    throw std::invalid_argument("correlative search: points and classes differ in number");
  }
  std::vector<Eigen::Vector2d> moving, fixed;
  for (std::size_t k = 0; k < source.size(); ++k) {
    if (takes_part(source.classes[k])) moving.push_back(source.points[k].head<2>());
  }
  Eigen::Vector2d low = Eigen::Vector2d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector2d high = -low;
  for (std::size_t k = 0; k < target.size(); ++k) {
    if (!takes_part(target.classes[k])) continue;
    fixed.push_back(target.points[k].head<2>());
    low = low.cwiseMin(fixed.back());
    high = high.cwiseMax(fixed.back());
  }
  CorrelativeSearchResult result;
  result.transform = guess;
  result.points = moving.size();
  if (moving.empty() || fixed.empty()) return result;
  if (!low.allFinite() || !high.allFinite()) throw std::invalid_argument("correlative search: non-finite points");
  result = search_level(moving, fixed, low, high, guess, params);
  if (params.refine && result.score > 0) {
    // Coarse to fine: around the best hypothesis, cells a third as large within one coarse cell,
    // and five yaws within one coarse yaw step (the coarse score is flat within a cell).
    CorrelativeSearchParams fine;
    fine.cell_m = params.cell_m / 3.0;
    fine.window_m = params.cell_m * params.step_cells;
    fine.step_cells = 1;
    fine.yaw_hypotheses = params.yaw_hypotheses > 1 ? 5 : 1;
    fine.yaw_window_rad = params.yaw_hypotheses > 1 ? 2.0 * params.yaw_window_rad / (params.yaw_hypotheses - 1) : 0.0;
    fine.tie_tolerance = params.tie_tolerance;
    result = search_level(moving, fixed, low, high, result.transform, fine);
  }
  return result;
}

}  // namespace terracube
