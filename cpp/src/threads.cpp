#include "threads.hpp"

#include <unistd.h>

#if defined(__linux__)
#include <sched.h>
#endif
#include <time.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <stdexcept>
#include <thread>

namespace terracube::detail {

void check_num_threads(int num_threads, const std::string& what) {
  if (num_threads < 0) {
    throw std::invalid_argument(what + ".num_threads must be >= 0 (0 = one per processor), got " +
                                std::to_string(num_threads));
  }
}

int processor_count() {
#if defined(__linux__)
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof(set), &set) == 0) return std::max(1, CPU_COUNT(&set));
#endif
  return static_cast<int>(std::max(1U, std::thread::hardware_concurrency()));
}

namespace {

/// At most this many parts per call and pool threads per process (a larger num_threads gets this
/// many threads; the parts of a call are numbered in 16 bits of the ticket below).
constexpr int kMaxThreads = 256;
/// A pool thread that finds nothing to claim keeps looking this long before it sleeps: the
/// parallel steps of one call (and a map followed by its classes) are microseconds apart, and
/// waking a sleeping thread costs far more (tens of microseconds on a quiet machine; on the shared
/// VMs this project is measured on, a call that woke one took about 1 ms longer, and GCC's OpenMP
/// pool, which woke its threads at every parallel step, took 12 ms instead of 1.5 for a map and its
/// classes every 100 ms). Calls that come more often than this keep the threads awake, spinning on
/// a processor each in between (as OpenMP runtimes do); rarer ones never wake them (below).
constexpr std::chrono::milliseconds kSpin{20};
/// The spin of pool threads beyond one per processor but one (a num_threads above the processor
/// count): spinning there would take the processors from the threads that have work.
constexpr std::chrono::microseconds kOversubscribedSpin{50};
/// Sleeping threads are woken (or the first ones started) only when calls have kept coming, each
/// within kSpin of the one before, for kSpin or longer (a workload that will keep them busy; a
/// robot's few calls per scan every 100 ms never wake them), when the calling thread kept its
/// processor busy for at least half the time since its last call, kSpin or more ago (see
/// busy_since_last_call), or for a call that has at least this many times the work of one part.
constexpr std::size_t kLargeWork = 32;

inline void pause() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#elif defined(__aarch64__)
  asm volatile("yield");
#endif
}

/// A ticket: generation (32 bits) | parts of the call (16 bits) | next unclaimed part (16 bits).
/// One word, so a claim (a compare-and-swap of it) sees the part count of its own call.
constexpr std::uint64_t kField = 0xFFFF;
constexpr std::uint64_t next_of(std::uint64_t ticket) { return ticket & kField; }
constexpr std::uint64_t parts_of(std::uint64_t ticket) { return (ticket >> 16) & kField; }
constexpr bool claimable(std::uint64_t ticket) { return next_of(ticket) < parts_of(ticket); }

struct Pool {
  const int processors = processor_count();   // at the pool's creation
  std::mutex mutex;                           // guards starting threads, and the sleep of pool threads
  std::condition_variable wake;               // pool threads sleep on it
  std::atomic<int> started{0};                // pool threads running (never stopped)
  std::atomic<int> sleeping{0};               // pool threads asleep, or about to sleep
  std::atomic<std::uint32_t> alarm{0};        // raised to wake sleeping threads without a job
  std::atomic<unsigned> wakeups{0};           // for tests
  std::atomic<std::int64_t> last_request{0};  // when thread_count last asked for several parts
  std::atomic<std::int64_t> burst_start{0};   // first of the requests since, each within kSpin of the last
  std::atomic<bool> busy{false};              // a call owns the job below
  // The job: written by its caller before it publishes the ticket, read after a claim.
  std::atomic<std::uint64_t> ticket{0};
  std::atomic<void (*)(const void*, int)> invoke{nullptr};
  std::atomic<const void*> context{nullptr};
  std::atomic<int> finished{0};  // parts of the job finished
  std::atomic<int> helpers{0};   // pool threads that ran a part of the job
  std::mutex error_mutex;
  std::exception_ptr error;  // the first exception a part of the job threw
};

/// The pool, never destroyed: its threads are detached and may still look at it at exit.
Pool& pool() {
  static Pool* const instance = new Pool;
  return *instance;
}

std::atomic<int> team_high_water{0};
std::atomic<bool> helpers_required{false};
/// The process that started the pool's threads (0: none yet). A fork() copies it into the child,
/// where getpid() differs and the threads do not exist.
std::atomic<pid_t> pool_process{0};

void note_team(int threads) {
  int seen = team_high_water.load(std::memory_order_relaxed);
  while (threads > seen && !team_high_water.compare_exchange_weak(seen, threads, std::memory_order_relaxed)) {
  }
}

void run_one(Pool& p, int part) {
  try {
    p.invoke.load(std::memory_order_relaxed)(p.context.load(std::memory_order_relaxed), part);
  } catch (...) {
    std::lock_guard<std::mutex> lock(p.error_mutex);
    if (!p.error) p.error = std::current_exception();
  }
  p.finished.fetch_add(1, std::memory_order_release);
}

/// Claims the job's next part and runs it: false when none is left (or there is no job). The
/// job's fields are those of the claimed ticket's call: that call waits for the part to finish.
bool claim_and_run(Pool& p, std::uint32_t* joined) {
  std::uint64_t ticket = p.ticket.load(std::memory_order_acquire);
  while (claimable(ticket)) {
    if (p.ticket.compare_exchange_weak(ticket, ticket + 1, std::memory_order_acq_rel, std::memory_order_acquire)) {
      const auto generation = static_cast<std::uint32_t>(ticket >> 32);
      if (joined != nullptr && *joined != generation) {
        *joined = generation;
        p.helpers.fetch_add(1, std::memory_order_relaxed);
      }
      run_one(p, static_cast<int>(next_of(ticket)));
      return true;
    }
  }
  return false;
}

void pool_thread(Pool& p, int index) {
  const std::chrono::microseconds spin = index + 1 < p.processors ? kSpin : kOversubscribedSpin;
  std::uint32_t joined = 0;
  auto idle_since = std::chrono::steady_clock::now();
  for (unsigned spins = 1;; ++spins) {
    if (claim_and_run(p, &joined)) {
      idle_since = std::chrono::steady_clock::now();
      continue;
    }
    pause();
    if (spins % 64 != 0 || std::chrono::steady_clock::now() - idle_since < spin) continue;
    std::unique_lock<std::mutex> lock(p.mutex);
    const std::uint32_t alarm = p.alarm.load();
    p.sleeping.fetch_add(1);  // before the check below: see run_parts
    p.wake.wait(lock, [&] { return claimable(p.ticket.load()) || p.alarm.load() != alarm; });
    p.sleeping.fetch_sub(1);
    p.wakeups.fetch_add(1, std::memory_order_relaxed);
    idle_since = std::chrono::steady_clock::now();
  }
}

/// Starts pool threads until there are `wanted` (fewer if the system refuses).
void start_threads(Pool& p, int wanted) {
  pid_t none = 0;
  pool_process.compare_exchange_strong(none, getpid(), std::memory_order_relaxed);
  std::lock_guard<std::mutex> lock(p.mutex);
  while (p.started.load(std::memory_order_relaxed) < wanted) {
    try {
      std::thread(pool_thread, std::ref(p), p.started.load(std::memory_order_relaxed)).detach();
    } catch (...) {  // std::system_error (no more threads), std::bad_alloc
      return;        // the calling thread runs what no pool thread claims
    }
    p.started.fetch_add(1, std::memory_order_relaxed);
  }
}

/// The calling thread's CPU time in nanoseconds (0 where it cannot be read).
std::int64_t thread_cpu_ns() {
#if defined(CLOCK_THREAD_CPUTIME_ID)
  timespec now{};
  if (clock_gettime(CLOCK_THREAD_CPUTIME_ID, &now) == 0) {
    return static_cast<std::int64_t>(now.tv_sec) * 1000000000 + now.tv_nsec;
  }
#endif
  return 0;
}

/// Whether the calling thread ran for at least half the time since its previous request for
/// several parts, made kSpin or more ago (`now` in steady-clock nanoseconds); records this request.
/// Such a caller (a program that computes between its calls, as a benchmark does between numpy and
/// terracube calls) gets the pool's sleeping threads woken: on the VMs this project is measured
/// on, a sleeping processor woke in about 90 us after its caller had been busy, against up to
/// milliseconds when the caller had been asleep too (a robot's loop, waiting for its next scan),
/// where a wake-up per call made a map every 100 ms slower than one thread. A caller's first
/// request, and one within kSpin of the previous (the burst rule's), never counts.
bool busy_since_last_call(std::int64_t now) {
  thread_local std::int64_t last_wall = 0;
  thread_local std::int64_t last_cpu = 0;
  const std::int64_t cpu = thread_cpu_ns();
  const std::int64_t wall = now - last_wall;
  const bool busy =
      last_wall != 0 && cpu != 0 && wall >= std::chrono::nanoseconds(kSpin).count() && 2 * (cpu - last_cpu) >= wall;
  last_wall = now;
  last_cpu = cpu;
  return busy;
}

void run_serially(int parts, void (*invoke)(const void*, int), const void* context) {
  std::exception_ptr error;
  for (int part = 0; part < parts; ++part) {
    try {
      invoke(context, part);
    } catch (...) {
      if (!error) error = std::current_exception();
    }
  }
  if (error) std::rethrow_exception(error);
}

}  // namespace

void require_helpers_in_tests(bool on) { helpers_required.store(on); }

PoolState pool_state() {
  const Pool& p = pool();
  return {p.started.load(), p.sleeping.load(), p.wakeups.load()};
}

int largest_team(bool reset) {
  return reset ? team_high_water.exchange(0, std::memory_order_relaxed)
               : team_high_water.load(std::memory_order_relaxed);
}

int thread_count(int num_threads, std::size_t work, std::size_t min_work) {
  const pid_t process = pool_process.load(std::memory_order_relaxed);
  if (process != 0 && process != getpid()) return 1;  // a forked child of a process that started the pool
  const int wanted = std::min(num_threads > 0 ? num_threads : processor_count(), kMaxThreads);
  const std::size_t useful = std::max<std::size_t>(1, work / std::max<std::size_t>(1, min_work));
  const int parts = static_cast<int>(std::min<std::size_t>(static_cast<std::size_t>(wanted), useful));
  if (parts <= 1 || helpers_required.load(std::memory_order_relaxed)) return std::max(parts, 1);
  // Only the pool threads that are awake now take part. Sleeping ones are woken for the calls
  // that follow when calls have kept coming for kSpin; for this one too (late ones join in) when
  // its caller was busy since its previous call, or this one is large.
  Pool& p = pool();
  const std::int64_t now =
      std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch()).count();
  const std::int64_t spin = std::chrono::nanoseconds(kSpin).count();
  const std::int64_t previous = p.last_request.exchange(now);
  if (now - previous >= spin) p.burst_start.store(now);  // a new burst (or the first request)
  const bool busy_burst = now - p.burst_start.load() >= spin;
  const bool busy_caller = busy_since_last_call(now);
  const int started = p.started.load(std::memory_order_relaxed);
  const int asleep = p.sleeping.load();
  if (busy_burst || busy_caller || useful >= kLargeWork) {
    if (started < parts - 1) start_threads(p, parts - 1);  // new threads are not counted awake yet
    if (asleep > 0) {
      p.alarm.fetch_add(1);
      { std::lock_guard<std::mutex> lock(p.mutex); }  // orders the notification after their check
      p.wake.notify_all();
    }
  }
  if (busy_caller || useful >= kLargeWork) return parts;  // threads that wake late join in (see for_each_part)
  return std::min(parts, 1 + std::max(0, started - asleep));
}

void run_parts(int parts, void (*invoke)(const void*, int), const void* context) {
  Pool& p = pool();
  bool idle = false;
  if (parts <= 1 || parts > kMaxThreads || !p.busy.compare_exchange_strong(idle, true, std::memory_order_acquire)) {
    run_serially(parts, invoke, context);  // one part, or a call from a part / another thread
    return;
  }
  if (p.started.load(std::memory_order_relaxed) < parts - 1) start_threads(p, parts - 1);
  p.invoke.store(invoke, std::memory_order_relaxed);
  p.context.store(context, std::memory_order_relaxed);
  p.finished.store(0, std::memory_order_relaxed);
  p.helpers.store(0, std::memory_order_relaxed);
  p.error = nullptr;
  const std::uint64_t generation = (p.ticket.load(std::memory_order_relaxed) >> 32) + 1;
  // Publishes the job, part 0 taken: the calling thread always runs it (so, on two threads, each
  // part stays on the same thread from call to call, and so do the caches it warmed).
  p.ticket.store(generation << 32 | static_cast<std::uint64_t>(parts) << 16 | 1);
  // A pool thread counts itself asleep before it checks the ticket, and this reads the count after
  // publishing it (both sequentially consistent): either it sees the job, or it is counted here.
  // Taking the mutex orders the notification after its check (it holds the mutex until it waits).
  if (p.sleeping.load() > 0) {
    { std::lock_guard<std::mutex> lock(p.mutex); }
    p.wake.notify_all();
  }
  if (helpers_required.load(std::memory_order_relaxed) && p.started.load(std::memory_order_relaxed) > 0) {
    while (claimable(p.ticket.load(std::memory_order_acquire))) pause();  // tests: the others are theirs
  }
  run_one(p, 0);
  while (claim_and_run(p, nullptr)) {
  }
  // Parts still running on pool threads: they are short, but a VM may pause a thread mid-part.
  for (unsigned spins = 1; p.finished.load(std::memory_order_acquire) < parts; ++spins) {
    if (spins % 1024 == 0) {
      std::this_thread::yield();
    } else {
      pause();
    }
  }
  note_team(1 + p.helpers.load(std::memory_order_relaxed));
  std::exception_ptr error = std::move(p.error);
  p.error = nullptr;
  p.busy.store(false, std::memory_order_release);
  if (error) std::rethrow_exception(error);
}

}  // namespace terracube::detail
