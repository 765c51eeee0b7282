// Private: the threads of the calls that take a num_threads parameter (terracube's own pool).
#pragma once

#include <cstddef>
#include <exception>
#include <string>

namespace terracube::detail {

/// Throws std::invalid_argument unless `num_threads` >= 0 (0 = one per processor). `what` names
/// the parameter's owner in the message.
void check_num_threads(int num_threads, const std::string& what);

/// The processors this process may run on (its CPU affinity on Linux), at least 1.
int processor_count();

/// How many parts a call splits into: `num_threads` (0 = one per processor the process may use),
/// but no more than one per `min_work` units of `work`, nor more than one plus the pool's threads
/// that are awake now, and at least 1. A pool thread sleeps after 20 ms without work, and waking it
/// costs tens of microseconds, on a virtual machine up to milliseconds: a call that finds the
/// threads asleep (or not yet started: the first calls) runs on fewer. They are woken (or started)
/// for the calls that follow once calls have kept coming, each within 20 ms of the one before, for
/// 20 ms or more. They are woken at once, and the call gets every part it asks for (threads that
/// wake late join in), when its thread ran for at least half the time since its previous call,
/// made 20 ms or more before (a program that computes between its calls, not a robot's loop that
/// waits for its next scan), or for a call of 32 parts' worth of work or more. The parts of a call
/// never change its result. When `num_threads` and the work allow 1 only, no thread is started or
/// woken, so a process that never asks for more never starts the pool. The pool's threads do not
/// survive fork(): in a forked child of a process that started them, always 1. With
/// require_helpers_in_tests on, the pool's state is ignored.
int thread_count(int num_threads, std::size_t work, std::size_t min_work);

/// The most threads that took part in one for_each_part call since the last reset (tests use it
/// to show that a call can run on several threads; it never changes what a call computes).
int largest_team(bool reset = false);

/// Tests only: while on, the calling thread of a call with several parts waits until pool threads
/// have claimed every part but the first, which is its own, so that the parts surely run on more
/// than one thread (largest_team() then counts them). Off by default.
void require_helpers_in_tests(bool on);

/// Tests only: the pool's threads now.
struct PoolState {
  int started = 0;       ///< threads started
  int asleep = 0;        ///< of which asleep (or about to sleep)
  unsigned wakeups = 0;  ///< times a thread woke up, since the first started
};
PoolState pool_state();

/// Runs invoke(context, part) for every part in [0, parts), each exactly once (see for_each_part).
void run_parts(int parts, void (*invoke)(const void* context, int part), const void* context);

/// Runs body(part) for every part in [0, parts), each exactly once, on up to `parts` threads: the
/// calling thread runs part 0, then claims the next unclaimed part until none is left, and each
/// pool thread that is awake claims parts the same way. The caller never waits for a thread that
/// has not started: a thread that wakes late (a sleeping processor of a virtual machine can take
/// milliseconds) finds the parts taken, and the call costs what it costs on one thread. So a part
/// must not depend on which thread runs it, nor on another part running at the same time. With 1
/// part, or when the pool is busy (a call from a part, or from another thread at the same time),
/// the calling thread runs every part itself, in order. An exception thrown by a part is rethrown
/// on the calling thread after all parts have finished (the first one caught, when several throw).
template <typename Body>
void for_each_part(int parts, const Body& body) {
  if (parts <= 1) {
    body(0);
    return;
  }
  run_parts(
      parts, [](const void* context, int part) { (*static_cast<const Body*>(context))(part); }, &body);
}

}  // namespace terracube::detail
