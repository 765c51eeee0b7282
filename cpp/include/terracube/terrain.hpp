// Terrain classes of elevation-map cells: [TC] section 3.2 and Table 1.
#pragma once

#include <Eigen/Core>
#include <cstdint>

#include "terracube/elevation_map.hpp"

namespace terracube {

/// Per-cell terrain class, stored as uint8.
enum class TerrainClass : std::uint8_t {
  kUnknown = 0,            ///< no data
  kGround = 1,             ///< low with a small spread: traversable
  kObstacle = 2,           ///< middle height (up to the robot's) with a small spread: low structures
  kOverhangingObject = 3,  ///< a discontinuity, or higher than the robot with a small spread (eaves, crowns)
  kVerticalObject = 4,     ///< a large spread without a discontinuity (walls, trunks, poles)
  kHorizontalEdge = 5,     ///< ground beside an obstacle, overhanging or vertical cell (curbs)
};

/// What "highest elevation" is measured from.
enum class GroundReference : std::uint8_t {
  /// The ground is the plane z = -sensor_height_m of a leveled sensor frame, as in the paper.
  kSensorHeight = 0,
  /// The ground is the lowest "min" elevation within local_ground_radius_cells of the cell: needed
  /// once maps are chained over slopes.
  kLocalGround = 1,
};

/// Thresholds of [TC] Table 1; defaults are the paper's values (section 3.2).
struct TerrainParams {
  double ground_height_m = 0.2;  ///< "low": relative height < this [m]
  double std_dev_m = 0.1;        ///< "small" spread: std-dev < this [m]
  double robot_height_m = 0.7;   ///< "high": relative height > this (strict) [m]; "middle" in between
  GroundReference reference = GroundReference::kSensorHeight;
  double sensor_height_m = 0.0;        ///< sensor above the ground [m], for kSensorHeight
  int local_ground_radius_cells = 10;  ///< window half-size for kLocalGround
  /// Threads, as ElevationParams::num_threads: 1 is the calling thread alone, 0 one per
  /// processor; the classes are the same whatever the number.
  int num_threads = 1;
};

/// Throws std::invalid_argument naming the first field out of range; classify_terrain calls it first, and a
/// configuration can call it before the first scan.
void check_terrain_params(const TerrainParams& params);

/// Per-cell classes (TerrainClass values), rows along x as the map's layers.
using TerrainClasses = Eigen::Matrix<std::uint8_t, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

/// Classes and the relative height they were decided on.
struct TerrainClassification {
  TerrainClasses classes;
  Layer relative_height;  ///< "max" minus the ground reference [m], NaN where empty
  Layer ground;           ///< the ground reference per cell [m]
};

/// [TC] Table 1, per cell with data (the map needs "max", "min", "std_dev" and "discontinuity"),
/// with h = "max" minus the ground reference:
///   discontinuity                                   -> overhanging object
///   large spread (std-dev >= std_dev_m), any height -> vertical object
///   small spread and h < ground_height_m            -> ground
///   small spread and h > robot_height_m             -> overhanging object
///   small spread otherwise (middle)                 -> obstacle
/// then a ground cell with an obstacle, overhanging or vertical neighbour (8-neighbourhood)
/// becomes a horizontal edge ([TC] section 3.2, class 5). Empty cells are unknown. Adds the layers
/// "class" (the class as a float, NaN for unknown), "relative_height" and "ground" to the map,
/// overwriting them when they exist. O(cells).
TerrainClassification classify_terrain(ElevationMap& map, const TerrainParams& params = {});

/// classify_terrain without copying relative_height and ground out of the map: the classes only
/// (the map gets the same layers).
TerrainClasses classify_terrain_layers(ElevationMap& map, const TerrainParams& params = {});

}  // namespace terracube
