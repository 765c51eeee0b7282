// The lowest vertical gap among a cell's heights ([TC] section 3.2's discontinuity), found without
// sorting. Shared by the elevation map and the local map. Not installed.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <limits>
#include <optional>
#include <vector>

namespace terracube::detail {

/// Two heights that are neighbours in sorted order: the one under the gap and the one over it.
struct HeightGap {
  double below, above;
};

/// The lowest gap of more than `threshold` between neighbouring heights (in sorted order) among
/// height(0) .. height(n - 1), all in [lowest, highest]; nullopt when there is none.
///
/// O(n): each height goes into the bucket floor((z - lowest) * 2 / threshold), which never
/// decreases as z grows (rounding is monotonic), and two heights of one bucket lie at most
/// threshold / 2 and a few ulps apart. So sorted neighbours either share a bucket (no gap) or are
/// the highest of one non-empty bucket and the lowest of the next; only those pairs are compared,
/// with the same subtraction as a sorted scan, so the answer is the sorted scan's. Heights needing
/// more than two buckets each (an outlier far off) are sorted instead. `buffer` is scratch space.
template <typename Height>
std::optional<HeightGap> lowest_gap(std::size_t n, double lowest, double highest, double threshold,
                                    const Height& height, std::vector<double>& buffer) {
  const double per_metre = 2.0 / threshold;
  const double last = (highest - lowest) * per_metre;  // the highest bucket (NaN or inf: sort)
  if (!(last < 2.0 * static_cast<double>(n))) {
    buffer.resize(n);
    for (std::size_t k = 0; k < n; ++k) buffer[k] = height(k);
    std::sort(buffer.begin(), buffer.end());
    for (std::size_t k = 1; k < n; ++k) {
      if (buffer[k] - buffer[k - 1] > threshold) return HeightGap{buffer[k - 1], buffer[k]};
    }
    return std::nullopt;
  }
  const auto buckets = static_cast<std::size_t>(last) + 1;
  buffer.assign(2 * buckets, std::numeric_limits<double>::quiet_NaN());  // lowest, highest per bucket
  for (std::size_t k = 0; k < n; ++k) {
    const double z = height(k);
    double* bucket = &buffer[2 * static_cast<std::size_t>((z - lowest) * per_metre)];
    bucket[0] = std::isnan(bucket[0]) ? z : std::min(bucket[0], z);
    bucket[1] = std::isnan(bucket[1]) ? z : std::max(bucket[1], z);
  }
  double below = buffer[1];  // the highest height of the last non-empty bucket (bucket 0 holds `lowest`)
  for (std::size_t b = 1; b < buckets; ++b) {
    if (std::isnan(buffer[2 * b])) continue;
    if (buffer[2 * b] - below > threshold) return HeightGap{below, buffer[2 * b]};
    below = buffer[2 * b + 1];
  }
  return std::nullopt;
}

}  // namespace terracube::detail
