// 2.5D elevation maps: one grid geometry plus named float layers, NaN for empty cells (in the
// manner of grid_map_core). The DEM of [CBC] is the "mean" layer; the per-cell
// statistics of [TC] (highest elevation, std-dev, discontinuity) are
// the "max", "std_dev" and "discontinuity" layers.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <limits>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "terracube/collapse.hpp"
#include "terracube/cube_grid.hpp"

namespace terracube {

/// One float layer: rows are cells along x (index i), columns cells along y (index j).
using Layer = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
/// A cell index (i along x, j along y).
using CellIndex = Eigen::Array2i;

/// Grid geometry. Convention: `origin_m` is the corner of cell (0, 0) with the smallest x and y;
/// cell (i, j) covers [origin + i * res, origin + (i + 1) * res) along x (likewise j along y) and
/// is centred on origin + (i + 0.5, j + 0.5) * res.
struct MapGeometry {
  double resolution_m = 0.1;                           ///< cell edge [m], > 0
  Eigen::Vector2d origin_m = Eigen::Vector2d::Zero();  ///< lower-left corner of cell (0, 0) [m]
  CellIndex size = CellIndex::Zero();                  ///< cells along x and y

  std::size_t num_cells() const { return static_cast<std::size_t>(size.x()) * static_cast<std::size_t>(size.y()); }
  /// Length of the map along x and y [m].
  Eigen::Vector2d length_m() const { return size.cast<double>() * resolution_m; }
  /// Centre of cell `index` [m].
  Eigen::Vector2d position_of(const CellIndex& index) const {
    return origin_m + (index.cast<double>() + 0.5).matrix() * resolution_m;
  }
  /// The cell holding `position`, or nothing when it lies outside the map.
  std::optional<CellIndex> index_of(const Eigen::Vector2d& position) const;
  /// The same grid: equal resolution, origin and size.
  bool operator==(const MapGeometry& other) const {
    return resolution_m == other.resolution_m && origin_m == other.origin_m && (size == other.size).all();
  }
  bool operator!=(const MapGeometry& other) const { return !(*this == other); }
};

/// A grid geometry with named float layers, NaN meaning "no data".
class ElevationMap {
 public:
  ElevationMap() = default;
  explicit ElevationMap(const MapGeometry& geometry);
  ElevationMap(const ElevationMap&) = default;
  ElevationMap(ElevationMap&&) = default;
  ElevationMap& operator=(const ElevationMap&) = default;
  ElevationMap& operator=(ElevationMap&&) = default;
  /// Keeps the layers' buffers for the next maps this thread makes (at most 32 MB a thread): a new
  /// map's layers are then no fresh memory, whose first touch can cost more than building the map.
  ~ElevationMap();

  const MapGeometry& geometry() const { return geometry_; }
  /// Moves the map to `geometry` without touching its layers' values (as grid_map's
  /// setPosition): references to the layers stay valid. The size must stay the same unless the
  /// map has no layers; throws std::invalid_argument otherwise or on an invalid geometry.
  void set_geometry(const MapGeometry& geometry);
  /// Adds (or overwrites) a layer filled with `value`.
  void add(const std::string& name, float value = std::numeric_limits<float>::quiet_NaN());
  /// Adds (or overwrites) a layer; throws std::invalid_argument when its size is not the map's.
  void add(const std::string& name, Layer data);
  bool exists(const std::string& name) const;
  /// Throws std::out_of_range naming the missing layer and the ones there are. The reference stays
  /// valid while the map lives, whatever layers are added later.
  const Layer& get(const std::string& name) const;
  Layer& get(const std::string& name);
  /// Layer names in the order they were added.
  std::vector<std::string> layers() const;

 private:
  MapGeometry geometry_;
  // A deque: adding a layer never moves the others, so references from get() stay valid.
  std::deque<std::pair<std::string, Layer>> layers_;
};

/// Parameters of build_elevation_map.
struct ElevationParams {
  double resolution_m = 0.1;  ///< cell edge [m], > 0
  /// Map extent. Unset: the points' bounding box in x and y, snapped outwards to the resolution.
  std::optional<Eigen::Vector2d> origin_m;
  std::optional<CellIndex> size;
  /// A cell is discontinuous when its sorted elevations contain a gap longer than this [m].
  double discontinuity_m = 1.0;
  /// Applied to the points before mapping (e.g. leveling_transform()).
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();
  /// Optional crop box in the transformed frame; points outside it take no part.
  std::optional<CropBox> crop;
  /// NaN/Inf rows: false -> std::invalid_argument; true -> ignored.
  bool drop_non_finite = false;
  /// Largest number of cells allowed (memory guard): 64 M cells = 256 MB per float layer.
  std::size_t max_cells = std::size_t{1} << 26;
  /// Threads: 1 runs on the calling thread alone (the default), 0 uses one per processor. The
  /// work is cut into parts by its size alone, so the map is the same bit for bit whatever the number.
  int num_threads = 1;
};

/// Throws std::invalid_argument naming the first field out of range; build_elevation_map calls it first, and a
/// configuration can call it before the first scan.
void check_elevation_params(const ElevationParams& params);

/// Builds the map in O(N + cells): one pass bins the points, a counting sort groups their
/// elevations by cell, and one pass over the cells writes the layers; only cells whose max - min
/// exceeds the discontinuity threshold (no other cell can hold a longer gap) are searched for one,
/// in buckets of half the threshold (O(their elevations), the same answer as sorting them).
/// Layers: "count" (0 for empty), "min", "max", "mean" (the DEM), "std_dev" (population, from the
/// elevations relative to the cell's first, added in row order), "discontinuity" (1 or 0); NaN
/// where a cell holds no point. Points outside the map are ignored. `use` (optional, one flag per
/// point) selects the points that take part. Thread-safe; each calling thread keeps its work
/// buffers (about 12 N + 4 cells bytes) for its next call, as fresh ones would cost a page fault
/// per 4 kB, and releases them after a call that needed over 64 MB.
ElevationMap build_elevation_map(const PointsView<float>& points, const ElevationParams& params,
                                 const std::vector<std::uint8_t>* use = nullptr);
ElevationMap build_elevation_map(const PointsView<double>& points, const ElevationParams& params,
                                 const std::vector<std::uint8_t>* use = nullptr);

/// build_elevation_map into an existing map, reusing its layers' buffers: a loop that refills one
/// map allocates nothing once warm, and references to its layers (and numpy views) stay valid
/// and see the new values. The map takes the build's geometry, whose size must be the map's
/// unless the map has no layers (so give a fixed extent); the six layers are overwritten and any
/// other layer (classify_terrain's, say, which a new classification refills in place) is reset
/// to NaN. Throws as build_elevation_map, and std::invalid_argument on a size mismatch, in which
/// cases the map is left unchanged.
void build_elevation_map_into(ElevationMap& map, const PointsView<float>& points, const ElevationParams& params,
                              const std::vector<std::uint8_t>* use = nullptr);
void build_elevation_map_into(ElevationMap& map, const PointsView<double>& points, const ElevationParams& params,
                              const std::vector<std::uint8_t>* use = nullptr);

/// [CBC]'s "DEM without overhangs" plus planner layers:
/// collapse_overhangs, then build_elevation_map from the points it kept, then
///  - "clearance": from the highest kept point below the cell's lowest overhang point up to that
///    point [m] (the free height under the overhang, never negative), +inf where the cell has no
///    overhang, NaN where it has no kept point (or none below the overhang);
///  - "step": the largest |max - max of a neighbour| over the 8 neighbours with data [m].
/// The map is built in collapse's frame: its transform and crop replace elevation's. Build the raw
/// DEM with the same ElevationParams (and that transform and crop) to compare.
/// `no_return_directions`: the scan's beams without a return, for the shadow-aware rule (see
/// collapse_overhangs).
struct OverhangFreeMap {
  ElevationMap map;         ///< layers of the kept points, plus clearance and step
  CollapseResult collapse;  ///< the overhang mask and cubes
};
OverhangFreeMap build_overhang_free_map(const PointsView<float>& points, const CollapseParams& collapse,
                                        const ElevationParams& elevation,
                                        const PointsView<double>& no_return_directions = {});
OverhangFreeMap build_overhang_free_map(const PointsView<double>& points, const CollapseParams& collapse,
                                        const ElevationParams& elevation,
                                        const PointsView<double>& no_return_directions = {});

/// The "step" layer of a height layer: the largest absolute difference to the 8 neighbours that
/// have data; 0 where no neighbour has data, NaN where the cell has none.
Layer step_layer(const Layer& height);

/// Two heights that are neighbours in sorted order: the one under a gap and the one over it [m].
struct HeightGap {
  double below_m = 0.0, above_m = 0.0;
};

/// [TC] section 3.2's discontinuity of one cell: the lowest gap of more than `threshold_m` between
/// neighbouring heights (in sorted order) among heights[0, n), all finite; nullopt when there is
/// none (the "discontinuity" layer is 1 where a cell has one). O(n) without sorting: each height
/// goes into the bucket floor((z - lowest) * 2 / threshold), which never decreases as z grows, and
/// two heights of one bucket lie at most threshold / 2 and a few ulps apart; so sorted neighbours
/// either share a bucket (no gap) or are the highest of one non-empty bucket and the lowest of the
/// next, compared with the same subtraction as a sorted scan: the sorted scan's answer. Heights
/// needing more than two buckets each (an outlier far off) are sorted instead. `scratch` is work
/// memory, reused between calls. Throws std::invalid_argument unless threshold_m > 0.
std::optional<HeightGap> lowest_height_gap(const double* heights, std::size_t n, double threshold_m,
                                           std::vector<double>& scratch);

}  // namespace terracube
