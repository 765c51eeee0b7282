// Private: test hooks of the thread pool behind every num_threads parameter (cpp/src/threads.hpp),
// for the threaded pytest cases only (not part of the API).
#include <pybind11/pybind11.h>

#include "threads.hpp"

namespace py = pybind11;

namespace terracube::python {

void bind_threads(py::module_& m) {
  m.def("_require_pool_threads", &detail::require_helpers_in_tests, py::arg("on"),
        "Tests only: while on, every call with several parts runs all but its first on pool threads.");
  m.def("_largest_team", &detail::largest_team, py::arg("reset") = false,
        "Tests only: the most threads that took part in one call since the last reset.");
}

}  // namespace terracube::python
