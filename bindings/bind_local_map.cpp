// Bindings for local_map.hpp.
#include <pybind11/eigen.h>
#include <pybind11/stl.h>
#include <terracube/local_map.hpp>

#include <sstream>

#include "pickle.hpp"
#include "points.hpp"

namespace terracube::python {

namespace {

/// A read-only (nx, ny) float32 view of a LocalMap layer (storage order) keeping the map alive.
py::array local_layer_view(const py::object& map_object, const std::string& name) {
  const auto& map = map_object.cast<const LocalMap&>();
  const Layer& layer = map.get(name);
  return read_only(py::array_t<float>(
      {layer.rows(), layer.cols()},
      {static_cast<py::ssize_t>(sizeof(float) * layer.cols()), static_cast<py::ssize_t>(sizeof(float))}, layer.data(),
      map_object));
}

Eigen::Matrix4d pose_matrix(const py::array& pose) {
  const auto matrix = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(pose);
  if (!matrix || matrix.ndim() != 2 || matrix.shape(0) != 4 || matrix.shape(1) != 4) {
    throw py::value_error("pose must be a 4x4 matrix (odometry <- sensor), got shape " + shape_string(pose));
  }
  return Eigen::Map<const Eigen::Matrix<double, 4, 4, Eigen::RowMajor>>(matrix.data());
}

}  // namespace

void bind_local_map(py::module_& m) {
  py::class_<LocalMapParams>(m, "LocalMapParams")
      .def(py::init<>())
      .def("check", &check_local_map_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_readwrite("length_m", &LocalMapParams::length_m)
      .def_readwrite("resolution_m", &LocalMapParams::resolution_m)
      .def_readwrite("collapse", &LocalMapParams::collapse)
      .def_readwrite("max_cells", &LocalMapParams::max_cells)
      .def_readwrite("min_range_m", &LocalMapParams::min_range_m)
      .def_readwrite("max_range_m", &LocalMapParams::max_range_m)
      .def_readwrite("range_sigma_m", &LocalMapParams::range_sigma_m)
      .def_readwrite("angle_sigma_rad", &LocalMapParams::angle_sigma_rad)
      .def_readwrite("cell_sigma_m", &LocalMapParams::cell_sigma_m)
      .def_readwrite("drift_m_per_sqrt_m", &LocalMapParams::drift_m_per_sqrt_m)
      .def_readwrite("gate_sigmas", &LocalMapParams::gate_sigmas)
      .def_readwrite("clear_seen_through", &LocalMapParams::clear_seen_through)
      .def_readwrite("clearing_margin_m", &LocalMapParams::clearing_margin_m)
      .def_readwrite("clearing_depth_m", &LocalMapParams::clearing_depth_m)
      .def_readwrite("clearing_beyond_m", &LocalMapParams::clearing_beyond_m)
      .def_readwrite("visibility_bin_rad", &LocalMapParams::visibility_bin_rad)
      .def_readwrite("discontinuity_m", &LocalMapParams::discontinuity_m)
      .def_readwrite("compute_planner_layers", &LocalMapParams::compute_planner_layers)
      .def_readwrite("traversability", &LocalMapParams::traversability)
      .def_readwrite("num_threads", &LocalMapParams::num_threads);

  py::class_<LocalMapUpdate>(m, "LocalMapUpdate")
      .def_readonly("num_points", &LocalMapUpdate::num_points)
      .def_readonly("num_in_map", &LocalMapUpdate::num_in_map)
      .def_readonly("num_overhang", &LocalMapUpdate::num_overhang)
      .def_readonly("num_dropped_non_finite", &LocalMapUpdate::num_dropped_non_finite)
      .def_readonly("num_cropped", &LocalMapUpdate::num_cropped)
      .def_readonly("num_out_of_range", &LocalMapUpdate::num_out_of_range)
      .def_readonly("num_fused_cells", &LocalMapUpdate::num_fused_cells)
      .def_readonly("num_replaced_cells", &LocalMapUpdate::num_replaced_cells)
      .def_readonly("num_cleared_cells", &LocalMapUpdate::num_cleared_cells)
      .def_readonly("map_reset", &LocalMapUpdate::map_reset)
      .def(pickle_by_fields<LocalMapUpdate>("LocalMapUpdate",
                                            [](auto& r, auto&& f) {
                                              f("num_points", r.num_points);
                                              f("num_in_map", r.num_in_map);
                                              f("num_overhang", r.num_overhang);
                                              f("num_dropped_non_finite", r.num_dropped_non_finite);
                                              f("num_cropped", r.num_cropped);
                                              f("num_out_of_range", r.num_out_of_range);
                                              f("num_fused_cells", r.num_fused_cells);
                                              f("num_replaced_cells", r.num_replaced_cells);
                                              f("num_cleared_cells", r.num_cleared_cells);
                                              f("map_reset", r.map_reset);
                                            }))
      .def("__repr__", [](const LocalMapUpdate& u) {
        std::ostringstream text;
        text << "LocalMapUpdate(num_points=" << u.num_points << ", num_in_map=" << u.num_in_map
             << ", num_overhang=" << u.num_overhang << ", num_cropped=" << u.num_cropped
             << ", num_out_of_range=" << u.num_out_of_range << ", num_fused_cells=" << u.num_fused_cells
             << ", num_replaced_cells=" << u.num_replaced_cells << ", num_cleared_cells=" << u.num_cleared_cells
             << ", map_reset=" << (u.map_reset ? "True" : "False") << ")";
        return text.str();
      });

  py::class_<LocalMap>(m, "LocalMap")
      .def(py::init<const LocalMapParams&>(), py::arg("params"))
      .def_property_readonly("params", &LocalMap::params)
      .def_property_readonly("geometry", &LocalMap::geometry)
      .def_property_readonly(
          "start_index",
          [](const LocalMap& map) { return std::make_pair(map.start_index().x(), map.start_index().y()); })
      .def_property_readonly("layers", &LocalMap::layers)
      .def_property_readonly("num_updates", &LocalMap::num_updates)
      .def_property_readonly("time_origin", &LocalMap::time_origin_s, "the first update's stamp [s]")
      .def("get", &local_layer_view, py::arg("name"), "(n, n) read-only float32 view of a layer, storage order")
      .def(
          "index_of",
          [](const LocalMap& map, double x, double y) -> std::optional<std::pair<int, int>> {
            const auto index = map.index_of({x, y});
            if (!index) return std::nullopt;
            return std::make_pair(index->x(), index->y());
          },
          py::arg("x"), py::arg("y"))
      .def(
          "position_of", [](const LocalMap& map, int i, int j) { return Eigen::Vector2d(map.position_of({i, j})); },
          py::arg("i"), py::arg("j"))
      .def(
          "update",
          [](LocalMap& map, const py::array& points, const py::array& pose, double stamp,
             const py::object& no_returns) {
            const Eigen::Matrix4d matrix = pose_matrix(pose);
            py::object keep;
            const PointsView<double> beams = directions_view(no_returns, "no_returns", keep);
            return with_points(points, "points", [&](const auto& view) {
              py::gil_scoped_release release;
              return map.update(view, matrix, stamp, beams);
            });
          },
          py::arg("points"), py::arg("pose"), py::arg("stamp") = std::numeric_limits<double>::quiet_NaN(),
          py::arg("no_returns") = py::none())
      .def(
          "move_to", [](LocalMap& map, double x, double y) { return map.move_to({x, y}); }, py::arg("x"), py::arg("y"),
          py::call_guard<py::gil_scoped_release>())
      .def("clear", &LocalMap::clear)
      .def("update_planner_layers", &LocalMap::update_planner_layers, py::call_guard<py::gil_scoped_release>())
      .def("to_elevation_map", &LocalMap::to_elevation_map);
}

}  // namespace terracube::python
