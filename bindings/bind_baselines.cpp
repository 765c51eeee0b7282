// Bindings for baselines.hpp.
#include <pybind11/eigen.h>
#include <pybind11/stl.h>
#include <terracube/baselines.hpp>

#include "points.hpp"

namespace terracube::python {

namespace {

py::array to_bool_array(std::vector<std::uint8_t>&& mask) {
  auto* owned = new std::vector<std::uint8_t>(std::move(mask));
  py::capsule free_when_done(owned, [](void* p) { delete static_cast<std::vector<std::uint8_t>*>(p); });
  return bool_view_of(*owned, free_when_done, /*writeable=*/true);
}

}  // namespace

void bind_baselines(py::module_& m) {
  py::class_<PointBasedParams>(m, "PointBasedParams")
      .def(py::init<>())
      .def("check", &check_point_based_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_readwrite("edge_m", &PointBasedParams::edge_m)
      .def_readwrite("sigma", &PointBasedParams::sigma)
      .def_readwrite("variance_threshold_m2", &PointBasedParams::variance_threshold_m2)
      .def_readwrite("transform", &PointBasedParams::transform)
      .def_readwrite("crop", &PointBasedParams::crop)
      .def_readwrite("drop_non_finite", &PointBasedParams::drop_non_finite);

  m.def(
      "point_based_overhangs",
      [](const py::array& points, const PointBasedParams& params) {
        return to_bool_array(with_points(points, "points", [&](const auto& view) {
          py::gil_scoped_release release;
          return point_based_overhangs(view, params);
        }));
      },
      py::arg("points"), py::arg("params"));
  m.def(
      "octomap_column_overhangs",
      [](const py::array& points, const CollapseParams& params) {
        return to_bool_array(with_points(points, "points", [&](const auto& view) {
          py::gil_scoped_release release;
          return octomap_column_overhangs(view, params);
        }));
      },
      py::arg("points"), py::arg("params"));
}

}  // namespace terracube::python
