// The thread pool behind every num_threads parameter (cpp/src/threads.hpp, private).
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <stdexcept>
#include <thread>
#include <vector>

#include "threads.hpp"

namespace terracube {
namespace {

/// Runs `parts` parts `rounds` times and checks that every part ran exactly once per round.
void expect_each_part_once(int parts, int rounds) {
  std::vector<std::atomic<int>> runs(static_cast<std::size_t>(parts));
  for (int round = 0; round < rounds; ++round) {
    detail::for_each_part(parts, [&](int part) {
      ASSERT_GE(part, 0);
      ASSERT_LT(part, parts);
      runs[static_cast<std::size_t>(part)].fetch_add(1);
    });
  }
  for (int part = 0; part < parts; ++part) {
    EXPECT_EQ(runs[static_cast<std::size_t>(part)].load(), rounds) << "part " << part << " of " << parts;
  }
}

TEST(ThreadPool, EveryPartRunsExactlyOnce) {
  for (const int parts : {1, 2, 3, 4, 7, 16, 64, 256}) expect_each_part_once(parts, 200);
  detail::require_helpers_in_tests(true);  // parts on several threads at once, every time
  for (const int parts : {2, 3, 5}) expect_each_part_once(parts, 200);
  detail::require_helpers_in_tests(false);
}

TEST(ThreadPool, PartsRunOnSeveralThreadsAtOnce) {
  // With the test switch on, the calling thread claims its part only after the pool's threads
  // have claimed theirs: two parts that each wait for the other finish only if both run at once.
  detail::require_helpers_in_tests(true);
  detail::largest_team(true);
  std::atomic<int> arrived{0};
  detail::for_each_part(2, [&](int) {
    arrived.fetch_add(1);
    while (arrived.load() < 2) std::this_thread::yield();
  });
  detail::require_helpers_in_tests(false);
  EXPECT_EQ(arrived.load(), 2);
  EXPECT_EQ(detail::largest_team(), 2);
}

TEST(ThreadPool, ACallFromAPartRunsItsPartsInOrderOnItsOwnThread) {
  // The outer call owns the pool: the inner one, from whichever thread runs part 0, runs its
  // parts itself instead of waiting for the pool (which would never come).
  std::vector<int> order;
  std::atomic<bool> inner_done{false};
  detail::for_each_part(2, [&](int part) {
    if (part != 0) return;
    detail::for_each_part(3, [&](int inner) { order.push_back(inner); });  // one thread: no race
    inner_done.store(true);
  });
  EXPECT_TRUE(inner_done.load());
  EXPECT_EQ(order, (std::vector<int>{0, 1, 2})) << "an inner call runs its parts in order on its thread";
}

TEST(ThreadPool, AnExceptionIsRethrownAfterEveryPartHasRun) {
  for (const bool helpers : {false, true}) {
    detail::require_helpers_in_tests(helpers);
    std::atomic<int> ran{0};
    const auto call = [&] {
      detail::for_each_part(4, [&](int part) {
        ran.fetch_add(1);
        if (part == 1 || part == 2) throw std::runtime_error("part " + std::to_string(part));
      });
    };
    EXPECT_THROW(call(), std::runtime_error);
    EXPECT_EQ(ran.load(), 4) << "the other parts still run";
    expect_each_part_once(4, 20);  // the pool is usable after an exception
    detail::require_helpers_in_tests(false);
  }
}

TEST(ThreadPool, CallsFromSeveralThreadsAtOnceEachRunAllTheirParts) {
  // One call owns the pool at a time; the others run their parts on their own threads.
  std::vector<std::thread> callers;
  std::atomic<int> wrong{0};
  for (int t = 0; t < 4; ++t) {
    callers.emplace_back([&wrong, t] {
      const int parts = 2 + t;
      for (int round = 0; round < 300; ++round) {
        std::vector<std::atomic<int>> runs(static_cast<std::size_t>(parts));
        detail::for_each_part(parts, [&](int part) { runs[static_cast<std::size_t>(part)].fetch_add(1); });
        for (const auto& r : runs) wrong.fetch_add(r.load() == 1 ? 0 : 1);
      }
    });
  }
  for (std::thread& caller : callers) caller.join();
  EXPECT_EQ(wrong.load(), 0);
}

TEST(ThreadPool, ASleepingPoolThreadIsWokenForTheNextCall) {
  // Pool threads sleep after 20 ms without work; a later call must still reach them (the test
  // switch makes the call wait for one, so a lost wake-up would hang here, not pass).
  detail::for_each_part(2, [](int) {});
  for (int round = 0; round < 5; ++round) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    detail::require_helpers_in_tests(true);
    detail::largest_team(true);
    detail::for_each_part(2, [](int) {});
    detail::require_helpers_in_tests(false);
    EXPECT_EQ(detail::largest_team(), 2) << "round " << round;
  }
}

TEST(ThreadPool, ThreadCountsFollowTheParameterTheWorkAndTheProcessors) {
  detail::require_helpers_in_tests(true);  // counts as asked, whatever the pool's threads do
  EXPECT_GE(detail::processor_count(), 1);
  EXPECT_EQ(detail::thread_count(1, 1000000, 1), 1);
  EXPECT_EQ(detail::thread_count(3, 1000000, 1), 3);
  EXPECT_EQ(detail::thread_count(0, 1000000, 1), std::min(detail::processor_count(), 256));
  EXPECT_EQ(detail::thread_count(4, 250, 100), 2) << "one part per 100 units of work";
  EXPECT_EQ(detail::thread_count(4, 50, 100), 1);
  EXPECT_EQ(detail::thread_count(100000, 100000000, 1), 256) << "capped";
  detail::require_helpers_in_tests(false);
  EXPECT_THROW(detail::check_num_threads(-1, "Params"), std::invalid_argument);
}

/// Waits up to 10 s for `ready` (a pool thread's state changes on its own schedule).
template <typename Ready>
bool eventually(const Ready& ready) {
  for (int tick = 0; tick < 10000; ++tick) {
    if (ready()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  return false;
}

/// Has the pool start two threads at least (a call of three parts, which the test switch gives to
/// them) and returns how many it has.
int start_pool_threads() {
  detail::require_helpers_in_tests(true);
  detail::for_each_part(3, [](int) {});
  detail::require_helpers_in_tests(false);
  return detail::pool_state().started;
}

TEST(ThreadPool, SleepingThreadsAreWokenForBurstsOfCallsAndForLargeOnes) {
  const int started = start_pool_threads();
  ASSERT_GE(started, 2);
  const auto all_asleep = [&] { return detail::pool_state().asleep == started; };
  ASSERT_TRUE(eventually(all_asleep)) << "idle pool threads never slept";
  // Three parts' worth of work: a few requests in a row (a robot's calls for one scan) run on the
  // calling thread and leave the threads asleep; requests that keep coming for 20 ms wake them.
  const unsigned wakeups = detail::pool_state().wakeups;
  for (int request = 0; request < 4; ++request) EXPECT_EQ(detail::thread_count(3, 3, 1), 1);
  EXPECT_EQ(detail::pool_state().wakeups, wakeups) << "four requests within microseconds do not wake";
  EXPECT_TRUE(eventually([&] {  // a request every millisecond
    detail::thread_count(3, 3, 1);
    return detail::pool_state().wakeups >= wakeups + static_cast<unsigned>(started);
  })) << "requests that kept coming did not wake the pool threads";
  // A large call gets every part it asks for, asleep or not, and wakes the threads.
  ASSERT_TRUE(eventually(all_asleep));
  const unsigned before_large = detail::pool_state().wakeups;
  EXPECT_EQ(detail::thread_count(3, 32, 1), 3);
  EXPECT_TRUE(
      eventually([&] { return detail::pool_state().wakeups >= before_large + static_cast<unsigned>(started); }));
  EXPECT_EQ(detail::thread_count(1, 1000000, 1), 1);
}

TEST(ThreadPool, ACallerThatWasBusySinceItsLastCallWakesTheSleepingThreads) {
  const int started = start_pool_threads();
  ASSERT_GE(started, 2);
  const auto all_asleep = [&] { return detail::pool_state().asleep == started; };
  // A caller that slept since its last request (a robot's loop) leaves the threads asleep.
  ASSERT_TRUE(eventually(all_asleep)) << "idle pool threads never slept";
  detail::thread_count(3, 3, 1);
  std::this_thread::sleep_for(std::chrono::milliseconds(30));
  const unsigned wakeups = detail::pool_state().wakeups;
  EXPECT_EQ(detail::thread_count(3, 3, 1), 1) << "an idle caller's call runs on the awake threads";
  EXPECT_EQ(detail::pool_state().wakeups, wakeups);
  // One that computed for 30 ms since (a program between its calls) gets them woken, and every
  // part it asks for: those that wake late join in. A host that takes the processor away for half
  // the time makes the caller look idle: up to five tries.
  bool woken = false;
  for (int attempt = 0; attempt < 5 && !woken; ++attempt) {
    ASSERT_TRUE(eventually(all_asleep));
    detail::thread_count(3, 3, 1);
    const auto busy_until = std::chrono::steady_clock::now() + std::chrono::milliseconds(30);
    volatile unsigned spin = 0;
    while (std::chrono::steady_clock::now() < busy_until) spin = spin + 1;
    const unsigned before_busy = detail::pool_state().wakeups;
    if (detail::thread_count(3, 3, 1) != 3) continue;
    woken = eventually([&] { return detail::pool_state().wakeups >= before_busy + static_cast<unsigned>(started); });
  }
  EXPECT_TRUE(woken) << "a caller busy for 30 ms did not get every part and the pool threads woken";
}

}  // namespace
}  // namespace terracube
