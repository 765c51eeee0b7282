// Ground as planes (RegistrationParams::ground_weight; not in [TC]): the target's ground points
// binned into square cells, each fitted with a plane. Private to the registration.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <vector>

namespace terracube::detail {

/// Square cells of side `cell` over (x, y), cell (kx, ky) = (floor(x / cell), floor(y / cell)),
/// numbered in the order their first point comes. Dense (an entry per cell of the points'
/// bounding box) when the box has at most 8 n + 65536 cells, else sorted keys and a binary search,
/// so that memory stays O(n) for any extent.
class GroundCells {
 public:
  GroundCells() = default;

  /// `id_of_point` receives each point's cell number. Throws std::invalid_argument when a point
  /// lies 2^31 or more cells from the origin.
  GroundCells(const std::vector<Eigen::Vector3d>& points, double cell, std::vector<std::uint32_t>& id_of_point)
      : cell_(cell) {
    const std::size_t n = points.size();
    std::vector<std::int64_t> kx(n), ky(n);
    for (std::size_t k = 0; k < n; ++k) {
      const double fx = std::floor(points[k].x() / cell), fy = std::floor(points[k].y() / cell);
      if (!(std::abs(fx) < kLimit && std::abs(fy) < kLimit)) {
        throw std::invalid_argument(
            "ground cell is too small for the extent of the ground points (2^31 cells or "
            "more from the origin)");
      }
      kx[k] = static_cast<std::int64_t>(fx), ky[k] = static_cast<std::int64_t>(fy);
      kx0_ = std::min(kx0_, kx[k]), kx1_ = std::max(kx1_, kx[k]);
      ky0_ = std::min(ky0_, ky[k]), ky1_ = std::max(ky1_, ky[k]);
    }
    id_of_point.resize(n);
    if (n == 0) return;
    columns_ = kx1_ - kx0_ + 1;
    const double cells = static_cast<double>(columns_) * static_cast<double>(ky1_ - ky0_ + 1);
    if (cells <= 8.0 * static_cast<double>(n) + 65536.0) {
      dense_.assign(static_cast<std::size_t>(cells), -1);
      for (std::size_t k = 0; k < n; ++k) {
        std::int32_t& id = dense_[static_cast<std::size_t>((kx[k] - kx0_) + (ky[k] - ky0_) * columns_)];
        if (id < 0) id = static_cast<std::int32_t>(size_++);
        id_of_point[k] = static_cast<std::uint32_t>(id);
      }
      return;
    }
    keys_.resize(n);
    for (std::size_t k = 0; k < n; ++k) keys_[k] = key(kx[k], ky[k]);
    std::sort(keys_.begin(), keys_.end());
    keys_.erase(std::unique(keys_.begin(), keys_.end()), keys_.end());
    size_ = keys_.size();
    for (std::size_t k = 0; k < n; ++k) {
      id_of_point[k] =
          static_cast<std::uint32_t>(std::lower_bound(keys_.begin(), keys_.end(), key(kx[k], ky[k])) - keys_.begin());
    }
  }

  std::size_t size() const { return size_; }

  /// The number of the cell holding (x, y), or -1 where no point fell (NaN included).
  std::int64_t find(double x, double y) const {
    const double fx = std::floor(x / cell_), fy = std::floor(y / cell_);
    if (!(fx >= static_cast<double>(kx0_) && fx <= static_cast<double>(kx1_) && fy >= static_cast<double>(ky0_) &&
          fy <= static_cast<double>(ky1_))) {
      return -1;
    }
    const auto ix = static_cast<std::int64_t>(fx), iy = static_cast<std::int64_t>(fy);
    if (!dense_.empty()) return dense_[static_cast<std::size_t>((ix - kx0_) + (iy - ky0_) * columns_)];
    const std::uint64_t wanted = key(ix, iy);
    const auto it = std::lower_bound(keys_.begin(), keys_.end(), wanted);
    return it != keys_.end() && *it == wanted ? it - keys_.begin() : -1;
  }

 private:
  static constexpr double kLimit = 2147483648.0;  // 2^31
  static std::uint64_t key(std::int64_t kx, std::int64_t ky) {
    return (static_cast<std::uint64_t>(kx + (std::int64_t{1} << 31)) << 32) |
           static_cast<std::uint64_t>(ky + (std::int64_t{1} << 31));
  }

  double cell_ = 1.0;
  std::int64_t kx0_ = std::numeric_limits<std::int64_t>::max(), ky0_ = std::numeric_limits<std::int64_t>::max();
  std::int64_t kx1_ = std::numeric_limits<std::int64_t>::min(), ky1_ = std::numeric_limits<std::int64_t>::min();
  std::int64_t columns_ = 0;
  std::vector<std::int32_t> dense_;
  std::vector<std::uint64_t> keys_;
  std::size_t size_ = 0;
};

/// A target ground cell's plane (RegistrationParams::ground_weight): a point on it (the mean of
/// the cell's points) and its unit normal.
struct GroundPlane {
  Eigen::Vector3d point, normal;
};

/// Per cell of `index`, the least-squares plane z = a + b x + c y of its points (`id_of_point`);
/// horizontal through the mean below three points or when the points nearly lie on a line.
std::vector<GroundPlane> fit_ground_planes(const std::vector<Eigen::Vector3d>& points,
                                           const std::vector<std::uint32_t>& id_of_point, std::size_t cells);

}  // namespace terracube::detail
