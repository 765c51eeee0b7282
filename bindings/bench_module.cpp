// terracube._bench: benchmark-only probes (bench/bench_collapse.py), built with TERRACUBE_BUILD_BENCH.
#include <pybind11/pybind11.h>

namespace py = pybind11;

namespace terracube::python {
void bind_bench(py::module_& m);
}  // namespace terracube::python

PYBIND11_MODULE(_bench, m) {
  m.doc() = "terracube benchmark probes (private: for bench/ only)";
  terracube::python::bind_bench(m);
}
