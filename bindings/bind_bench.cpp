// Private: the memory floor of overhang removal, for bench/bench_collapse.py only (not part of the
// API). Bare C++ loops time the memory traffic that any exact single-threaded implementation of
// Algorithm 1 must do on a cloud, so that the benchmark can print, in the same process as the
// numpy baseline, the largest speed-up over numpy that the hardware allows.
#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <limits>
#include <vector>

#include "points.hpp"

namespace terracube::python {

namespace {

/// The fastest of `repeat` runs of f, in milliseconds (the floor is a lower bound: the minimum).
template <typename F>
double fastest_ms(int repeat, F&& f) {
  double best = std::numeric_limits<double>::infinity();
  for (int run = 0; run < repeat; ++run) {
    const auto start = std::chrono::steady_clock::now();
    f();
    const std::chrono::duration<double, std::milli> elapsed = std::chrono::steady_clock::now() - start;
    best = std::min(best, elapsed.count());
  }
  return best;
}

/// Reads every byte once (a bitwise OR of them), 32 bytes per load and eight loads in flight.
__attribute__((target("avx2"))) std::uint64_t or_bytes_avx2(const unsigned char* data, std::size_t bytes) {
  using Vector = long long __attribute__((vector_size(32), aligned(1)));
  Vector acc[8] = {};
  std::size_t at = 0;
  for (; at + 256 <= bytes; at += 256) {
    for (int k = 0; k < 8; ++k) acc[k] |= *reinterpret_cast<const Vector*>(data + at + 32 * k);
  }
  std::uint64_t result = 0;
  for (int k = 0; k < 8; ++k) {
    for (int lane = 0; lane < 4; ++lane) result |= static_cast<std::uint64_t>(acc[k][lane]);
  }
  for (; at < bytes; ++at) result |= data[at];
  return result;
}

std::uint64_t or_bytes(const unsigned char* data, std::size_t bytes) {
  if (__builtin_cpu_supports("avx2")) return or_bytes_avx2(data, bytes);
  std::uint64_t acc[8] = {};
  std::size_t at = 0;
  for (; at + 64 <= bytes; at += 64) {
    for (int k = 0; k < 8; ++k) {
      std::uint64_t word;
      std::memcpy(&word, data + at + 8 * k, 8);
      acc[k] |= word;
    }
  }
  std::uint64_t result = 0;
  for (const std::uint64_t word : acc) result |= word;
  for (; at < bytes; ++at) result |= data[at];
  return result;
}

/// Reads the first `used` bytes (x, y, z) of `rows` rows `stride` bytes apart, where rows lie too
/// far apart for every byte between them to be read (a strided subset of a cloud).
std::uint64_t or_rows(const unsigned char* data, std::size_t rows, std::size_t stride, std::size_t used) {
  std::uint64_t result = 0;
  for (std::size_t row = 0; row < rows; ++row) {
    const unsigned char* p = data + row * stride;
    std::size_t at = 0;
    for (; at + 8 <= used; at += 8) {
      std::uint64_t word;
      std::memcpy(&word, p + at, 8);
      result |= word;
    }
    if (at < used) {  // the last four bytes of a float row
      std::uint32_t word;
      std::memcpy(&word, p + used - 4, 4);
      result |= word;
    }
  }
  return result;
}

}  // namespace

void bind_bench(py::module_& m) {
  m.def(
      "_memory_floor",
      [](const py::array& points,
         const py::array_t<std::uint32_t, py::array::c_style | py::array::forcecast>& entry_of_point,
         std::size_t num_entries, int repeat) {
        if (repeat < 1) throw py::value_error("repeat must be at least 1");
        const std::size_t rows = static_cast<std::size_t>(entry_of_point.size());
        if (entry_of_point.ndim() != 1) throw py::value_error("entry_of_point must be one-dimensional");
        const std::uint32_t* entry = entry_of_point.data();
        for (std::size_t row = 0; row < rows; ++row) {
          if (entry[row] >= num_entries) throw py::value_error("entry_of_point holds an entry past num_entries");
        }
        // The rows as they lie in memory: every byte from the first row's x to the last row's z
        // while rows are at most 32 bytes apart (x y z, x y z i: their cache lines hold nothing
        // else), else each row's x, y and z alone.
        const unsigned char* first = nullptr;
        std::size_t bytes = 0, row_bytes = 0, used = 0;
        with_points(points, "points", [&](const auto& view) {
          using Scalar = std::remove_cv_t<std::remove_pointer_t<decltype(view.data)>>;
          if (view.size != rows) throw py::value_error("points and entry_of_point differ in length");
          if (view.column_stride != 1 || view.row_stride < 3) {
            throw py::value_error("points must have adjacent x, y, z in rows of at least three scalars");
          }
          first = reinterpret_cast<const unsigned char*>(view.data);
          row_bytes = static_cast<std::size_t>(view.row_stride) * sizeof(Scalar);
          used = 3 * sizeof(Scalar);
          bytes = rows == 0 ? 0 : (rows - 1) * row_bytes + used;
          if (row_bytes > 32) bytes = rows * used;
          return 0;
        });
        std::vector<std::uint8_t> table(num_entries + 1, 0), mask(rows, 0);
        volatile std::uint64_t sink = 0;
        py::dict out;
        {
          py::gil_scoped_release release;
          // Eqs. (1)-(3) need the bounding box before any cube index: a first pass that reads the
          // rows, then a second one that reads them again.
          const double read = fastest_ms(
              repeat, [&] { sink = row_bytes > 32 ? or_rows(first, rows, row_bytes, used) : or_bytes(first, bytes); });
          // Line 3 of Algorithm 1: the point's cube marked occupied, a store per point (into a
          // byte per occupied cube, the smallest table there is).
          const double store = fastest_ms(repeat, [&] {
            std::uint8_t* const t = table.data();
            std::size_t row = 0;
            for (; row + 4 <= rows; row += 4) {
              t[entry[row]] = 1;
              t[entry[row + 1]] = 1;
              t[entry[row + 2]] = 1;
              t[entry[row + 3]] = 1;
            }
            for (; row < rows; ++row) t[entry[row]] = 1;
            sink = t[0];
          });
          // The mask: once R is known, a load of the point's cube per point and a byte written.
          const double load = fastest_ms(repeat, [&] {
            const std::uint8_t* const t = table.data();
            std::uint8_t* const out_mask = mask.data();
            std::size_t row = 0;
            for (; row + 4 <= rows; row += 4) {
              out_mask[row] = t[entry[row]];
              out_mask[row + 1] = t[entry[row + 1]];
              out_mask[row + 2] = t[entry[row + 2]];
              out_mask[row + 3] = t[entry[row + 3]];
            }
            for (; row < rows; ++row) out_mask[row] = t[entry[row]];
            sink = out_mask[rows / 2];
          });
          py::gil_scoped_acquire acquire;
          out["read_ms"] = read;
          out["store_ms"] = store;
          out["load_ms"] = load;
          out["bytes"] = bytes;
        }
        return out;
      },
      py::arg("points"), py::arg("entry_of_point"), py::arg("num_entries"), py::arg("repeat") = 15,
      "Private, for bench/bench_collapse.py: the fastest of `repeat` runs of three bare loops over the "
      "cloud (read its rows; a byte store per point at entry_of_point; a byte load per point there plus "
      "a mask byte written), in ms.");
}

}  // namespace terracube::python
