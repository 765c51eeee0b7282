#include "cloud_frame.hpp"

#include <Eigen/Dense>
#include <sstream>
#include <stdexcept>

#include "number_text.hpp"
#include "parallel.hpp"

namespace terracube::detail {

void throw_non_finite_rows(const NonFiniteRows& rows, std::size_t num_rows) {
  throw std::invalid_argument(std::to_string(rows.count) + " of " + std::to_string(num_rows) +
                              " point rows contain NaN or Inf (first at row " + std::to_string(rows.first_row) +
                              "); clean the cloud or set drop_non_finite=True to drop them");
}

void check_rigid_transform(const Eigen::Matrix4d& transform, const std::string& what) {
  if (!transform.allFinite()) throw std::invalid_argument(what + " contains NaN or Inf");
  const Eigen::Matrix3d rotation = transform.topLeftCorner<3, 3>();
  const double deviation = (rotation.transpose() * rotation - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  const double last_row = (transform.row(3) - Eigen::RowVector4d(0, 0, 0, 1)).cwiseAbs().maxCoeff();
  std::string problem;
  if (last_row > 1e-9) {
    problem = "its last row is not 0 0 0 1";
  } else if (deviation > kRigidTolerance) {
    problem = "|R^T R - I| reaches " + number_text(deviation) + ", over " + number_text(kRigidTolerance) +
              "; replace R by its nearest rotation (U V^T of its SVD)";
  } else if (rotation.determinant() < 0.0) {
    problem = "its 3x3 block is a reflection (negative determinant)";
  } else {
    return;
  }
  throw std::invalid_argument(what +
                              " must be a rigid 4x4 transform (a proper rotation R, last row 0 0 0 1): " + problem);
}

void check_crop(const std::optional<CropBox>& crop) {
  if (crop && (!crop->min.allFinite() || !crop->max.allFinite() || (crop->min.array() > crop->max.array()).any())) {
    throw std::invalid_argument("crop box must be finite with min <= max on every axis");
  }
}

CubeGrid make_grid(const CloudExtent& extent, double edge_m) {
  CubeGrid grid;
  grid.edge_m = edge_m;
  grid.min_corner = extent.min;
  const double inverse_edge = 1.0 / edge_m;
  // Keep every count and their product below 2^62 so that [CBC] eq. (7) never overflows.
  constexpr double kLimit = 4.611686018427388e18;  // 2^62
  double counts[3];
  long double product = 1.0L;
  for (int axis = 0; axis < 3; ++axis) {
    counts[axis] = std::floor((extent.max[axis] - extent.min[axis]) * inverse_edge + 0.5) + 1.0;
    product *= static_cast<long double>(counts[axis]);
  }
  if (!(counts[0] < kLimit && counts[1] < kLimit && counts[2] < kLimit && product < kLimit)) {
    std::ostringstream message;
    message << "the cloud's extent (" << extent.max[0] - extent.min[0] << " x " << extent.max[1] - extent.min[1]
            << " x " << extent.max[2] - extent.min[2] << " m) at edge " << edge_m << " m needs "
            << static_cast<double>(product)
            << " cubes, which overflows a 64-bit cube index; crop the cloud or use a larger edge";
    throw std::invalid_argument(message.str());
  }
  grid.ixmax = static_cast<std::int64_t>(counts[0]);
  grid.iymax = static_cast<std::int64_t>(counts[1]);
  grid.izmax = static_cast<std::int64_t>(counts[2]);
  return grid;
}

}  // namespace terracube::detail
