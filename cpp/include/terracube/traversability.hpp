// Planner layers of a height grid: step, slope, roughness and a traversability cost from a plane
// fitted over a robot-footprint window around every cell. An extension beyond the papers (issue
// 35); LocalMap refreshes them after every update, and any ElevationMap can get them.
#pragma once

#include <string>

#include "terracube/elevation_map.hpp"

namespace terracube {

/// Thresholds of the traversability layer. With, per cell, the plane z = a x + b y + c fitted by
/// least squares to the known cells of the (2r + 1)^2 window around it (clipped at the map's
/// border), r = max(1, round(footprint_radius_m / resolution)) (a plane needs neighbours: at
/// least the 3 x 3 cells around, also when the cells are coarser than the footprint):
///   slope     = atan(sqrt(a^2 + b^2))                         [rad]
///   roughness = RMS distance of the window's heights to the plane (vertical) [m]
///   step      = highest minus lowest height in the window      [m]
/// the traversability is
///   0                                                        when slope > max_slope_rad, step >
///        max_step_m, roughness > max_roughness_m or clearance < min_clearance_m;
///   1 - (w_s slope / max_slope + w_t step / max_step + w_r roughness / max_roughness) / (w_s + w_t + w_r)
///        otherwise,
/// so 1 is flat, smooth open ground and 0 impassable; NaN where the cell has no height or its
/// window fewer than min_window_cells known cells (or only collinear ones).
struct TraversabilityParams {
  double footprint_radius_m = 0.3;  ///< half-side of the window (robot footprint) [m], >= 0
  double max_slope_rad = 0.35;      ///< about 20 degrees, > 0
  double max_step_m = 0.2;          ///< > 0
  double max_roughness_m = 0.05;    ///< > 0
  double min_clearance_m = 0.7;     ///< robot height ([TC]'s robot height) [m], >= 0
  double slope_weight = 1.0;        ///< >= 0; the three weights must not all be 0
  double step_weight = 1.0;
  double roughness_weight = 1.0;
  int min_window_cells = 4;  ///< >= 3
};

/// Throws std::invalid_argument naming the first invalid field.
void check_traversability_params(const TraversabilityParams& params);

/// The window's half-side r = max(1, round(footprint_radius_m / resolution_m)) in cells on a map of
/// `size` cells, at most its longer side (a window over the whole map). Throws std::invalid_argument when
/// r > kMaxWindowRadius: a window's extremes cost 2 (2r + 1) reads a cell, so a footprint of
/// hundreds of cells (a fine resolution) on a large map would take hours.
constexpr int kMaxWindowRadius = 255;
int traversability_window_radius(const TraversabilityParams& params, double resolution_m, const CellIndex& size);

/// Adds the layers "step", "slope", "roughness" and "traversability" to `map` (or refreshes them
/// in place) from its `height_layer` ("mean" for build_elevation_map's maps, "elevation" for a
/// LocalMap's; NaN or +-inf is unknown) and, when the map has one, its "clearance" layer (free
/// height above each cell [m]; without it nothing overhangs). A "step" layer already there is
/// replaced (dem_without_overhangs' step to the 8 neighbours becomes the window's). `start` is the
/// storage index of the map's geometric cell (0, 0): (0, 0) for an ElevationMap,
/// LocalMap::start_index() for a circular buffer, whose windows then stop at the map's border
/// instead of wrapping. The same bits for any `num_threads` (1: the calling thread, 0: one per
/// processor). Throws std::invalid_argument on invalid parameters (a window wider than
/// kMaxWindowRadius, or whose rows' sums would need over 1 GB: a map of very many columns) and
/// std::out_of_range when the height layer is missing.
void add_traversability_layers(ElevationMap& map, const TraversabilityParams& params = {},
                               const std::string& height_layer = "mean", const CellIndex& start = CellIndex(0, 0),
                               int num_threads = 1);

}  // namespace terracube
