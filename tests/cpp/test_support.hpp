// Shared helpers for the C++ tests: locating ../shared/data and reading its scans, poses, and
// checking exception messages.
#pragma once

#include <gtest/gtest.h>
#include <terracube/cube_grid.hpp>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <optional>
#include <random>
#include <string>
#include <vector>

namespace terracube::test {

/// The shared real-data folder: $TERRACUBE_DATA_DIR, else ../shared/data beside the repository,
/// else /work/shared/data. Empty when none exists.
std::optional<std::string> shared_data_dir();

/// A KITTI-style .bin scan: float32 rows of (x, y, z, intensity).
struct XyziScan {
  std::vector<float> values;  // N * 4
  PointsView<float> xyz() const { return {values.data(), values.size() / 4, 4, 1}; }
  std::vector<Eigen::Vector3d> as_vectors() const;
};
XyziScan read_xyzi_bin(const std::string& path);

/// SemanticKITTI labels: the low 16 bits of each uint32 are the semantic class.
std::vector<std::uint16_t> read_semantic_labels(const std::string& path);

/// A seeded random scene: rough ground, some canopy blobs over it, walls, trunks and noise.
std::vector<Eigen::Vector3d> random_scene(std::uint32_t seed, std::size_t num_points, double extent_m);

/// `v` rounded to Scalar and back. Out of line on purpose: inlined into a loop that writes a
/// Vector3d back in place, GCC 12.2 at -O2 was seen to drop the rounding of x and y (the pair it
/// moves as one vector), also for p.cast<float>().cast<double>().
template <typename Scalar>
__attribute__((noinline)) double rounded_to(double v) {
  return static_cast<double>(static_cast<Scalar>(v));
}

/// `p` with each coordinate rounded to Scalar and back (see above).
template <typename Scalar>
Eigen::Vector3d rounded_to(const Eigen::Vector3d& p) {
  return {rounded_to<Scalar>(p.x()), rounded_to<Scalar>(p.y()), rounded_to<Scalar>(p.z())};
}

/// Runs `call`, expects it to throw `Error` whose message contains every one of `parts`.
template <typename Error>
void expect_throw_with(const std::function<void()>& call, const std::vector<std::string>& parts) {
  try {
    call();
    ADD_FAILURE() << "expected an exception";
  } catch (const Error& error) {
    const std::string message = error.what();
    for (const std::string& part : parts) {
      EXPECT_NE(message.find(part), std::string::npos) << "'" << part << "' not in: " << message;
    }
  }
}

/// The rigid transform at (x, y, z) [m] turned by yaw, then pitch, then roll [degrees].
inline Eigen::Matrix4d pose(double x, double y, double z, double yaw_deg, double pitch_deg = 0.0,
                            double roll_deg = 0.0) {
  constexpr double kRadPerDeg = 3.14159265358979323846 / 180.0;
  Eigen::Matrix4d t = Eigen::Matrix4d::Identity();
  t.topLeftCorner<3, 3>() = (Eigen::AngleAxisd(yaw_deg * kRadPerDeg, Eigen::Vector3d::UnitZ()) *
                             Eigen::AngleAxisd(pitch_deg * kRadPerDeg, Eigen::Vector3d::UnitY()) *
                             Eigen::AngleAxisd(roll_deg * kRadPerDeg, Eigen::Vector3d::UnitX()))
                                .toRotationMatrix();
  t.topRightCorner<3, 1>() = Eigen::Vector3d(x, y, z);
  return t;
}

}  // namespace terracube::test
