// Collapsible cubes: overhang removal, [CBC] section III. Algorithm 1 is collapse_columns below;
// the passes over the points around it build its input (V and L) and apply its output (R).
#include "terracube/collapse.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <exception>
#include <limits>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <unordered_map>

#include "cloud_frame.hpp"
#include "number_text.hpp"
#include "parallel.hpp"

namespace terracube {

namespace {

/// Rows per part of the passes over the points (a fixed partition: see parallel.hpp).
constexpr std::size_t kRowsPerPart = 32768;

/// The cube index I of a row is 32-bit on the dense storage (fewer than 2^31 cubes), which halves
/// the memory the passes over the rows read and write, and 64-bit on the sparse one.
using DenseIndex = std::uint32_t;
using SparseIndex = std::int64_t;
/// The cube of a row that takes no part.
template <typename Index>
constexpr Index kNoCube = std::numeric_limits<Index>::max();

/// [CBC] Algorithm 1: sweeps the occupied cubes L, sorted by I, and returns the collapsed cubes R
/// (ascending). Sorting by I ([CBC] eq. (1)) visits the layers bottom-up, so every column is seen
/// bottom-up too. `ground_of(column)` is M: the layer i_z of the column's current ground cube, or
/// -1 (no ground yet). An occupied cube separated from its column's ground by fewer than σ empty
/// cubes becomes the new ground; otherwise it is collapsed into R.
template <typename GroundOf>
std::vector<std::int64_t> collapse_columns(const std::vector<std::int64_t>& sorted_occupied, std::int64_t num_columns,
                                           int sigma, GroundOf&& ground_of) {
  std::vector<std::int64_t> removed;
  for (const std::int64_t cube : sorted_occupied) {
    const std::int64_t layer = cube / num_columns;  // i_z, [CBC] eq. (9)
    const std::int64_t column = cube - layer * num_columns;
    auto& ground = ground_of(column);
    if (ground < 0 || layer - ground - 1 < sigma) {
      ground = static_cast<std::remove_reference_t<decltype(ground)>>(layer);
    } else {
      removed.push_back(cube);
    }
  }
  return removed;
}

/// R from L: [CBC] Algorithm 1 (collapse_columns), or the shadow-aware rule (shadow_aware.hpp),
/// which also fills the result's cube reasons.
template <typename GroundOf>
std::vector<std::int64_t> removed_cubes_of(const std::vector<std::int64_t>& sorted_occupied,
                                           const CollapseParams& params, const NextPoints& next_points,
                                           const PointsView<double>& no_returns, CollapseResult& result,
                                           GroundOf&& ground_of) {
  if (params.method != CollapseMethod::kShadowAware) {
    return collapse_columns(sorted_occupied, result.grid.num_columns(), params.sigma, ground_of);
  }
  const Eigen::Vector3d origin = params.shadow_aware.sensor_origin.value_or(params.transform.block<3, 1>(0, 3));
  ShadowAwareDecision decision =
      shadow_aware_collapse(result.grid, sorted_occupied, next_points, params.sigma, origin, params.shadow_aware,
                            no_returns, params.transform.topLeftCorner<3, 3>());
  result.cube_reasons = std::move(decision.reasons);
  return std::move(decision.removed_cubes);
}

/// [CBC] eqs. (4)-(6) and (1): the index I of the cube holding a leveled point, or kNoCube when
/// the point takes no part or lies outside the grid (NaN compares false: NaN/Inf rows fall out
/// here too). A measured point lies inside, but the caller's array may change during a call
/// (another thread, a recycled driver buffer, a memory map): such a row then takes no part, and
/// nothing is written out of bounds (nor is an out-of-range double cast to an integer). Without
/// branches: a pass over a scan would otherwise stall on them.
template <typename Index>
struct CubeIndexer {
  explicit CubeIndexer(const CubeGrid& grid)
      : min_corner(grid.min_corner),
        inverse_edge(1.0 / grid.edge_m),
        cubes(static_cast<double>(grid.ixmax), static_cast<double>(grid.iymax), static_cast<double>(grid.izmax)),
        ixmax(static_cast<Index>(grid.ixmax)),
        layer(static_cast<Index>(grid.num_columns())) {}

  // Inlined into each of the layouts' passes (GCC would otherwise call it once per row).
  [[gnu::always_inline]] Index operator()(const Eigen::Vector3d& p, bool takes_part) const {
    const double x = (p.x() - min_corner.x()) * inverse_edge + 0.5;  // round half up
    const double y = (p.y() - min_corner.y()) * inverse_edge + 0.5;
    const double z = (p.z() - min_corner.z()) * inverse_edge + 0.5;
    const bool inside =
        takes_part & (x >= 0.0) & (y >= 0.0) & (z >= 0.0) & (x < cubes.x()) & (y < cubes.y()) & (z < cubes.z());
    // Inside the grid truncation is the floor of eqs. (4)-(6); outside, 0 is converted instead.
    const Index cube = floor_of(inside ? x : 0.0) + floor_of(inside ? y : 0.0) * ixmax +
                       floor_of(inside ? z : 0.0) * layer;  // eq. (1)
    return inside ? cube : kNoCube<Index>;
  }

  /// A non-negative coordinate below the grid's cube count on its axis, truncated.
  static Index floor_of(double position) {
    if constexpr (std::is_same_v<Index, DenseIndex>) {
      return static_cast<Index>(static_cast<std::int32_t>(position));  // < 2^31 on the dense storage
    } else {
      return static_cast<Index>(position);
    }
  }

  Eigen::Vector3d min_corner;
  double inverse_edge;
  Eigen::Vector3d cubes;  // ixmax, iymax, izmax
  Index ixmax;
  Index layer;
};

/// V as a bit per cube, its summary as a bit per 64 cubes, plus M as a 32-bit layer per column [bytes].
std::size_t dense_bytes(const CubeGrid& grid) {
  const auto words = static_cast<std::size_t>((grid.num_cubes() + 63) / 64);
  return (words + (words + 63) / 64) * 8 + static_cast<std::size_t>(grid.num_columns()) * sizeof(std::int32_t);
}

CubeStorage choose_storage(const CubeGrid& grid, const CollapseParams& params, std::size_t num_used) {
  const bool fits = grid.num_cubes() < (std::int64_t{1} << 31) && dense_bytes(grid) <= params.dense_budget_bytes;
  if (params.storage == CubeStorage::kDense) {
    if (!fits) {
      throw std::invalid_argument("dense cube storage would need " + std::to_string(dense_bytes(grid)) + " bytes for " +
                                  std::to_string(grid.num_cubes()) +
                                  " cubes, over dense_budget_bytes; use storage auto or sparse");
    }
    return CubeStorage::kDense;
  }
  if (params.storage == CubeStorage::kSparse) return CubeStorage::kSparse;
  // Auto: dense only while clearing V and M costs about as much as a pass over the points.
  const std::size_t affordable = (std::size_t{16} << 20) + 16 * num_used;
  return fits && dense_bytes(grid) <= affordable ? CubeStorage::kDense : CubeStorage::kSparse;
}

/// The extent of the rows that take part, measured in parts merged in row order.
template <typename Cloud>
detail::CloudExtent measure_extent_in_parts(const Cloud& cloud, bool drop_non_finite, int num_threads) {
  const int parts = detail::fixed_parts(cloud.size(), kRowsPerPart);
  std::vector<detail::CloudExtent> extents(static_cast<std::size_t>(parts));
  detail::for_each_part(num_threads, parts, [&](int part) {
    const auto [begin, end] = detail::part_range(cloud.size(), part, parts);
    cloud.with_fixed_layout([&, begin = begin, end = end](const auto& rows) {
      extents[static_cast<std::size_t>(part)] = detail::extent_of_rows(rows, begin, end);
    });
  });
  detail::CloudExtent extent;
  for (const detail::CloudExtent& piece : extents) extent.merge(piece);
  if (extent.non_finite.count > 0 && !drop_non_finite) detail::throw_non_finite_rows(extent.non_finite, cloud.size());
  return extent;
}

/// The buffers of one call, kept by the calling thread for its next call: on the VMs this project
/// is measured on, first touching fresh memory costs about 2.5 us per 4 kB page, which for a scan's
/// cube indices alone is more than the rest of the call. Released after a call that needed over 64 MB.
struct Workspace {
  std::vector<DenseIndex> dense_cubes;    ///< I per row, dense storage
  std::vector<SparseIndex> sparse_cubes;  ///< I per row, sparse storage
  std::vector<std::uint64_t> occupancy;   ///< V, dense storage
  std::vector<std::uint64_t> summary;     ///< a bit per word of V: set when the word may not be 0
  std::vector<std::int32_t> ground;       ///< M, dense storage

  void release_if_large() {
    const std::size_t bytes = 4 * dense_cubes.capacity() +
                              8 * (sparse_cubes.capacity() + occupancy.capacity() + summary.capacity()) +
                              4 * ground.capacity();
    if (bytes > (std::size_t{64} << 20)) *this = Workspace();
  }
};

Workspace& thread_workspace() {
  thread_local Workspace workspace;
  return workspace;
}

/// The cube index I of every row (kNoCube for rows that take no part) into `cubes`, in parts.
template <typename Index, typename Cloud>
void cube_of_rows(const Cloud& cloud, const CubeGrid& grid, int num_threads, std::vector<Index>& cubes) {
  const CubeIndexer<Index> index_of(grid);
  cubes.resize(cloud.size());
  const int parts = detail::fixed_parts(cloud.size(), kRowsPerPart);
  detail::for_each_part(num_threads, parts, [&](int part) {
    const auto [begin, end] = detail::part_range(cloud.size(), part, parts);
    cloud.with_fixed_layout([&, begin = begin, end = end](const auto& rows) {
      Index* const out = cubes.data();  // local copies: a store to out[] could change members
      const CubeIndexer<Index> index_in_grid = index_of;
      for (std::size_t row = begin; row < end; ++row) {
        const Eigen::Vector3d p = rows.level(row);
        out[row] = index_in_grid(p, rows.in_crop(p));
      }
    });
  });
}

/// The shadow-aware rule's rays: the rows that take part (their cube is not kNoCube), leveled
/// again, with their cube, in row order, a chunk at a time (the paper's rule never asks).
template <typename Index, typename Cloud>
NextPoints points_of_rows(const Cloud& cloud, const std::vector<Index>& cubes) {
  return [&cloud, &cubes, row = std::size_t{0}](CubePoint* out, std::size_t capacity) mutable {
    std::size_t count = 0;
    Eigen::Vector3d p;
    for (; row < cubes.size() && count < capacity; ++row) {
      if (cubes[row] != kNoCube<Index> && cloud.map(row, p) == 0) {
        out[count++] = {p, static_cast<std::int64_t>(cubes[row])};
      }
    }
    return count;
  };
}

/// The overhang mask: rows whose cube `is_removed`, computed in parts; returns how many.
template <typename Index, typename IsRemoved>
std::size_t write_mask(const std::vector<Index>& cube_of_row, int num_threads, const IsRemoved& is_removed,
                       std::vector<std::uint8_t>& overhang_of_row) {
  const int parts = detail::fixed_parts(cube_of_row.size(), kRowsPerPart);
  std::vector<std::size_t> counts(static_cast<std::size_t>(parts), 0);
  detail::for_each_part(num_threads, parts, [&](int part) {
    const auto [begin, end] = detail::part_range(cube_of_row.size(), part, parts);
    // Plain local pointers and a local copy of the test: a byte store may alias anything, so
    // through references the compiler would reload them on every row.
    const Index* const cubes = cube_of_row.data();
    std::uint8_t* const overhang = overhang_of_row.data();
    const IsRemoved removed_cube = is_removed;
    std::size_t count = 0;
    for (std::size_t row = begin; row < end; ++row) {
      const std::uint8_t removed = cubes[row] != kNoCube<Index> && removed_cube(cubes[row]) ? 1 : 0;
      overhang[row] = removed;
      count += removed;
    }
    counts[static_cast<std::size_t>(part)] = count;
  });
  std::size_t total = 0;
  for (const std::size_t count : counts) total += count;
  return total;
}

/// Sets V's bit of every row's cube and, with kSummary, the summary's bit of that bit's word.
template <bool kSummary>
void mark_occupied(const std::vector<DenseIndex>& cubes, std::uint64_t* occupancy, std::uint64_t* summary) {
  const auto mark = [occupancy, summary](DenseIndex cube) {
    if (cube == kNoCube<DenseIndex>) return;
    occupancy[cube >> 6] |= std::uint64_t{1} << (cube & 63);
    if constexpr (kSummary) summary[cube >> 12] |= std::uint64_t{1} << ((cube >> 6) & 63);
  };
  // Rows in two interleaved halves: neighbouring rows of a scan often set bits of one word, and
  // each such update would wait for the one before.
  const std::size_t half = cubes.size() / 2;
  for (std::size_t row = 0; row < half; ++row) {
    mark(cubes[row]);
    mark(cubes[half + row]);
  }
  if (cubes.size() % 2 == 1) mark(cubes.back());
}

/// Appends the cubes of V's word `word` to L, in ascending order.
void list_word(std::uint64_t bits, std::size_t word, std::vector<std::int64_t>& occupied) {
  for (; bits != 0; bits &= bits - 1) occupied.push_back(static_cast<std::int64_t>(word * 64) + __builtin_ctzll(bits));
}

/// Dense storage: V is a bit per cube of the grid, M a layer per column. Reading V in index order
/// lists L already sorted (a bucket sort). When V has more words than the cloud has rows (a
/// long-range scan: an Ouster scan at E = 0.5 m has 44 M cubes, 22 k of them occupied), a summary
/// bit per word of V marks the words that hold a cube and the listing skips empty stretches 4096
/// cubes at a time; on smaller grids reading every word costs less than keeping the summary.
/// The workspace keeps V, the summary and M clear between calls: a call clears only what it set,
/// O(|L|), not the whole grid.
void collapse_dense(Workspace& workspace, const CollapseParams& params, const NextPoints& next_points,
                    const PointsView<double>& no_returns, CollapseResult& result) {
  const CubeGrid& grid = result.grid;
  const std::vector<DenseIndex>& cubes = workspace.dense_cubes;
  const auto words = static_cast<std::size_t>((grid.num_cubes() + 63) / 64);
  const bool summarise = words > cubes.size();
  const std::size_t summary_words = summarise ? (words + 63) / 64 : 0;
  const auto num_columns = static_cast<std::size_t>(grid.num_columns());
  if (workspace.occupancy.size() < words) workspace.occupancy.resize(words, 0);
  if (workspace.summary.size() < summary_words) workspace.summary.resize(summary_words, 0);
  if (workspace.ground.size() < num_columns) workspace.ground.resize(num_columns, -1);
  std::uint64_t* const occupancy = workspace.occupancy.data();  // V
  std::uint64_t* const summary = workspace.summary.data();
  std::vector<std::int64_t>& occupied = result.occupied_cubes;  // L, sorted
  if (summarise) {
    mark_occupied<true>(cubes, occupancy, summary);
    for (std::size_t block = 0; block < summary_words; ++block) {
      for (std::uint64_t marked = summary[block]; marked != 0; marked &= marked - 1) {
        const std::size_t word = block * 64 + static_cast<std::size_t>(__builtin_ctzll(marked));
        list_word(occupancy[word], word, occupied);
      }
    }
  } else {
    mark_occupied<false>(cubes, occupancy, summary);
    for (std::size_t word = 0; word < words; ++word) list_word(occupancy[word], word, occupied);
  }
  std::vector<std::int32_t>& ground = workspace.ground;  // M
  result.removed_cubes =
      removed_cubes_of(occupied, params, next_points, no_returns, result,
                       [&](std::int64_t column) -> auto& { return ground[static_cast<std::size_t>(column)]; });
  // R's bits cleared in V: a row is overhang when its cube's bit is gone.
  for (const std::int64_t cube : result.removed_cubes) {
    occupancy[static_cast<std::size_t>(cube >> 6)] &= ~(std::uint64_t{1} << (cube & 63));
  }
  result.num_overhang = write_mask(
      cubes, params.num_threads,
      [occupancy](DenseIndex cube) { return ((occupancy[cube >> 6] >> (cube & 63)) & 1U) == 0; }, result.overhang);
  for (const std::int64_t cube : occupied) {  // V, its summary and M cleared for the next call
    occupancy[static_cast<std::size_t>(cube >> 6)] = 0;
    if (summarise) summary[static_cast<std::size_t>(cube >> 12)] = 0;
    ground[static_cast<std::size_t>(cube % grid.num_columns())] = -1;
  }
}

/// Sparse storage: L is the sorted distinct cubes of the rows and M a hash map over the columns
/// that hold points, so memory is O(N) whatever the extent.
void collapse_sparse(const std::vector<SparseIndex>& cubes, const NextPoints& next_points,
                     const PointsView<double>& no_returns, const CollapseParams& params, CollapseResult& result) {
  const int num_threads = params.num_threads;
  std::vector<std::int64_t>& occupied = result.occupied_cubes;  // L
  occupied.reserve(cubes.size());
  for (const SparseIndex cube : cubes) {
    if (cube != kNoCube<SparseIndex>) occupied.push_back(cube);
  }
  std::sort(occupied.begin(), occupied.end());
  occupied.erase(std::unique(occupied.begin(), occupied.end()), occupied.end());
  std::unordered_map<std::int64_t, std::int64_t> ground;  // M, only for columns that hold points
  ground.reserve(occupied.size());
  result.removed_cubes = removed_cubes_of(
      occupied, params, next_points, no_returns, result,
      [&](std::int64_t column) -> std::int64_t& { return ground.try_emplace(column, -1).first->second; });
  const std::vector<std::int64_t>& removed = result.removed_cubes;  // sorted, as L is
  result.num_overhang = write_mask(
      cubes, num_threads, [&](SparseIndex cube) { return std::binary_search(removed.begin(), removed.end(), cube); },
      result.overhang);
}

template <typename Scalar>
CollapseResult collapse_impl(const PointsView<Scalar>& points, const CollapseParams& params,
                             const PointsView<double>& no_returns) {
  check_collapse_params(params);
  check_directions(no_returns, "no_return_directions");
  if (points.size > 0 && points.data == nullptr) {
    throw std::invalid_argument("points view has no data but claims " + std::to_string(points.size) + " rows");
  }
  CollapseResult result;
  result.num_points = points.size;
  result.overhang.assign(points.size, 0);
  result.grid.edge_m = params.edge_m;
  result.storage_used = params.storage == CubeStorage::kSparse ? CubeStorage::kSparse : CubeStorage::kDense;
  detail::visit_leveled(points, params.transform, params.crop, [&](const auto& cloud) {
    // The bounding box ([CBC] section II needs xmin, ymin, zmin), then the grid, [CBC] eqs. (2)-(3).
    const detail::CloudExtent extent = measure_extent_in_parts(cloud, params.drop_non_finite, params.num_threads);
    result.num_used = extent.num_used;
    result.num_cropped = extent.num_cropped;
    result.num_dropped_non_finite = extent.non_finite.count;
    if (extent.num_used == 0) return;  // empty grid, nothing occupied, nothing removed
    result.grid = detail::make_grid(extent, params.edge_m);
    result.storage_used = choose_storage(result.grid, params, extent.num_used);
    // One O(N) pass computes I for every point ([CBC] section III-B); V and L follow from them.
    Workspace& workspace = thread_workspace();
    struct ReleaseOnExit {  // and drops the workspace when a call throws (V and M may be dirty)
      Workspace& workspace;
      int exceptions = std::uncaught_exceptions();
      ~ReleaseOnExit() {
        if (std::uncaught_exceptions() > exceptions) {
          workspace = Workspace();
        } else {
          workspace.release_if_large();
        }
      }
    } release_on_exit{workspace};
    if (result.storage_used == CubeStorage::kDense) {
      cube_of_rows(cloud, result.grid, params.num_threads, workspace.dense_cubes);
      collapse_dense(workspace, params, points_of_rows(cloud, workspace.dense_cubes), no_returns, result);
    } else {
      cube_of_rows(cloud, result.grid, params.num_threads, workspace.sparse_cubes);
      collapse_sparse(workspace.sparse_cubes, points_of_rows(cloud, workspace.sparse_cubes), no_returns, params,
                      result);
    }
  });
  return result;
}

/// point_reasons(): the cube of each row that takes part, found again as cube_of_rows does (64-bit
/// indices for any grid), looked up in L; neighbouring rows mostly share a cube, so the last one
/// found is tried first.
template <typename Scalar>
std::vector<CubeReason> point_reasons_impl(const PointsView<Scalar>& points, const CollapseParams& params,
                                           const CollapseResult& result) {
  const std::vector<std::int64_t>& occupied = result.occupied_cubes;
  if (result.cube_reasons.size() != occupied.size() || (occupied.empty() && result.num_used > 0)) {
    throw std::invalid_argument("point_reasons needs the result of a shadow_aware collapse_overhangs (cube reasons)");
  }
  if (points.size != result.num_points) {
    throw std::invalid_argument("point_reasons: " + std::to_string(points.size) + " points given, the result is of " +
                                std::to_string(result.num_points));
  }
  if (points.size > 0 && points.data == nullptr) {
    throw std::invalid_argument("points view has no data but claims " + std::to_string(points.size) + " rows");
  }
  check_collapse_params(params);
  std::vector<CubeReason> reasons(points.size, CubeReason::kNotUsed);
  const CubeIndexer<SparseIndex> index_of(result.grid);
  std::size_t position = 0;  // in L, of the last row's cube
  detail::visit_leveled(points, params.transform, params.crop, [&](const auto& cloud) {
    Eigen::Vector3d p;
    for (std::size_t row = 0; row < cloud.size(); ++row) {
      if (cloud.map(row, p) != 0) continue;  // NaN/Inf or outside the crop: it took no part
      const SparseIndex cube = index_of(p, true);
      if (occupied.empty() || occupied[position] != cube) {
        const auto found = std::lower_bound(occupied.begin(), occupied.end(), cube);
        if (found == occupied.end() || *found != cube) {  // also a row outside the grid (kNoCube)
          throw std::invalid_argument("point_reasons: row " + std::to_string(row) +
                                      " lies in no occupied cube of the result; pass the points and parameters of "
                                      "the collapse_overhangs call");
        }
        position = static_cast<std::size_t>(found - occupied.begin());
      }
      reasons[row] = result.cube_reasons[position];
    }
  });
  return reasons;
}

}  // namespace

void check_collapse_params(const CollapseParams& params) {
  if (!(params.edge_m > 0.0) || !std::isfinite(params.edge_m)) {
    throw std::invalid_argument("edge must be a positive finite length in metres, got " +
                                detail::number_text(params.edge_m));
  }
  if (!std::isfinite(1.0 / params.edge_m)) {
    throw std::invalid_argument("edge " + detail::number_text(params.edge_m) + " m is too small to quantise with");
  }
  if (params.sigma < 1) {
    throw std::invalid_argument("sigma must be at least 1 cube, got " + std::to_string(params.sigma));
  }
  detail::check_rigid_transform(params.transform, "transform");
  detail::check_crop(params.crop);
  detail::check_num_threads(params.num_threads, "CollapseParams");
  check_shadow_aware_params(params.shadow_aware);
}

int sigma_from_robot_height(double robot_height_m, double edge_m) {
  if (!(robot_height_m > 0.0) || !std::isfinite(robot_height_m)) {
    throw std::invalid_argument("robot height must be a positive finite length in metres");
  }
  if (!(edge_m > 0.0) || !std::isfinite(edge_m)) {
    throw std::invalid_argument("edge must be a positive finite length in metres");
  }
  // [CBC] section IV-B: sigma = ceil(robot height / E). Decimal lengths are not exact in binary
  // (2.1 / 0.3 = 7.000000000000001), so a ratio within 1e-9 (relative) of a whole number is that
  // number: 2.1 / 0.3 gives 7, not 8.
  const double ratio = robot_height_m / edge_m;
  const double nearest = std::round(ratio);
  const double cubes = std::abs(ratio - nearest) <= 1e-9 * std::max(1.0, nearest) ? nearest : std::ceil(ratio);
  if (cubes > static_cast<double>(std::numeric_limits<int>::max())) {
    throw std::invalid_argument("robot height / edge is too large for sigma");
  }
  return std::max(1, static_cast<int>(cubes));
}

Eigen::Matrix4d leveling_transform(double roll_rad, double pitch_rad) {
  if (!std::isfinite(roll_rad) || !std::isfinite(pitch_rad)) {
    throw std::invalid_argument("roll and pitch must be finite angles in radians");
  }
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();
  transform.topLeftCorner<3, 3>() =
      (Eigen::AngleAxisd(pitch_rad, Eigen::Vector3d::UnitY()) * Eigen::AngleAxisd(roll_rad, Eigen::Vector3d::UnitX()))
          .toRotationMatrix();
  return transform;
}

Attitude attitude_from_gravity(const Eigen::Vector3d& up) {
  if (!up.allFinite() || !(up.norm() > 0.0)) {
    throw std::invalid_argument("attitude_from_gravity: the up direction must be finite and not zero");
  }
  // Rx(roll) turns up into the x-z plane, then Ry(pitch) onto +z.
  const double roll = std::atan2(up.y(), up.z());
  return {roll, std::atan2(-up.x(), std::hypot(up.y(), up.z()))};
}

CollapseResult collapse_overhangs(const PointsView<float>& points, const CollapseParams& params,
                                  const PointsView<double>& no_return_directions) {
  return collapse_impl(points, params, no_return_directions);
}

CollapseResult collapse_overhangs(const PointsView<double>& points, const CollapseParams& params,
                                  const PointsView<double>& no_return_directions) {
  return collapse_impl(points, params, no_return_directions);
}

CollapseResult collapse_overhangs(const std::vector<Eigen::Vector3d>& points, const CollapseParams& params,
                                  const PointsView<double>& no_return_directions) {
  return collapse_impl(PointsView<double>(points), params, no_return_directions);
}

std::vector<CubeReason> point_reasons(const PointsView<float>& points, const CollapseParams& params,
                                      const CollapseResult& result) {
  return point_reasons_impl(points, params, result);
}

std::vector<CubeReason> point_reasons(const PointsView<double>& points, const CollapseParams& params,
                                      const CollapseResult& result) {
  return point_reasons_impl(points, params, result);
}

}  // namespace terracube
