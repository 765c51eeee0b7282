// Private: the threads of the calls that take a num_threads parameter, on oneTBB. Not installed.
//
// A call cuts its work into a FIXED number of parts that depends on the amount of work only
// (fixed_parts), never on the number of threads; each part writes its own output, and the caller
// merges the parts in part order. So the result is the same, bit for bit, on any number of threads.
//
// num_threads = 1 (the default everywhere) runs every part on the calling thread, in order, and
// never touches TBB. Otherwise each call makes its own tbb::task_arena of that many slots (0: TBB's
// default, one per processor the process may use) and runs the parts in it: no global state is
// set, and nothing is left running by us when the call returns. TBB itself keeps its worker
// threads for the life of the process (created on first use); once an arena has no work they
// leave it and, after a short bounded spin inside TBB, block in the kernel until the next call.
#pragma once

#include <oneapi/tbb/blocked_range.h>
#include <oneapi/tbb/parallel_for.h>
#include <oneapi/tbb/task_arena.h>

#include <algorithm>
#include <cstddef>
#include <stdexcept>
#include <string>

namespace terracube::detail {

/// Throws std::invalid_argument unless `num_threads` >= 0 (0 = one per processor). `what` names
/// the parameter's owner in the message.
inline void check_num_threads(int num_threads, const std::string& what) {
  if (num_threads < 0) {
    throw std::invalid_argument(what + ".num_threads must be >= 0 (0 = one per processor), got " +
                                std::to_string(num_threads));
  }
}

/// The number of parts of `work` units in parts of at least `min_work` units, at most `max_parts`:
/// a function of the work alone, so that results never depend on the number of threads.
inline int fixed_parts(std::size_t work, std::size_t min_work, int max_parts = 64) {
  const std::size_t parts = work / (min_work > 0 ? min_work : 1);
  return parts < 1 ? 1 : (parts > static_cast<std::size_t>(max_parts) ? max_parts : static_cast<int>(parts));
}

/// The half-open range [begin, end) of part `part` of `parts` over `count` items.
struct PartRange {
  std::size_t begin, end;
};
inline PartRange part_range(std::size_t count, int part, int parts) {
  const auto p = static_cast<std::size_t>(part);
  const auto n = static_cast<std::size_t>(parts);
  return {count * p / n, count * (p + 1) / n};
}

/// Runs body(part) once for every part in [0, parts) on up to `num_threads` threads (see above).
/// Parts must write disjoint outputs. An exception thrown by a part propagates to the caller.
template <typename Body>
void for_each_part(int num_threads, int parts, const Body& body) {
  if (num_threads == 1 || parts <= 1) {
    for (int part = 0; part < parts; ++part) body(part);
    return;
  }
  // No more slots than parts: an arena of a billion slots (a mistyped num_threads) crashed TBB.
  tbb::task_arena arena(num_threads == 0 ? tbb::task_arena::automatic : std::min(num_threads, parts));
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<int>(0, parts, 1), [&](const tbb::blocked_range<int>& range) {
      for (int part = range.begin(); part < range.end(); ++part) body(part);
    });
  });
}

}  // namespace terracube::detail
