// Global elevation maps from scan sequences ([TC] sections 3.3 and 4):
// every ~3 m of travel a local classified elevation map is built from the scan, registered to the
// previous local map by the class-weighted ICP (odometry as the initial guess) and fused into a
// global elevation map that grows with the area covered. Revisits are detected (pose proximity,
// then map overlap), registered, and the pose graph is optimised with Ceres; the global map is then
// rebuilt from the corrected keyframe poses.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <vector>

#include "terracube/cube_grid.hpp"
#include "terracube/elevation_map.hpp"
#include "terracube/icp.hpp"
#include "terracube/terrain.hpp"

namespace terracube {

/// Parameters of the Mapper. Frames: scans arrive in the sensor frame with an odometry pose
/// world <- sensor; each keyframe's local map lives in its leveled frame L (origin at the sensor,
/// z up along gravity as odometry's roll and pitch give it, x along the sensor's heading).
struct MapperParams {
  /// A new local map every this much travel [m] (the paper: about 3 m). > 0.
  double keyframe_distance_m = 3.0;
  /// A new local map also when odometry turned by this much since the last one [rad]. > 0.
  double keyframe_rotation_rad = 0.5;
  /// add_scan refuses odometry that moved farther than this since the previous scan [m] (a
  /// glitch, e.g. a GPS jump: one would stretch the global map over kilometres); > 0.
  double max_odometry_step_m = 50.0;

  /// Local maps: cell size [m] (also the global map's; [TC] section 2.1: 0.1 m) and the square
  /// extent centred on the sensor [m].
  double resolution_m = 0.1;
  double local_map_size_m = 40.0;
  /// A local map is built from the keyframe's scan and the scans since the previous keyframe (at most
  /// this many scans in all, the newest), moved into the keyframe's leveled frame by odometry. Denser
  /// maps from sparse scanners, but odometry's drift within a keyframe distorts them (measured on the
  /// test world with 0.23 deg/m of yaw drift: chaining error 0.02 m with 1 scan, 0.5 m with 3).
  /// 1 (default): the keyframe's scan alone, as in the paper.
  int max_scans_per_local_map = 1;
  /// Threads of each keyframe's local map (ElevationParams::num_threads: 1 the calling thread, 0
  /// one per processor; the same map whatever the number). Its classes take terrain.num_threads.
  int num_threads = 1;
  /// Keep every keyframe's local map (all layers) for local_map(k). Off, only the newest is kept and
  /// a keyframe holds its cells (about 28 bytes each) and the cells its class weights can pair.
  bool keep_local_maps = false;
  /// Points nearer the sensor than min_range_m (the robot itself) or farther than max_range_m take
  /// no part (counted in ScanReport::num_out_of_range) [m]. 0 <= min_range_m < max_range_m (+inf:
  /// no limit).
  double min_range_m = 0.5;
  double max_range_m = std::numeric_limits<double>::infinity();
  /// Discontinuity threshold of the elevations within a cell [m] (the paper: 1 m).
  double discontinuity_m = 1.0;
  /// [TC] Table 1 thresholds. The default measures heights from the local ground (lowest elevations around
  /// the cell), which keeps classes right on slopes; the paper's sensor-height reference is available.
  /// The window is 5 cells (0.5 m at 0.1 m): the window minimum lies slope x radius below a cell
  /// on a slope, so a larger window calls ramps obstacles.
  TerrainParams terrain = [] {
    TerrainParams t;
    t.reference = GroundReference::kLocalGround;
    t.local_ground_radius_cells = 5;
    return t;
  }();

  /// false: chain local maps by odometry alone (no scan matching): a baseline.
  bool use_registration = true;
  /// LiDAR-only mode (no odometry): the translation and yaw of the poses given to add_scan are
  /// ignored (their roll and pitch still level the local maps: pass identity for a level sensor,
  /// or an IMU's attitude). Every scan is registered to the newest keyframe from a constant-velocity
  /// prediction (the previous scan's motion repeated, from the Mapper's own estimates; none before
  /// the first registered scan, which is searched within keyframe_distance_m + the registration's
  /// search window), and becomes a keyframe once the estimates travelled keyframe_distance_m (or
  /// turned keyframe_rotation_rad) since the newest one: feed every scan of a sequence. A trusted
  /// registration is accepted whatever its correction of the prediction (max_correction_m and
  /// max_correction_rad bound odometry's corrections only); an untrusted one keeps the
  /// prediction. Each scan costs a local map and a registration. Local maps are single scans.
  /// The height comes from the ground (ground_step_height). Without an attitude the motion is
  /// level: a ramp's height is not followed.
  /// Needs use_registration. keyframe_odometry() then returns the predictions.
  bool lidar_only = false;
  RegistrationParams registration;
  /// Local maps live in leveled frames (odometry's roll and pitch, as from an IMU), so the motion
  /// between two of them is a translation and a yaw: true keeps only those of the 6-DOF ICP result
  /// (the ground takes no part in it, which leaves roll and pitch weakly constrained; their noise
  /// would tilt the fused global map). false: the full 6-DOF result, as the paper.
  bool yaw_only_registration = true;
  /// A registered step's or loop edge's height from the ground the two local maps share (the
  /// median offset of their common ground cells; not in [TC]): the ICP leaves the ground out, so
  /// only the objects hold the height, loosely (on the simulated loop the steps moved it by up to
  /// 1.2 m although odometry's was right to 0.02 m). false: the ICP's height, as the paper.
  bool ground_step_height = true;
  /// With odometry, a step is first registered from odometry's guess without the correlative
  /// search (it can only blur a good guess), and again with it (registration.correlative_search)
  /// only when that answer is not trusted.
  /// A registration is rejected (odometry is used for that step, counted in
  /// MapperTimings::untrusted_steps) when it is not trusted (RegistrationResult::trusted), or when
  /// it moves the odometry guess by more than these [m], [rad].
  double max_correction_m = 1.5;
  double max_correction_rad = 0.15;
  /// Standard deviations that weight the pose-graph edges (information = 1 / sigma^2):
  /// registered steps, odometry-only steps (per metre travelled, at least `odometry_sigma_min`) and loops.
  double registration_sigma_m = 0.05;
  double registration_sigma_rad = 0.005;
  double odometry_sigma_m_per_m = 0.05;
  double odometry_sigma_rad_per_m = 0.01;

  /// Loop closing (independent of use_registration, so drifting odometry alone can be corrected):
  /// a keyframe is a candidate when its estimated position lies within
  /// loop_search_radius_m of the new keyframe and at least loop_min_travel_m of path separates them;
  /// then at least loop_min_overlap of the new local map's cells must land on cells of the candidate's.
  bool loop_closing = true;
  double loop_search_radius_m = 10.0;
  double loop_min_travel_m = 30.0;
  double loop_min_overlap = 0.3;
  /// Overlap is counted on blocks of this size [m] (sparse scans sample different cells of one surface).
  double overlap_block_m = 1.0;
  /// At most this many candidates (the nearest first) are registered per keyframe.
  int loop_max_candidates = 2;
  /// Loop registrations start from drifted estimates: a correlative search over yaw offsets
  /// (loop_yaw_hypotheses spread evenly over +-loop_yaw_search_rad; 1 = the estimate's yaw only) and
  /// translations within +-loop_search_window_m (two-cell steps) maximises the number of non-ground
  /// cells that land on non-ground cells of the candidate; the ICP starts from the best hypothesis.
  double loop_search_window_m = 6.0;
  double loop_yaw_search_rad = 0.15;
  int loop_yaw_hypotheses = 13;
  /// A loop registration is accepted when it converged (or hit the iteration limit) with a weighted RMSE
  /// below this [m] and at least registration.min_correspondences pairs.
  double loop_max_rmse_m = 0.2;
  /// ... and when at least this share of the new map's weighted cells found a correspondence.
  double loop_min_inlier_ratio = 0.3;
  /// Ceres iterations for the pose graph.
  int pose_graph_iterations = 50;
  /// While a revisit keeps closing loops, the pose graph is optimised (and the global map rebuilt,
  /// both O(keyframes)) at most once per this many keyframes; Mapper::optimize() applies loops
  /// still pending (call it after the last scan). 1: after every new loop.
  int optimize_interval_keyframes = 5;
};

/// Throws std::invalid_argument naming the first field out of range; the Mapper calls it first, and a
/// configuration can call it before the first scan.
void check_mapper_params(const MapperParams& params);

/// What happened to one scan given to Mapper::add_scan.
struct ScanReport {
  bool keyframe = false;             ///< a local map was built from this scan
  std::ptrdiff_t index = -1;         ///< its keyframe index, or -1
  bool registered = false;           ///< the step was scan-matched (false: odometry was used)
  RegistrationResult registration;   ///< of the step to the previous keyframe (when tried)
  std::size_t loops_closed = 0;      ///< loop edges added by this keyframe
  std::size_t num_out_of_range = 0;  ///< points left out by min_range_m and max_range_m
  /// The scan's estimated world <- sensor pose when it was added: its keyframe's estimate (after
  /// any loop closing of this call) moved by odometry since that keyframe (LiDAR-only: its own
  /// registration). Later loop closing may correct the keyframes; this is the pose a robot would
  /// act on at the time.
  Eigen::Matrix4d pose = Eigen::Matrix4d::Identity();
};

/// A loop edge between two keyframes.
struct LoopClosure {
  std::size_t from = 0, to = 0;                            ///< keyframe indices, from < to
  Eigen::Matrix4d relative = Eigen::Matrix4d::Identity();  ///< L_from <- L_to
  double rmse_m = 0.0;
  double overlap = 0.0;
};

/// Milliseconds spent per stage, summed over all scans so far.
struct MapperTimings {
  double map_building_ms = 0.0;  ///< leveling + elevation map layers
  double classification_ms = 0.0;
  double registration_ms = 0.0;  ///< step registrations
  double fusion_ms = 0.0;        ///< into the global map (including rebuilds)
  double loop_closing_ms = 0.0;  ///< candidate search, loop registrations, pose graph
  std::size_t scans = 0;
  std::size_t keyframes = 0;
  /// Steps whose registration was accepted (a step: a keyframe to the previous one; LiDAR-only,
  /// every scan after the first to the newest keyframe).
  std::size_t registered_steps = 0;
  /// Steps whose registration was not trusted (RegistrationResult::trusted false): odometry (in
  /// LiDAR-only mode the constant-velocity prediction) was used instead.
  std::size_t untrusted_steps = 0;
};

/// The global elevation map: square tiles allocated as cells are first touched, so its memory grows
/// with the area covered. Per cell: count, min, max (the paper's "highest elevation"), the sums
/// that give mean (the DEM) and std-dev, and the discontinuity flag (any fused local cell had one).
class TiledElevationMap {
 public:
  static constexpr int kTileCells = 64;  ///< cells along each tile side

  explicit TiledElevationMap(double resolution_m = 0.1);
  ~TiledElevationMap();
  TiledElevationMap(TiledElevationMap&&) noexcept;
  TiledElevationMap& operator=(TiledElevationMap&&) noexcept;
  double resolution_m() const { return resolution_m_; }
  void clear();
  /// Fuses one local cell sample at world position (x, y).
  void fuse(double x, double y, float z_min, float z_max, float z_mean, float z_std, std::uint32_t count,
            bool discontinuous);
  std::size_t num_tiles() const;
  std::size_t memory_bytes() const;
  /// A dense map over the tiles' bounding box with layers count, min, max, mean, std_dev and
  /// discontinuity (NaN where no data). Throws std::length_error beyond max_cells.
  ElevationMap to_map(std::size_t max_cells = std::size_t{1} << 26) const;

 private:
  double resolution_m_;
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// Chains scans into a global elevation map (see the file comment).
class Mapper {
 public:
  explicit Mapper(const MapperParams& params = {});
  ~Mapper();
  Mapper(Mapper&&) noexcept;
  Mapper& operator=(Mapper&&) noexcept;

  const MapperParams& params() const;

  /// Feeds one scan (points in the sensor frame) with its odometry pose (world <- sensor, rigid).
  /// Builds a keyframe when the robot moved keyframe_distance_m (or turned keyframe_rotation_rad)
  /// since the last one (LiDAR-only: by the Mapper's own estimates); the first scan is always a
  /// keyframe. ScanReport::pose is the scan's estimated pose. Throws std::invalid_argument for a
  /// non-finite or non-rigid pose and for NaN/Inf points.
  ScanReport add_scan(const PointsView<float>& points, const Eigen::Matrix4d& odometry_pose);
  ScanReport add_scan(const PointsView<double>& points, const Eigen::Matrix4d& odometry_pose);

  std::size_t num_keyframes() const;
  /// Points of the scans added so far left out by min_range_m and max_range_m.
  std::size_t points_out_of_range() const;
  /// Loop edges added since the last pose-graph optimisation (see optimize_interval_keyframes).
  std::size_t pending_loops() const;
  /// Estimated world <- sensor pose of every keyframe (after loop closing when it happened).
  std::vector<Eigen::Matrix4d> keyframe_poses() const;
  /// Odometry world <- sensor pose of every keyframe, as given.
  std::vector<Eigen::Matrix4d> keyframe_odometry() const;
  /// Index (count of add_scan calls before it) of the scan each keyframe was built from.
  std::vector<std::size_t> keyframe_scan_indices() const;
  const std::vector<LoopClosure>& loop_closures() const;
  const MapperTimings& timings() const;

  /// The local classified map of keyframe k, in its leveled frame (layers of build_elevation_map
  /// plus classify_terrain's). Only the newest keyframe's is kept unless keep_local_maps;
  /// std::out_of_range otherwise.
  const ElevationMap& local_map(std::size_t k) const;
  /// The global map with layers count, min, max (highest elevation), mean (DEM), std_dev,
  /// discontinuity and, when `classify`, the classes of classify_terrain (local ground reference).
  ElevationMap global_map(bool classify = true) const;
  const TiledElevationMap& tiles() const;

  /// Optimises the pose graph (steps + loop edges) with Ceres and rebuilds the global map from the
  /// corrected poses. add_scan calls it when it closes loops (at most every
  /// optimize_interval_keyframes); call it after the last scan for loops still pending. A no-op
  /// without loop edges.
  void optimize();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace terracube
