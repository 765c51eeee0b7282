// terracube._core: assembles the per-area binding files.
#include <pybind11/pybind11.h>

namespace py = pybind11;

namespace terracube::python {
void bind_collapse(py::module_& m);
void bind_baselines(py::module_& m);
void bind_elevation(py::module_& m);
void bind_fuzzy(py::module_& m);
void bind_icp(py::module_& m);
void bind_simulation(py::module_& m);
void bind_evaluation(py::module_& m);
void bind_pose_graph(py::module_& m);
void bind_mapper(py::module_& m);
void bind_local_map(py::module_& m);
void bind_traversability(py::module_& m);
}  // namespace terracube::python

PYBIND11_MODULE(_core, m) {
  m.doc() = "terracube C++ core (private: use the terracube package)";
  terracube::python::bind_collapse(m);
  terracube::python::bind_baselines(m);
  terracube::python::bind_elevation(m);
  terracube::python::bind_fuzzy(m);
  terracube::python::bind_icp(m);
  terracube::python::bind_simulation(m);
  terracube::python::bind_evaluation(m);
  terracube::python::bind_pose_graph(m);
  terracube::python::bind_mapper(m);
  terracube::python::bind_traversability(m);
  terracube::python::bind_local_map(m);
}
