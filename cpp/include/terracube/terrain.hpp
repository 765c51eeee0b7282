// Terrain classes of elevation-map cells (the classification paper, section 3.2 and Table 1).
#pragma once

#include <Eigen/Core>
#include <cstdint>

#include "terracube/elevation_map.hpp"

namespace terracube {

/// Per-cell terrain class, stored as uint8.
enum class TerrainClass : std::uint8_t {
  kUnknown = 0,            ///< no data
  kGround = 1,             ///< low and smooth: traversable
  kObstacle = 2,           ///< middle height, or high with a small spread of elevations
  kOverhangingObject = 3,  ///< elevations with a vertical gap (canopy, eaves, bridge decks over ground)
  kVerticalObject = 4,     ///< high with a large spread of elevations (walls, trunks, poles)
  kHorizontalEdge = 5,     ///< ground beside a cell of another known class
};

/// What "highest elevation" is measured from.
enum class GroundReference : std::uint8_t {
  /// The ground is the plane z = -sensor_height_m of a leveled sensor frame, as in the paper.
  kSensorHeight = 0,
  /// The ground is the lowest "min" elevation within local_ground_radius_cells of the cell: needed
  /// once maps are chained over slopes.
  kLocalGround = 1,
};

/// Thresholds of Table 1; defaults are the paper's values.
struct TerrainParams {
  double ground_height_m = 0.2;  ///< "low": relative height < this
  double std_dev_m = 0.1;        ///< "small" spread: std-dev < this
  double robot_height_m = 0.7;   ///< "high": relative height >= this; "middle" in between
  GroundReference reference = GroundReference::kSensorHeight;
  double sensor_height_m = 0.0;        ///< sensor above the ground [m], for kSensorHeight
  int local_ground_radius_cells = 10;  ///< window half-size for kLocalGround
  /// Threads, as ElevationParams::num_threads: 1 is the calling thread alone, 0 one per
  /// processor; the classes are the same whatever the number.
  int num_threads = 1;
};

/// Per-cell classes (TerrainClass values), rows along x as the map's layers.
using TerrainClasses = Eigen::Matrix<std::uint8_t, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

/// Classes and the relative height they were decided on.
struct TerrainClassification {
  TerrainClasses classes;
  Layer relative_height;  ///< "max" minus the ground reference [m], NaN where empty
  Layer ground;           ///< the ground reference per cell [m]
};

/// Table 1, per cell with data (the map needs "max", "min", "std_dev" and "discontinuity"):
///   discontinuity                     -> overhanging object
///   low (h < ground) and std small    -> ground;   low and std large -> obstacle
///   middle (ground <= h < robot)      -> obstacle
///   high (h >= robot) and std large   -> vertical object; high and std small -> obstacle
/// then a ground cell with an obstacle, overhanging or vertical neighbour (8-neighbourhood)
/// becomes a horizontal edge. Empty cells are unknown. Adds the layers "class" (the class as a
/// float, NaN for unknown), "relative_height" and "ground" to the map.
/// O(cells), branch-free and vectorised (the relative-height and spread tests run on floats
/// against the smallest float at or above each double threshold, which decides exactly as a
/// double comparison would); the layers are overwritten in place when they exist.
TerrainClassification classify_terrain(ElevationMap& map, const TerrainParams& params = {});

/// classify_terrain without copying relative_height and ground out of the map: the classes only
/// (the map gets the same layers).
TerrainClasses classify_terrain_layers(ElevationMap& map, const TerrainParams& params = {});

}  // namespace terracube
