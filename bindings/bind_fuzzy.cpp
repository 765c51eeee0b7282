// Bindings for fuzzy.hpp.
#include <pybind11/eigen.h>
#include <pybind11/stl.h>
#include <terracube/fuzzy.hpp>

#include <sstream>

#include "points.hpp"

namespace terracube::python {

void bind_fuzzy(py::module_& m) {
  py::enum_<MembershipFamily>(m, "MembershipFamily")
      .value("triangular", MembershipFamily::kTriangularPartition)
      .value("gaussian", MembershipFamily::kGaussian);
  py::enum_<StepRule>(m, "StepRule").value("guarded", StepRule::kGuarded).value("jang", StepRule::kJang);

  py::class_<FuzzyParams>(m, "FuzzyParams")
      .def(py::init<>())
      .def("check", &check_fuzzy_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_readwrite("rules_x", &FuzzyParams::rules_x)
      .def_readwrite("rules_y", &FuzzyParams::rules_y)
      .def_readwrite("membership", &FuzzyParams::membership)
      .def_readwrite("gaussian_width", &FuzzyParams::gaussian_width)
      .def_readwrite("epochs", &FuzzyParams::epochs)
      .def_readwrite("step_rule", &FuzzyParams::step_rule)
      .def_readwrite("learning_rate", &FuzzyParams::learning_rate)
      .def_readwrite("ridge", &FuzzyParams::ridge)
      .def_readwrite("smoothness", &FuzzyParams::smoothness)
      .def(
          "set_extent",
          [](FuzzyParams& p, double x0, double y0, double x1, double y1) { p.extent = Extent2d{{x0, y0}, {x1, y1}}; },
          py::arg("x_min"), py::arg("y_min"), py::arg("x_max"), py::arg("y_max"))
      .def("clear_extent", [](FuzzyParams& p) { p.extent.reset(); })
      .def_property_readonly("has_extent", [](const FuzzyParams& p) { return p.extent.has_value(); })
      .def_readwrite("min_points_per_rule", &FuzzyParams::min_points_per_rule)
      .def_readwrite("min_confidence", &FuzzyParams::min_confidence);

  using RowsXY = Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::RowMajor>>;
  py::class_<FuzzyElevationMap>(m, "FuzzyElevationMap")
      .def(py::init([](const FuzzyParams& params, Eigen::VectorXd centers_x, Eigen::VectorXd centers_y,
                       Eigen::MatrixXd consequents, Eigen::MatrixXd rule_support, std::vector<double> rmse_history,
                       std::size_t num_training_points) {
             return FuzzyElevationMap(params, std::move(centers_x), std::move(centers_y), std::move(consequents),
                                      std::move(rule_support), std::move(rmse_history), num_training_points);
           }),
           py::arg("params"), py::arg("centers_x"), py::arg("centers_y"), py::arg("consequents"),
           py::arg("rule_support"), py::arg("rmse_history") = std::vector<double>{}, py::arg("num_training_points") = 0)
      .def_property_readonly("params", &FuzzyElevationMap::params)
      .def_property_readonly(
          "extent",
          [](const FuzzyElevationMap& f) {
            Eigen::Matrix2d e;
            e.row(0) = f.extent().min_m;
            e.row(1) = f.extent().max_m;
            return e;
          },
          "((x_min, y_min), (x_max, y_max)) [m]")
      .def_property_readonly("num_rules", &FuzzyElevationMap::num_rules)
      .def_property_readonly("num_parameters", &FuzzyElevationMap::num_parameters)
      .def_property_readonly("centers_x", &FuzzyElevationMap::centers_x)
      .def_property_readonly("centers_y", &FuzzyElevationMap::centers_y)
      .def_property_readonly("consequents", &FuzzyElevationMap::consequents)
      .def_property_readonly("rule_support", &FuzzyElevationMap::rule_support)
      .def_property_readonly("rmse_history", &FuzzyElevationMap::rmse_history)
      .def_property_readonly("num_training_points", &FuzzyElevationMap::num_training_points)
      .def_property_readonly("gaussian_sigma", &FuzzyElevationMap::gaussian_sigma_m)
      .def(
          "evaluate",
          [](const FuzzyElevationMap& f, const RowsXY& xy) {
            py::gil_scoped_release release;
            return f.evaluate(xy);
          },
          py::arg("xy"))
      .def(
          "confidence",
          [](const FuzzyElevationMap& f, const RowsXY& xy) {
            py::gil_scoped_release release;
            return f.confidence(xy);
          },
          py::arg("xy"))
      .def("to_layer", &FuzzyElevationMap::to_layer, py::arg("map"), py::arg("min_confidence"), py::arg("name"),
           py::call_guard<py::gil_scoped_release>());

  m.def(
      "fit_fuzzy_elevation_map",
      [](const py::array& points, const FuzzyParams& params,
         const std::optional<py::array_t<bool, py::array::c_style | py::array::forcecast>>& use) {
        return with_points(points, "points", [&](const auto& view) {
          std::vector<std::uint8_t> flags;
          if (use) {
            if (use->ndim() != 1 || static_cast<std::size_t>(use->shape(0)) != view.size) {
              throw py::value_error("use must be an (N,) bool array with one flag per point");
            }
            flags.assign(use->data(), use->data() + view.size);
          }
          py::gil_scoped_release release;
          return fit_fuzzy_elevation_map(view, params, use ? &flags : nullptr);
        });
      },
      py::arg("points"), py::arg("params"), py::arg("use") = py::none());
}

}  // namespace terracube::python
