// Shadow-aware overhang removal: an extension of [CBC] Algorithm 1 for columns whose ground the
// sensor cannot see (sensor shadows, occlusions, ground between rays at range). Not in the paper.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <vector>

#include "terracube/cube_grid.hpp"

namespace terracube {

/// Which rule collapse_overhangs applies to the occupied cubes L.
enum class CollapseMethod : std::uint8_t {
  kPaper = 0,        ///< [CBC] Algorithm 1, bit for bit (the default)
  kShadowAware = 1,  ///< shadow_aware_collapse() below
};

/// Why shadow_aware_collapse() kept or removed a cube (one per occupied cube, aligned with L).
/// A "chain" is a maximal run of occupied cubes of one column whose gaps are < σ empty cubes.
enum class CubeReason : std::uint8_t {
  kSupported = 0,         ///< kept: its chain starts less than σ empty cubes above the ground estimate G
  kBelowGround = 1,       ///< kept: its whole chain lies below G (multipath, reflections); never ground
  kNoGroundEstimate = 2,  ///< kept: no reliable ground within ground_radius_m of the column
  kShadowed = 3,          ///< kept: its chain floats σ or more above G but no ray shows the space under it empty
  kRemovedAboveKept = 4,  ///< removed: a kept chain (not below G) lies under it, σ or more empty cubes down
  kRemovedFreeBelow = 5,  ///< removed: its chain floats σ or more above G and a ray crossed the column below it
  kThin = 6,              ///< kept: it floats, no kept chain below, its bottom is thin (a trunk or pole), no rim
  kRemovedRim = 7,        ///< removed: a thin chain at the rim of a removed one (remove_rims), a ray under it
  kNotUsed = 255,         ///< point_reasons() only: the row took no part (NaN/Inf dropped, outside the crop)
};

/// The short name of a reason ("supported", "below_ground", ...), as Python shows it.
const char* cube_reason_name(CubeReason reason);

/// Parameters of the shadow-aware rule (CollapseParams::shadow_aware).
struct ShadowAwareParams {
  /// The sensor's position [m] in the leveled frame; unset: the transform's translation (the
  /// sensor at the origin of the cloud's own frame, as for a single scan). A position more than
  /// 10 m below every point (a survey in its own coordinates, with the default) is refused.
  std::optional<Eigen::Vector3d> sensor_origin;
  /// Ground is looked for within this horizontal distance [m] (a square of ceil(r / E) columns
  /// each side), >= 0.
  double ground_radius_m = 5.0;
  /// A column's lowest cube is reliable ground when at least this many columns of its 3x3
  /// neighbourhood (itself included) have their lowest cube within one layer of it, and more of
  /// them do than have their lowest cube σ or more layers above it: isolated returns below the
  /// ground never qualify, nor a small patch of them under the road. The default, 4, is a 2 x 2
  /// block's worth: an L of three columns (a reflection 2 m under the street of the bundled Ouster
  /// sample) is not enough. In 1..9.
  int ground_support = 4;
  /// Reliable ground that lies more than this far [m] under the line of sight over reliable ground
  /// nearer the sensor (and below it) is no ground: the sensor cannot have seen it through the
  /// road (multipath, reflections). Rays pass under car bodies by less, under crowns and decks
  /// (above the sensor) by any height. >= 0.
  double hidden_ground_margin_m = 2.0;
  /// A ray proves the space under a chain empty only when it passes at least this far [m] below the
  /// chain's bottom face (rays through a car's windows or beside a wall's edge pass just under it), >= 0.
  double free_margin_m = 0.25;
  /// A floating chain is removed only when its bottom is wide (a crown's or a ceiling's underside
  /// is; a trunk seen over a car is not): at least this many of the 8 columns around it hold a cube
  /// within one layer of its bottom, or, when none of those 8 holds a grounded chain there, this many
  /// columns of the bottom_window square hold a floating chain there; 0..(2 bottom_window + 1)^2 - 1.
  int min_bottom_neighbours = 4;
  /// Half-width [columns] of the square whose floating chains can make a bottom wide (1: the 8
  /// neighbours only; 2: 24 columns, which finds the sparse scan rings under a ceiling), 1..8.
  int bottom_window = 2;
  /// A thin chain is the rim of an overhang (a crown's edge, a deck's border, a scan ring under a
  /// ceiling: too few columns around its bottom) when, among the 8 columns around it, one holds a
  /// cube of a removed wide chain or rim (kRemovedFreeBelow, kRemovedRim) within one layer of its
  /// bottom and no more hold a grounded (supported) cube there than such a removed one (a pole's or
  /// a trunk's top beside a sign or a crown has its own grounded column beside it). A cube removed
  /// above a kept chain (kRemovedAboveKept) was never judged wide (a trunk's top over a bush) and
  /// makes no rim. A rim is judged as a wide chain: removed (kRemovedRim) when a ray crossed the
  /// column under it, else shadowed. Rims pass the removal on along themselves.
  bool remove_rims = true;
  /// Azimuth sectors of the free-space floor around the sensor (pseudo-angle bins), >= 1. Each
  /// should hold a few azimuth steps of the sensor (KITTI's HDL-64: about 2000 per turn).
  int azimuth_bins = 512;
  /// How far [m] a beam without a return (the `no_returns` of shadow_aware_collapse) shows the
  /// space empty: a range within which the sensor sees every surface that matters (dark cars,
  /// foliage), > 0.
  double no_return_range_m = 30.0;
};

/// The decision of shadow_aware_collapse().
struct ShadowAwareDecision {
  std::vector<std::int64_t> removed_cubes;  ///< R, ascending
  std::vector<CubeReason> reasons;          ///< one per cube of L, aligned with it
};

/// A point that takes part (collapse_overhangs passes its rows): the point [m] in the leveled frame
/// and the index I of its cube.
struct CubePoint {
  Eigen::Vector3d point;
  std::int64_t cube = 0;
};

/// Fills `out` (room for `capacity` points) with the next points that take part and returns how
/// many, 0 after the last: the points come a chunk at a time, without a copy of them all.
using NextPoints = std::function<std::size_t(CubePoint* out, std::size_t capacity)>;

/// The shadow-aware rule over the occupied cubes L (sorted ascending, indices I of `grid`):
///  1. the lowest cube of each column is reliable ground when `ground_support` columns of its 3x3
///     neighbourhood have their lowest cube within one layer of it, and more of them than have
///     theirs σ or more layers above it, and when no reliable lowest cube nearer the sensor in its
///     pseudo-azimuth sector hides it: one below the sensor whose bottom face lies more than
///     hidden_ground_margin_m above the ray to this cube's top face (both at their column's centre);
///  2. G0(column) is the lowest reliable ground within the ground radius (a square window);
///  3. the rays from the sensor to the points whose cube is not below G0 - 1, and the beams
///     without a return that point at or above the horizon (ending no_return_range_m out), give, per
///     (pseudo-azimuth sector, range step E), the lowest slope of the rays that end beyond the step:
///     F(column) = sensor z + that slope * the horizontal distance of the column's centre (from
///     the bin of that centre) is the lowest height at which a ray crosses the column;
///     a reliable lowest cube with F below its bottom face is no ground (the underside of a crown
///     seen over a curb), and G(column) is step 2 again without those;
///  4. each column's chains are judged bottom-up as CubeReason says: a floating chain (bottom σ or
///     more empty cubes above G) is removed over a kept chain (as in [CBC] Algorithm 1), or, when
///     its bottom is wide (min_bottom_neighbours), when F is below its bottom face by
///     free_margin_m; it is kept otherwise (a wall or trunk whose foot is hidden);
///  5. with remove_rims, a thin chain beside cubes of removed wide chains or rims at its bottom's
///     height is judged again as a wide one, until no more change (the result does not depend on
///     the order).
/// `no_returns`: the directions of the scan's beams that returned nothing (the empty pixels of an
/// organised scan; any length but zero), which `leveling` (CollapseParams::transform's rotation)
/// turns into the grid's frame. A beam level with or above the horizon there crossed free space
/// out to no_return_range_m, so in step 3 it counts as a ray to a point that far; beams below the
/// horizon are not used (a dark or wet road returns nothing too).
/// O(N + |L| + columns + beams + azimuth_bins * range steps); single-threaded, deterministic.
/// Throws std::invalid_argument on invalid parameters or beams, a grid of more than 2^27 columns
/// or a sensor origin more than 10 m below every point.
ShadowAwareDecision shadow_aware_collapse(const CubeGrid& grid, const std::vector<std::int64_t>& sorted_occupied,
                                          const NextPoints& next_points, int sigma,
                                          const Eigen::Vector3d& sensor_origin, const ShadowAwareParams& params = {},
                                          const PointsView<double>& no_returns = {},
                                          const Eigen::Matrix3d& leveling = Eigen::Matrix3d::Identity());

/// Throws std::invalid_argument "<name> row k must be a finite, non-zero direction" for the first
/// such row of `directions` (and for a view without data that claims rows).
void check_directions(const PointsView<double>& directions, const char* name);

/// Throws std::invalid_argument naming the first invalid field of `params`.
void check_shadow_aware_params(const ShadowAwareParams& params);

}  // namespace terracube
