// Class-weighted ICP between classified elevation maps ([TC] sections 2.2 and 3.3 and its
// appendix): point-to-point ICP whose correspondences pair a source
// cell only with the nearest target cell of the same terrain class, each class with its own
// weight ([TC] eq. (4)), ground taking no part. With classes off and unit weights it is the paper's
// "conventional" ICP over all cells.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "terracube/elevation_map.hpp"
#include "terracube/terrain.hpp"

namespace terracube {

/// Number of TerrainClass values (unknown .. horizontal edge).
inline constexpr std::size_t kNumTerrainClasses = 6;

/// One weight per TerrainClass, indexed by its value.
using ClassWeights = std::array<double, kNumTerrainClasses>;

/// [TC] Table 2: obstacle 0.8, overhanging 0.5, vertical 0.5, horizontal
/// edge 0.8; unknown and ground 0 (they take no part).
inline constexpr ClassWeights kDefaultClassWeights = {0.0, 0.0, 0.8, 0.5, 0.5, 0.8};

/// A set of 3D points, each with a terrain class (the cells of a classified map).
struct ClassifiedPoints {
  std::vector<Eigen::Vector3d> points;  ///< [m]
  std::vector<std::uint8_t> classes;    ///< TerrainClass values, one per point
  std::size_t size() const { return points.size(); }
};

/// Every cell with data in "max" becomes the point (x centre, y centre, max) with the class of
/// the "class" layer written by classify_terrain (unknown where that layer is NaN or absent).
/// Throws std::out_of_range when the map has no "max" layer.
ClassifiedPoints points_of_map(const ElevationMap& map);

/// Which set's points look for partners in a correspondence pass.
enum class Pairing : std::uint8_t {
  /// Each point of the moving map (source, [TC]'s Q) pairs with its nearest in the reference
  /// (target, P): one search per source point, with certificates that skip most searches.
  kSourceToTarget = 0,
  /// [TC] section 2.2, step 2: each point of the reference P pairs with its nearest moved point of
  /// Q. The moved points are indexed again at every pass.
  kTargetToSource = 1,
};

/// Parameters of correlative_search. The defaults cover starts up to about 1.5 m and 14 degrees
/// of yaw from the answer (issue 38's basin: 1 m + 10 degrees) in 0.3 m and 2 degree steps.
struct CorrelativeSearchParams {
  /// Translations within +-window_m of the guess along x and along y [m]. > 0.
  double window_m = 1.5;
  /// Occupancy cell [m]: target cells are marked with their eight neighbours, so a source point
  /// scores within about one cell of a target point. > 0.
  double cell_m = 0.3;
  int step_cells = 1;  ///< translation step in cells, >= 1
  /// Yaw offsets: yaw_hypotheses values spread evenly over +-yaw_window_rad (1: the guess's yaw
  /// only) [rad]. >= 0 and >= 1.
  double yaw_window_rad = 0.25;
  int yaw_hypotheses = 15;
  /// Coarse to fine: then search again around the best hypothesis with cells a third as large
  /// within +-cell_m * step_cells and 5 yaws within +-one yaw step (the coarse score is flat within
  /// a cell). The result's score is the fine level's.
  bool refine = true;
  /// Hypotheses scoring at least (1 - tie_tolerance) times the best count as ties, and ties keep
  /// the hypothesis nearest the guess (cells, a yaw step counting as one): a good guess moves only
  /// for a clearly better match. In [0, 1); 0: exact ties only.
  double tie_tolerance = 0.03;
};

/// Throws std::invalid_argument naming the first field out of range (and a search of over 4 M
/// candidates); correlative_search calls it first.
void check_correlative_search_params(const CorrelativeSearchParams& params);

/// Outcome of correlative_search.
struct CorrelativeSearchResult {
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();  ///< the best hypothesis (target <- source)
  std::size_t score = 0;   ///< source points on occupied target cells at `transform` (the last level's)
  std::size_t points = 0;  ///< source points that took part (non-ground classes)
};

/// Correlative search (in the manner of Olson's real-time correlative scan matching; not in
/// [TC]) over yaw offsets about the source origin and a translation window in x and y: the score
/// of a hypothesis guess * (translation) * Rz(yaw) is the number of the source's non-ground points
/// (class >= kObstacle) that land on a non-ground target cell (dilated by one cell). Near-ties
/// (CorrelativeSearchParams::tie_tolerance) keep the hypothesis nearest the guess. Used before the ICP
/// (RegistrationParams::correlative_search) and by the Mapper's loop closing. Returns the guess with score 0 when
/// either set has no non-ground point, or when the target's non-ground points span more than 2.5e8
/// cells of a level with its margins (about 4.7 km square at the default 0.3 m; 1.5 km for the
/// 0.1 m refinement, which then keeps the coarse answer). Throws std::invalid_argument for invalid parameters or a
/// non-rigid guess.
CorrelativeSearchResult correlative_search(const ClassifiedPoints& source, const ClassifiedPoints& target,
                                           const Eigen::Matrix4d& guess, const CorrelativeSearchParams& params = {});

/// The most updates an iterative solver here may be asked for (RegistrationParams,
/// PclIcpParams, PoseGraphParams, MapperParams): one that has not converged in 10,000 will not,
/// and a larger count only turns a bad pair into a call that seems to hang.
constexpr int kMaxIterationsLimit = 10000;

/// Parameters of register_maps / register_points; defaults follow the paper where it gives them.
struct RegistrationParams {
  /// Before the ICP (a departure, issue 38: the ICP's basin alone is a few degrees of yaw), a
  /// correlative yaw x translation search on the classified points (correlative_search with
  /// `search`) moves the start to the best hypothesis near `initial`. false: the ICP starts from
  /// `initial`, as in the paper.
  bool correlative_search = true;
  CorrelativeSearchParams search;
  /// The paper's plain weighted ICP ([TC] sec. 2.2, eq. (4), Table 2 weights): no correlative
  /// search, no extrapolation, no coarse-to-fine; everything else at the defaults.
  static RegistrationParams paper_icp() {
    RegistrationParams p;
    p.correlative_search = false;
    p.extrapolate = false;
    p.coarse_subsample = 1;
    return p;
  }
  /// true: a source point pairs only with target points of its class and carries its class's
  /// weight (classes of weight 0 take no part). false: the conventional ICP, every point pairs
  /// with the nearest target point of any class at unit weight.
  bool use_classes = true;
  ClassWeights class_weights = kDefaultClassWeights;  ///< [TC] eq. (4) weights, >= 0
  /// Correspondences farther apart than this take no part [m]. At iteration k (from 0) the limit
  /// is max(min_correspondence_distance_m, max_correspondence_distance_m * decay^k).
  double max_correspondence_distance_m = 1.5;
  double min_correspondence_distance_m = 0.3;
  double correspondence_distance_decay = 0.85;  ///< in (0, 1]; 1 keeps the limit fixed
  int max_iterations = 30;                      ///< in [1, kMaxIterationsLimit]
  /// Stop (converged) when an update rotates less than this [rad] and moves less than
  /// translation_tolerance_m [m].
  double rotation_tolerance_rad = 5e-4;
  double translation_tolerance_m = 5e-4;
  /// Stop (converged) when the weighted RMSE of [TC] eq. (2)/(4) falls below this [m]; 0 disables it.
  double error_threshold_m = 0.0;
  std::size_t min_correspondences = 10;  ///< fewer: stop with kTooFewCorrespondences, >= 3
  /// The 6x6 normal matrix is degenerate when its smallest eigenvalue divided by its largest is
  /// below this; registration then stops with kDegenerate (keeping the last estimate) rather than
  /// move along unconstrained directions. In [0, 1). Note: in point-to-point ICP the translation
  /// block of H is sum(w) I, so H stays full rank for points on a plane (sliding along a flat road
  /// shows only in the result, not in H); the test catches collinear or coincident points
  /// (rotation about the line is free). The eigenvalues are reported either way.
  double degeneracy_threshold = 1e-6;
  /// Acceleration after Besl and McKay (the ICP paper, sec. IV-C), guarded (not in either
  /// paper): when two successive updates point the same way and shrink, try a jump along them by
  /// the geometric series' remainder (at most 10 steps) and keep it only if the [TC] eq. (4) error
  /// truncated at the next distance limit, sum w min(d^2, limit^2) over the source points that
  /// take part (class pairs; the ground planes' are left out), is no larger there than after the
  /// plain step (both are evaluated, so a try costs one more correspondence pass). false: the
  /// plain iteration of the paper.
  bool extrapolate = true;
  /// Who looks for partners (a departure: the paper searches from the reference map's points).
  Pairing pairing = Pairing::kSourceToTarget;
  /// Coarse to fine (not in the paper): the first iterations pair only every n-th source point
  /// (>= 1; 1 disables it; also off when fewer than 500 points would remain), until an update
  /// moves the points by less than coarse_until_motion_m (|t| + |omega| * rms radius) [m]. Every
  /// stopping decision and the final estimate use all the points.
  int coarse_subsample = 4;
  double coarse_until_motion_m = 0.05;
  /// Ground as planes (not in the paper, where ground takes no part; 0 keeps it out). With a
  /// positive weight and use_classes, the ground cells add a point-to-plane term: the target's
  /// ground points are binned into square cells of ground_cell_m, each fitted with a plane (least
  /// squares z = a + b x + c y; a horizontal plane at the mean below three points or when
  /// ill-conditioned); the source's ground points are binned alike and each occupied cell's mean
  /// point is one sample, paired with the plane of the target cell its moved (x, y) falls in
  /// (no search) and weighted ground_weight in [TC] eq. (4), its residual the distance along the
  /// plane's normal. Such pairs fix height, roll and pitch, which the non-ground classes leave
  /// loose, without the pull along the road of point-to-point ground pairs. They count in
  /// correspondences_per_class[ground], the RMSE and the normal matrix. Independent of
  /// class_weights[ground] (point-to-point ground pairs). >= 0.
  double ground_weight = 0.0;
  double ground_cell_m = 0.5;  ///< > 0 [m]
  /// Radius of the target neighbourhoods behind RegistrationResult::constraint_matrix [m]; 0 (the
  /// default) skips that analysis and leaves the matrix zero. About three cells suits a map (0.3
  /// for 0.1 m cells). A direction counts as one along which a partner's neighbourhood extends
  /// when its points' standard deviation along it exceeds a quarter of the radius. The analysis
  /// runs once, at the final estimate, in O(correspondences x neighbours): on KITTI 0.1 m maps it
  /// adds 1-2 ms to a registration (a neighbourhood query and a 3 x 3 eigen-decomposition per
  /// correspondence), and a radius spanning the whole map makes it quadratic. >= 0.
  double structure_radius_m = 0.3;
  /// Thresholds of RegistrationResult::trusted (issue 38; not in the paper). Trusted needs all of:
  /// the ICP stopped converged (or at max_iterations); overlap >= trust_min_overlap; overlap >=
  /// trust_min_contrast * chance_overlap (the match beats coincidence); rmse_m <=
  /// trust_max_rmse_m; and, when the constraint analysis ran (structure_radius_m > 0), every
  /// direction held by at least trust_min_held of the pairs' weight (RegistrationResult::held).
  /// Measured (bench/bench_basin.py, 60 x 40 m maps at 0.1 m): related KITTI and simulated pairs
  /// reach overlap 0.57-0.89 at 2.5-3.3 times the chance overlap, held >= 0.06; the two Ouster
  /// scans of different places 0.35-0.39 at 1.1 times; a simulated loop frame against one of the
  /// straight road (another world) fails both.
  double trust_min_overlap = 0.25;  ///< in [0, 1]
  double trust_min_contrast = 2.0;  ///< >= 0
  double trust_max_rmse_m = 0.2;    ///< > 0 [m]
  double trust_min_held = 0.05;     ///< in [0, 1]
};

/// Throws std::invalid_argument naming the first field out of range; the registration calls it first, and a
/// configuration can call it before the first scan.
void check_registration_params(const RegistrationParams& params);

/// Why registration stopped.
enum class StopReason : std::uint8_t {
  kConverged = 0,              ///< the update fell below both tolerances
  kErrorBelowThreshold = 1,    ///< the weighted RMSE fell below error_threshold_m
  kMaxIterations = 2,          ///< max_iterations updates without converging
  kTooFewCorrespondences = 3,  ///< fewer than min_correspondences pairs within the distance
  kNoCommonClass = 4,          ///< no class of non-zero weight has points in both sets
  kDegenerate = 5,             ///< the normal matrix leaves some direction unconstrained
};

/// A short lower-case name ("converged", "max_iterations", ...).
const char* to_string(StopReason reason);

/// Outcome of a registration.
struct RegistrationResult {
  /// Maps source coordinates into the target frame: q ~ transform * p. On kDegenerate,
  /// kTooFewCorrespondences and kNoCommonClass it is the last estimate before the failure.
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();
  /// Where the ICP started: `initial`, or the correlative search's best hypothesis near it.
  Eigen::Matrix4d icp_start = Eigen::Matrix4d::Identity();
  bool converged = false;  ///< reason is kConverged or kErrorBelowThreshold
  StopReason reason = StopReason::kMaxIterations;
  int iterations = 0;  ///< updates applied
  /// Correspondence passes (nearest-neighbour sweeps over the source): one per iteration, plus one
  /// more for each extrapolation tried (both the jump and the plain step are evaluated).
  int passes = 0;
  int extrapolations = 0;  ///< extrapolated jumps accepted by the guard
  /// sqrt(sum w_i |R p_i + t - q_i|^2 / sum w_i) over the correspondences at `transform` [m]
  /// ([TC] eq. (2), weighted as [TC] eq. (4)); NaN without correspondences.
  double rmse_m = 0.0;
  double correspondence_distance_m = 0.0;  ///< the distance limit of the last pass [m]
  std::size_t num_correspondences = 0;
  std::array<std::size_t, kNumTerrainClasses> correspondences_per_class{};  ///< by source class
  /// The weighted normal matrix H = sum w_i J_i^T J_i of [TC] eq. (A6) at `transform`, unknowns
  /// (rotation [rad], translation [m]) about the correspondences' weighted source centroid.
  Eigen::Matrix<double, 6, 6> normal_matrix = Eigen::Matrix<double, 6, 6>::Zero();
  Eigen::Matrix<double, 6, 1> eigenvalues = Eigen::Matrix<double, 6, 1>::Zero();  ///< of H, ascending
  /// What the geometry constrains (not in the paper): sum w_i J_i^T P_i J_i over the final
  /// correspondences, J_i the point-to-point Jacobian of normal_matrix (same unknowns, same
  /// centroid) and P_i the projector onto the directions in which the partner's neighbourhood
  /// (its class's target points within structure_radius_m) has no extent: the normal of a surface
  /// (a road), the plane across a line (the top of a wall), every direction at an isolated point
  /// (the top of a pole). Ground planes (ground_weight) add their normals. It is the Gauss-Newton
  /// matrix of the distances to the target's structures: motions along them get eigenvalues near
  /// zero (a flat road: x, y and yaw; a street between straight walls or a tunnel: its direction),
  /// which normal_matrix, full rank whenever the points span a plane, cannot show. Zero unless
  /// RegistrationParams::structure_radius_m > 0 and there are correspondences.
  Eigen::Matrix<double, 6, 6> constraint_matrix = Eigen::Matrix<double, 6, 6>::Zero();
  Eigen::Matrix<double, 6, 1> constraint_eigenvalues = Eigen::Matrix<double, 6, 1>::Zero();  ///< ascending
  /// Unit eigenvectors of constraint_matrix, as columns in the order of constraint_eigenvalues.
  Eigen::Matrix<double, 6, 6> constraint_eigenvectors = Eigen::Matrix<double, 6, 6>::Zero();

  // The verdict (issue 38; not in the paper): whether the answer can be trusted, and why.
  /// Share of the source's object cells (the classes from kObstacle up that take part; every
  /// point without classes) with a partner within min_correspondence_distance_m (0.3 m) at
  /// `transform`, whatever distance limit the ICP stopped at.
  double overlap = 0.0;
  /// The overlap at `transform` moved by 1 m along +x, -x, +y or -y, the least of the four: what
  /// coincidence alone gives in these maps (a corridor keeps its overlap along itself, not
  /// across). A real match stands well above it.
  double chance_overlap = 0.0;
  /// Per source class: the share of its points that take part with a partner within
  /// min_correspondence_distance_m (0 without points).
  std::array<double, kNumTerrainClasses> inlier_share_per_class{};
  /// How firmly the scene holds each motion: the eigenvalues (ascending) of constraint_matrix per
  /// unit of the class pairs' weight W (without ground planes, a third of the trace of
  /// normal_matrix's translation block; the planes, which hold only height, roll and pitch, are
  /// not counted), rotations scaled by those pairs' rms radius r (trace of their rotation block =
  /// 2 W r^2): 1 along a translation means every pair holds it fully, 0 that none does. Zero
  /// without the analysis.
  Eigen::Matrix<double, 6, 1> held = Eigen::Matrix<double, 6, 1>::Zero();
  /// Unit eigenvectors of `held` as columns, in the scaled unknowns (rotation x r, translation).
  Eigen::Matrix<double, 6, 6> held_directions = Eigen::Matrix<double, 6, 6>::Zero();
  /// All of RegistrationParams' trust thresholds are met.
  bool trusted = false;
  /// The verdict in plain words, e.g. "trusted: overlap 81 %, RMSE 0.06 m, every direction held by
  /// at least 22 % of the pairs' weight" or "not trusted: sliding along x is held by 6 % of the
  /// pairs' weight: the result along x is not trustworthy".
  std::string verdict;
};

/// Registers `source` onto `target` starting from `initial` (a rigid 4x4, e.g. odometry).
/// Each iteration pairs every source point (moved by the current estimate) with its nearest
/// target point within the current distance limit (of its class when use_classes), builds the
/// linearised weighted normal equations of [TC] eq. (A6), solves them with LDLT and composes the
/// update as an exact rotation (Rodrigues). Throws std::invalid_argument for invalid parameters,
/// a non-finite or non-rigid `initial`, non-finite points or class values >= 6.
RegistrationResult register_points(const ClassifiedPoints& source, const ClassifiedPoints& target,
                                   const Eigen::Matrix4d& initial, const RegistrationParams& params = {});

/// register_points on points_of_map(source) and points_of_map(target), with the same result; only
/// the cells that can take part are turned into points (with use_classes, those of classes with a
/// positive weight: ground, usually most of a map, is skipped). With use_classes the maps need the
/// "class" layer (classify_terrain); std::invalid_argument otherwise.
RegistrationResult register_maps(const ElevationMap& source, const ElevationMap& target, const Eigen::Matrix4d& initial,
                                 const RegistrationParams& params = {});

/// The paper's conventional ICP: register_maps with use_classes = false (every cell, unit weight).
RegistrationResult register_maps_all_cells(const ElevationMap& source, const ElevationMap& target,
                                           const Eigen::Matrix4d& initial, RegistrationParams params = {});

/// Exact nearest neighbour among a fixed set of 3D points (a compact k-d tree). Kept as a general
/// index; register_points uses NearestNeighborGrid, which is faster on map cells.
class NearestNeighbor3d {
 public:
  NearestNeighbor3d() = default;
  explicit NearestNeighbor3d(std::vector<Eigen::Vector3d> points);
  /// Index (into the constructor's points) of the nearest point whose squared distance is at most
  /// `max_squared_distance` (ties: any one), or -1. `squared_distance` receives that distance.
  std::ptrdiff_t nearest(const Eigen::Vector3d& query, double max_squared_distance, double& squared_distance) const;
  std::size_t size() const { return points_.size(); }
  /// The constructor's point `index`.
  const Eigen::Vector3d& point(std::size_t index) const { return points_[position_[index]]; }

 private:
  struct Node {
    double split = 0.0;
    std::uint32_t begin = 0, end = 0;  // leaf range in order_ (leaves only)
    std::int32_t left = -1, right = -1;
    std::int8_t axis = -1;  // -1: leaf
  };
  std::int32_t build(std::uint32_t begin, std::uint32_t end);
  std::vector<Eigen::Vector3d> points_;  // in leaf order once built
  std::vector<std::uint32_t> original_;  // constructor index of points_[k]
  std::vector<std::uint32_t> position_;  // inverse of original_
  std::vector<Node> nodes_;
};

/// Exact nearest neighbour (3D Euclidean) among a fixed set of points bucketed on a 2D (x, y)
/// grid: suited to the cells of 2.5D maps, where a column holds one or a few points. A query
/// scans whole rows of buckets (contiguous memory) outward from its own row, each row only as
/// wide as the best distance so far allows, and stops when a row's y gap alone exceeds it; every
/// point within the limit that could be nearer is examined, so the answer is exact whatever the
/// data (tall 3D columns only make it slower). Used by register_points for every class.
class NearestNeighborGrid {
 public:
  NearestNeighborGrid() = default;
  /// `bucket_size_m` > 0 sets the bucket edge [m]; 0 picks half the mean point spacing over the
  /// points' (x, y) bounding box (about four buckets per point). Throws std::invalid_argument for
  /// non-finite points, a negative or non-finite bucket size, or a grid of more than 2^31 buckets.
  explicit NearestNeighborGrid(std::vector<Eigen::Vector3d> points, double bucket_size_m = 0.0);
  /// Index (into the constructor's points) of the nearest point whose squared distance is at most
  /// `max_squared_distance` (ties: any one), or -1. `squared_distance` receives that distance.
  std::ptrdiff_t nearest(const Eigen::Vector3d& query, double max_squared_distance, double& squared_distance) const;
  /// The two nearest points within the limit and a bound on all the others: `indices` receives
  /// the nearest and the second-nearest (-1 where there is none), `squared_distances` their squared
  /// distances (`max_squared_distance` where there is none) and `others_squared_distance` a value
  /// that every other point's squared distance reaches: the third-nearest's, or
  /// `max_squared_distance` when no third point lies within the limit. Ties: any order. Returns
  /// indices[0]. register_points uses the bound to prove that a moved query keeps its nearest
  /// point among the two without searching again.
  std::ptrdiff_t nearest_two(const Eigen::Vector3d& query, double max_squared_distance,
                             std::array<std::ptrdiff_t, 2>& indices, std::array<double, 2>& squared_distances,
                             double& others_squared_distance) const;
  /// Appends to `out` the constructor indices of the points within `radius` (3D) of `query`, in
  /// no particular order.
  void within(const Eigen::Vector3d& query, double radius, std::vector<std::uint32_t>& out) const;
  /// Whether a point's squared distance to `query` is at most `max_squared_distance`: exactly when
  /// nearest() finds one, with no nearest sought (a search stops at the first).
  bool any_within(const Eigen::Vector3d& query, double max_squared_distance) const;
  std::size_t size() const { return points_.size(); }
  /// The constructor's point `index`.
  const Eigen::Vector3d& point(std::size_t index) const { return points_[position_[index]]; }
  double bucket_size_m() const { return bucket_size_m_; }

 private:
  /// The search behind nearest() (kKeep 1) and nearest_two() (kKeep 2, kBound): best[] holds the
  /// kKeep (+ 1 with kBound) smallest squared distances, found[] the indices of the first kKeep.
  template <int kKeep, bool kBound>
  void search(const Eigen::Vector3d& query, double max_squared_distance, std::ptrdiff_t* found, double* best) const;
  /// Calls visit(k) for the position k in points_ of every point of the buckets that can hold a
  /// point within `radius` of `query` (and a few more), until visit returns true; returns whether it did.
  template <typename Visit>
  bool visit_near(const Eigen::Vector3d& query, double radius, const Visit& visit) const;

  double bucket_size_m_ = 1.0;
  double inverse_bucket_size_ = 1.0;
  Eigen::Vector2d origin_ = Eigen::Vector2d::Zero();  // lower corner of bucket (0, 0) [m]
  std::int64_t columns_ = 0, rows_ = 0;               // buckets along x, along y
  std::vector<std::uint32_t> start_;                  // bucket b = row * columns_ + column: [start_[b], start_[b+1])
  std::vector<Eigen::Vector3d> points_;               // in bucket order
  std::vector<std::uint32_t> original_;               // constructor index of points_[k]
  std::vector<std::uint32_t> position_;               // inverse of original_
};

}  // namespace terracube
