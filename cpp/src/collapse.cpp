#include "terracube/collapse.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <unordered_map>

#include "cloud_frame.hpp"
#include "quantize_kernels.hpp"
#include "threads.hpp"

namespace terracube {

namespace {

/// Algorithm 1, lines 5-15: sweep the sorted occupied cubes L. Sorting by I (eq. 7) visits the
/// layers bottom-up, so every column is seen bottom-up too. ground_of(column) is M: the layer iz
/// of the column's current ground cube, -1 for none. An occupied cube separated from the ground
/// by fewer than σ empty cubes becomes the new ground; otherwise it is collapsed into R.
template <typename F>
void for_each_column(const std::vector<std::int64_t>& occupied, std::int64_t num_columns, F&& f) {
  // L is sorted, so the layer only grows: one division per layer instead of one per cube.
  std::int64_t layer = 0;
  std::int64_t layer_start = 0;
  std::int64_t next_layer_start = 0;
  for (const std::int64_t cube : occupied) {
    if (cube >= next_layer_start) {
      layer = cube / num_columns;
      layer_start = layer * num_columns;
      next_layer_start = layer_start + num_columns;  // at most the cube count, which fits int64
    }
    f(cube, cube - layer_start, layer);
  }
}

template <typename GroundOf>
void sweep_columns(const std::vector<std::int64_t>& occupied, std::int64_t num_columns, int sigma, GroundOf&& ground_of,
                   std::vector<std::int64_t>& removed) {
  for_each_column(occupied, num_columns, [&](std::int64_t cube, std::int64_t column, std::int64_t layer) {
    auto& ground = ground_of(column);
    const std::int64_t empty_between = layer - ground - 1;
    if (ground < 0 || empty_between < sigma) {
      ground = static_cast<std::remove_reference_t<decltype(ground)>>(layer);
    } else {
      removed.push_back(cube);
    }
  });
}

struct GridQuantizer {
  Eigen::Vector3d min_corner;
  double inverse_edge;
  std::int64_t ixmax;
  std::int64_t layer_size;

  explicit GridQuantizer(const CubeGrid& grid)
      : min_corner(grid.min_corner),
        inverse_edge(1.0 / grid.edge_m),
        ixmax(grid.ixmax),
        layer_size(grid.ixmax * grid.iymax) {}

  /// Eqs. (1)-(3) and (7).
  std::int64_t operator()(const Eigen::Vector3d& p) const {
    return quantize(p.x(), min_corner.x(), inverse_edge) + quantize(p.y(), min_corner.y(), inverse_edge) * ixmax +
           quantize(p.z(), min_corner.z(), inverse_edge) * layer_size;
  }
};

std::size_t dense_bytes(const CubeGrid& grid) {
  return static_cast<std::size_t>((grid.num_cubes() + 63) / 64) * 8 +
         static_cast<std::size_t>(grid.num_columns()) * sizeof(std::int32_t);
}

CubeStorage choose_storage(const CubeGrid& grid, const CollapseParams& params, std::size_t num_used) {
  // 2^31 cubes keeps per-point indices in 32 bits on the dense path.
  const bool fits = grid.num_cubes() < (std::int64_t{1} << 31) - 64 && dense_bytes(grid) <= params.dense_budget_bytes;
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

/// Cube indices of rows [begin, end) into `out`, dense path only (every count and the product
/// stay below 2^31, so 32-bit truncation is the floor of eqs. 1-3). Rows that take no part get
/// `no_cube`. The plain, all-used case is a branch-free loop the compiler vectorises. Returns how
/// many rows the float kernel left to the double formula (0 when it did not run).
template <typename Cloud>
std::size_t quantize_block(const Cloud& cloud, const CubeGrid& grid, bool all_used, std::uint32_t no_cube,
                           float float_margin, std::size_t begin, std::size_t end, std::uint32_t* out) {
  const double inverse_edge = 1.0 / grid.edge_m;
  const double x0 = grid.min_corner.x();
  const double y0 = grid.min_corner.y();
  const double z0 = grid.min_corner.z();
  const auto ixmax = static_cast<std::uint32_t>(grid.ixmax);
  const auto layer = static_cast<std::uint32_t>(grid.num_columns());
  const auto cube_of = [&](double x, double y, double z) {
    const auto ix = static_cast<std::uint32_t>(static_cast<std::int32_t>((x - x0) * inverse_edge + 0.5));
    const auto iy = static_cast<std::uint32_t>(static_cast<std::int32_t>((y - y0) * inverse_edge + 0.5));
    const auto iz = static_cast<std::uint32_t>(static_cast<std::int32_t>((z - z0) * inverse_edge + 0.5));
    return ix + iy * ixmax + iz * layer;  // eq. (7)
  };
  if constexpr (Cloud::kPlain) {
    const auto& view = cloud.view();
    if (all_used && view.column_stride == 1 && (view.row_stride == 3 || view.row_stride == 4)) {
      const detail::QuantizeConstants constants{x0, y0, z0, inverse_edge, ixmax, layer, float_margin};
      return detail::quantize_rows(view.data + static_cast<std::ptrdiff_t>(begin) * view.row_stride, end - begin,
                                   static_cast<int>(view.row_stride), constants, out);
    }
    if (all_used) {
      for (std::size_t row = begin; row < end; ++row) {
        out[row - begin] = cube_of(cloud.raw(row, 0), cloud.raw(row, 1), cloud.raw(row, 2));
      }
      return 0;
    }
  }
  std::size_t first = begin;  // rows before it went through the leveling kernel (AVX2 CPUs)
  if constexpr (!Cloud::kPlain) {
    const auto& view = cloud.view();
    const detail::QuantizeConstants constants{x0, y0, z0, inverse_edge, ixmax, layer};
    first +=
        detail::quantize_leveled_rows(view.data + static_cast<std::ptrdiff_t>(begin) * view.row_stride, end - begin,
                                      view.row_stride, view.column_stride, cloud.constants(), constants, no_cube, out);
  }
  Eigen::Vector3d p;
  for (std::size_t row = first; row < end; ++row) {
    out[row - begin] = cloud.map(row, p) == 0 ? cube_of(p.x(), p.y(), p.z()) : no_cube;
  }
  return 0;
}

/// Cube indices of rows [first_row, end_row) into `cubes`, in blocks that stay in L1:
/// `mark(begin, end)` reads each block's indices while they are there.
template <typename Cloud, typename Mark>
void quantize_rows_of(const Cloud& cloud, const CubeGrid& grid, bool all_used, std::uint32_t no_cube,
                      std::uint32_t* cubes, std::size_t first_row, std::size_t end_row, Mark&& mark) {
  constexpr std::size_t kBlock = 2048;
  // Plain float rows may be quantised in float arithmetic (see detail::float_estimate_margin).
  // Rows within its margin of a cube border are quantised again in doubles, one by one: on lattice
  // data (coordinates on a 1 cm grid put 2 % of the rows of each axis exactly on the borders of
  // 0.5 m cubes) that costs more than it saves, so a block with more than 1 % such rows hands the
  // rest of the call to the double kernel.
  float float_margin = detail::quantize_float_margin(grid.min_corner.x(), grid.min_corner.y(), grid.min_corner.z(),
                                                     grid.edge_m, grid.ixmax, grid.iymax, grid.izmax);
  for (std::size_t begin = first_row; begin < end_row; begin += kBlock) {
    const std::size_t end = std::min(end_row, begin + kBlock);
    const std::size_t undecided =
        quantize_block(cloud, grid, all_used, no_cube, float_margin, begin, end, cubes + begin);
    if (undecided * 100 > end - begin) float_margin = 0.0F;
    mark(begin, end);
  }
}

/// quantize_rows_of over all rows.
template <typename Cloud, typename Mark>
void quantize_and_mark(const Cloud& cloud, const CubeGrid& grid, bool all_used, std::uint32_t no_cube,
                       std::uint32_t* cubes, Mark&& mark) {
  quantize_rows_of(cloud, grid, all_used, no_cube, cubes, 0, cloud.size(), std::forward<Mark>(mark));
}

/// The rows [begin, end) of part `part` of `parts`, in whole blocks of `block` rows.
std::pair<std::size_t, std::size_t> part_rows(std::size_t rows, std::size_t block, int part, int parts) {
  const std::size_t blocks = (rows + block - 1) / block;
  const auto k = static_cast<std::size_t>(part);
  const auto n = static_cast<std::size_t>(parts);
  return {std::min(rows, blocks * k / n * block), std::min(rows, blocks * (k + 1) / n * block)};
}

/// quantize_and_mark on `parts` threads: each quantises a run of whole blocks (each with its own
/// float/double kernel choice; both give eqs. 1-3's indices), then `mark(0, rows)` runs on the
/// calling thread. With one part, quantize_and_mark itself.
template <typename Cloud, typename Mark>
void quantize_then_mark(const Cloud& cloud, const CubeGrid& grid, bool all_used, std::uint32_t no_cube,
                        std::uint32_t* cubes, int parts, Mark&& mark) {
  if (parts <= 1) {
    quantize_and_mark(cloud, grid, all_used, no_cube, cubes, std::forward<Mark>(mark));
    return;
  }
  detail::for_each_part(parts, [&](int part) {
    const auto [begin, end] = part_rows(cloud.size(), 2048, part, parts);
    if (begin >= end) return;
    quantize_rows_of(cloud, grid, all_used, no_cube, cubes, begin, end, [](std::size_t, std::size_t) {});
  });
  mark(std::size_t{0}, cloud.size());
}

/// Calls f(row) for every row of [begin, end), in eight interleaved streams an eighth of the range
/// apart. Consecutive rows of a scan often reach the same word of V, so a plain loop chains each
/// read-modify-write of it to the previous one's store; rows far apart reach different words and
/// the eight chains overlap (marking V on a KITTI scan took 0.12 ms in order and 0.07 ms so, see
/// docs/benchmarks.md). Every row is visited once; only the order changes, which |= ignores.
template <typename F>
inline __attribute__((always_inline)) void for_each_interleaved(std::size_t begin, std::size_t end, F&& f) {
  const std::size_t stride = (end - begin) / 8;
  for (std::size_t row = begin; row < begin + stride; ++row) {
    f(row);
    f(row + stride);
    f(row + 2 * stride);
    f(row + 3 * stride);
    f(row + 4 * stride);
    f(row + 5 * stride);
    f(row + 6 * stride);
    f(row + 7 * stride);
  }
  for (std::size_t row = begin + 8 * stride; row < end; ++row) f(row);
}

/// The dense path's buffers, one set per thread (shared by every cloud type): in a long-running
/// process a fresh multi-megabyte buffer costs a page fault per 4 kB on every call. V, its summary
/// and M keep their values between calls (all clear, all clear, all -1) and each call restores
/// only what it touched, O(|L|), so a large sparse grid costs no clearing. A call that throws
/// drops them all; buffers over kKeepBytes are dropped after the call.
struct DenseScratch {
  std::vector<std::uint64_t> occupancy;  // V, plus a word for rows that take no part
  std::vector<std::uint64_t> summary;    // a bit per word of V: the word is non-zero
  std::vector<std::int32_t> ground;      // M; layers fit 32 bits on the dense path
  std::vector<std::uint32_t> cubes;      // I of every point
  std::vector<std::uint32_t> words;      // the non-zero words of V, in order
  std::vector<std::uint8_t> flags;       // V as a byte per cube (and R's marks), for small grids
  std::vector<std::uint8_t> removed;     // a byte per cube of R, for the bit vector's mask pass
  std::vector<std::int64_t> collapsed;   // R while it grows (the result gets an exact copy)

  static constexpr std::size_t kKeepBytes = std::size_t{64} << 20;

  std::size_t bytes() const {
    return occupancy.capacity() * 8 + summary.capacity() * 8 + ground.capacity() * 4 + cubes.capacity() * 4 +
           words.capacity() * 4 + flags.capacity() + removed.capacity() + collapsed.capacity() * 8;
  }
};

DenseScratch& dense_scratch() {
  thread_local DenseScratch scratch;
  return scratch;
}

/// Drops the scratch unless dismissed: the invariants of V, the summary and M may be broken.
struct ScratchGuard {
  DenseScratch& scratch;
  bool dismissed = false;
  ~ScratchGuard() {
    if (!dismissed || scratch.bytes() > DenseScratch::kKeepBytes) scratch = DenseScratch{};
  }
};

/// The number of overhang points of a mask of 0/1 bytes, eight at a time: the top byte of a word
/// times 0x0101010101010101 is the sum of its bytes (summed in the loop that writes the mask, it
/// would be an add per row).
std::size_t count_overhang(const std::uint8_t* overhang, std::size_t rows) {
  std::size_t count = 0;
  std::size_t row = 0;
  for (; row + 8 <= rows; row += 8) {
    std::uint64_t bytes;
    std::memcpy(&bytes, overhang + row, 8);
    count += static_cast<std::size_t>((bytes * 0x0101010101010101ULL) >> 56);
  }
  for (; row < rows; ++row) count += overhang[row];
  return count;
}

/// The mask of rows [0, rows): overhang[row] = flag(row), on `parts` threads (whole blocks of
/// rows each), and the number of overhang rows.
template <typename Flag>
std::size_t write_mask(std::uint8_t* overhang, std::size_t rows, int parts, const Flag& flag) {
  std::vector<std::size_t> counted(static_cast<std::size_t>(std::max(parts, 1)), 0);
  detail::for_each_part(parts, [&](int part) {
    const auto [begin, end] = part_rows(rows, 2048, part, parts);
    // Local copies: a byte store may alias anything reached through a reference (the captured
    // pointer, the flag's), which the compiler would then reload on every row.
    std::uint8_t* const out = overhang;
    const Flag of = flag;
    std::size_t row = begin;
    for (; row + 4 <= end; row += 4) {  // unrolled by hand (GCC does not at -O3)
      out[row] = of(row);
      out[row + 1] = of(row + 1);
      out[row + 2] = of(row + 2);
      out[row + 3] = of(row + 3);
    }
    for (; row < end; ++row) out[row] = of(row);
    counted[static_cast<std::size_t>(part)] = count_overhang(out + begin, end - begin);
  });
  std::size_t total = 0;
  for (const std::size_t count : counted) total += count;
  return total;
}

/// Lines 5-15 of Algorithm 1 over the sorted L with M (scratch.ground, all -1 before and after):
/// R into result.removed_cubes.
void sweep_dense(const CubeGrid& grid, int sigma, DenseScratch& scratch, CollapseResult& result) {
  const std::vector<std::int64_t>& occupied = result.occupied_cubes;
  // R grows in scratch and is copied once at its final size: growing the result's own vector
  // would touch (and page-fault) about twice the memory.
  std::int32_t* const ground = scratch.ground.data();
  scratch.collapsed.clear();
  sweep_columns(
      occupied, grid.num_columns(), sigma,
      [ground](std::int64_t column) -> std::int32_t& { return ground[static_cast<std::size_t>(column)]; },
      scratch.collapsed);
  result.removed_cubes.assign(scratch.collapsed.begin(), scratch.collapsed.end());
  // M restored to -1: all of it when it has no more entries than L (a vectorised fill), else only
  // on the columns L touched.
  const auto num_columns = static_cast<std::size_t>(grid.num_columns());
  if (num_columns <= occupied.size()) {
    std::fill_n(ground, num_columns, -1);
  } else {
    for_each_column(occupied, grid.num_columns(), [ground](std::int64_t, std::int64_t column, std::int64_t) {
      ground[static_cast<std::size_t>(column)] = -1;
    });
  }
}

/// Whether the dense path keeps V as a byte per cube: on grids of no more cubes than twice the
/// points (so O(points) bytes) and at most 2^16 cubes (64 kB, about the L1 cache). There consecutive
/// points of an ordered scan often fall in one cube, and setting its bit is a load, an OR and a
/// store that wait for the previous row's store to the same word; a byte is one store. On larger
/// grids the bytes miss L1 where the bits (8x smaller) do not (the synthetic 500k cloud's 0.2 M
/// cubes: slower with bytes).
bool use_byte_occupancy(const CubeGrid& grid, std::size_t rows) {
  constexpr std::int64_t kMaxByteCubes = std::int64_t{1} << 16;
  return grid.num_cubes() <= kMaxByteCubes && static_cast<std::size_t>(grid.num_cubes()) <= 2 * rows;
}

/// Dense path with V as a byte per cube (see use_byte_occupancy): marking a cube is one store.
/// The same byte then marks R (2) for the mask pass. scratch.flags is all zero before and after.
template <typename Cloud>
void collapse_dense_bytes(const Cloud& cloud, const CollapseParams& params, int parts, CollapseResult& result) {
  const CubeGrid& grid = result.grid;
  const bool all_used = result.num_used == cloud.size();
  const std::size_t rows = cloud.size();
  const auto num_cubes = static_cast<std::size_t>(grid.num_cubes());
  // Rows that take no part get no_cube, a byte past the last cube.
  const auto no_cube = static_cast<std::uint32_t>(num_cubes);
  const auto num_columns = static_cast<std::size_t>(grid.num_columns());

  DenseScratch& scratch = dense_scratch();
  ScratchGuard guard{scratch};
  // V's bytes, read eight at a time below: rounded up to a whole word past no_cube.
  const std::size_t flag_words = num_cubes / 8 + 1;
  if (scratch.flags.size() < flag_words * 8) scratch.flags.resize(flag_words * 8, 0);
  if (scratch.ground.size() < num_columns) scratch.ground.resize(num_columns, -1);
  if (scratch.cubes.size() < rows) scratch.cubes.resize(rows);
  std::uint8_t* const flags = scratch.flags.data();
  std::uint32_t* const cubes = scratch.cubes.data();

  // Algorithm 1, lines 1-4: one O(N) pass sets V.
  quantize_then_mark(cloud, grid, all_used, no_cube, cubes, parts, [flags, cubes](std::size_t begin, std::size_t end) {
    // Unrolled by hand (GCC does not at -O3): four independent stores per iteration.
    std::size_t row = begin;
    for (; row + 4 <= end; row += 4) {
      flags[cubes[row]] = 1;
      flags[cubes[row + 1]] = 1;
      flags[cubes[row + 2]] = 1;
      flags[cubes[row + 3]] = 1;
    }
    for (; row < end; ++row) flags[cubes[row]] = 1;
  });
  // L sorted: V read in index order, eight cubes a word (no_cube's byte is left out).
  std::vector<std::int64_t>& occupied = result.occupied_cubes;
  // Bytes are 0 or 1: the top byte of a word times 0x0101010101010101 is the sum of its bytes.
  std::size_t num_occupied = 0;
  for (std::size_t w = 0; w < flag_words; ++w) {
    std::uint64_t bits;
    std::memcpy(&bits, flags + w * 8, 8);
    num_occupied += static_cast<std::size_t>((bits * 0x0101010101010101ULL) >> 56);
  }
  occupied.reserve(num_occupied - flags[no_cube]);
  for (std::size_t w = 0; w < flag_words; ++w) {
    std::uint64_t bits;
    std::memcpy(&bits, flags + w * 8, 8);
    for (; bits != 0; bits &= bits - 1) {
      const std::size_t cube = w * 8 + static_cast<std::size_t>(__builtin_ctzll(bits)) / 8;
      if (cube < num_cubes) occupied.push_back(static_cast<std::int64_t>(cube));
    }
  }
  sweep_dense(grid, params.sigma, scratch, result);

  // Points in R's cubes are overhang: R's bytes become 2 (no_cube's stays 1).
  for (const std::int64_t cube : result.removed_cubes) flags[static_cast<std::size_t>(cube)] = 2;
  const std::uint8_t* const marks = flags;
  result.num_overhang = write_mask(result.overhang.data(), rows, parts, [marks, cubes](std::size_t row) {
    return static_cast<std::uint8_t>(marks[cubes[row]] >> 1);
  });

  // V restored to all zero.
  for (const std::int64_t cube : occupied) flags[static_cast<std::size_t>(cube)] = 0;
  flags[no_cube] = 0;
  guard.dismissed = true;
}

/// The number of set bits (without the POPCNT instruction, which the baseline x86-64 target
/// lacks: __builtin_popcountll would call libgcc).
inline std::size_t bit_count(std::uint64_t x) {
  x -= (x >> 1) & 0x5555555555555555ULL;
  x = (x & 0x3333333333333333ULL) + ((x >> 2) & 0x3333333333333333ULL);
  x = (x + (x >> 4)) & 0x0F0F0F0F0F0F0F0FULL;
  return static_cast<std::size_t>((x * 0x0101010101010101ULL) >> 56);
}

/// The indices of the non-zero words among words[0, count), ascending, into `nonzero` (which
/// ends up with that many entries); `most` bounds their number. Branch-free: every word's index
/// is stored, and the end moves past it when the word is non-zero (whether a word of V is zero
/// is close to random, so a branch on it would often be mispredicted).
__attribute__((noinline)) void find_nonzero_words(const std::uint64_t* words, std::size_t count, std::size_t most,
                                                  std::vector<std::uint32_t>& nonzero) {
  nonzero.resize(most + 1);  // + 1: the store after the last non-zero word
  std::uint32_t* __restrict out = nonzero.data();
  std::size_t end = 0;
  for (std::size_t word = 0; word < count; ++word) {
    out[end] = static_cast<std::uint32_t>(word);
    end += words[word] != 0 ? 1 : 0;
  }
  nonzero.resize(end);
}

/// The set bits of the listed words of V, as cube indices in ascending order: L sorted.
__attribute__((noinline)) void list_set_bits(const std::uint64_t* occupancy, const std::vector<std::uint32_t>& nonzero,
                                             std::vector<std::int64_t>& occupied) {
  std::size_t total = 0;
  for (const std::uint32_t word : nonzero) total += bit_count(occupancy[word]);
  occupied.clear();
  occupied.reserve(total);  // not resize(): no zeros written first
  for (const std::uint32_t word : nonzero) {
    const auto base = static_cast<std::int64_t>(std::size_t{word} * 64);
    for (std::uint64_t bits = occupancy[word]; bits != 0; bits &= bits - 1) {
      occupied.push_back(base + __builtin_ctzll(bits));
    }
  }
}

/// Dense path: V is a bit vector over all cubes, M a vector over all columns.
template <typename Cloud>
void collapse_dense(const Cloud& cloud, const CollapseParams& params, int parts, CollapseResult& result) {
  const CubeGrid& grid = result.grid;
  const std::size_t rows = cloud.size();
  if (use_byte_occupancy(grid, rows)) {
    collapse_dense_bytes(cloud, params, parts, result);
    return;
  }
  const bool all_used = result.num_used == cloud.size();
  const std::size_t words = static_cast<std::size_t>((grid.num_cubes() + 63) / 64);
  const auto num_columns = static_cast<std::size_t>(grid.num_columns());
  // Rows that take no part get no_cube, the first bit of the extra word after V.
  const auto no_cube = static_cast<std::uint32_t>(words * 64);
  // A summary of V pays off when V has more words than the cloud has points (a sparse grid):
  // then L is read from the non-zero words only.
  const bool summarise = words > rows;
  const std::size_t summary_words = words / 64 + 1;

  DenseScratch& scratch = dense_scratch();
  ScratchGuard guard{scratch};
  if (scratch.occupancy.size() < words + 1) scratch.occupancy.resize(words + 1, 0);
  if (summarise && scratch.summary.size() < summary_words) scratch.summary.resize(summary_words, 0);
  if (scratch.ground.size() < num_columns) scratch.ground.resize(num_columns, -1);
  if (scratch.cubes.size() < rows) scratch.cubes.resize(rows);
  std::uint64_t* const occupancy = scratch.occupancy.data();
  std::uint64_t* const summary = scratch.summary.data();
  std::uint32_t* const cubes = scratch.cubes.data();

  // Algorithm 1, lines 1-4: one O(N) pass sets V.
  quantize_then_mark(cloud, grid, all_used, no_cube, cubes, parts, [&](std::size_t begin, std::size_t end) {
    if (summarise) {
      for_each_interleaved(begin, end, [occupancy, summary, cubes](std::size_t row) {
        const std::uint32_t cube = cubes[row];
        occupancy[cube >> 6] |= std::uint64_t{1} << (cube & 63);
        summary[cube >> 12] |= std::uint64_t{1} << ((cube >> 6) & 63);
      });
    } else {
      for_each_interleaved(begin, end, [occupancy, cubes](std::size_t row) {
        const std::uint32_t cube = cubes[row];
        occupancy[cube >> 6] |= std::uint64_t{1} << (cube & 63);
      });
    }
  });

  // L sorted: reading V in index order is a bucket sort of L, O(|V| / 64 + |L|) (or O(|V| / 4096
  // + |L|) through the summary).
  std::vector<std::uint32_t>& nonzero = scratch.words;
  if (summarise) {
    nonzero.clear();
    for (std::size_t s = 0; s < summary_words; ++s) {
      for (std::uint64_t bits = summary[s]; bits != 0; bits &= bits - 1) {
        const std::size_t word = s * 64 + static_cast<std::size_t>(__builtin_ctzll(bits));
        if (word >= words) continue;  // the word of rows that take no part
        nonzero.push_back(static_cast<std::uint32_t>(word));
      }
      summary[s] = 0;  // restored
    }
  } else {
    find_nonzero_words(occupancy, words, std::min(words, rows), nonzero);
  }
  list_set_bits(occupancy, nonzero, result.occupied_cubes);

  sweep_dense(grid, params.sigma, scratch, result);

  // Points in R's cubes are overhang. Plain local pointers: a byte store may alias anything, so
  // through the vectors the compiler would reload their data pointers on every row.
  std::uint8_t* const overhang = result.overhang.data();
  if (static_cast<std::size_t>(grid.num_cubes()) <= 2 * rows) {
    // A byte per cube for R (no more bytes than two per point): one load per point, no bit
    // arithmetic. no_cube lies past the last cube and is never removed.
    std::vector<std::uint8_t>& removed_map = scratch.removed;
    removed_map.assign(static_cast<std::size_t>(no_cube) + 1, 0);
    for (const std::int64_t cube : result.removed_cubes) removed_map[static_cast<std::size_t>(cube)] = 1;
    const std::uint8_t* const removed = removed_map.data();
    result.num_overhang =
        write_mask(overhang, rows, parts, [removed, cubes](std::size_t row) { return removed[cubes[row]]; });
  } else {
    // R's bits cleared in V: a point is overhang when its cube's bit is gone. The extra word is
    // all ones, so no_cube is never overhang.
    for (const std::int64_t cube : result.removed_cubes) {
      occupancy[static_cast<std::size_t>(cube >> 6)] &= ~(std::uint64_t{1} << (cube & 63));
    }
    occupancy[words] = ~std::uint64_t{0};
    const std::uint64_t* const remaining = occupancy;
    result.num_overhang = write_mask(overhang, rows, parts, [remaining, cubes](std::size_t row) {
      const std::uint32_t cube = cubes[row];
      return static_cast<std::uint8_t>(((remaining[cube >> 6] >> (cube & 63)) & 1U) ^ 1U);
    });
  }

  // V restored to all clear.
  for (const std::uint32_t word : nonzero) occupancy[word] = 0;
  occupancy[words] = 0;
  guard.dismissed = true;
}

/// An insert-only open-addressing hash set of cube indices that grows with the number of distinct
/// cubes (not points), so it stays cache-sized for typical scans. Slots are final once growth stops.
class CubeSet {
 public:
  CubeSet() { rehash(1024); }

  void insert(std::int64_t cube) {
    std::size_t slot = home(cube);
    while (keys_[slot] != cube) {
      if (keys_[slot] == kEmpty) {
        keys_[slot] = cube;
        if (2 * ++size_ > keys_.size()) rehash(2 * keys_.size());
        return;
      }
      slot = (slot + 1) & mask_;
    }
  }

  /// The slot of a cube that was inserted.
  std::size_t find(std::int64_t cube) const {
    std::size_t slot = home(cube);
    while (keys_[slot] != cube) slot = (slot + 1) & mask_;
    return slot;
  }

  std::size_t capacity() const { return keys_.size(); }

  /// The distinct cubes, in no particular order: the unsorted list L.
  std::vector<std::int64_t> keys() const {
    std::vector<std::int64_t> out;
    out.reserve(size_);
    for (const std::int64_t key : keys_) {
      if (key != kEmpty) out.push_back(key);
    }
    return out;
  }

 private:
  static constexpr std::int64_t kEmpty = -1;

  std::size_t home(std::int64_t cube) const {  // Fibonacci hashing, top bits
    return static_cast<std::size_t>((static_cast<std::uint64_t>(cube) * 0x9E3779B97F4A7C15ULL) >> shift_);
  }

  void rehash(std::size_t capacity) {
    std::vector<std::int64_t> old = std::move(keys_);
    keys_.assign(capacity, kEmpty);
    mask_ = capacity - 1;
    shift_ = 64 - static_cast<int>(__builtin_ctzll(capacity));
    size_ = 0;
    for (const std::int64_t key : old) {
      if (key != kEmpty) insert(key);
    }
  }

  std::vector<std::int64_t> keys_;
  std::size_t mask_ = 0;
  int shift_ = 64;
  std::size_t size_ = 0;
};

/// Sparse path: V is a hash set over the occupied cubes only and M a hash map over the columns
/// that hold points, so memory is O(N) whatever the extent.
template <typename Cloud>
void collapse_sparse(const Cloud& cloud, const CollapseParams& params, CollapseResult& result) {
  const CubeGrid& grid = result.grid;
  const GridQuantizer quantizer(grid);
  CubeSet occupancy;  // V
  std::vector<std::int64_t> cube_of_point(cloud.size(), -1);
  Eigen::Vector3d p;
  std::int64_t previous = -1;
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    if (cloud.map(row, p) != 0) continue;
    const std::int64_t cube = quantizer(p);
    cube_of_point[row] = cube;
    if (cube != previous) occupancy.insert(cube);  // scans are ordered: neighbours share cubes
    previous = cube;
  }
  std::vector<std::int64_t>& occupied = result.occupied_cubes;
  occupied = occupancy.keys();  // unsorted L
  std::sort(occupied.begin(), occupied.end());

  std::unordered_map<std::int64_t, std::int64_t> ground;  // M, only for columns that hold points
  ground.reserve(occupied.size());
  sweep_columns(
      occupied, grid.num_columns(), params.sigma,
      [&ground](std::int64_t column) -> std::int64_t& { return ground.try_emplace(column, -1).first->second; },
      result.removed_cubes);

  std::vector<std::uint8_t> removed_slot(occupancy.capacity(), 0);
  for (const std::int64_t cube : result.removed_cubes) removed_slot[occupancy.find(cube)] = 1;
  std::size_t count = 0;
  std::uint8_t* const overhang = result.overhang.data();
  for (std::size_t row = 0; row < cloud.size(); ++row) {
    const std::int64_t cube = cube_of_point[row];
    const std::uint8_t removed = cube < 0 ? 0 : removed_slot[occupancy.find(cube)];
    overhang[row] = removed;
    count += removed;
  }
  result.num_overhang = count;
}

/// detail::measure_extent, on `parts` threads for a plain cloud (each measures a run of rows; the
/// bounding box does not depend on the order).
template <typename Cloud>
detail::CloudExtent measure_extent_on(const Cloud& cloud, bool drop_non_finite, int parts) {
  if constexpr (!Cloud::kPlain) {
    return detail::measure_extent(cloud, drop_non_finite);
  } else {
    if (parts <= 1) return detail::measure_extent(cloud, drop_non_finite);
    using Scalar = std::remove_cv_t<std::remove_pointer_t<decltype(cloud.view().data)>>;
    const PointsView<Scalar>& view = cloud.view();
    std::vector<detail::CloudExtent> extents(static_cast<std::size_t>(parts));
    detail::for_each_part(parts, [&](int part) {
      const auto [begin, end] = part_rows(view.size, 2048, part, parts);
      PointsView<Scalar> rows = view;
      rows.data = view.data + static_cast<std::ptrdiff_t>(begin) * view.row_stride;
      rows.size = end - begin;
      const Cloud piece(rows, Eigen::Matrix4d::Identity(), std::nullopt);
      extents[static_cast<std::size_t>(part)] = detail::measure_extent(piece, true);
      extents[static_cast<std::size_t>(part)].first_non_finite_row += begin;
    });
    detail::CloudExtent extent;
    for (const detail::CloudExtent& piece : extents) {
      extent.min = extent.min.cwiseMin(piece.min);
      extent.max = extent.max.cwiseMax(piece.max);
      extent.num_used += piece.num_used;
      if (piece.num_non_finite > 0 && extent.num_non_finite == 0) {
        extent.first_non_finite_row = piece.first_non_finite_row;  // parts are in row order
      }
      extent.num_non_finite += piece.num_non_finite;
      extent.num_cropped += piece.num_cropped;
    }
    if (extent.num_non_finite > 0 && !drop_non_finite) {
      detail::throw_non_finite_rows(extent.num_non_finite, cloud.size(), extent.first_non_finite_row);
    }
    return extent;
  }
}

template <typename Scalar>
CollapseResult collapse_impl(const PointsView<Scalar>& points, const CollapseParams& params) {
  detail::check_collapse_params(params);
  if (points.size > 0 && points.data == nullptr) {
    throw std::invalid_argument("points view has no data but claims " + std::to_string(points.size) + " rows");
  }
  CollapseResult result;
  result.num_points = points.size;
  result.overhang.assign(points.size, 0);
  result.grid.edge_m = params.edge_m;
  result.storage_used = params.storage == CubeStorage::kSparse ? CubeStorage::kSparse : CubeStorage::kDense;

  // A transform or a crop is applied on the fly: with AVX2 the extent and quantisation kernels
  // level four rows at a time (the arithmetic of LeveledCloud::map), so each pass reads the input
  // rows once and nothing is written per row but the cube index.
  constexpr std::size_t kRowsPerThread = 32768;
  const int parts = detail::thread_count(params.num_threads, points.size, kRowsPerThread);
  detail::visit_leveled(points, params.transform, params.crop, [&](const auto& cloud) {
    const detail::CloudExtent extent = measure_extent_on(cloud, params.drop_non_finite, parts);
    result.num_used = extent.num_used;
    result.num_cropped = extent.num_cropped;
    result.num_dropped_non_finite = extent.num_non_finite;
    if (extent.num_used == 0) return;  // empty grid, nothing occupied, nothing removed
    result.grid = detail::make_grid(extent, params.edge_m);
    result.storage_used = choose_storage(result.grid, params, extent.num_used);
    if (result.storage_used == CubeStorage::kDense) {
      collapse_dense(cloud, params, parts, result);
    } else {
      collapse_sparse(cloud, params, result);
    }
  });
  return result;
}

}  // namespace

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

CollapseResult collapse_overhangs(const PointsView<float>& points, const CollapseParams& params) {
  return collapse_impl(points, params);
}

CollapseResult collapse_overhangs(const PointsView<double>& points, const CollapseParams& params) {
  return collapse_impl(points, params);
}

CollapseResult collapse_overhangs(const std::vector<Eigen::Vector3d>& points, const CollapseParams& params) {
  return collapse_impl(PointsView<double>(points), params);
}

}  // namespace terracube
