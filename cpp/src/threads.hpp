// Private: the threads of the calls that take a num_threads parameter (OpenMP, GCC's libgomp).
#pragma once

#include <cstddef>
#include <exception>
#include <string>

namespace terracube::detail {

/// Throws std::invalid_argument unless `num_threads` >= 0 (0 = one per processor). `what` names
/// the parameter's owner in the message.
void check_num_threads(int num_threads, const std::string& what);

/// How many parts a call splits into: `num_threads` (0 = one per processor the process may use),
/// but no more than one per `min_work` units of `work` (threads cost several microseconds to wake
/// up), and at least 1. With 1 no thread is started, so a process that never asks for more never
/// starts OpenMP's thread pool. The pool does not survive fork() (in a child, GCC's libgomp hangs
/// at the next parallel region): in a forked child of a process that started it, always 1.
int thread_count(int num_threads, std::size_t work, std::size_t min_work);

/// Records that this process starts OpenMP's thread pool (for thread_count's fork check).
void note_pool_start();

/// Called inside a parallel region: records its number of threads for largest_team().
void note_team();

/// The most threads that a for_each_part call has run on since the last reset (tests use it to
/// show that a call ran on several threads; it never changes what a call computes).
int largest_team(bool reset = false);

/// Runs body(part) for every part in [0, parts), each exactly once, on up to `parts` threads (the
/// calling thread among them); with 1 part, on the calling thread without OpenMP. An exception
/// thrown by a part is rethrown on the calling thread after all parts have finished (the first
/// one caught, when several throw).
template <typename Body>
void for_each_part(int parts, const Body& body) {
  if (parts <= 1) {
    body(0);
    return;
  }
  note_pool_start();
  std::exception_ptr error;
#pragma omp parallel for schedule(static, 1) num_threads(parts)
  for (int part = 0; part < parts; ++part) {
    if (part == 0) note_team();
    try {
      body(part);
    } catch (...) {
#pragma omp critical(terracube_for_each_part_error)
      if (!error) error = std::current_exception();
    }
  }
  if (error) std::rethrow_exception(error);
}

}  // namespace terracube::detail
