// Collapsible cubes: overhang removal, [CBC] = Reina et al., IEEE AIM 2014, section III, Algorithm 1.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include "terracube/cube_grid.hpp"
#include "terracube/shadow_aware.hpp"

namespace terracube {

/// An axis-aligned box [m] in the leveled frame; points outside it take no part.
struct CropBox {
  Eigen::Vector3d min = Eigen::Vector3d::Constant(-1e9);
  Eigen::Vector3d max = Eigen::Vector3d::Constant(1e9);
};

/// How the occupancy bit vector V and the ground matrix M are stored. Both give bit-identical
/// results; kAuto picks kDense when V and M fit `dense_budget_bytes` and cost no more than a few
/// bytes per point, and kSparse (sorting I, hashing columns) otherwise, so memory stays O(N).
enum class CubeStorage { kAuto = 0, kDense = 1, kSparse = 2 };

/// Parameters of collapse_overhangs. Defaults follow the paper's examples.
struct CollapseParams {
  /// Cube edge E [m], > 0.
  double edge_m = 0.5;
  /// σ [cubes], >= 1: an occupied cube separated from its column's ground by σ or more empty
  /// cubes is collapsed. Use sigma_from_robot_height() for σ = ceil(robot height / E).
  int sigma = 2;
  /// Rigid transform applied to every point before CBC (leveling, see leveling_transform()).
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();
  /// Optional crop box in the transformed (leveled) frame.
  std::optional<CropBox> crop;
  /// NaN/Inf rows: false -> std::invalid_argument naming how many; true -> such rows are
  /// dropped (never overhang) and counted in CollapseResult::num_dropped_non_finite.
  bool drop_non_finite = false;
  CubeStorage storage = CubeStorage::kAuto;
  /// Largest V + M allowed for the dense storage [bytes].
  std::size_t dense_budget_bytes = std::size_t{256} << 20;
  /// Threads for the passes over the points (bounding box, cube indices, the mask): 1 is the
  /// calling thread alone (the default), 0 one per processor. V, L, Algorithm 1 and the sparse
  /// storage stay on the calling thread. The result is the same whatever the number.
  int num_threads = 1;
  /// The rule applied to L: kPaper is [CBC] Algorithm 1 bit for bit; kShadowAware also removes
  /// overhangs over ground the sensor cannot see (shadow_aware.hpp), recommended for mapping.
  CollapseMethod method = CollapseMethod::kPaper;
  /// Parameters of kShadowAware (ignored by kPaper, but validated).
  ShadowAwareParams shadow_aware;
};

/// Throws std::invalid_argument naming the first field out of range (edge, sigma, a non-rigid
/// transform, the crop, num_threads, then shadow_aware's); collapse_overhangs calls it first, and a
/// configuration can call it before the first scan.
void check_collapse_params(const CollapseParams& params);

/// σ = ceil(robot_height_m / edge_m), at least 1 (section III).
int sigma_from_robot_height(double robot_height_m, double edge_m);

/// The rotation that levels a sensor whose attitude is (roll, pitch) [rad]:
/// R = Ry(pitch) * Rx(roll), i.e. the sensor-to-gravity-aligned rotation with yaw = 0.
Eigen::Matrix4d leveling_transform(double roll_rad, double pitch_rad);

/// A sensor's attitude from the direction of gravity's reaction in its frame: an accelerometer at
/// rest (it reads +g along up), or the world's up turned into the sensor frame. The (roll, pitch)
/// [rad] whose leveling_transform() turns `up` onto +z ([CBC] section IV-B's IMU attitude). Only
/// the direction counts. Throws std::invalid_argument when `up` is zero or not finite.
struct Attitude {
  double roll_rad = 0.0;
  double pitch_rad = 0.0;
};
Attitude attitude_from_gravity(const Eigen::Vector3d& up);

/// Result of collapse_overhangs.
struct CollapseResult {
  CubeGrid grid;
  /// One flag per input point, in input order: 1 = the point lies in a collapsed cube.
  std::vector<std::uint8_t> overhang;
  /// L, sorted ascending: indices I of the occupied cubes ([CBC] eq. (1)).
  std::vector<std::int64_t> occupied_cubes;
  /// R, sorted ascending: indices I of the collapsed cubes.
  std::vector<std::int64_t> removed_cubes;
  std::size_t num_points = 0;              ///< N, input rows
  std::size_t num_used = 0;                ///< rows that entered CBC
  std::size_t num_cropped = 0;             ///< rows outside the crop box
  std::size_t num_dropped_non_finite = 0;  ///< NaN/Inf rows dropped (drop_non_finite)
  std::size_t num_overhang = 0;            ///< rows flagged overhang
  CubeStorage storage_used = CubeStorage::kDense;
  /// kShadowAware only (empty for kPaper): why each cube of occupied_cubes was kept or removed.
  std::vector<CubeReason> cube_reasons;
};

/// [CBC] Algorithm 1: builds the CBC (V and L in one O(N) pass), sorts L, sweeps every column
/// bottom-up keeping its ground in M and collapses the cubes σ or more empty cubes above it.
/// Each calling thread keeps its work buffers (the cube indices, and V and M of the dense storage)
/// for its next call, released after a call that needed over 64 MB.
/// `no_return_directions`: the scan's beams that returned nothing, in the points' frame, for
/// CollapseMethod::kShadowAware (shadow_aware_collapse's `no_returns`); viewed, not copied.
/// Throws std::invalid_argument on a non-positive edge, σ < 1, a non-rigid transform, NaN/Inf
/// rows (unless dropped), a zero or non-finite beam or an extent whose cube count would overflow
/// a 64-bit index.
CollapseResult collapse_overhangs(const PointsView<float>& points, const CollapseParams& params = {},
                                  const PointsView<double>& no_return_directions = {});
CollapseResult collapse_overhangs(const PointsView<double>& points, const CollapseParams& params = {},
                                  const PointsView<double>& no_return_directions = {});
CollapseResult collapse_overhangs(const std::vector<Eigen::Vector3d>& points, const CollapseParams& params = {},
                                  const PointsView<double>& no_return_directions = {});

/// Why each row of `points` was kept or removed by the shadow-aware `result` =
/// collapse_overhangs(points, params): the CubeReason of the cube that holds the row (from
/// result.cube_reasons), or CubeReason::kNotUsed for a row that took no part (NaN/Inf dropped,
/// outside the crop). Each row's cube is found again with the call's own arithmetic (params'
/// transform and crop, result.grid). For debugging and pictures: O(N log K), not part of a call.
/// Throws std::invalid_argument unless `result` holds cube reasons (method kShadowAware) and
/// belongs to these rows: as many rows, and every row's cube among result.occupied_cubes.
std::vector<CubeReason> point_reasons(const PointsView<float>& points, const CollapseParams& params,
                                      const CollapseResult& result);
std::vector<CubeReason> point_reasons(const PointsView<double>& points, const CollapseParams& params,
                                      const CollapseResult& result);

}  // namespace terracube
