// The nearest-neighbour indexes of the registration: a k-d tree over 3D points and a 2D bucket
// grid over map cells (icp.hpp).
#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <stdexcept>
#include <string>

#include "terracube/icp.hpp"

namespace terracube {

namespace {
constexpr std::uint32_t kLeafSize = 8;
}  // namespace

// --- k-d tree ---------------------------------------------------------------------------------

NearestNeighbor3d::NearestNeighbor3d(std::vector<Eigen::Vector3d> points) {
  if (points.size() >= std::numeric_limits<std::uint32_t>::max()) {
    throw std::invalid_argument("too many points for the nearest-neighbour index");
  }
  points_ = std::move(points);
  original_.resize(points_.size());
  std::iota(original_.begin(), original_.end(), std::uint32_t{0});
  if (points_.empty()) return;
  nodes_.reserve(2 * (points_.size() / kLeafSize + 1));
  build(0, static_cast<std::uint32_t>(points_.size()));
  // Store the points in leaf order so that a leaf scan reads contiguous memory.
  std::vector<Eigen::Vector3d> ordered(points_.size());
  position_.resize(points_.size());
  for (std::size_t k = 0; k < points_.size(); ++k) {
    ordered[k] = points_[original_[k]];
    position_[original_[k]] = static_cast<std::uint32_t>(k);
  }
  points_ = std::move(ordered);
}

std::int32_t NearestNeighbor3d::build(std::uint32_t begin, std::uint32_t end) {
  // original_ holds the permutation being partitioned; points_ is still in input order.
  const auto index = static_cast<std::int32_t>(nodes_.size());
  nodes_.emplace_back();
  if (end - begin <= kLeafSize) {
    nodes_[static_cast<std::size_t>(index)].begin = begin;
    nodes_[static_cast<std::size_t>(index)].end = end;
    return index;
  }
  Eigen::Vector3d low = points_[original_[begin]], high = low;
  for (std::uint32_t k = begin + 1; k < end; ++k) {
    low = low.cwiseMin(points_[original_[k]]);
    high = high.cwiseMax(points_[original_[k]]);
  }
  int axis = 0;
  (high - low).maxCoeff(&axis);
  const std::uint32_t middle = begin + (end - begin) / 2;
  std::nth_element(original_.begin() + begin, original_.begin() + middle, original_.begin() + end,
                   [&](std::uint32_t a, std::uint32_t b) { return points_[a][axis] < points_[b][axis]; });
  const double split = points_[original_[middle]][axis];
  const std::int32_t left = build(begin, middle);
  const std::int32_t right = build(middle, end);
  Node& node = nodes_[static_cast<std::size_t>(index)];
  node.axis = static_cast<std::int8_t>(axis);
  node.split = split;
  node.left = left;
  node.right = right;
  return index;
}

std::ptrdiff_t NearestNeighbor3d::nearest(const Eigen::Vector3d& query, double max_squared_distance,
                                          double& squared_distance) const {
  std::ptrdiff_t best = -1;
  double best_squared = max_squared_distance;
  if (nodes_.empty()) return best;
  // Depth-first with an explicit stack of (node, lower bound on its squared distance).
  struct Entry {
    std::int32_t node;
    double bound;
  };
  Entry stack[64];
  int top = 0;
  stack[top++] = {0, 0.0};
  while (top > 0) {
    const Entry entry = stack[--top];
    if (entry.bound > best_squared) continue;
    // Descend to the leaf on the query's side, pushing each far side that may still hold a
    // nearer point (its bound: the squared distance to the splitting plane).
    const Node* node = &nodes_[static_cast<std::size_t>(entry.node)];
    while (node->axis >= 0) {
      const double offset = query[node->axis] - node->split;
      const double far_bound = std::max(entry.bound, offset * offset);
      if (far_bound <= best_squared) stack[top++] = {offset < 0.0 ? node->right : node->left, far_bound};
      node = &nodes_[static_cast<std::size_t>(offset < 0.0 ? node->left : node->right)];
    }
    for (std::uint32_t k = node->begin; k < node->end; ++k) {
      const double d = (points_[k] - query).squaredNorm();
      if (d <= best_squared) {
        best_squared = d;
        best = static_cast<std::ptrdiff_t>(k);
      }
    }
  }
  if (best >= 0) {
    squared_distance = best_squared;
    return static_cast<std::ptrdiff_t>(original_[static_cast<std::size_t>(best)]);
  }
  return -1;
}

// --- 2D bucket grid -------------------------------------------------------------------------

namespace {
// Slack on the pruning bounds [buckets]: a point whose bucket was computed with rounding on the
// other side of a boundary is still examined, so the search stays exact.
constexpr double kBucketSlack = 1e-6;
}  // namespace

NearestNeighborGrid::NearestNeighborGrid(std::vector<Eigen::Vector3d> points, double bucket_size_m) {
  if (points.size() >= std::numeric_limits<std::uint32_t>::max()) {
    throw std::invalid_argument("too many points for the nearest-neighbour grid");
  }
  if (!(bucket_size_m >= 0.0 && std::isfinite(bucket_size_m))) {
    throw std::invalid_argument("nearest-neighbour grid bucket size must be finite and >= 0 [m]");
  }
  for (std::size_t k = 0; k < points.size(); ++k) {
    if (!points[k].allFinite()) {
      throw std::invalid_argument("nearest-neighbour grid point " + std::to_string(k) + " is NaN or Inf");
    }
  }
  const std::size_t n = points.size();
  if (n == 0) return;
  Eigen::Vector2d low = points[0].head<2>(), high = low;
  for (const Eigen::Vector3d& p : points) {
    low = low.cwiseMin(p.head<2>());
    high = high.cwiseMax(p.head<2>());
  }
  const Eigen::Vector2d extent = high - low;
  if (bucket_size_m == 0.0) {
    // Half the mean spacing over the box (about four buckets per point); a line of points (zero
    // area) gets a quarter of its spacing; a single column one bucket.
    const auto count = static_cast<double>(n);
    bucket_size_m = std::max(0.5 * std::sqrt(extent.x() * extent.y() / count), extent.maxCoeff() / (4.0 * count));
    if (!(bucket_size_m > 0.0)) bucket_size_m = 1.0;
  }
  const double columns = std::floor(extent.x() / bucket_size_m) + 1.0;
  const double rows = std::floor(extent.y() / bucket_size_m) + 1.0;
  if (columns * rows > static_cast<double>(std::numeric_limits<std::int32_t>::max())) {
    throw std::invalid_argument("nearest-neighbour grid bucket size " + std::to_string(bucket_size_m) +
                                " m gives more than 2^31 buckets over the points' extent");
  }
  bucket_size_m_ = bucket_size_m;
  inverse_bucket_size_ = 1.0 / bucket_size_m;
  origin_ = low;
  columns_ = static_cast<std::int64_t>(columns);
  rows_ = static_cast<std::int64_t>(rows);
  // Counting sort of the points by bucket.
  const auto bucket_of = [&](const Eigen::Vector3d& p) {
    const auto column = std::min(columns_ - 1, static_cast<std::int64_t>((p.x() - low.x()) * inverse_bucket_size_));
    const auto row = std::min(rows_ - 1, static_cast<std::int64_t>((p.y() - low.y()) * inverse_bucket_size_));
    return static_cast<std::size_t>(row * columns_ + column);
  };
  start_.assign(static_cast<std::size_t>(columns_ * rows_) + 1, 0);
  std::vector<std::uint32_t> bucket(n);
  for (std::size_t k = 0; k < n; ++k) {
    bucket[k] = static_cast<std::uint32_t>(bucket_of(points[k]));
    ++start_[bucket[k] + 1];
  }
  std::partial_sum(start_.begin(), start_.end(), start_.begin());
  std::vector<std::uint32_t> next(start_.begin(), start_.end() - 1);
  points_.resize(n);
  original_.resize(n);
  position_.resize(n);
  for (std::size_t k = 0; k < n; ++k) {
    const std::uint32_t slot = next[bucket[k]]++;
    points_[slot] = points[k];
    original_[slot] = static_cast<std::uint32_t>(k);
    position_[k] = slot;
  }
}

std::ptrdiff_t NearestNeighborGrid::nearest(const Eigen::Vector3d& query, double max_squared_distance,
                                            double& squared_distance) const {
  std::ptrdiff_t found[1] = {-1};
  double best[1];
  search<1, false>(query, max_squared_distance, found, best);
  if (found[0] < 0) return -1;
  squared_distance = best[0];
  return found[0];
}

std::ptrdiff_t NearestNeighborGrid::nearest_two(const Eigen::Vector3d& query, double max_squared_distance,
                                                std::array<std::ptrdiff_t, 2>& indices,
                                                std::array<double, 2>& squared_distances,
                                                double& others_squared_distance) const {
  std::ptrdiff_t found[2] = {-1, -1};
  double best[3];
  search<2, true>(query, max_squared_distance, found, best);
  indices = {found[0], found[1]};
  squared_distances = {best[0], best[1]};
  others_squared_distance = best[2];
  return found[0];
}

template <typename Visit>
bool NearestNeighborGrid::visit_near(const Eigen::Vector3d& query, double radius, const Visit& visit) const {
  if (points_.empty() || !(radius >= 0.0)) return false;
  // The buckets that can hold a point within the radius (with slack; the caller's distance decides).
  const double reach = radius * inverse_bucket_size_ + kBucketSlack;
  const double u = (query.x() - origin_.x()) * inverse_bucket_size_;
  const double v = (query.y() - origin_.y()) * inverse_bucket_size_;
  const auto clamp_to = [](double value, std::int64_t count) {
    return static_cast<std::int64_t>(std::clamp(std::floor(value), 0.0, static_cast<double>(count - 1)));
  };
  if (u + reach < 0.0 || v + reach < 0.0 || u - reach >= static_cast<double>(columns_) ||
      v - reach >= static_cast<double>(rows_)) {
    return false;
  }
  const std::int64_t first_column = clamp_to(u - reach, columns_), last_column = clamp_to(u + reach, columns_);
  const std::int64_t first_row = clamp_to(v - reach, rows_), last_row = clamp_to(v + reach, rows_);
  for (std::int64_t row = first_row; row <= last_row; ++row) {
    const auto base = static_cast<std::size_t>(row * columns_);
    const std::uint32_t end = start_[base + static_cast<std::size_t>(last_column) + 1];
    for (std::uint32_t k = start_[base + static_cast<std::size_t>(first_column)]; k < end; ++k) {
      if (visit(k)) return true;
    }
  }
  return false;
}

void NearestNeighborGrid::within(const Eigen::Vector3d& query, double radius, std::vector<std::uint32_t>& out) const {
  const double squared = radius * radius;
  visit_near(query, radius, [&](std::uint32_t k) {
    if ((points_[k] - query).squaredNorm() <= squared) out.push_back(original_[k]);
    return false;
  });
}

bool NearestNeighborGrid::any_within(const Eigen::Vector3d& query, double max_squared_distance) const {
  // The squared distance as search() computes it, so that the answer is nearest()'s.
  return visit_near(query, std::sqrt(std::max(max_squared_distance, 0.0)), [&](std::uint32_t k) {
    const double dx = points_[k].x() - query.x(), dy = points_[k].y() - query.y(), dz = points_[k].z() - query.z();
    return dx * dx + dy * dy + dz * dz <= max_squared_distance;
  });
}

template <int kKeep, bool kBound>
void NearestNeighborGrid::search(const Eigen::Vector3d& query, double max_squared_distance, std::ptrdiff_t* found_out,
                                 double* best_out) const {
  constexpr int kLast = kBound ? kKeep : kKeep - 1;  // best[kLast] is the pruning distance
  // Kept in locals (registers) while scanning, copied out at the end.
  double best[kLast + 1];
  std::ptrdiff_t found[kKeep];
  for (int k = 0; k <= kLast; ++k) best[k] = max_squared_distance;
  for (int k = 0; k < kKeep; ++k) found[k] = -1;
  const auto copy_out = [&] {
    for (int k = 0; k <= kLast; ++k) best_out[k] = best[k];
    for (int k = 0; k < kKeep; ++k) {
      found_out[k] = found[k] >= 0 ? static_cast<std::ptrdiff_t>(original_[static_cast<std::size_t>(found[k])]) : -1;
    }
  };
  if (points_.empty()) return copy_out();
  // Pruning uses the largest distance kept: every point nearer than it is examined.
  double& prune = best[kLast];
  // The query in bucket units (it may lie outside the grid).
  const double u = (query.x() - origin_.x()) * inverse_bucket_size_;
  const double v = (query.y() - origin_.y()) * inverse_bucket_size_;
  const double bucket_squared = bucket_size_m_ * bucket_size_m_;
  const double last_column = static_cast<double>(columns_ - 1);
  const double qx = query.x(), qy = query.y(), qz = query.z();
  const Eigen::Vector3d* points = points_.data();
  // Scans the buckets of `row` whose x range can hold a point within `prune`, given that every
  // point of the row is at least `gap` buckets away in y. Points of consecutive buckets are
  // contiguous, so the scan is one loop.
  const auto scan_row = [&](std::int64_t row, double gap) {
    const double reach_squared = prune / bucket_squared - gap * gap;
    if (reach_squared < 0.0) return;
    const double reach = std::sqrt(reach_squared) + kBucketSlack;
    const double low = u - reach, high = u + reach;
    if (high < 0.0 || low >= static_cast<double>(columns_)) return;
    // Truncation of a non-negative value is floor.
    const std::size_t first = low <= 0.0 ? 0 : static_cast<std::size_t>(low);
    const std::size_t last =
        high >= last_column ? static_cast<std::size_t>(columns_ - 1) : static_cast<std::size_t>(high);
    const std::size_t base = static_cast<std::size_t>(row * columns_);
    const std::uint32_t end = start_[base + last + 1];
    for (std::uint32_t k = start_[base + first]; k < end; ++k) {
      const Eigen::Vector3d& point = points[k];
      const double dx = point.x() - qx, dy = point.y() - qy, dz = point.z() - qz;
      const double d = dx * dx + dy * dy + dz * dz;
      // Insert into the sorted best[] (the nearest first; a tie puts the new point first), without
      // branches: whether a point is nearer than those kept is data, not a pattern a branch
      // predictor learns, so the choices are masks (-1: take) and min/max. A point beyond
      // best[kLast] changes nothing. Slots go from the last down, each from old values.
      const auto index = static_cast<std::ptrdiff_t>(k);
      for (int slot = kLast; slot > 0; --slot) {
        if (slot < kKeep) {
          const std::ptrdiff_t shift = -static_cast<std::ptrdiff_t>(d <= best[slot - 1]);
          const std::ptrdiff_t take = -static_cast<std::ptrdiff_t>(d <= best[slot]);
          const std::ptrdiff_t kept = (index & take) | (found[slot] & ~take);
          found[slot] = (found[slot - 1] & shift) | (kept & ~shift);
        }
        best[slot] = std::min(std::max(d, best[slot - 1]), best[slot]);
      }
      const std::ptrdiff_t take = -static_cast<std::ptrdiff_t>(d <= best[0]);
      found[0] = (index & take) | (found[0] & ~take);
      best[0] = std::min(d, best[0]);
    }
  };
  // floor(v) clamped to [-1, rows_]: truncation of the non-negative v + 1 is its floor.
  const auto row_of_query = static_cast<std::int64_t>(std::clamp(v, -1.0, static_cast<double>(rows_)) + 1.0) - 1;
  // Upward from the query's row (gap 0 within it), then downward; a row whose gap alone exceeds
  // the pruning distance ends its direction.
  for (std::int64_t row = std::max<std::int64_t>(row_of_query, 0); row < rows_; ++row) {
    const double gap = std::max(0.0, static_cast<double>(row) - v - kBucketSlack);
    if (gap * gap * bucket_squared > prune) break;
    scan_row(row, gap);
  }
  for (std::int64_t row = std::min(row_of_query - 1, rows_ - 1); row >= 0; --row) {
    const double gap = std::max(0.0, v - static_cast<double>(row + 1) - kBucketSlack);
    if (gap * gap * bucket_squared > prune) break;
    scan_row(row, gap);
  }
  copy_out();
}

}  // namespace terracube
