// Accuracy measures for trajectories and maps: the absolute trajectory error (with optional
// rigid alignment), the KITTI-devkit relative pose error over path-length segments, and the DSM
// comparison of [TC] section 4.2 (distance errors of region pairs, [TC] eq. (5), and angle errors
// of region triples, [TC] eq. (6)).
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace terracube {

/// How the estimate is brought into the ground truth's frame before the absolute error.
enum class TrajectoryAlignment {
  kNone = 0,       ///< compare as given
  kFirstPose = 1,  ///< move the estimate so that its first pose equals the first true pose
  kRigid = 2,      ///< least-squares rotation + translation of the positions (Umeyama/Horn, no scale)
};

/// Summary of a list of non-negative errors.
struct ErrorStatistics {
  double rmse = 0.0;    ///< sqrt(mean(e^2))
  double mean = 0.0;    ///< mean(e)
  double median = 0.0;  ///< middle value (mean of the two middle values for an even count)
  double max = 0.0;     ///< largest
  std::size_t count = 0;
};

/// Statistics of `errors`; all NaN (count 0) when `errors` is empty.
ErrorStatistics error_statistics(const std::vector<double>& errors);

/// Outcome of absolute_trajectory_error.
struct AbsoluteTrajectoryError {
  /// The transform applied to the estimate: aligned_k = alignment * estimate_k.
  Eigen::Matrix4d alignment = Eigen::Matrix4d::Identity();
  std::vector<double> translation_errors_m;  ///< |t(gt_k) - t(aligned_k)| per pose [m]
  std::vector<double> rotation_errors_deg;   ///< angle of R(gt_k)^T R(aligned_k) per pose [deg]
  ErrorStatistics translation;               ///< over translation_errors_m [m]
  ErrorStatistics rotation;                  ///< over rotation_errors_deg [deg]
};

/// Absolute trajectory error of `estimate` against `ground_truth` (same length, pose k of one
/// matched with pose k of the other; poses are rigid 4x4 sensor-to-world transforms). With
/// kRigid the positions are aligned by the closed-form least-squares rotation and translation
/// (Umeyama 1991, eqs. (34)-(42) without scale); a single pose is aligned by translation only.
/// Throws std::invalid_argument for empty or unequal inputs and non-finite or non-rigid poses.
AbsoluteTrajectoryError absolute_trajectory_error(const std::vector<Eigen::Matrix4d>& estimate,
                                                  const std::vector<Eigen::Matrix4d>& ground_truth,
                                                  TrajectoryAlignment alignment = TrajectoryAlignment::kRigid);

/// The rigid transform T minimising sum_k |T source_k - target_k|^2 (rotation and translation,
/// no scale; reflections excluded). Needs at least one point; with fewer than three non-collinear
/// points the rotation is not unique and one minimiser is returned.
Eigen::Matrix4d rigid_alignment(const std::vector<Eigen::Vector3d>& source, const std::vector<Eigen::Vector3d>& target);

/// Parameters of relative_pose_error (KITTI odometry devkit conventions).
struct RelativePoseErrorParams {
  /// Segment lengths along the ground-truth path [m]; KITTI uses 100, 200, ..., 800. Short
  /// sequences need short ones (e.g. 5, 10, 20). Each must be positive and finite.
  std::vector<double> lengths_m = {100, 200, 300, 400, 500, 600, 700, 800};
  std::size_t step_frames = 10;  ///< a segment starts every step_frames frames (>= 1)
};

/// One segment's errors.
struct PoseSegmentError {
  std::size_t first_frame = 0;
  std::size_t last_frame = 0;
  double length_m = 0.0;               ///< the requested length L [m]
  double translation_percent = 0.0;    ///< 100 |t(E)| / L
  double rotation_deg_per_100m = 0.0;  ///< 100 angle(E) / L, angle in degrees
};

/// Averages over the segments of one length.
struct SegmentLengthError {
  double length_m = 0.0;
  std::size_t num_segments = 0;
  double translation_percent = 0.0;    ///< NaN without segments
  double rotation_deg_per_100m = 0.0;  ///< NaN without segments
};

/// Outcome of relative_pose_error.
struct RelativePoseError {
  std::size_t num_segments = 0;
  double translation_percent = 0.0;            ///< mean over every segment of every length; NaN without segments
  double rotation_deg_per_100m = 0.0;          ///< likewise
  std::vector<SegmentLengthError> per_length;  ///< one entry per requested length, in order
  std::vector<PoseSegmentError> segments;      ///< every segment, by first frame then length
};

/// KITTI-devkit relative pose error. For each first frame i = 0, step, 2 step, ... and each
/// length L, the segment ends at the first frame j whose ground-truth path length from i is >= L
/// (the path length is the sum of the distances between consecutive true positions); segments
/// that would run past the end are skipped. The error is E = inv(inv(gt_i) gt_j) (inv(est_i) est_j);
/// the translation error is |t(E)| / L and the rotation error angle(R(E)) / L. No segment fits:
/// num_segments 0 and NaN averages (not an error). Throws std::invalid_argument for unequal or
/// empty inputs, non-finite or non-rigid poses and invalid parameters.
RelativePoseError relative_pose_error(const std::vector<Eigen::Matrix4d>& estimate,
                                      const std::vector<Eigen::Matrix4d>& ground_truth,
                                      const RelativePoseErrorParams& params = {});

/// Which region relations compare_region_layouts forms.
enum class RegionRelations : std::uint8_t {
  /// [TC] Tables 4-5: the K consecutive pairs 1-2, 2-3, ..., K-1 (wrapping around) and the K
  /// consecutive triples K-1-2, 1-2-3, ..., (K-1)-K-1, the angle at the middle region.
  kConsecutive = 0,
  /// Every pair i < j and every triple i < j < k (angle at j): more relations, not the paper's.
  kAllPairs = 1,
};

/// One pair of regions in compare_region_layouts.
struct RegionPairError {
  std::size_t i = 0, j = 0;     ///< the regions, 0-based
  double map_distance_m = 0.0;  ///< |m_i - m_j|
  double dsm_distance_m = 0.0;  ///< |d_i - d_j|
  double error_m = 0.0;         ///< [TC] eq. (5), signed as Table 4: map_distance - dsm_distance
};

/// One triple of regions: the angle at the middle region j between the rays to i and to k.
struct RegionTripleError {
  std::size_t i = 0, j = 0, k = 0;  ///< the regions, 0-based; j is the vertex
  double map_angle_deg = 0.0;       ///< angle(m_i - m_j, m_k - m_j) in [0, 180]
  double dsm_angle_deg = 0.0;       ///< angle(d_i - d_j, d_k - d_j)
  double error_deg = 0.0;           ///< [TC] eq. (6), signed as Table 5: map_angle - dsm_angle
};

/// Outcome of compare_region_layouts. The means and maxima are of the absolute errors, as the
/// "Avg." rows of [TC] Tables 4-5 (3.88 m and 2.91 deg).
struct RegionLayoutComparison {
  std::vector<RegionPairError> pairs;      ///< in the order of RegionRelations
  std::vector<RegionTripleError> triples;  ///< in the order of RegionRelations
  double mean_distance_error_m = 0.0;      ///< mean |error_m|, NaN without pairs
  double max_distance_error_m = 0.0;       ///< max |error_m|, NaN without pairs
  double mean_angle_error_deg = 0.0;       ///< mean |error_deg|, NaN without triples
  double max_angle_error_deg = 0.0;        ///< max |error_deg|, NaN without triples
};

/// The DSM comparison of [TC] section 4.2: the same K regions, listed in order around the site,
/// are located in the robot's global elevation map (map_centres) and in an aerial DSM
/// (dsm_centres); the layouts are compared without registering one to the other, by the distance
/// errors of region pairs ([TC] eq. (5)) and the angle errors of region triples ([TC] eq. (6)).
/// `relations` picks the paper's consecutive relations (default) or every pair and triple. With
/// K = 2 there is one pair and no triple. Points may be 2D (x, y) or 3D ([TC] Table 3);
/// both sets must have the same dimension. Throws std::invalid_argument for fewer than two
/// regions, unequal counts, non-finite coordinates, or two regions at the same place in one set.
RegionLayoutComparison compare_region_layouts(const std::vector<Eigen::VectorXd>& map_centres,
                                              const std::vector<Eigen::VectorXd>& dsm_centres,
                                              RegionRelations relations = RegionRelations::kConsecutive);

}  // namespace terracube
