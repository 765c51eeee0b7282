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
  py::class_<PointGapParams>(m, "PointGapParams")
      .def(py::init<>())
      .def_readwrite("cell_m", &PointGapParams::cell_m)
      .def_readwrite("min_gap_m", &PointGapParams::min_gap_m)
      .def_readwrite("transform", &PointGapParams::transform)
      .def_readwrite("crop", &PointGapParams::crop)
      .def_readwrite("drop_non_finite", &PointGapParams::drop_non_finite);

  m.def(
      "point_gap_overhangs",
      [](const py::array& points, const PointGapParams& params) {
        return to_bool_array(with_points(points, "points", [&](const auto& view) {
          py::gil_scoped_release release;
          return point_gap_overhangs(view, params);
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
