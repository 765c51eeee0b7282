// Bindings for icp.hpp (and pcl_baseline.hpp when the PCL baseline was built).
#include <pybind11/eigen.h>
#include <pybind11/stl.h>
#include <terracube/icp.hpp>

#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "pickle.hpp"
#include "points.hpp"

#ifdef TERRACUBE_HAVE_PCL
#include <terracube/pcl_baseline.hpp>
#endif

namespace terracube::python {

namespace {

/// (N, 3) points and an optional (N,) uint8 class array as ClassifiedPoints (one copy).
ClassifiedPoints classified(const py::array& points, const std::optional<py::array>& classes, const char* name) {
  ClassifiedPoints set;
  with_points(points, name, [&](const auto& view) {
    set.points.reserve(view.size);
    for (std::size_t k = 0; k < view.size; ++k) {
      const auto* row = view.data + static_cast<std::ptrdiff_t>(k) * view.row_stride;
      set.points.emplace_back(static_cast<double>(row[0]), static_cast<double>(row[view.column_stride]),
                              static_cast<double>(row[2 * view.column_stride]));
    }
    return 0;
  });
  if (classes) {
    const auto labels = py::array_t<std::uint8_t, py::array::c_style | py::array::forcecast>::ensure(*classes);
    if (!labels || labels.ndim() != 1 || static_cast<std::size_t>(labels.shape(0)) != set.size()) {
      throw py::value_error(std::string(name) + " classes must be an (N,) uint8 array with one class per point");
    }
    set.classes.assign(labels.data(), labels.data() + set.size());
  } else {
    set.classes.assign(set.size(), std::uint8_t{0});
  }
  return set;
}

std::vector<Eigen::Vector3d> plain_points(const py::array& points, const char* name) {
  return classified(points, std::nullopt, name).points;
}

/// The fields of a RegistrationResult by their Python names (its pickled state).
constexpr auto kRegistrationFields = [](auto& r, auto&& f) {
  f("transform", r.transform);
  f("icp_start", r.icp_start);
  f("converged", r.converged);
  f("reason", r.reason);
  f("iterations", r.iterations);
  f("passes", r.passes);
  f("extrapolations", r.extrapolations);
  f("rmse", r.rmse_m);
  f("correspondence_distance", r.correspondence_distance_m);
  f("num_correspondences", r.num_correspondences);
  f("correspondences_per_class", r.correspondences_per_class);
  f("normal_matrix", r.normal_matrix);
  f("eigenvalues", r.eigenvalues);
  f("constraint_matrix", r.constraint_matrix);
  f("constraint_eigenvalues", r.constraint_eigenvalues);
  f("constraint_eigenvectors", r.constraint_eigenvectors);
  f("overlap", r.overlap);
  f("chance_overlap", r.chance_overlap);
  f("inlier_share_per_class", r.inlier_share_per_class);
  f("held", r.held);
  f("held_directions", r.held_directions);
  f("trusted", r.trusted);
  f("verdict", r.verdict);
};

}  // namespace

void bind_icp(py::module_& m) {
  py::enum_<Pairing>(m, "Pairing")
      .value("source_to_target", Pairing::kSourceToTarget)
      .value("target_to_source", Pairing::kTargetToSource);
  py::enum_<StopReason>(m, "StopReason")
      .value("converged", StopReason::kConverged)
      .value("error_below_threshold", StopReason::kErrorBelowThreshold)
      .value("max_iterations", StopReason::kMaxIterations)
      .value("too_few_correspondences", StopReason::kTooFewCorrespondences)
      .value("no_common_class", StopReason::kNoCommonClass)
      .value("degenerate", StopReason::kDegenerate);

  py::class_<CorrelativeSearchParams>(m, "CorrelativeSearchParams")
      .def(py::init<>())
      .def_readwrite("window_m", &CorrelativeSearchParams::window_m)
      .def_readwrite("cell_m", &CorrelativeSearchParams::cell_m)
      .def_readwrite("step_cells", &CorrelativeSearchParams::step_cells)
      .def_readwrite("yaw_window_rad", &CorrelativeSearchParams::yaw_window_rad)
      .def_readwrite("yaw_hypotheses", &CorrelativeSearchParams::yaw_hypotheses)
      .def_readwrite("refine", &CorrelativeSearchParams::refine)
      .def_readwrite("tie_tolerance", &CorrelativeSearchParams::tie_tolerance);

  py::class_<RegistrationParams>(m, "RegistrationParams")
      .def(py::init<>())
      .def("check", &check_registration_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_static("paper_icp", &RegistrationParams::paper_icp,
                  "the paper's plain weighted ICP: no correlative search, extrapolation or coarse-to-fine")
      .def_readwrite("correlative_search", &RegistrationParams::correlative_search)
      .def_readwrite("search", &RegistrationParams::search)
      .def_readwrite("use_classes", &RegistrationParams::use_classes)
      .def_readwrite("class_weights", &RegistrationParams::class_weights)
      .def_readwrite("max_correspondence_distance_m", &RegistrationParams::max_correspondence_distance_m)
      .def_readwrite("min_correspondence_distance_m", &RegistrationParams::min_correspondence_distance_m)
      .def_readwrite("correspondence_distance_decay", &RegistrationParams::correspondence_distance_decay)
      .def_readwrite("max_iterations", &RegistrationParams::max_iterations)
      .def_readwrite("rotation_tolerance_rad", &RegistrationParams::rotation_tolerance_rad)
      .def_readwrite("translation_tolerance_m", &RegistrationParams::translation_tolerance_m)
      .def_readwrite("error_threshold_m", &RegistrationParams::error_threshold_m)
      .def_readwrite("min_correspondences", &RegistrationParams::min_correspondences)
      .def_readwrite("degeneracy_threshold", &RegistrationParams::degeneracy_threshold)
      .def_readwrite("extrapolate", &RegistrationParams::extrapolate)
      .def_readwrite("pairing", &RegistrationParams::pairing)
      .def_readwrite("coarse_subsample", &RegistrationParams::coarse_subsample)
      .def_readwrite("coarse_until_motion_m", &RegistrationParams::coarse_until_motion_m)
      .def_readwrite("ground_weight", &RegistrationParams::ground_weight)
      .def_readwrite("ground_cell_m", &RegistrationParams::ground_cell_m)
      .def_readwrite("structure_radius_m", &RegistrationParams::structure_radius_m)
      .def_readwrite("trust_min_overlap", &RegistrationParams::trust_min_overlap)
      .def_readwrite("trust_min_contrast", &RegistrationParams::trust_min_contrast)
      .def_readwrite("trust_max_rmse_m", &RegistrationParams::trust_max_rmse_m)
      .def_readwrite("trust_min_held", &RegistrationParams::trust_min_held);

  py::class_<RegistrationResult>(m, "RegistrationResult")
      .def_readonly("transform", &RegistrationResult::transform, "(4, 4) source -> target")
      .def_readonly("icp_start", &RegistrationResult::icp_start,
                    "(4, 4) where the ICP started: initial, or the correlative search's best hypothesis")
      .def_readonly("converged", &RegistrationResult::converged)
      .def_readonly("reason", &RegistrationResult::reason)
      .def_readonly("iterations", &RegistrationResult::iterations)
      .def_readonly("passes", &RegistrationResult::passes,
                    "correspondence passes: one per iteration, one more per extrapolation tried")
      .def_readonly("extrapolations", &RegistrationResult::extrapolations, "extrapolated jumps kept by the guard")
      .def_readonly("rmse", &RegistrationResult::rmse_m, "weighted RMSE of the final correspondences [m]")
      .def_readonly("correspondence_distance", &RegistrationResult::correspondence_distance_m)
      .def_readonly("num_correspondences", &RegistrationResult::num_correspondences)
      .def_readonly("correspondences_per_class", &RegistrationResult::correspondences_per_class)
      .def_readonly("normal_matrix", &RegistrationResult::normal_matrix, "(6, 6) H of eq. (A6)")
      .def_readonly("eigenvalues", &RegistrationResult::eigenvalues, "(6,) eigenvalues of H, ascending")
      .def_readonly("constraint_matrix", &RegistrationResult::constraint_matrix,
                    "(6, 6) what the geometry constrains (structure_radius > 0)")
      .def_readonly("constraint_eigenvalues", &RegistrationResult::constraint_eigenvalues,
                    "(6,) eigenvalues of constraint_matrix, ascending")
      .def_readonly("constraint_eigenvectors", &RegistrationResult::constraint_eigenvectors,
                    "(6, 6) unit eigenvectors of constraint_matrix, as columns")
      .def_readonly("overlap", &RegistrationResult::overlap,
                    "share of the source's object cells with a partner within the last distance limit")
      .def_readonly("chance_overlap", &RegistrationResult::chance_overlap,
                    "the overlap at the result moved by 1 m along +-x or +-y, the least: coincidence alone")
      .def_readonly("inlier_share_per_class", &RegistrationResult::inlier_share_per_class,
                    "(6,) per source class: share of its points with a partner")
      .def_readonly("held", &RegistrationResult::held,
                    "(6,) how firmly each motion is held, per unit of the class pairs' weight, ascending (0 none, 1 "
                    "every pair)")
      .def_readonly("held_directions", &RegistrationResult::held_directions,
                    "(6, 6) unit eigenvectors of held as columns (rotation x rms radius, translation)")
      .def_readonly("trusted", &RegistrationResult::trusted, "every trust threshold of RegistrationParams met")
      .def_readonly("verdict", &RegistrationResult::verdict, "why the result is (not) trusted, in plain words")
      .def(pickle_by_fields<RegistrationResult>("RegistrationResult", kRegistrationFields))
      .def("__repr__", [](const RegistrationResult& r) {
        std::ostringstream text;
        text << "RegistrationResult(reason=" << to_string(r.reason) << ", iterations=" << r.iterations
             << ", passes=" << r.passes << ", rmse=" << r.rmse_m << " m, correspondences=" << r.num_correspondences
             << ", overlap=" << r.overlap << ", trusted=" << (r.trusted ? "True" : "False") << ")";
        return text.str();
      });

  m.def(
      "register_points",
      [](const py::array& source, const std::optional<py::array>& source_classes, const py::array& target,
         const std::optional<py::array>& target_classes, const Eigen::Matrix4d& initial,
         const RegistrationParams& params) {
        const ClassifiedPoints s = classified(source, source_classes, "source");
        const ClassifiedPoints t = classified(target, target_classes, "target");
        py::gil_scoped_release release;
        return register_points(s, t, initial, params);
      },
      py::arg("source"), py::arg("source_classes"), py::arg("target"), py::arg("target_classes"), py::arg("initial"),
      py::arg("params"));
  m.def(
      "register_maps",
      [](const ElevationMap& source, const ElevationMap& target, const Eigen::Matrix4d& initial,
         const RegistrationParams& params) {
        py::gil_scoped_release release;
        return register_maps(source, target, initial, params);
      },
      py::arg("source"), py::arg("target"), py::arg("initial"), py::arg("params"));
  py::class_<CorrelativeSearchResult>(m, "CorrelativeSearchResult")
      .def_readonly("transform", &CorrelativeSearchResult::transform, "(4, 4) the best hypothesis, source -> target")
      .def_readonly("score", &CorrelativeSearchResult::score, "source points on occupied target cells")
      .def_readonly("points", &CorrelativeSearchResult::points, "source points that took part (non-ground)")
      .def(pickle_by_fields<CorrelativeSearchResult>("CorrelativeSearchResult",
                                                     [](auto& r, auto&& f) {
                                                       f("transform", r.transform);
                                                       f("score", r.score);
                                                       f("points", r.points);
                                                     }))
      .def("__repr__", [](const CorrelativeSearchResult& r) {
        return "CorrelativeSearchResult(score=" + std::to_string(r.score) + ", points=" + std::to_string(r.points) +
               ")";
      });
  m.def(
      "correlative_search",
      [](const py::array& source, const py::array& source_classes, const py::array& target,
         const py::array& target_classes, const Eigen::Matrix4d& guess, const CorrelativeSearchParams& params) {
        const ClassifiedPoints s = classified(source, source_classes, "source");
        const ClassifiedPoints t = classified(target, target_classes, "target");
        py::gil_scoped_release release;
        return correlative_search(s, t, guess, params);
      },
      py::arg("source"), py::arg("source_classes"), py::arg("target"), py::arg("target_classes"), py::arg("guess"),
      py::arg("params"));
  m.def(
      "points_of_map",
      [](const ElevationMap& map) {
        ClassifiedPoints set;
        {
          py::gil_scoped_release release;
          set = points_of_map(map);
        }
        py::array_t<double> points({static_cast<py::ssize_t>(set.size()), py::ssize_t{3}});
        auto out = points.mutable_unchecked<2>();
        for (std::size_t k = 0; k < set.size(); ++k) {
          for (int axis = 0; axis < 3; ++axis) out(static_cast<py::ssize_t>(k), axis) = set.points[k][axis];
        }
        py::array_t<std::uint8_t> classes(static_cast<py::ssize_t>(set.size()), set.classes.data());
        return py::make_tuple(points, classes);
      },
      py::arg("map"), "((N, 3) float64 cell centres at max, (N,) uint8 classes)");

#ifdef TERRACUBE_HAVE_PCL
  m.attr("has_pcl") = true;
  py::class_<PclIcpParams>(m, "PclIcpParams")
      .def(py::init<>())
      .def("check", &check_pcl_icp_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_readwrite("max_correspondence_distance_m", &PclIcpParams::max_correspondence_distance_m)
      .def_readwrite("max_iterations", &PclIcpParams::max_iterations)
      .def_readwrite("transformation_epsilon", &PclIcpParams::transformation_epsilon)
      .def_readwrite("rotation_epsilon", &PclIcpParams::rotation_epsilon)
      .def_readwrite("euclidean_fitness_epsilon", &PclIcpParams::euclidean_fitness_epsilon)
      .def_readwrite("relative_mse_epsilon", &PclIcpParams::relative_mse_epsilon);
  py::class_<PclIcpResult>(m, "PclIcpResult")
      .def_readonly("transform", &PclIcpResult::transform)
      .def_readonly("converged", &PclIcpResult::converged)
      .def_readonly("fitness", &PclIcpResult::fitness_m2, "mean squared pair distance [m^2]")
      .def_readonly("iterations", &PclIcpResult::iterations)
      .def(pickle_by_fields<PclIcpResult>("PclIcpResult",
                                          [](auto& r, auto&& f) {
                                            f("transform", r.transform);
                                            f("converged", r.converged);
                                            f("fitness", r.fitness_m2);
                                            f("iterations", r.iterations);
                                          }))
      .def("__repr__", [](const PclIcpResult& r) {
        std::ostringstream text;
        text << "PclIcpResult(converged=" << (r.converged ? "True" : "False") << ", iterations=" << r.iterations
             << ", fitness=" << r.fitness_m2 << " m^2)";
        return text.str();
      });
  // pcl_icp and pcl_gicp: the same arguments and result.
  using PclMethod = PclIcpResult (*)(const std::vector<Eigen::Vector3d>&, const std::vector<Eigen::Vector3d>&,
                                     const Eigen::Matrix4d&, const PclIcpParams&);
  for (const auto& [name, method] : {std::pair<const char*, PclMethod>{"pcl_icp", &pcl_icp},
                                     std::pair<const char*, PclMethod>{"pcl_gicp", &pcl_gicp}}) {
    m.def(
        name,
        [method = method](const py::array& source, const py::array& target, const Eigen::Matrix4d& initial,
                          const PclIcpParams& params) {
          const std::vector<Eigen::Vector3d> s = plain_points(source, "source");
          const std::vector<Eigen::Vector3d> t = plain_points(target, "target");
          py::gil_scoped_release release;
          return method(s, t, initial, params);
        },
        py::arg("source"), py::arg("target"), py::arg("initial"), py::arg("params"));
  }
#else
  m.attr("has_pcl") = false;
#endif
}

}  // namespace terracube::python
