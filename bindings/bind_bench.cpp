// Private: the memory floor of overhang removal, for bench/bench_collapse.py only (not part of the
// API). Bare C++ loops time the memory traffic that any exact implementation of Algorithm 1 must
// do on a cloud, on one thread or split over several, so that the benchmark can print, in the same
// process as the numpy baseline, the largest speed-up over numpy that the hardware allows.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <limits>
#include <thread>
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

/// The fastest of `repeat` runs of f(part) on `parts` threads at once, in milliseconds. The threads
/// start together (a spin barrier) and each times its own part; a run takes as long as its slowest
/// part. Waking the threads and joining them is not timed: the floor leaves out what threads cost.
template <typename F>
double fastest_parallel_ms(int repeat, int parts, F&& f) {
  if (parts == 1) return fastest_ms(repeat, [&] { f(0); });
  std::vector<double> elapsed(static_cast<std::size_t>(parts) * static_cast<std::size_t>(repeat), 0.0);
  std::atomic<int> arrived{0};
  const auto worker = [&](int part) {
    for (int run = 0; run < repeat; ++run) {
      // Barrier `run`: wait until every part has arrived (parts * (run + 1) arrivals in all).
      arrived.fetch_add(1);
      while (arrived.load() < parts * (run + 1)) {
      }
      const auto start = std::chrono::steady_clock::now();
      f(part);
      const std::chrono::duration<double, std::milli> took = std::chrono::steady_clock::now() - start;
      elapsed[static_cast<std::size_t>(run) * static_cast<std::size_t>(parts) + static_cast<std::size_t>(part)] =
          took.count();
    }
  };
  std::vector<std::thread> threads;
  for (int part = 1; part < parts; ++part) threads.emplace_back(worker, part);
  worker(0);
  for (std::thread& thread : threads) thread.join();
  double best = std::numeric_limits<double>::infinity();
  for (int run = 0; run < repeat; ++run) {
    const double* first = elapsed.data() + static_cast<std::size_t>(run) * static_cast<std::size_t>(parts);
    best = std::min(best, *std::max_element(first, first + parts));
  }
  return best;
}

/// [begin, end) of part `part` of `parts` equal parts of `count` items.
std::pair<std::size_t, std::size_t> part_range(std::size_t count, int part, int parts) {
  const auto p = static_cast<std::size_t>(part), n = static_cast<std::size_t>(parts);
  return {count * p / n, count * (p + 1) / n};
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
         std::size_t num_entries, int repeat, int threads) {
        if (repeat < 1) throw py::value_error("repeat must be at least 1");
        if (threads < 1 || threads > 256) throw py::value_error("threads must be between 1 and 256");
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
        std::vector<std::vector<std::uint8_t>> tables(static_cast<std::size_t>(threads),
                                                      std::vector<std::uint8_t>(num_entries + 1, 0));
        std::vector<std::uint8_t> mask(rows, 0);
        std::vector<std::uint64_t> sinks(static_cast<std::size_t>(threads) * 8, 0);  // a cache line per part
        volatile std::uint64_t sink = 0;
        py::dict out;
        {
          py::gil_scoped_release release;
          // [CBC] eqs. (2)-(6) need the bounding box before any cube index: a first pass that reads the
          // rows, then a second one that reads them again.
          const double read = fastest_parallel_ms(repeat, threads, [&](int part) {
            if (row_bytes > 32) {
              const auto [begin, end] = part_range(rows, part, threads);
              sinks[8 * part] = or_rows(first + begin * row_bytes, end - begin, row_bytes, used);
            } else {
              const auto [begin, end] = part_range(bytes, part, threads);
              sinks[8 * part] = or_bytes(first + begin, end - begin);
            }
          });
          // Line 3 of [CBC] Algorithm 1: the point's cube marked occupied, a store per point (into a
          // byte per occupied cube, the smallest table there is; a table per thread, and merging
          // them is not timed).
          const double store = fastest_parallel_ms(repeat, threads, [&](int part) {
            std::uint8_t* const t = tables[static_cast<std::size_t>(part)].data();
            const auto [begin, end] = part_range(rows, part, threads);
            std::size_t row = begin;
            for (; row + 4 <= end; row += 4) {
              t[entry[row]] = 1;
              t[entry[row + 1]] = 1;
              t[entry[row + 2]] = 1;
              t[entry[row + 3]] = 1;
            }
            for (; row < end; ++row) t[entry[row]] = 1;
            sinks[8 * part] = t[0];
          });
          // The mask: once R is known, a load of the point's cube per point and a byte written.
          const double load = fastest_parallel_ms(repeat, threads, [&](int part) {
            const std::uint8_t* const t = tables[0].data();
            std::uint8_t* const out_mask = mask.data();
            const auto [begin, end] = part_range(rows, part, threads);
            std::size_t row = begin;
            for (; row + 4 <= end; row += 4) {
              out_mask[row] = t[entry[row]];
              out_mask[row + 1] = t[entry[row + 1]];
              out_mask[row + 2] = t[entry[row + 2]];
              out_mask[row + 3] = t[entry[row + 3]];
            }
            for (; row < end; ++row) out_mask[row] = t[entry[row]];
            sinks[8 * part] = begin < end ? out_mask[begin] : 0;
          });
          for (const std::uint64_t value : sinks) sink = sink | value;
          py::gil_scoped_acquire acquire;
          out["read_ms"] = read;
          out["store_ms"] = store;
          out["load_ms"] = load;
          out["bytes"] = bytes;
        }
        return out;
      },
      py::arg("points"), py::arg("entry_of_point"), py::arg("num_entries"), py::arg("repeat") = 15,
      py::arg("threads") = 1,
      "Private, for bench/bench_collapse.py: the fastest of `repeat` runs of three bare loops over the "
      "cloud (read its rows; a byte store per point at entry_of_point; a byte load per point there plus "
      "a mask byte written), in ms, each split into `threads` equal parts run at once (a run as long "
      "as its slowest part).");
}

}  // namespace terracube::python
