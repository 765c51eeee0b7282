// Bindings for cube_grid.hpp and collapse.hpp.
#include <pybind11/eigen.h>
#include <pybind11/stl.h>
#include <terracube/collapse.hpp>

#include <algorithm>
#include <sstream>

#include "pickle.hpp"
#include "points.hpp"

namespace terracube::python {

namespace {

const char* storage_name(CubeStorage storage) {
  switch (storage) {
    case CubeStorage::kDense:
      return "dense";
    case CubeStorage::kSparse:
      return "sparse";
    default:
      return "auto";
  }
}

/// A read-only uint8 view of cube reasons that keeps `owner` alive.
py::array reasons_view(const std::vector<CubeReason>& reasons, const py::object& owner) {
  static_assert(sizeof(CubeReason) == 1);
  return read_only(py::array_t<std::uint8_t>({static_cast<py::ssize_t>(reasons.size())}, {py::ssize_t{1}},
                                             reinterpret_cast<const std::uint8_t*>(reasons.data()), owner));
}

/// A result's pickled state: its grid, read-only views of its arrays (pickle copies them into its
/// bytes) and its counts.
py::tuple result_state(const py::object& self) {
  const auto& r = self.cast<const CollapseResult&>();
  return py::make_tuple(r.grid, view_of(r.overhang, self), view_of(r.occupied_cubes, self),
                        view_of(r.removed_cubes, self), reasons_view(r.cube_reasons, self), r.num_points, r.num_used,
                        r.num_cropped, r.num_dropped_non_finite, r.num_overhang, static_cast<int>(r.storage_used));
}

/// The result of a pickled state; ValueError when its parts do not belong together.
CollapseResult result_from_state(const py::tuple& state) {
  const py::tuple items = state_items(state, 11, "CollapseResult");
  CollapseResult r;
  r.grid = items[0].cast<CubeGrid>();
  r.overhang = vector_of<std::uint8_t>(items[1], "CollapseResult overhang");
  r.occupied_cubes = vector_of<std::int64_t>(items[2], "CollapseResult occupied_cubes");
  r.removed_cubes = vector_of<std::int64_t>(items[3], "CollapseResult removed_cubes");
  for (const std::uint8_t reason : vector_of<std::uint8_t>(items[4], "CollapseResult cube_reasons")) {
    if (reason > static_cast<std::uint8_t>(CubeReason::kRemovedRim)) {
      throw py::value_error("CollapseResult: the pickled state holds an unknown cube reason " + std::to_string(reason));
    }
    r.cube_reasons.push_back(static_cast<CubeReason>(reason));
  }
  r.num_points = items[5].cast<std::size_t>();
  r.num_used = items[6].cast<std::size_t>();
  r.num_cropped = items[7].cast<std::size_t>();
  r.num_dropped_non_finite = items[8].cast<std::size_t>();
  r.num_overhang = items[9].cast<std::size_t>();
  const int storage = items[10].cast<int>();
  if (r.overhang.size() != r.num_points ||
      (!r.cube_reasons.empty() && r.cube_reasons.size() != r.occupied_cubes.size()) || storage < 0 ||
      storage > static_cast<int>(CubeStorage::kSparse)) {
    throw py::value_error("CollapseResult: the pickled state's parts do not belong together");
  }
  r.storage_used = static_cast<CubeStorage>(storage);
  return r;
}

}  // namespace

void bind_collapse(py::module_& m) {
  py::class_<CubeGrid>(m, "CubeGrid", "CBC grid geometry ([CBC] eqs. (1)-(9)); cube (0,0,0) is centred on min_corner.")
      .def(py::init<>())
      .def_readonly("min_corner", &CubeGrid::min_corner, "(3,) float64: (xmin, ymin, zmin) [m]")
      .def_readonly("edge", &CubeGrid::edge_m, "cube edge E [m]")
      .def_readonly("ixmax", &CubeGrid::ixmax, "cubes along x")
      .def_readonly("iymax", &CubeGrid::iymax, "cubes along y")
      .def_readonly("izmax", &CubeGrid::izmax, "cubes along z")
      .def_property_readonly("num_cubes", &CubeGrid::num_cubes)
      .def_property_readonly("num_columns", &CubeGrid::num_columns)
      .def(
          "coordinates",
          [](const CubeGrid& grid, const py::array_t<std::int64_t, py::array::c_style | py::array::forcecast>& index) {
            auto in = index.unchecked<1>();
            py::array_t<std::int64_t> out({in.shape(0), py::ssize_t{3}});
            auto o = out.mutable_unchecked<2>();
            const std::int64_t cubes = grid.num_cubes();
            for (py::ssize_t i = 0; i < in.shape(0); ++i) {
              if (in(i) < 0 || in(i) >= cubes) throw py::index_error("cube index out of the grid");
              const CubeCoordinates c = grid.coordinates(in(i));
              o(i, 0) = c.x();
              o(i, 1) = c.y();
              o(i, 2) = c.z();
            }
            return out;
          },
          py::arg("index"), "(K,) int64 cube indices I -> (K, 3) int64 (ix, iy, iz), [CBC] eqs. (7)-(9)")
      .def(
          "centers",
          [](const CubeGrid& grid, const py::array_t<std::int64_t, py::array::c_style | py::array::forcecast>& index) {
            auto in = index.unchecked<1>();
            py::array_t<double> out({in.shape(0), py::ssize_t{3}});
            auto o = out.mutable_unchecked<2>();
            const std::int64_t cubes = grid.num_cubes();
            for (py::ssize_t i = 0; i < in.shape(0); ++i) {
              if (in(i) < 0 || in(i) >= cubes) throw py::index_error("cube index out of the grid");
              const Eigen::Vector3d c = grid.center(in(i));
              for (int a = 0; a < 3; ++a) o(i, a) = c[a];
            }
            return out;
          },
          py::arg("index"), "(K,) int64 cube indices I -> (K, 3) float64 cube centres [m]")
      .def(pickle_by_fields<CubeGrid>("CubeGrid",
                                      [](auto& grid, auto&& f) {
                                        f("min_corner", grid.min_corner);
                                        f("edge", grid.edge_m);
                                        f("ixmax", grid.ixmax);
                                        f("iymax", grid.iymax);
                                        f("izmax", grid.izmax);
                                      }))
      .def("__repr__", [](const CubeGrid& grid) {
        std::ostringstream text;
        text << "CubeGrid(edge=" << grid.edge_m << ", ixmax=" << grid.ixmax << ", iymax=" << grid.iymax
             << ", izmax=" << grid.izmax << ", min_corner=[" << grid.min_corner.transpose() << "])";
        return text.str();
      });

  py::enum_<CubeStorage>(m, "CubeStorage")
      .value("auto", CubeStorage::kAuto)
      .value("dense", CubeStorage::kDense)
      .value("sparse", CubeStorage::kSparse);

  py::class_<CropBox>(m, "CropBox")
      .def(py::init([](const Eigen::Vector3d& min, const Eigen::Vector3d& max) { return CropBox{min, max}; }),
           py::arg("min"), py::arg("max"))
      .def_readwrite("min", &CropBox::min)
      .def_readwrite("max", &CropBox::max);

  py::enum_<CollapseMethod>(m, "CollapseMethod")
      .value("paper", CollapseMethod::kPaper)
      .value("shadow_aware", CollapseMethod::kShadowAware);

  py::enum_<CubeReason>(m, "CubeReason",
                        "Why the shadow-aware rule kept or removed a cube (terracube::CubeReason, uint8)")
      .value("supported", CubeReason::kSupported)
      .value("below_ground", CubeReason::kBelowGround)
      .value("no_ground_estimate", CubeReason::kNoGroundEstimate)
      .value("shadowed", CubeReason::kShadowed)
      .value("removed_above_kept", CubeReason::kRemovedAboveKept)
      .value("removed_free_below", CubeReason::kRemovedFreeBelow)
      .value("thin", CubeReason::kThin)
      .value("removed_rim", CubeReason::kRemovedRim)
      .value("not_used", CubeReason::kNotUsed);

  py::class_<ShadowAwareParams>(m, "ShadowAwareParams")
      .def(py::init<>())
      .def("check", &check_shadow_aware_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_readwrite("sensor_origin", &ShadowAwareParams::sensor_origin)
      .def_readwrite("ground_radius_m", &ShadowAwareParams::ground_radius_m)
      .def_readwrite("ground_support", &ShadowAwareParams::ground_support)
      .def_readwrite("hidden_ground_margin_m", &ShadowAwareParams::hidden_ground_margin_m)
      .def_readwrite("free_margin_m", &ShadowAwareParams::free_margin_m)
      .def_readwrite("min_bottom_neighbours", &ShadowAwareParams::min_bottom_neighbours)
      .def_readwrite("bottom_window", &ShadowAwareParams::bottom_window)
      .def_readwrite("remove_rims", &ShadowAwareParams::remove_rims)
      .def_readwrite("azimuth_bins", &ShadowAwareParams::azimuth_bins)
      .def_readwrite("no_return_range_m", &ShadowAwareParams::no_return_range_m);

  py::class_<CollapseParams>(m, "CollapseParams")
      .def(py::init<>())
      .def("check", &check_collapse_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_readwrite("edge_m", &CollapseParams::edge_m)
      .def_readwrite("sigma", &CollapseParams::sigma)
      .def_readwrite("transform", &CollapseParams::transform)
      .def_readwrite("crop", &CollapseParams::crop)
      .def_readwrite("drop_non_finite", &CollapseParams::drop_non_finite)
      .def_readwrite("storage", &CollapseParams::storage)
      .def_readwrite("dense_budget_bytes", &CollapseParams::dense_budget_bytes)
      .def_readwrite("num_threads", &CollapseParams::num_threads)
      .def_readwrite("method", &CollapseParams::method)
      .def_readwrite("shadow_aware", &CollapseParams::shadow_aware);

  py::class_<CollapseResult>(
      m, "CollapseResult", "Result of collapse_overhangs; arrays are views into it. Pickles whole (its arrays copied).")
      .def_readonly("grid", &CollapseResult::grid)
      .def_property_readonly(
          "overhang",
          [](const py::object& self) { return bool_view_of(self.cast<const CollapseResult&>().overhang, self); },
          "(N,) bool: the point lies in a collapsed cube (input order)")
      .def_property_readonly(
          "occupied_cubes",
          [](const py::object& self) { return view_of(self.cast<const CollapseResult&>().occupied_cubes, self); },
          "(K,) int64: L, indices I of occupied cubes, sorted")
      .def_property_readonly(
          "removed_cubes",
          [](const py::object& self) { return view_of(self.cast<const CollapseResult&>().removed_cubes, self); },
          "(R,) int64: R, indices I of collapsed cubes, sorted")
      .def_property_readonly(
          "cube_reasons",
          [](const py::object& self) { return reasons_view(self.cast<const CollapseResult&>().cube_reasons, self); },
          "(K,) uint8: CubeReason per cube of occupied_cubes (method shadow_aware; empty for paper)")
      .def_readonly("num_points", &CollapseResult::num_points)
      .def_readonly("num_used", &CollapseResult::num_used)
      .def_readonly("num_cropped", &CollapseResult::num_cropped)
      .def_readonly("num_dropped_non_finite", &CollapseResult::num_dropped_non_finite)
      .def_readonly("num_overhang", &CollapseResult::num_overhang)
      .def_property_readonly("storage_used",
                             [](const CollapseResult& result) { return storage_name(result.storage_used); })
      .def(py::pickle(&result_state, &result_from_state))
      .def("__repr__", [](const CollapseResult& result) {
        std::ostringstream text;
        text << "CollapseResult(points=" << result.num_points << ", overhang=" << result.num_overhang
             << ", occupied_cubes=" << result.occupied_cubes.size() << ", removed_cubes=" << result.removed_cubes.size()
             << ", cropped=" << result.num_cropped << ", dropped_non_finite=" << result.num_dropped_non_finite
             << ", grid=" << result.grid.ixmax << "x" << result.grid.iymax << "x" << result.grid.izmax << " @ "
             << result.grid.edge_m << " m, storage=" << storage_name(result.storage_used) << ")";
        return text.str();
      });

  m.def(
      "collapse_overhangs",
      [](const py::array& points, const CollapseParams& params, const py::object& no_returns) {
        py::object keep;
        const PointsView<double> beams = directions_view(no_returns, "no_returns", keep);
        return with_points(points, "points", [&](const auto& view) {
          py::gil_scoped_release release;
          return collapse_overhangs(view, params, beams);
        });
      },
      py::arg("points"), py::arg("params"), py::arg("no_returns") = py::none());
  m.def(
      "point_reasons",
      [](const py::array& points, const CollapseParams& params, const CollapseResult& result) {
        std::vector<CubeReason> reasons = with_points(points, "points", [&](const auto& view) {
          py::gil_scoped_release release;
          return point_reasons(view, params, result);
        });
        py::array_t<std::uint8_t> out(static_cast<py::ssize_t>(reasons.size()));
        std::copy_n(reinterpret_cast<const std::uint8_t*>(reasons.data()), reasons.size(), out.mutable_data());
        return out;
      },
      py::arg("points"), py::arg("params"), py::arg("result"),
      "(N,) uint8: the CubeReason of each point's cube (not_used: it took no part)");
  m.def(
      "cube_reason_name", [](int reason) { return cube_reason_name(static_cast<CubeReason>(reason)); },
      py::arg("reason"));
  m.def("sigma_from_robot_height", &sigma_from_robot_height, py::arg("robot_height"), py::arg("edge"));
  m.def("leveling_transform", &leveling_transform, py::arg("roll"), py::arg("pitch"));
  m.def(
      "attitude_from_gravity",
      [](const Eigen::Vector3d& up) {
        const Attitude attitude = attitude_from_gravity(up);
        return py::make_tuple(attitude.roll_rad, attitude.pitch_rad);
      },
      py::arg("up"));
}

}  // namespace terracube::python
