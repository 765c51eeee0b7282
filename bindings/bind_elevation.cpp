// Bindings for elevation_map.hpp and terrain.hpp.
#include <pybind11/eigen.h>
#include <pybind11/stl.h>
#include <terracube/elevation_map.hpp>
#include <terracube/terrain.hpp>

#include <memory>
#include <sstream>

#include "pickle.hpp"
#include "points.hpp"

namespace terracube::python {

namespace {

/// A writeable (nx, ny) float32 view of a layer that keeps the map alive.
py::array layer_view(const py::object& map_object, const std::string& name) {
  auto& map = map_object.cast<ElevationMap&>();
  Layer& layer = map.get(name);
  return py::array_t<float>(
      {layer.rows(), layer.cols()},
      {static_cast<py::ssize_t>(sizeof(float) * layer.cols()), static_cast<py::ssize_t>(sizeof(float))}, layer.data(),
      map_object);
}

std::vector<std::uint8_t> selection(
    const std::optional<py::array_t<bool, py::array::c_style | py::array::forcecast>>& use, std::size_t rows) {
  std::vector<std::uint8_t> flags;
  if (!use) return flags;
  if (use->ndim() != 1 || static_cast<std::size_t>(use->shape(0)) != rows) {
    throw py::value_error("use must be an (N,) bool array with one flag per point");
  }
  flags.assign(use->data(), use->data() + rows);
  return flags;
}

MapGeometry make_geometry(double resolution, const Eigen::Vector2d& origin, const Eigen::Vector2i& size) {
  MapGeometry g;
  g.resolution_m = resolution;
  g.origin_m = origin;
  g.size = size.array();
  return g;
}

/// A map's pickled state: its geometry and its layers in order, each a read-only (nx, ny) view
/// (pickle copies them into its bytes: no copy of the map besides).
py::tuple map_state(const py::object& self) {
  const auto& map = self.cast<const ElevationMap&>();
  py::list layers;
  for (const std::string& name : map.layers()) layers.append(py::make_tuple(name, read_only(layer_view(self, name))));
  return py::make_tuple(map.geometry(), layers);
}

/// The map of a pickled state; ValueError when a layer does not fit its geometry.
ElevationMap map_from_state(const py::tuple& state) {
  const py::tuple items = state_items(state, 2, "ElevationMap");
  ElevationMap map(items[0].cast<MapGeometry>());
  for (const py::handle layer : items[1].cast<py::list>()) {
    const auto entry = layer.cast<py::tuple>();
    const auto name = entry[0].cast<std::string>();
    const auto data = py::array_t<float, py::array::c_style | py::array::forcecast>::ensure(entry[1]);
    if (!data || data.ndim() != 2 || data.shape(0) != map.geometry().size.x() ||
        data.shape(1) != map.geometry().size.y()) {
      throw py::value_error("ElevationMap: the pickled layer " + name + " does not have the map's (nx, ny) shape");
    }
    map.add(name, Eigen::Map<const Layer>(data.data(), data.shape(0), data.shape(1)));
  }
  return map;
}

}  // namespace

void bind_elevation(py::module_& m) {
  py::class_<MapGeometry>(m, "MapGeometry",
                          "Cell (i, j) is centred on origin + (i + 0.5, j + 0.5) * resolution; i along x, j along y.")
      .def(py::init(&make_geometry), py::arg("resolution"), py::arg("origin"), py::arg("size"))
      .def_readonly("resolution", &MapGeometry::resolution_m, "cell edge [m]")
      .def_readonly("origin", &MapGeometry::origin_m, "(2,) lower-left corner of cell (0, 0) [m]")
      .def_property_readonly(
          "size", [](const MapGeometry& g) { return Eigen::Vector2i(g.size.matrix()); }, "(2,) cells along x and y")
      .def_property_readonly("length", &MapGeometry::length_m, "(2,) map length along x and y [m]")
      .def_property_readonly("num_cells", &MapGeometry::num_cells)
      .def(
          "__eq__", [](const MapGeometry& a, const MapGeometry& b) { return a == b; }, py::is_operator())
      .def(
          "__ne__", [](const MapGeometry& a, const MapGeometry& b) { return a != b; }, py::is_operator())
      .def(
          "position_of", [](const MapGeometry& g, int i, int j) { return Eigen::Vector2d(g.position_of({i, j})); },
          py::arg("i"), py::arg("j"), "centre of cell (i, j) [m]")
      .def(
          "index_of",
          [](const MapGeometry& g, double x, double y) -> std::optional<std::pair<int, int>> {
            const auto index = g.index_of({x, y});
            if (!index) return std::nullopt;
            return std::make_pair(index->x(), index->y());
          },
          py::arg("x"), py::arg("y"), "cell (i, j) holding (x, y), or None outside the map")
      .def(pickle_by_fields<MapGeometry>("MapGeometry",
                                         [](auto& g, auto&& f) {
                                           f("resolution", g.resolution_m);
                                           f("origin", g.origin_m);
                                           f("size", g.size);
                                         }))
      .def("__repr__", [](const MapGeometry& g) {
        std::ostringstream text;
        text << "MapGeometry(resolution=" << g.resolution_m << ", origin=[" << g.origin_m.transpose() << "], size=["
             << g.size.transpose() << "])";
        return text.str();
      });

  py::class_<ElevationMap>(m, "ElevationMap")
      .def(py::init<const MapGeometry&>(), py::arg("geometry"))
      .def_property_readonly("geometry", &ElevationMap::geometry)
      .def_property_readonly("layers", &ElevationMap::layers)
      .def("exists", &ElevationMap::exists, py::arg("name"))
      .def("get", &layer_view, py::arg("name"), "(nx, ny) float32 view of a layer; KeyError when missing")
      .def(
          "add",
          [](ElevationMap& map, const std::string& name,
             const py::array_t<float, py::array::c_style | py::array::forcecast>& data) {
            if (data.ndim() != 2) throw py::value_error("a layer must be a 2D (nx, ny) array");
            Layer layer = Eigen::Map<const Layer>(data.data(), data.shape(0), data.shape(1));
            map.add(name, std::move(layer));
          },
          py::arg("name"), py::arg("data"))
      .def("add_constant", py::overload_cast<const std::string&, float>(&ElevationMap::add), py::arg("name"),
           py::arg("value"))
      .def(py::pickle(&map_state, &map_from_state));

  py::class_<ElevationParams>(m, "ElevationParams")
      .def(py::init<>())
      .def("check", &check_elevation_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_readwrite("resolution_m", &ElevationParams::resolution_m)
      .def(
          "set_extent",
          [](ElevationParams& p, double origin_x, double origin_y, int size_x, int size_y) {
            p.origin_m = Eigen::Vector2d(origin_x, origin_y);
            p.size = CellIndex(size_x, size_y);
          },
          py::arg("origin_x"), py::arg("origin_y"), py::arg("size_x"), py::arg("size_y"))
      .def("clear_extent",
           [](ElevationParams& p) {
             p.origin_m.reset();
             p.size.reset();
           })
      .def_property_readonly("has_extent", [](const ElevationParams& p) { return p.origin_m.has_value(); })
      .def_readwrite("discontinuity_m", &ElevationParams::discontinuity_m)
      .def_readwrite("transform", &ElevationParams::transform)
      .def_readwrite("crop", &ElevationParams::crop)
      .def_readwrite("drop_non_finite", &ElevationParams::drop_non_finite)
      .def_readwrite("max_cells", &ElevationParams::max_cells)
      .def_readwrite("num_threads", &ElevationParams::num_threads);

  m.def(
      "build_elevation_map",
      [](const py::array& points, const ElevationParams& params,
         const std::optional<py::array_t<bool, py::array::c_style | py::array::forcecast>>& use) {
        return with_points(points, "points", [&](const auto& view) {
          const std::vector<std::uint8_t> flags = selection(use, view.size);
          py::gil_scoped_release release;
          return build_elevation_map(view, params, use ? &flags : nullptr);
        });
      },
      py::arg("points"), py::arg("params"), py::arg("use") = py::none());
  m.def(
      "build_elevation_map_into",
      [](ElevationMap& map, const py::array& points, const ElevationParams& params,
         const std::optional<py::array_t<bool, py::array::c_style | py::array::forcecast>>& use) {
        with_points(points, "points", [&](const auto& view) {
          const std::vector<std::uint8_t> flags = selection(use, view.size);
          py::gil_scoped_release release;
          build_elevation_map_into(map, view, params, use ? &flags : nullptr);
          return 0;
        });
      },
      py::arg("map"), py::arg("points"), py::arg("params"), py::arg("use") = py::none());

  py::class_<OverhangFreeMap>(m, "OverhangFreeMap")
      .def_readonly("map", &OverhangFreeMap::map)
      .def_readonly("collapse", &OverhangFreeMap::collapse)
      .def(py::pickle([](const OverhangFreeMap& r) { return py::make_tuple(r.map, r.collapse); },
                      [](const py::tuple& state) {
                        const py::tuple items = state_items(state, 2, "OverhangFreeMap");
                        return OverhangFreeMap{items[0].cast<ElevationMap>(), items[1].cast<CollapseResult>()};
                      }));
  m.def(
      "build_overhang_free_map",
      [](const py::array& points, const CollapseParams& collapse, const ElevationParams& elevation,
         const py::object& no_returns) {
        py::object keep;
        const PointsView<double> beams = directions_view(no_returns, "no_returns", keep);
        return with_points(points, "points", [&](const auto& view) {
          py::gil_scoped_release release;
          return build_overhang_free_map(view, collapse, elevation, beams);
        });
      },
      py::arg("points"), py::arg("collapse"), py::arg("elevation"), py::arg("no_returns") = py::none());

  py::enum_<GroundReference>(m, "GroundReference")
      .value("sensor_height", GroundReference::kSensorHeight)
      .value("local_ground", GroundReference::kLocalGround);

  py::class_<TerrainParams>(m, "TerrainParams")
      .def(py::init<>())
      .def("check", &check_terrain_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_readwrite("ground_height_m", &TerrainParams::ground_height_m)
      .def_readwrite("std_dev_m", &TerrainParams::std_dev_m)
      .def_readwrite("robot_height_m", &TerrainParams::robot_height_m)
      .def_readwrite("reference", &TerrainParams::reference)
      .def_readwrite("sensor_height_m", &TerrainParams::sensor_height_m)
      .def_readwrite("local_ground_radius_cells", &TerrainParams::local_ground_radius_cells)
      .def_readwrite("num_threads", &TerrainParams::num_threads);

  m.def(
      "classify_terrain",
      [](ElevationMap& map, const TerrainParams& params) {
        auto classes = std::make_unique<TerrainClasses>();
        {
          py::gil_scoped_release release;
          *classes = classify_terrain_layers(map, params);
        }
        // The array owns the classes (no copy).
        const py::ssize_t rows = classes->rows();
        const py::ssize_t cols = classes->cols();
        std::uint8_t* data = classes->data();
        py::capsule owner(classes.release(), [](void* p) { delete static_cast<TerrainClasses*>(p); });
        return py::array_t<std::uint8_t>({rows, cols}, data, owner);
      },
      py::arg("map"), py::arg("params"), "(nx, ny) uint8 classes; adds class, relative_height, ground layers");
  m.def("step_layer", [](const py::array_t<float, py::array::c_style | py::array::forcecast>& height) {
    if (height.ndim() != 2) throw py::value_error("height must be a 2D array");
    const Layer in = Eigen::Map<const Layer>(height.data(), height.shape(0), height.shape(1));
    return Layer(step_layer(in));
  });
}

}  // namespace terracube::python
