// Private helpers of the simulator's two sources (simulation.cpp: scenes and ray casting,
// simulation_world.cpp: the loop world, trajectories and sequences). Not installed.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>

#include "number_text.hpp"

namespace terracube::simulation::support {

constexpr double kPi = 3.14159265358979323846;
constexpr double kInf = std::numeric_limits<double>::infinity();

inline double deg2rad(double degrees) { return degrees * kPi / 180.0; }

[[noreturn]] inline void fail(const std::string& message) { throw std::invalid_argument(message); }

inline void require_finite(double value, const char* name) {
  if (!std::isfinite(value)) fail(std::string(name) + " must be finite, got " + detail::number_text(value));
}

inline void require_positive(double value, const char* name) {
  if (!std::isfinite(value) || !(value > 0.0))
    fail(std::string(name) + " must be positive, got " + detail::number_text(value));
}

inline void require_non_negative(double value, const char* name) {
  if (!std::isfinite(value) || value < 0.0)
    fail(std::string(name) + " must be >= 0, got " + detail::number_text(value));
}

inline double clamp01(double value) { return std::min(1.0, std::max(0.0, value)); }

inline double wrap_angle(double angle) { return std::remainder(angle, 2.0 * kPi); }

/// SplitMix64: decorrelates (seed, index) pairs into seeds for independent generators.
inline std::uint64_t mix_seed(std::uint64_t value) {
  value += 0x9E3779B97F4A7C15ULL;
  value = (value ^ (value >> 30)) * 0xBF58476D1CE4E5B9ULL;
  value = (value ^ (value >> 27)) * 0x94D049BB133111EBULL;
  return value ^ (value >> 31);
}

/// Standard normal deviates by Box-Muller on std::mt19937_64 (whose output the standard fixes), so
/// sequences are identical on every platform, unlike std::normal_distribution.
class Gaussian {
 public:
  explicit Gaussian(std::uint64_t seed) : engine_(seed) {}
  double operator()() {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    const double u1 = 1.0 - uniform();  // (0, 1]
    const double u2 = uniform();
    const double radius = std::sqrt(-2.0 * std::log(u1));
    spare_ = radius * std::sin(2.0 * kPi * u2);
    has_spare_ = true;
    return radius * std::cos(2.0 * kPi * u2);
  }
  double uniform() { return static_cast<double>(engine_() >> 11) * (1.0 / 9007199254740992.0); }  // [0, 1)

 private:
  std::mt19937_64 engine_;
  double spare_ = 0.0;
  bool has_spare_ = false;
};

inline Eigen::Matrix4d make_pose(const Eigen::Vector3d& position, double yaw, double pitch, double roll) {
  Eigen::Matrix4d pose = Eigen::Matrix4d::Identity();
  pose.topLeftCorner<3, 3>() =
      (Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(pitch, Eigen::Vector3d::UnitY()) *
       Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()))
          .toRotationMatrix();
  pose.topRightCorner<3, 1>() = position;
  return pose;
}

}  // namespace terracube::simulation::support
