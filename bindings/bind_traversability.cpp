// Bindings for traversability.hpp.
#include <pybind11/eigen.h>
#include <pybind11/pybind11.h>
#include <terracube/traversability.hpp>

namespace py = pybind11;

namespace terracube::python {

void bind_traversability(py::module_& m) {
  py::class_<TraversabilityParams>(m, "TraversabilityParams")
      .def(py::init<>())
      .def("check", &check_traversability_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_readwrite("footprint_radius_m", &TraversabilityParams::footprint_radius_m)
      .def_readwrite("max_slope_rad", &TraversabilityParams::max_slope_rad)
      .def_readwrite("max_step_m", &TraversabilityParams::max_step_m)
      .def_readwrite("max_roughness_m", &TraversabilityParams::max_roughness_m)
      .def_readwrite("min_clearance_m", &TraversabilityParams::min_clearance_m)
      .def_readwrite("slope_weight", &TraversabilityParams::slope_weight)
      .def_readwrite("step_weight", &TraversabilityParams::step_weight)
      .def_readwrite("roughness_weight", &TraversabilityParams::roughness_weight)
      .def_readwrite("min_window_cells", &TraversabilityParams::min_window_cells);

  m.def("add_traversability_layers", &add_traversability_layers, py::arg("map"), py::arg("params"),
        py::arg("height_layer"), py::arg("start"), py::arg("num_threads"), py::call_guard<py::gil_scoped_release>());
}

}  // namespace terracube::python
