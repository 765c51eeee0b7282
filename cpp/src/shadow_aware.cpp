// Shadow-aware overhang removal (not in [CBC]): the ground under a column is estimated from its
// neighbourhood, and a chain of cubes floating above it goes only when a ray shows the space under
// it empty or a kept chain lies below it. See shadow_aware.hpp for the rule, step by step.
#include "terracube/shadow_aware.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

#include "number_text.hpp"

namespace terracube {

namespace {

constexpr std::int32_t kNone = std::numeric_limits<std::int32_t>::max();
constexpr std::int64_t kMaxColumns = std::int64_t{1} << 27;
constexpr std::int64_t kMaxSectorSteps = std::int64_t{1} << 27;
/// How far below every return a sensor origin may lie [m] (a scan of a steep slope from its foot).
constexpr double kMaxSensorBelowCloud_m = 10.0;
constexpr double kInf = std::numeric_limits<double>::infinity();

/// Per-call arrays kept by the calling thread (first touching fresh pages costs more than the rule).
/// A column with a reliable lowest cube, and the bin and horizontal distance of its centre in the
/// free-space floor.
struct PlacedColumn {
  std::size_t column, bin;
  double distance;
};

struct Workspace {
  std::vector<std::int32_t> column_of;  ///< the column of each cube of L
  std::vector<std::int32_t> layer_of;   ///< the layer of each cube of L
  std::vector<std::int32_t> lowest;     ///< lowest occupied layer per column, kNone if empty
  std::vector<std::int32_t> reliable;   ///< the lowest layer where it is reliable ground, else kNone
  std::vector<PlacedColumn> placed;     ///< the reliable columns, placed in the free-space floor
  std::vector<std::int32_t> scratch;    ///< the window minimum along x
  std::vector<std::int32_t> ground;     ///< G per column, kNone if no reliable ground in the window
  std::vector<std::int32_t> start;      ///< first position of each column in `by_column`
  std::vector<std::int32_t> by_column;  ///< positions in L, column by column, layers ascending
  std::vector<double> slope;            ///< per (range step, sector): lowest slope of rays ending beyond it
  std::vector<std::int32_t> line;       ///< the window minimum's line buffers
  std::vector<CubePoint> chunk;         ///< the points of the rays, a chunk at a time
};

/// Not inlined: in a shared library (the Python module) the compiler may compute the address of a
/// thread_local object it can see again (a __tls_get_addr call) wherever it needs it, also inside
/// the loops; the opaque reference is computed once (measured: 0.15 ms of 2.8 ms per KITTI scan).
[[gnu::noinline]] Workspace& thread_workspace() {
  thread_local Workspace workspace;
  return workspace;
}

/// The column and layer of every cube of L ([CBC] eq. (1): I = column + layer * columns) with a
/// division per layer, not per cube: L is sorted by I, so its layers ascend (and a cube out of
/// order is divided too).
void split_cubes(const std::vector<std::int64_t>& occupied, std::int64_t num_columns, Workspace& w) {
  w.column_of.resize(occupied.size());
  w.layer_of.resize(occupied.size());
  std::int64_t layer = -1, layer_start = 0;
  for (std::size_t position = 0; position < occupied.size(); ++position) {
    const std::int64_t cube = occupied[position];
    if (layer < 0 || cube < layer_start || cube - layer_start >= num_columns) {
      layer = cube / num_columns;
      layer_start = layer * num_columns;
    }
    w.column_of[position] = static_cast<std::int32_t>(cube - layer_start);
    w.layer_of[position] = static_cast<std::int32_t>(layer);
  }
}

/// The lowest occupied layer of every column: L is sorted by I, so a column's first cube is its lowest.
void lowest_layers(std::int64_t num_columns, Workspace& w) {
  w.lowest.assign(static_cast<std::size_t>(num_columns), kNone);
  for (std::size_t position = 0; position < w.column_of.size(); ++position) {
    std::int32_t& slot = w.lowest[static_cast<std::size_t>(w.column_of[position])];
    if (slot == kNone) slot = w.layer_of[position];
  }
}

/// 1 when `other` lies within one layer of `layer` (other - layer + 1 in [0, 2]), 0 otherwise and
/// for kNone (far above any layer); unsigned, without a branch.
int within_one_layer(std::int32_t other, std::int32_t layer) {
  return static_cast<std::uint32_t>(other) - static_cast<std::uint32_t>(layer) + 1U <= 2U ? 1 : 0;
}

/// 1 when `other` (not kNone) lies σ or more layers above `layer`, 0 otherwise; both are layers
/// (>= 0), so their difference cannot overflow.
int far_above(std::int32_t other, std::int32_t layer, int sigma) {
  return (other != kNone) & (other - layer >= sigma) ? 1 : 0;
}

/// Step 1's test of a column's lowest layer from the lowest layers of its 3x3 neighbourhood
/// (itself included): `near` of them within one layer of it, `far` σ or more layers above it.
/// Reliable ground needs `support` near ones, and more near ones than far ones: a patch of
/// multipath returns under the road can reach `support`, but the road lies over most of its
/// neighbours.
bool is_reliable(int near, int far, int support) { return (near >= support) & (near > far); }

/// Step 1 at one column, its neighbourhood clipped to the grid: its lowest layer if reliable, else kNone.
std::int32_t reliable_at(const CubeGrid& grid, const std::vector<std::int32_t>& lowest, int support, int sigma,
                         std::int64_t ix, std::int64_t iy) {
  const std::int64_t nx = grid.ixmax, ny = grid.iymax;
  const std::int32_t layer = lowest[static_cast<std::size_t>(ix + iy * nx)];
  if (layer == kNone) return kNone;
  int near = 0, far = 0;
  for (std::int64_t y = std::max<std::int64_t>(0, iy - 1); y <= std::min(ny - 1, iy + 1); ++y) {
    for (std::int64_t x = std::max<std::int64_t>(0, ix - 1); x <= std::min(nx - 1, ix + 1); ++x) {
      const std::int32_t other = lowest[static_cast<std::size_t>(x + y * nx)];
      near += within_one_layer(other, layer);
      far += far_above(other, layer, sigma);
    }
  }
  return is_reliable(near, far, support) ? layer : kNone;
}

/// Step 1: a column's lowest layer where it is reliable ground (is_reliable); kNone elsewhere.
/// The grid's border clipped (reliable_at), the inner columns of a row in one branch-free run the
/// compiler vectorises.
void reliable_ground(const CubeGrid& grid, const std::vector<std::int32_t>& lowest, int support, int sigma,
                     std::vector<std::int32_t>& reliable) {
  const std::int64_t nx = grid.ixmax, ny = grid.iymax;
  reliable.resize(lowest.size());
  for (std::int64_t iy = 0; iy < ny; ++iy) {
    std::int32_t* const out = reliable.data() + iy * nx;
    if (iy == 0 || iy == ny - 1 || nx < 3) {
      for (std::int64_t ix = 0; ix < nx; ++ix) out[ix] = reliable_at(grid, lowest, support, sigma, ix, iy);
      continue;
    }
    const std::int32_t* const row = lowest.data() + iy * nx;
    const std::int32_t* const below = row - nx;
    const std::int32_t* const above = row + nx;
    out[0] = reliable_at(grid, lowest, support, sigma, 0, iy);
    for (std::int64_t ix = 1; ix < nx - 1; ++ix) {
      const std::int32_t layer = row[ix];
      int near = 0, far = 0;
      for (std::int64_t x = ix - 1; x <= ix + 1; ++x) {
        near += within_one_layer(below[x], layer) + within_one_layer(row[x], layer) + within_one_layer(above[x], layer);
        far += far_above(below[x], layer, sigma) + far_above(row[x], layer, sigma) + far_above(above[x], layer, sigma);
      }
      out[ix] = (layer != kNone) & is_reliable(near, far, support) ? layer : kNone;
    }
    out[nx - 1] = reliable_at(grid, lowest, support, sigma, nx - 1, iy);
  }
}

/// out[k] = min(a[k], b[k]) for k < lanes.
void lane_minimum(const std::int32_t* a, const std::int32_t* b, std::int64_t lanes, std::int32_t* out) {
  for (std::int64_t k = 0; k < lanes; ++k) out[k] = std::min(a[k], b[k]);
}

/// out[i] = the minimum of in[i - radius .. i + radius] (clipped to [0, n)) for `lanes` lines side
/// by side (element i of lane k at in[i * stride + k], likewise in out): van Herk / Gil-Werman over
/// the lines padded with kNone, three minima per element whatever the radius. Side by side, the
/// lines' minima are contiguous loops, also when the lines are the grid's columns.
void line_minimum(const std::int32_t* in, std::ptrdiff_t stride, std::int64_t n, std::int64_t lanes,
                  std::int64_t radius, std::int32_t* out, std::vector<std::int32_t>& buffer) {
  if (n <= 0) return;
  // A window reaching past both ends is the whole line: the same minima with radius n - 1, and a
  // grid two million columns long and one wide no longer pads its columns by millions of kNone.
  radius = std::min(radius, n - 1);
  const std::int64_t width = 2 * radius + 1, padded = n + 2 * radius;
  buffer.resize(static_cast<std::size_t>(3 * padded * lanes));
  std::int32_t* const line = buffer.data();              // the lines with radius kNone on each side
  std::int32_t* const prefix = line + padded * lanes;    // minimum from its block's start
  std::int32_t* const suffix = prefix + padded * lanes;  // minimum to its block's end
  const auto at = [lanes](std::int32_t* lines, std::int64_t i) { return lines + i * lanes; };
  std::fill(line, at(line, radius), kNone);
  for (std::int64_t i = 0; i < n; ++i) std::copy_n(in + i * stride, lanes, at(line, radius + i));
  std::fill(at(line, radius + n), at(line, padded), kNone);
  for (std::int64_t block = 0; block < padded; block += width) {
    const std::int64_t last = std::min(padded, block + width) - 1;
    std::copy_n(at(line, block), lanes, at(prefix, block));
    for (std::int64_t j = block + 1; j <= last; ++j) lane_minimum(at(prefix, j - 1), at(line, j), lanes, at(prefix, j));
    std::copy_n(at(line, last), lanes, at(suffix, last));
    for (std::int64_t j = last - 1; j >= block; --j) lane_minimum(at(suffix, j + 1), at(line, j), lanes, at(suffix, j));
  }
  for (std::int64_t i = 0; i < n; ++i) lane_minimum(at(suffix, i), at(prefix, i + width - 1), lanes, out + i * stride);
}

/// Step 2: out = the minimum of `in` over the square of half-width `radius` columns around each
/// column (clipped to the grid): rows, then columns in bands of kBand side by side.
void window_minimum(const CubeGrid& grid, std::int64_t radius, const std::vector<std::int32_t>& in,
                    std::vector<std::int32_t>& along_x, std::vector<std::int32_t>& out,
                    std::vector<std::int32_t>& buffer) {
  constexpr std::int64_t kBand = 64;
  const std::int64_t nx = grid.ixmax, ny = grid.iymax;
  along_x.resize(in.size());
  out.resize(in.size());
  for (std::int64_t iy = 0; iy < ny; ++iy) {
    line_minimum(in.data() + iy * nx, 1, nx, 1, radius, along_x.data() + iy * nx, buffer);
  }
  for (std::int64_t ix = 0; ix < nx; ix += kBand) {
    line_minimum(along_x.data() + ix, nx, ny, std::min(kBand, nx - ix), radius, out.data() + ix, buffer);
  }
}

/// The pseudo-angle of (dx, dy) != 0 in [0, 4): monotone in the azimuth, without atan2.
double pseudo_angle(double dx, double dy) {
  if (dy >= 0.0) return dx >= 0.0 ? dy / (dx + dy) : 1.0 - dx / (-dx + dy);
  return dx < 0.0 ? 2.0 - dy / (-dx - dy) : 3.0 + dx / (dx - dy);
}

/// The height [m] of the bottom face of the cubes of `layer`.
double bottom_face(const CubeGrid& grid, std::int64_t layer) {
  return grid.min_corner.z() + (static_cast<double>(layer) - 0.5) * grid.edge_m;
}

/// Step 3: horizontal geometry of the rays from the sensor, per (range step E, sector).
class FreeSpaceFloor {
 public:
  FreeSpaceFloor(const CubeGrid& grid, const Eigen::Vector3d& origin, int sectors, std::vector<double>& slope)
      : grid_(grid), origin_(origin), sectors_(sectors), slope_(slope) {
    double farthest = 0.0;
    for (const double x : {grid.min_corner.x(), grid.min_corner.x() + grid.edge_m * static_cast<double>(grid.ixmax)}) {
      for (const double y :
           {grid.min_corner.y(), grid.min_corner.y() + grid.edge_m * static_cast<double>(grid.iymax)}) {
        farthest = std::max(farthest, std::hypot(x - origin.x(), y - origin.y()));
      }
    }
    if (!(farthest / grid.edge_m < static_cast<double>(kMaxSectorSteps))) {
      throw std::invalid_argument("shadow_aware: the sensor origin lies too far from the cloud (" +
                                  detail::number_text(farthest) + " m); set sensor_origin in the leveled frame");
    }
    // A ground sensor sees some ground below it: one far under every return (a survey in its own
    // coordinates with the default origin at 0) would reason from rays out of the ground.
    const double below = grid.min_corner.z() - origin.z();
    if (below > kMaxSensorBelowCloud_m) {
      throw std::invalid_argument("shadow_aware: the sensor origin lies " + detail::number_text(below) +
                                  " m below the lowest point; set sensor_origin to the scanner's position in the "
                                  "leveled frame, or use the paper's method");
    }
    steps_ = static_cast<std::int64_t>(farthest / grid.edge_m) + 2;
    if (steps_ > kMaxSectorSteps / sectors_) {  // a survey far from the origin, or a huge cloud
      throw std::invalid_argument("shadow_aware: the cloud reaches " + detail::number_text(farthest) +
                                  " m from the sensor origin (" + std::to_string(sectors_) + " azimuth bins x " +
                                  std::to_string(steps_) +
                                  " range steps is too many); set sensor_origin to the scanner's position in the "
                                  "leveled frame or crop the cloud (an airborne cloud: use the paper's method)");
    }
    reset();
  }

  /// Forgets every ray.
  void reset() { slope_.assign(static_cast<std::size_t>(steps_ * sectors_), kInf); }

  /// Adds the ray from the sensor to `point`.
  void add_ray(const Eigen::Vector3d& point) {
    double distance = 0.0;
    const std::int64_t bin = bin_of(point, distance);
    if (bin < 0) return;
    double& slot = slope_[static_cast<std::size_t>(bin)];
    slot = std::min(slot, (point.z() - origin_.z()) / distance);
  }

  /// Adds a beam without a return, `d` in the leveled frame, scaled so that its largest component
  /// is about 1 (its squares neither overflow nor vanish): one at or above the horizon ends `range`
  /// out (past the last step when that lies beyond the grid); the rest are not used.
  void add_free_beam(const Eigen::Vector3d& d, double range) {
    if (!(d.z() >= 0.0)) return;  // below the horizon
    const double horizontal_squared = d.x() * d.x() + d.y() * d.y();
    if (!(horizontal_squared > 0.0)) return;  // straight up: it crosses no column
    const double horizontal = std::sqrt(horizontal_squared);
    const double end = range * horizontal / std::sqrt(horizontal_squared + d.z() * d.z());  // horizontally
    const auto step = static_cast<std::int64_t>(std::min(end * inverse_edge_, static_cast<double>(steps_ - 1)));
    const std::int64_t bin = step * sectors_ + sector_of(d.x(), d.y());
    double& slot = slope_[static_cast<std::size_t>(bin)];
    slot = std::min(slot, d.z() / horizontal);
  }

  /// After the last ray: each bin holds the lowest slope of the rays that END beyond its step.
  void finish() {
    std::vector<double> beyond(static_cast<std::size_t>(sectors_), kInf);  // per sector, from the far end in
    for (std::int64_t step = steps_ - 1; step >= 0; --step) {
      double* const slots = slope_.data() + step * sectors_;
      for (std::size_t sector = 0; sector < beyond.size(); ++sector) {
        const double ending_here = slots[sector];
        slots[sector] = beyond[sector];
        beyond[sector] = std::min(beyond[sector], ending_here);
      }
    }
  }

  /// F: the lowest height [m] at which a ray crosses the centre of column (ix, iy), +inf if none does.
  double floor_of(std::int64_t ix, std::int64_t iy) const {
    double distance = 0.0;
    const std::int64_t bin = column_bin(ix, iy, distance);
    return bin < 0 ? kInf : floor_at(static_cast<std::size_t>(bin), distance);
  }

  /// F at a column centre of bin `bin` (>= 0) and horizontal distance `distance` (column_bin's).
  double floor_at(std::size_t bin, double distance) const {
    const double slope = slope_[bin];
    return slope == kInf ? kInf : origin_.z() + slope * distance;
  }

  /// The bin of the centre of column (ix, iy) and its horizontal distance [m]; -1 at the sensor.
  std::int64_t column_bin(std::int64_t ix, std::int64_t iy, double& distance) const {
    // The column's centre as CubeGrid::center() gives it (z unused), without its divisions.
    const Eigen::Vector3d centre(grid_.min_corner.x() + grid_.edge_m * static_cast<double>(ix),
                                 grid_.min_corner.y() + grid_.edge_m * static_cast<double>(iy), 0.0);
    return bin_of(centre, distance);
  }

  std::int64_t sectors() const { return sectors_; }
  std::int64_t steps() const { return steps_; }
  const Eigen::Vector3d& origin() const { return origin_; }

 private:
  /// The bin of a point's horizontal position and its horizontal distance; -1 at the sensor.
  std::int64_t bin_of(const Eigen::Vector3d& point, double& distance) const {
    const double dx = point.x() - origin_.x(), dy = point.y() - origin_.y();
    distance = std::sqrt(dx * dx + dy * dy);
    const double step = distance * inverse_edge_;
    // Outside the bins only if the caller's array changed during the call: no ray then.
    if (!(distance > 0.0) || !(step < static_cast<double>(steps_))) return -1;
    // Step-major: the points of a scan ring at one range fall in one row of sectors, side by side.
    return static_cast<std::int64_t>(step) * sectors_ + sector_of(dx, dy);
  }

  /// The sector of the horizontal direction (dx, dy) != 0.
  std::int64_t sector_of(double dx, double dy) const {
    return std::min<std::int64_t>(sectors_ - 1, static_cast<std::int64_t>(pseudo_angle(dx, dy) / 4.0 * sectors_));
  }

  const CubeGrid& grid_;
  Eigen::Vector3d origin_;
  std::int64_t sectors_;
  std::int64_t steps_ = 0;
  double inverse_edge_ = 1.0 / grid_.edge_m;
  std::vector<double>& slope_;
};

/// w.placed: the columns with a reliable lowest cube (step 1), in column order, with the bin and
/// horizontal distance of their centres in `floor` (those at the sensor left out), computed once
/// for the passes of steps 1b and 2.
void place_reliable_columns(const CubeGrid& grid, const FreeSpaceFloor& floor, Workspace& w) {
  w.placed.clear();
  for (std::int64_t iy = 0; iy < grid.iymax; ++iy) {
    for (std::int64_t ix = 0; ix < grid.ixmax; ++ix) {
      const auto column = static_cast<std::size_t>(ix + iy * grid.ixmax);
      if (w.reliable[column] == kNone) continue;
      double distance = 0.0;
      const std::int64_t bin = floor.column_bin(ix, iy, distance);
      if (bin >= 0) w.placed.push_back({column, static_cast<std::size_t>(bin), distance});
    }
  }
}

/// Calls f(layer, bin, distance) for each column of w.placed still reliable: `layer` is its entry
/// of w.reliable (f may clear it), `bin` and `distance` those of the column's centre in the floor.
template <typename F>
void for_each_reliable_column(Workspace& w, F&& f) {
  for (const PlacedColumn& placed : w.placed) {
    std::int32_t& layer = w.reliable[placed.column];
    if (layer != kNone) f(layer, placed.bin, placed.distance);
  }
}

/// Step 1b: reliable ground the sensor cannot have seen is no ground (multipath and reflections
/// under the road). A reliable lowest cube below the sensor is opaque: a ray to a point more than
/// `margin` under its bottom face, farther out in its sector, would have ended on it. Per (sector,
/// range step) the steepest such limit, (bottom face - margin - sensor z) / distance of the
/// column's centre, is carried outwards; a reliable lowest cube whose top face lies under the limit
/// of the nearer steps of its sector loses its reliability. Rays pass under crowns and decks
/// (above the sensor) and under car bodies (less than `margin` above the road): neither hides
/// anything. The limits use the bins of `floor` and its storage (w.slope), which holds no ray yet.
void hide_occluded_ground(const CubeGrid& grid, FreeSpaceFloor& floor, double margin, Workspace& w) {
  const std::int64_t sectors = floor.sectors();
  const double sensor_z = floor.origin().z();
  std::vector<double>& horizon = w.slope;
  horizon.assign(static_cast<std::size_t>(floor.steps() * sectors), -kInf);
  for_each_reliable_column(w, [&](std::int32_t layer, std::size_t bin, double distance) {
    const double bottom = bottom_face(grid, layer);  // the limits, at each column's centre
    if (bottom < sensor_z) horizon[bin] = std::max(horizon[bin], (bottom - margin - sensor_z) / distance);
  });
  std::vector<double> nearer(static_cast<std::size_t>(sectors), -kInf);  // per sector, from the sensor out
  for (std::int64_t step = 0; step < floor.steps(); ++step) {
    double* const slots = horizon.data() + step * sectors;
    for (std::size_t sector = 0; sector < nearer.size(); ++sector) {
      const double here = slots[sector];
      slots[sector] = nearer[sector];
      nearer[sector] = std::max(nearer[sector], here);
    }
  }
  for_each_reliable_column(w, [&](std::int32_t& layer, std::size_t bin, double distance) {
    if ((bottom_face(grid, layer) + grid.edge_m - sensor_z) / distance < horizon[bin]) layer = kNone;  // hidden
  });
  floor.reset();
}

/// Step 3's rays: those to the points whose cube is not below G0 - 1 (`ground`, per column).
void add_rays(const CubeGrid& grid, const NextPoints& next_points, const std::vector<std::int32_t>& ground,
              FreeSpaceFloor& floor, std::vector<CubePoint>& chunk) {
  constexpr std::size_t kChunk = 2048;  // 64 kB: stays in the cache between the caller and here
  chunk.resize(kChunk);
  const std::int64_t num_columns = grid.num_columns();
  for (std::size_t count = 0; (count = next_points(chunk.data(), chunk.size())) > 0;) {
    for (std::size_t i = 0; i < std::min(count, chunk.size()); ++i) {
      const CubePoint& taking_part = chunk[i];
      // The column and layer of I by [CBC] eq. (1) (one division is cheaper than quantising the point again).
      const std::int64_t layer = taking_part.cube / num_columns;
      const std::int32_t below = ground[static_cast<std::size_t>(taking_part.cube - layer * num_columns)];
      if (below == kNone || layer >= std::int64_t{below} - 1) floor.add_ray(taking_part.point);  // not below G0
    }
  }
}

/// L's positions column by column (a counting sort by column; layers stay ascending).
void order_by_column(std::int64_t num_columns, Workspace& w) {
  w.start.assign(static_cast<std::size_t>(num_columns) + 1, 0);
  for (const std::int32_t column : w.column_of) ++w.start[static_cast<std::size_t>(column) + 1];
  for (std::size_t column = 0; column < static_cast<std::size_t>(num_columns); ++column) {
    w.start[column + 1] += w.start[column];
  }
  w.by_column.resize(w.column_of.size());
  std::vector<std::int32_t>& next = w.scratch;  // reused: the window pass is over
  next.assign(w.start.begin(), w.start.end() - 1);
  for (std::size_t position = 0; position < w.column_of.size(); ++position) {
    w.by_column[static_cast<std::size_t>(next[static_cast<std::size_t>(w.column_of[position])]++)] =
        static_cast<std::int32_t>(position);
  }
}

bool is_removal(CubeReason reason) {
  return reason == CubeReason::kRemovedAboveKept || reason == CubeReason::kRemovedFreeBelow ||
         reason == CubeReason::kRemovedRim;
}

/// Whether a removed cube makes the thin chains beside it rims (step 5): a wide chain's removal
/// and a rim's do; the removal above a kept chain ([CBC]'s case) does not, since its bottom was
/// never judged wide (a trunk's top over a bush would carry it up the trunk).
bool passes_removal_on(CubeReason reason) {
  return reason == CubeReason::kRemovedFreeBelow || reason == CubeReason::kRemovedRim;
}

/// A chain of a column: its positions [first, last] in Workspace::by_column.
struct Chain {
  std::int64_t ix, iy;
  std::size_t first, last;
};

/// Step 4: judges the chains of every column bottom-up; step 5: the rims.
class ColumnJudge {
 public:
  ColumnJudge(const CubeGrid& grid, const Workspace& w, int sigma, const ShadowAwareParams& params,
              const FreeSpaceFloor& floor)
      : grid_(grid), w_(w), sigma_(sigma), params_(params), floor_(floor) {}

  /// The reasons of the cubes of column (ix, iy) (at their positions in L); its thin chains are
  /// appended to `thin`.
  void judge(std::int64_t ix, std::int64_t iy, std::vector<CubeReason>& reasons, std::vector<Chain>& thin) const {
    const std::int64_t column = ix + iy * grid_.ixmax;
    const auto [begin, end] = range(column);
    if (begin == end) return;  // most columns are empty
    const std::int32_t ground = w_.ground[static_cast<std::size_t>(column)];
    bool kept_below = false;
    double free_floor = std::numeric_limits<double>::quiet_NaN();  // F, computed when first needed
    for (std::size_t first = begin; first < end;) {
      const std::size_t last = chain_end(first, end);
      const std::int64_t bottom = layer_at(first), top = layer_at(last);
      CubeReason reason;
      if (ground == kNone) {
        reason = CubeReason::kNoGroundEstimate;
      } else if (top < ground) {
        reason = CubeReason::kBelowGround;
      } else if (bottom - ground - 1 < sigma_) {
        reason = CubeReason::kSupported;
      } else if (kept_below) {
        reason = CubeReason::kRemovedAboveKept;  // [CBC] Algorithm 1's case: observed support below
      } else if (!bottom_is_wide(ix, iy, bottom)) {
        reason = CubeReason::kThin;
        thin.push_back({ix, iy, first, last});
      } else {
        if (std::isnan(free_floor)) free_floor = floor_.floor_of(ix, iy);
        reason = free_below(free_floor, bottom) ? CubeReason::kRemovedFreeBelow : CubeReason::kShadowed;
      }
      kept_below = kept_below || !(reason == CubeReason::kBelowGround || reason == CubeReason::kRemovedAboveKept ||
                                   reason == CubeReason::kRemovedFreeBelow);
      for (std::size_t i = first; i <= last; ++i) reasons[position(i)] = reason;
      first = last + 1;
    }
  }

  /// Step 5 (remove_rims): the thin chains `thin` that lie at the rim of a removed chain, judged
  /// as wide ones, with a work list: a chain that goes puts the thin chains of the columns around it
  /// back on the list. Removals only add removed cubes, so the result is the same in any order.
  void remove_rims(std::vector<Chain> thin, std::vector<CubeReason>& reasons) const {
    while (!thin.empty()) {
      const Chain chain = thin.back();
      thin.pop_back();
      if (reasons[position(chain.first)] != CubeReason::kThin ||
          !at_rim(chain.ix, chain.iy, layer_at(chain.first), reasons))
        continue;
      const bool removed = free_below(floor_.floor_of(chain.ix, chain.iy), layer_at(chain.first));
      for (std::size_t i = chain.first; i <= chain.last; ++i) {
        reasons[position(i)] = removed ? CubeReason::kRemovedRim : CubeReason::kShadowed;
      }
      if (removed) thin_chains_around(chain.ix, chain.iy, reasons, thin);
    }
  }

 private:
  /// Whether a ray crossed the column, whose free-space floor is F, under the bottom face of `bottom`.
  bool free_below(double free_floor, std::int64_t bottom) const {
    return free_floor < bottom_face(grid_, bottom) - params_.free_margin_m;
  }

  /// Whether, among the 8 columns around (ix, iy), one holds a cube within one layer of `bottom`
  /// that passes its removal on, and no more hold a supported one there than such a removed one.
  bool at_rim(std::int64_t ix, std::int64_t iy, std::int64_t bottom, const std::vector<CubeReason>& reasons) const {
    int removed = 0, grounded = 0;
    for_each_column_around(ix, iy, [&](std::size_t begin, std::size_t end, std::int64_t, std::int64_t) {
      bool removed_here = false, grounded_here = false;
      for (std::size_t i = begin; i < end && layer_at(i) <= bottom + 1; ++i) {
        if (layer_at(i) < bottom - 1) continue;
        removed_here = removed_here || passes_removal_on(reasons[position(i)]);
        grounded_here = grounded_here || reasons[position(i)] == CubeReason::kSupported;
      }
      removed += removed_here ? 1 : 0;
      grounded += grounded_here ? 1 : 0;
    });
    return removed > 0 && removed >= grounded;
  }

  /// Appends the thin chains of the 8 columns around (ix, iy) to `thin`.
  void thin_chains_around(std::int64_t ix, std::int64_t iy, const std::vector<CubeReason>& reasons,
                          std::vector<Chain>& thin) const {
    for_each_column_around(ix, iy, [&](std::size_t begin, std::size_t end, std::int64_t x, std::int64_t y) {
      for (std::size_t first = begin; first < end;) {
        const std::size_t last = chain_end(first, end);
        if (reasons[position(first)] == CubeReason::kThin) thin.push_back({x, y, first, last});
        first = last + 1;
      }
    });
  }

  std::pair<std::size_t, std::size_t> range(std::int64_t column) const {
    return {static_cast<std::size_t>(w_.start[static_cast<std::size_t>(column)]),
            static_cast<std::size_t>(w_.start[static_cast<std::size_t>(column) + 1])};
  }

  /// The position in L of position i of Workspace::by_column.
  std::size_t position(std::size_t i) const { return static_cast<std::size_t>(w_.by_column[i]); }

  std::int64_t layer_at(std::size_t i) const { return w_.layer_of[position(i)]; }

  /// The last position of the chain that starts at position `first` of a column ending at `end`.
  std::size_t chain_end(std::size_t first, std::size_t end) const {
    std::size_t last = first;
    while (last + 1 < end && layer_at(last + 1) - layer_at(last) - 1 < sigma_) ++last;
    return last;
  }

  /// Calls f(begin, end, x, y) for each of the (up to 8) columns (x, y) around (ix, iy) in the grid.
  template <typename F>
  void for_each_column_around(std::int64_t ix, std::int64_t iy, F&& f) const {
    for (std::int64_t y = std::max<std::int64_t>(0, iy - 1); y <= std::min(grid_.iymax - 1, iy + 1); ++y) {
      for (std::int64_t x = std::max<std::int64_t>(0, ix - 1); x <= std::min(grid_.ixmax - 1, ix + 1); ++x) {
        if (x == ix && y == iy) continue;
        const auto [begin, end] = range(x + y * grid_.ixmax);
        f(begin, end, x, y);
      }
    }
  }

  /// Whether the bottom of a floating chain of column (ix, iy) is wide, as a crown's or a ceiling's
  /// underside is and a trunk's or a pole's is not: `min_bottom_neighbours` of the 8 columns around
  /// hold a cube within one layer of `bottom`; or, when none of those 8 holds a grounded chain at
  /// that height (so the chain is no part of a pole, car or wall beside it), as many columns of the
  /// wider square (bottom_window) hold a floating chain there (sparse scan rings under a ceiling).
  bool bottom_is_wide(std::int64_t ix, std::int64_t iy, std::int64_t bottom) const {
    int beside = 0, floating = 0;
    bool grounded_beside = false;
    const std::int64_t reach = params_.bottom_window;
    for (std::int64_t y = std::max<std::int64_t>(0, iy - reach); y <= std::min(grid_.iymax - 1, iy + reach); ++y) {
      for (std::int64_t x = std::max<std::int64_t>(0, ix - reach); x <= std::min(grid_.ixmax - 1, ix + reach); ++x) {
        if (x == ix && y == iy) continue;
        const std::int64_t column = x + y * grid_.ixmax;
        const auto [begin, end] = range(column);
        std::size_t i = begin;
        while (i < end && layer_at(i) < bottom - 1) ++i;
        if (i == end || layer_at(i) > bottom + 1) continue;  // no cube within one layer of the bottom
        const bool adjacent = std::abs(x - ix) <= 1 && std::abs(y - iy) <= 1;
        const bool floats = chain_floats(column, begin, i);
        beside += adjacent ? 1 : 0;
        floating += floats ? 1 : 0;
        grounded_beside = grounded_beside || (adjacent && !floats);
      }
    }
    const int needed = params_.min_bottom_neighbours;
    return beside >= needed || (!grounded_beside && floating >= needed);
  }

  /// Whether the chain holding position i of `column` (whose cubes start at `begin`) floats: its
  /// bottom lies σ or more empty cubes above the column's ground G (false without a G).
  bool chain_floats(std::int64_t column, std::size_t begin, std::size_t i) const {
    const std::int32_t ground = w_.ground[static_cast<std::size_t>(column)];
    if (ground == kNone) return false;
    while (i > begin && layer_at(i) - layer_at(i - 1) - 1 < sigma_) --i;
    return layer_at(i) - ground - 1 >= sigma_;
  }

  const CubeGrid& grid_;
  const Workspace& w_;
  int sigma_;
  const ShadowAwareParams& params_;
  const FreeSpaceFloor& floor_;
};

}  // namespace

const char* cube_reason_name(CubeReason reason) {
  switch (reason) {
    case CubeReason::kSupported:
      return "supported";
    case CubeReason::kBelowGround:
      return "below_ground";
    case CubeReason::kNoGroundEstimate:
      return "no_ground_estimate";
    case CubeReason::kShadowed:
      return "shadowed";
    case CubeReason::kRemovedAboveKept:
      return "removed_above_kept";
    case CubeReason::kRemovedFreeBelow:
      return "removed_free_below";
    case CubeReason::kThin:
      return "thin";
    case CubeReason::kRemovedRim:
      return "removed_rim";
    case CubeReason::kNotUsed:
      return "not_used";
  }
  return "unknown";
}

void check_shadow_aware_params(const ShadowAwareParams& params) {
  if (params.sensor_origin && !params.sensor_origin->allFinite()) {
    throw std::invalid_argument("shadow_aware sensor_origin must be finite");
  }
  if (!(params.ground_radius_m >= 0.0) || !std::isfinite(params.ground_radius_m)) {
    throw std::invalid_argument("shadow_aware ground_radius_m must be a finite length >= 0 m, got " +
                                detail::number_text(params.ground_radius_m));
  }
  if (params.ground_support < 1 || params.ground_support > 9) {
    throw std::invalid_argument("shadow_aware ground_support must be 1..9 columns of a 3x3 neighbourhood, got " +
                                std::to_string(params.ground_support));
  }
  if (!(params.hidden_ground_margin_m >= 0.0) || !std::isfinite(params.hidden_ground_margin_m)) {
    throw std::invalid_argument("shadow_aware hidden_ground_margin_m must be a finite length >= 0 m, got " +
                                detail::number_text(params.hidden_ground_margin_m));
  }
  if (!(params.free_margin_m >= 0.0) || !std::isfinite(params.free_margin_m)) {
    throw std::invalid_argument("shadow_aware free_margin_m must be a finite length >= 0 m, got " +
                                detail::number_text(params.free_margin_m));
  }
  if (params.bottom_window < 1 || params.bottom_window > 8) {
    throw std::invalid_argument("shadow_aware bottom_window must be 1..8 columns, got " +
                                std::to_string(params.bottom_window));
  }
  const int around = (2 * params.bottom_window + 1) * (2 * params.bottom_window + 1) - 1;
  if (params.min_bottom_neighbours < 0 || params.min_bottom_neighbours > around) {
    throw std::invalid_argument("shadow_aware min_bottom_neighbours must be 0.." + std::to_string(around) +
                                " columns, got " + std::to_string(params.min_bottom_neighbours));
  }
  if (!(params.no_return_range_m > 0.0) || !std::isfinite(params.no_return_range_m)) {
    throw std::invalid_argument("shadow_aware no_return_range_m must be a positive finite length, got " +
                                detail::number_text(params.no_return_range_m));
  }
  if (params.azimuth_bins < 1 || params.azimuth_bins > (1 << 20)) {
    throw std::invalid_argument("shadow_aware azimuth_bins must be 1..2^20, got " +
                                std::to_string(params.azimuth_bins));
  }
}

void check_directions(const PointsView<double>& directions, const char* name) {
  if (directions.size > 0 && directions.data == nullptr) {
    throw std::invalid_argument(std::string(name) + " view has no data but claims " + std::to_string(directions.size) +
                                " rows");
  }
  for (std::size_t k = 0; k < directions.size; ++k) {
    const Eigen::Vector3d d = directions.point(k);
    if (!d.allFinite() || d.isZero(0.0)) {
      throw std::invalid_argument(std::string(name) + " row " + std::to_string(k) +
                                  " must be a finite, non-zero direction");
    }
  }
}

ShadowAwareDecision shadow_aware_collapse(const CubeGrid& grid, const std::vector<std::int64_t>& sorted_occupied,
                                          const NextPoints& next_points, int sigma,
                                          const Eigen::Vector3d& sensor_origin, const ShadowAwareParams& params,
                                          const PointsView<double>& no_returns, const Eigen::Matrix3d& leveling) {
  check_shadow_aware_params(params);
  check_directions(no_returns, "no_return_directions");
  if (!leveling.allFinite()) throw std::invalid_argument("shadow_aware leveling rotation must be finite");
  if (sigma < 1) throw std::invalid_argument("sigma must be at least 1 cube, got " + std::to_string(sigma));
  if (!sensor_origin.allFinite()) throw std::invalid_argument("shadow_aware sensor origin must be finite");
  ShadowAwareDecision decision;
  if (sorted_occupied.empty()) return decision;
  const std::int64_t num_columns = grid.num_columns();
  if (num_columns > kMaxColumns || grid.izmax >= kNone - 1 ||
      sorted_occupied.size() > static_cast<std::size_t>(kNone)) {
    throw std::invalid_argument("shadow_aware needs per-column arrays; " + std::to_string(num_columns) +
                                " columns (or its layers) is over 2^27: crop the cloud or use a larger edge");
  }
  Workspace& w = thread_workspace();
  split_cubes(sorted_occupied, num_columns, w);
  lowest_layers(num_columns, w);
  reliable_ground(grid, w.lowest, params.ground_support, sigma, w.reliable);
  FreeSpaceFloor floor(grid, sensor_origin, params.azimuth_bins, w.slope);
  place_reliable_columns(grid, floor, w);
  hide_occluded_ground(grid, floor, params.hidden_ground_margin_m, w);
  // The window in columns, clipped to the grid in doubles: a radius of 1e300 m is finite, and its
  // column count would overflow a 64-bit integer.
  const auto radius = static_cast<std::int64_t>(std::min(std::ceil(params.ground_radius_m / grid.edge_m - 1e-9),
                                                         static_cast<double>(std::max(grid.ixmax, grid.iymax))));
  window_minimum(grid, radius, w.reliable, w.scratch, w.ground, w.line);  // G0
  add_rays(grid, next_points, w.ground, floor, w.chunk);
  for (std::size_t k = 0; k < no_returns.size; ++k) {
    const Eigen::Vector3d direction = no_returns.point(k);
    floor.add_free_beam(leveling * (direction / direction.cwiseAbs().maxCoeff()), params.no_return_range_m);
  }
  floor.finish();
  // Step 2 again: a lowest cube with a ray under it is no ground (a crown's underside), then G.
  for_each_reliable_column(w, [&](std::int32_t& layer, std::size_t bin, double distance) {
    if (floor.floor_at(bin, distance) < bottom_face(grid, layer)) layer = kNone;
  });
  window_minimum(grid, radius, w.reliable, w.scratch, w.ground, w.line);
  order_by_column(num_columns, w);
  decision.reasons.assign(sorted_occupied.size(), CubeReason::kSupported);
  const ColumnJudge judge(grid, w, sigma, params, floor);
  std::vector<Chain> thin;
  for (std::int64_t iy = 0; iy < grid.iymax; ++iy) {
    for (std::int64_t ix = 0; ix < grid.ixmax; ++ix) judge.judge(ix, iy, decision.reasons, thin);
  }
  if (params.remove_rims) judge.remove_rims(std::move(thin), decision.reasons);
  for (std::size_t position = 0; position < sorted_occupied.size(); ++position) {
    if (is_removal(decision.reasons[position])) decision.removed_cubes.push_back(sorted_occupied[position]);
  }
  if (num_columns * 12 > (std::int64_t{64} << 20)) w = Workspace();  // release after a large call
  return decision;
}

}  // namespace terracube
