#include "threads.hpp"

#include <omp.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <stdexcept>

namespace terracube::detail {

void check_num_threads(int num_threads, const std::string& what) {
  if (num_threads < 0) {
    throw std::invalid_argument(what + ".num_threads must be >= 0 (0 = one per processor), got " +
                                std::to_string(num_threads));
  }
}

namespace {
std::atomic<int> team_high_water{0};
/// The process that started OpenMP's thread pool (0: none yet). A fork() copies it into the
/// child, where getpid() differs: the child must not use the pool (GCC's libgomp would hang).
std::atomic<pid_t> pool_process{0};
}  // namespace

void note_pool_start() {
  pid_t none = 0;
  pool_process.compare_exchange_strong(none, getpid(), std::memory_order_relaxed);
}

void note_team() {
  const int threads = omp_get_num_threads();
  int seen = team_high_water.load(std::memory_order_relaxed);
  while (threads > seen && !team_high_water.compare_exchange_weak(seen, threads, std::memory_order_relaxed)) {
  }
}

int largest_team(bool reset) {
  return reset ? team_high_water.exchange(0, std::memory_order_relaxed)
               : team_high_water.load(std::memory_order_relaxed);
}

int thread_count(int num_threads, std::size_t work, std::size_t min_work) {
  const pid_t pool = pool_process.load(std::memory_order_relaxed);
  if (pool != 0 && pool != getpid()) return 1;  // a forked child of a process that used the pool
  const int wanted = num_threads > 0 ? num_threads : omp_get_num_procs();
  const std::size_t useful = std::max<std::size_t>(1, work / std::max<std::size_t>(1, min_work));
  return static_cast<int>(std::max<std::size_t>(1, std::min<std::size_t>(static_cast<std::size_t>(wanted), useful)));
}

}  // namespace terracube::detail
