// A robot-centric local elevation map fused over time (issue 35): an extension beyond the papers.
// Each scan is leveled and its overhangs removed ([CBC] Algorithm 1, collapse_overhangs), binned
// into cells and fused into each cell's height by a 1-D Kalman update; the map follows the robot
// by shifting a circular buffer (as grid_map's move), clears heights that this scan's rays saw
// through, and keeps the [TC] Table 1 inputs ("max", "min", "std_dev", "discontinuity") so that
// classify_terrain runs on to_elevation_map().
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "terracube/collapse.hpp"
#include "terracube/cube_grid.hpp"
#include "terracube/elevation_map.hpp"
#include "terracube/traversability.hpp"

namespace terracube {

/// Parameters of LocalMap. Defaults: a 20 x 20 m map at 0.1 m, [CBC]'s cube edge and sigma.
struct LocalMapParams {
  double length_m = 20.0;     ///< side of the square map [m], > 0; cells = round(length / resolution)
  double resolution_m = 0.1;  ///< cell edge [m], > 0
  /// Largest number of cells allowed (memory guard): a map keeps about 72 bytes a cell (14 float
  /// layers and the update's per-cell work), so the default 16 M cells (4096 x 4096) is about 1.2 GB.
  std::size_t max_cells = std::size_t{1} << 24;
  /// Overhang removal of each scan. update() sets its transform (the scan's pose) and bounds it
  /// by the map's area; every other field is used as given (drop_non_finite decides whether NaN/Inf
  /// rows are dropped or refused). Its crop, when set, is a box around the sensor: the scan leveled
  /// by the pose, relative to the sensor's position (z >= -3 m leaves out multipath returns under a
  /// road seen from 1.7 m up); returns outside it take no part, not even in the see-through test
  /// (counted in LocalMapUpdate::num_cropped).
  CollapseParams collapse;
  /// Returns nearer the sensor than min_range_m (the robot's own body, no-returns stored as
  /// (0, 0, 0)) or farther than max_range_m take no part (counted in LocalMapUpdate::num_out_of_range);
  /// 0 <= min_range_m < max_range_m (+inf: no limit).
  double min_range_m = 0.1;
  double max_range_m = std::numeric_limits<double>::infinity();
  /// Measurement noise model: a return at range r and elevation angle phi from the sensor has
  /// the height variance  var_z = range_sigma^2 sin^2(phi) + (r angle_sigma)^2 cos^2(phi)  (range
  /// noise along the beam, angular noise across it). A cell's measurement from one scan is the
  /// mean z of its n kept points with the variance  (mean var_z + spread^2) / n + cell_sigma^2,
  /// spread^2 the population variance of those heights, cell_sigma the height error that does
  /// not average out over the points: on sloped ground their mean lies off the cell's centre, and
  /// a moving sensor's sweep is distorted.
  /// Defaults for a Velodyne HDL-64E-class sensor on a vehicle; the simulator's exact noise is
  /// range 0.02, angle 0, cell 0.004 (the normalised error is then about 1 on a drive). Scans from
  /// a sensor standing still repeat the same beams, whose errors are not independent: the
  /// variance then shrinks faster than the error.
  double range_sigma_m = 0.02;      ///< >= 0
  double angle_sigma_rad = 0.0015;  ///< >= 0
  double cell_sigma_m = 0.02;       ///< > 0
  /// Height drift of the odometry: before each update every known cell's variance grows by
  /// drift^2 times the distance the sensor moved since the last update [m] (a random walk per
  /// metre travelled, as elevation_mapping's robot-motion variance). 0 for exact poses.
  double drift_m_per_sqrt_m = 0.01;  ///< >= 0
  /// A measurement further than gate_sigmas standard deviations of the innovation from the cell's
  /// estimate replaces it (the cell changed, e.g. an object came or went) instead of being fused.
  double gate_sigmas = 3.0;  ///< > 0
  /// A cell's height is cleared when this scan's rays passed through its column, on their way to
  /// returns at least clearing_beyond_m further away (more than a sweep's motion distortion or a
  /// pose error moves a surface), between its lowest fused point (or clearing_depth_m below its
  /// height, if lower) and clearing_margin_m below its height: where its own points would have
  /// stopped them (it was seen through: a person or car that left). Rays below everything the cell
  /// holds (under a car's body or a table) say nothing about it. The test bins this scan's returns
  /// by direction from the sensor (bins of visibility_bin_rad in elevation, twice that in azimuth)
  /// and keeps each bin's nearest horizontal range (returns 1000 km or more away, or within a
  /// micrometre of the vertical through the sensor, are left out); a bin counts when all its returns
  /// lie beyond.
  /// A cell this scan measures again is not cleared (rays that pass beside a thin pole inside its
  /// cell would otherwise clear it every scan): its measurement is fused, or replaces the height
  /// when it fails the gate. Transparent and porous things (car windows, foliage) that no return
  /// lands in this time are cleared too, and measured again when hit again.
  bool clear_seen_through = true;
  double clearing_margin_m = 0.1;      ///< >= 0
  double clearing_depth_m = 0.5;       ///< > clearing_margin_m
  double clearing_beyond_m = 0.5;      ///< >= 0 (at least one cell is used)
  double visibility_bin_rad = 0.0087;  ///< in [0.001, 0.5]
  /// A cell is discontinuous when one scan's sorted kept heights in it have a gap over this [m].
  double discontinuity_m = 1.0;
  /// Recompute step, slope, roughness and traversability after every update (else call
  /// update_planner_layers()).
  bool compute_planner_layers = true;
  TraversabilityParams traversability;
  /// Threads of the collapse and the planner layers: 1 (default) the calling thread, 0 one per
  /// processor. The map is the same bit for bit whatever the number.
  int num_threads = 1;
};

/// Throws std::invalid_argument naming the first field out of range; the LocalMap calls it first, and a
/// configuration can call it before the first scan.
void check_local_map_params(const LocalMapParams& params);

/// What one LocalMap::update did.
struct LocalMapUpdate {
  std::size_t num_points = 0;    ///< rows given
  std::size_t num_in_map = 0;    ///< finite rows inside the map's area
  std::size_t num_overhang = 0;  ///< rows collapse_overhangs flagged (not fused)
  std::size_t num_dropped_non_finite = 0;
  std::size_t num_cropped = 0;         ///< finite rows outside collapse.crop around the sensor
  std::size_t num_out_of_range = 0;    ///< rows nearer than min_range_m or farther than max_range_m
  std::size_t num_fused_cells = 0;     ///< cells that got a measurement
  std::size_t num_replaced_cells = 0;  ///< of those, cells whose measurement failed the gate
  std::size_t num_cleared_cells = 0;   ///< cells cleared because this scan saw through them
  bool map_reset = false;              ///< the pose jumped by a map length or more: all cells dropped
};

/// A square robot-centric elevation map in the odometry frame.
///
/// Cells are the global cells floor(x / resolution), floor(y / resolution) of the odometry frame;
/// the map holds the size x size of them centred on the robot's cell. The layers live in a
/// circular buffer: global cell (gx, gy) is stored at index (gx mod size, gy mod size), so moving
/// the map clears the rows and columns that leave (they become the entering ones) and copies
/// nothing else. Read a layer with index_of(), or take to_elevation_map() for a copy in map order.
///
/// Layers (float, NaN = unknown, "count" 0): "elevation" (Kalman estimate of the overhang-free
/// height [m]), "variance" [m^2], "count" (kept points fused since the cell was last reset),
/// "time" (stamp of the last update that measured the cell minus time_origin_s() [s]), "min", "max", "std_dev" (of
/// those points), "discontinuity" (of the last scan that measured the cell, 1 or 0), "overhang_min" (lowest overhang
/// point of the last scan that saw one in the cell), "clearance" (overhang_min - elevation, 0 when that
/// point lies at or below the elevation: a cube column straddling the cell can flag a point level with its ground,
/// and 0 blocks rather than guesses; +inf when no overhang was seen, NaN without elevation), and the planner layers
/// "step", "slope", "roughness", "traversability" (TraversabilityParams).
class LocalMap {
 public:
  /// Throws std::invalid_argument naming the first bad parameter.
  explicit LocalMap(const LocalMapParams& params = {});

  const LocalMapParams& params() const { return params_; }
  /// The map's area: origin is its lower-left corner in the odometry frame (a multiple of the
  /// resolution, raised by the ulps that put it inside the lower-left cell), size its cells.
  /// Before the first update or move the map is centred on (0, 0).
  const MapGeometry& geometry() const { return geometry_; }
  /// Storage index of the map's lower-left cell (geometric cell (0, 0)).
  CellIndex start_index() const;
  /// Storage index of the cell holding `position` [m], or nothing outside the map.
  std::optional<CellIndex> index_of(const Eigen::Vector2d& position) const;
  /// Centre [m] of the cell at storage index `index`; std::out_of_range when it is no cell of the map.
  Eigen::Vector2d position_of(const CellIndex& index) const;

  /// A layer in storage order; std::out_of_range naming the missing layer.
  const Layer& get(const std::string& name) const;
  std::vector<std::string> layers() const;

  /// Fuses one scan given in the sensor frame with its pose (odometry <- sensor, a rigid 4x4):
  /// moves the map to the pose (see move_to), removes overhangs, clears cells seen through, fuses
  /// the kept points and refreshes the planner layers. `stamp_s` goes into "time" (NaN: the
  /// number of the update; every update gives a stamp, or none). An empty scan only moves the map.
  /// Throws std::invalid_argument on a non-finite or non-rigid pose (or a position move_to
  /// refuses), NaN/Inf rows (unless collapse.drop_non_finite), an infinite stamp, a NaN stamp
  /// after stamped updates or the reverse, or one over 1e30 s from the first, before changing anything: a
  /// failed update leaves the map as it was. `no_return_directions`: the scan's beams that
  /// returned nothing, in the sensor frame, for the shadow-aware overhang removal
  /// (collapse_overhangs); a zero or non-finite one is refused too.
  LocalMapUpdate update(const PointsView<float>& points, const Eigen::Matrix4d& pose,
                        double stamp_s = std::numeric_limits<double>::quiet_NaN(),
                        const PointsView<double>& no_return_directions = {});
  LocalMapUpdate update(const PointsView<double>& points, const Eigen::Matrix4d& pose,
                        double stamp_s = std::numeric_limits<double>::quiet_NaN(),
                        const PointsView<double>& no_return_directions = {});

  /// Centres the map on the cell of `position` [m]. Cells that leave are dropped, cells that
  /// enter are empty; a move by the map's size or more drops every cell (returns true then). With
  /// compute_planner_layers the planner layers are refreshed after a move (the windows near the
  /// entering border held cells that left).
  /// Throws std::invalid_argument unless the position is finite, within 1e12 m and within 2^52
  /// cells of the origin (its cell index exact in a double).
  bool move_to(const Eigen::Vector2d& position);
  /// Drops every cell (the map stays where it is).
  void clear();
  /// Recomputes "step", "slope", "roughness" and "traversability" from "elevation" and "clearance".
  void update_planner_layers();
  /// A copy in map order (cell (i, j) of the copy is geometric cell (i, j)) with geometry(): what
  /// classify_terrain, the writers and the plots take.
  ElevationMap to_elevation_map() const;
  std::size_t num_updates() const { return num_updates_; }
  /// The first update's stamp, which "time" is relative to (NaN before the first update).
  double time_origin_s() const { return time_origin_s_.value_or(std::numeric_limits<double>::quiet_NaN()); }

 private:
  /// Throws unless `stamp_s` (relative_s from origin_s) can be this update's: finite or NaN, NaN
  /// exactly when the earlier updates had no stamp, within 1e30 s of the first.
  void check_stamp(double stamp_s, double relative_s, double origin_s) const;
  template <typename Scalar>
  LocalMapUpdate update_impl(const PointsView<Scalar>& points, const Eigen::Matrix4d& pose, double stamp_s,
                             const PointsView<double>& no_return_directions);
  /// move_to without the planner layers' refresh (update() refreshes them once, at its end).
  bool shift_to(const Eigen::Vector2d& position);
  void clear_cells(std::size_t first, std::size_t count, std::size_t stride);
  std::int64_t storage_of(std::int64_t global, int axis) const;

  LocalMapParams params_;
  MapGeometry geometry_;
  Eigen::Matrix<std::int64_t, 2, 1> origin_cell_ = Eigen::Matrix<std::int64_t, 2, 1>::Zero();
  ElevationMap layers_;  // storage order; its own geometry is not meaningful
  // Per cell, in storage order: the reference height and the sums of (z - reference) and of its
  // square over the fused points (for "std_dev").
  std::vector<double> reference_, sum_, sum_squares_;
  std::size_t num_updates_ = 0;
  std::optional<Eigen::Vector3d> last_sensor_;  // for the drift
  std::optional<double> time_origin_s_;
  bool stamped_ = false;  // whether the updates so far had stamps (all do, or none)
};

}  // namespace terracube
