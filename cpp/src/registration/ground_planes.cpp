// Ground as planes: the least-squares plane of each ground cell.
#include "ground_planes.hpp"

namespace terracube::detail {

/// Per cell of `index`, the least-squares plane z = a + b x + c y of its points (`id_of_point`);
/// horizontal through the mean below three points or when the points nearly lie on a line.
std::vector<GroundPlane> fit_ground_planes(const std::vector<Eigen::Vector3d>& points,
                                           const std::vector<std::uint32_t>& id_of_point, std::size_t cells) {
  // Sums relative to each cell's first point, so that they stay well conditioned far from zero:
  // n, x, y, z, xx, xy, yy, xz, yz.
  std::vector<std::array<double, 9>> sums(cells, std::array<double, 9>{});
  std::vector<Eigen::Vector3d> first(cells);
  for (std::size_t k = 0; k < points.size(); ++k) {
    auto& m = sums[id_of_point[k]];
    if (m[0] == 0.0) first[id_of_point[k]] = points[k];
    const Eigen::Vector3d d = points[k] - first[id_of_point[k]];
    m[0] += 1.0, m[1] += d.x(), m[2] += d.y(), m[3] += d.z();
    m[4] += d.x() * d.x(), m[5] += d.x() * d.y(), m[6] += d.y() * d.y(), m[7] += d.x() * d.z(), m[8] += d.y() * d.z();
  }
  std::vector<GroundPlane> planes(cells);
  for (std::size_t c = 0; c < cells; ++c) {
    const auto& m = sums[c];
    const double n = m[0];
    const Eigen::Vector3d mean(m[1] / n, m[2] / n, m[3] / n);
    // Centred moments.
    const double xx = m[4] - m[1] * mean.x(), xy = m[5] - m[1] * mean.y(), yy = m[6] - m[2] * mean.y();
    const double xz = m[7] - m[1] * mean.z(), yz = m[8] - m[2] * mean.z();
    const double det = xx * yy - xy * xy;
    double b = 0.0, slope_y = 0.0;
    if (n >= 3.0 && det > 1e-6 * (xx + yy) * (xx + yy)) {
      b = (yy * xz - xy * yz) / det;
      slope_y = (xx * yz - xy * xz) / det;
    }
    planes[c].point = first[c] + mean;
    planes[c].normal = Eigen::Vector3d(-b, -slope_y, 1.0).normalized();
  }
  return planes;
}

}  // namespace terracube::detail
