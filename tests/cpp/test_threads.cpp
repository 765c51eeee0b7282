// The parts of the calls that take a num_threads parameter (cpp/src/parallel.hpp, private).
#include <gtest/gtest.h>

#include <atomic>
#include <mutex>
#include <set>
#include <stdexcept>
#include <thread>
#include <vector>

#include "parallel.hpp"

namespace terracube {
namespace {

TEST(Parts, ThePartitionDependsOnTheWorkAloneNeverOnTheThreads) {
  EXPECT_EQ(detail::fixed_parts(0, 100), 1);
  EXPECT_EQ(detail::fixed_parts(99, 100), 1);
  EXPECT_EQ(detail::fixed_parts(250, 100), 2);
  EXPECT_EQ(detail::fixed_parts(1000000, 100), 64);
  EXPECT_EQ(detail::fixed_parts(1000000, 100, 8), 8);
  // The ranges cover [0, count) in order, without gaps or overlaps.
  for (const int parts : {1, 3, 7, 64}) {
    std::size_t next = 0;
    for (int part = 0; part < parts; ++part) {
      const auto [begin, end] = detail::part_range(1001, part, parts);
      EXPECT_EQ(begin, next);
      EXPECT_LE(begin, end);
      next = end;
    }
    EXPECT_EQ(next, 1001U);
  }
}

TEST(Parts, EveryPartRunsExactlyOnceOnAnyNumberOfThreads) {
  for (const int threads : {1, 2, 4, 0}) {
    for (const int parts : {1, 2, 3, 7, 64}) {
      std::vector<std::atomic<int>> runs(static_cast<std::size_t>(parts));
      detail::for_each_part(threads, parts, [&](int part) { runs[static_cast<std::size_t>(part)].fetch_add(1); });
      for (int part = 0; part < parts; ++part) {
        EXPECT_EQ(runs[static_cast<std::size_t>(part)].load(), 1) << threads << " threads, part " << part;
      }
    }
  }
}

TEST(Parts, AnAbsurdThreadCountRunsOnNoMoreThreadsThanParts) {
  // A billion arena slots crashed TBB (found by fuzzing num_threads); the parts bound them.
  std::vector<std::atomic<int>> runs(3);
  detail::for_each_part(1000000000, 3, [&](int part) { runs[static_cast<std::size_t>(part)].fetch_add(1); });
  for (const auto& run : runs) EXPECT_EQ(run.load(), 1);
}

TEST(Parts, OneThreadRunsThePartsInOrderOnTheCallingThread) {
  std::vector<int> order;
  const std::thread::id caller = std::this_thread::get_id();
  detail::for_each_part(1, 5, [&](int part) {
    EXPECT_EQ(std::this_thread::get_id(), caller);
    order.push_back(part);
  });
  EXPECT_EQ(order, (std::vector<int>{0, 1, 2, 3, 4}));
}

TEST(Parts, SeveralThreadsCanRunPartsAtOnce) {
  // Two parts that each wait for the other finish only if both run at the same time.
  std::atomic<int> arrived{0};
  std::mutex mutex;
  std::set<std::thread::id> threads;
  detail::for_each_part(2, 2, [&](int) {
    arrived.fetch_add(1);
    {
      const std::lock_guard<std::mutex> lock(mutex);
      threads.insert(std::this_thread::get_id());
    }
    while (arrived.load() < 2) std::this_thread::yield();
  });
  EXPECT_EQ(threads.size(), 2U);
}

TEST(Parts, AnExceptionOfAPartReachesTheCaller) {
  for (const int threads : {1, 2}) {
    EXPECT_THROW(detail::for_each_part(threads, 4,
                                       [](int part) {
                                         if (part == 2) throw std::runtime_error("part 2");
                                       }),
                 std::runtime_error);
  }
}

TEST(Parts, NegativeThreadCountsAreRejectedNamingTheOwner) {
  EXPECT_NO_THROW(detail::check_num_threads(0, "ElevationParams"));
  try {
    detail::check_num_threads(-1, "ElevationParams");
    ADD_FAILURE() << "expected std::invalid_argument";
  } catch (const std::invalid_argument& error) {
    EXPECT_NE(std::string(error.what()).find("ElevationParams.num_threads"), std::string::npos);
  }
}

}  // namespace
}  // namespace terracube
