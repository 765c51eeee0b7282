// Bindings for evaluation.hpp (trajectory errors and the DSM region-layout comparison).
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>
#include <terracube/evaluation.hpp>

#include <sstream>
#include <string>
#include <vector>

#include "pickle.hpp"
#include "points.hpp"

namespace terracube::python {

/// A (K, 4, 4) numeric array as K poses (one copy). Shared with bind_pose_graph.cpp.
std::vector<Eigen::Matrix4d> poses_from_array(const py::array& array, const char* name) {
  const auto values = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(array);
  if (!values) throw py::type_error(std::string(name) + " must be a numeric (K, 4, 4) array of poses");
  if (values.ndim() != 3 || values.shape(1) != 4 || values.shape(2) != 4) {
    throw py::value_error(std::string(name) + " must be a (K, 4, 4) array of poses, got shape " + shape_string(values));
  }
  std::vector<Eigen::Matrix4d> poses(static_cast<std::size_t>(values.shape(0)));
  const double* data = values.data();
  for (std::size_t k = 0; k < poses.size(); ++k) {
    poses[k] = Eigen::Map<const Eigen::Matrix<double, 4, 4, Eigen::RowMajor>>(data + 16 * k);
  }
  return poses;
}

/// K poses as a new (K, 4, 4) float64 array. Shared with bind_pose_graph.cpp.
py::array array_of_poses(const std::vector<Eigen::Matrix4d>& poses) {
  py::array_t<double> out({static_cast<py::ssize_t>(poses.size()), py::ssize_t{4}, py::ssize_t{4}});
  double* data = out.mutable_data();
  for (std::size_t k = 0; k < poses.size(); ++k) {
    Eigen::Map<Eigen::Matrix<double, 4, 4, Eigen::RowMajor>>(data + 16 * k) = poses[k];
  }
  return out;
}

namespace {

std::vector<Eigen::VectorXd> centres_from_array(const py::array& array, const char* name) {
  const auto values = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(array);
  if (!values) throw py::type_error(std::string(name) + " must be a numeric (K, 2) or (K, 3) array");
  if (values.ndim() != 2 || (values.shape(1) != 2 && values.shape(1) != 3)) {
    throw py::value_error(std::string(name) + " must be a (K, 2) or (K, 3) array of region centres, got shape " +
                          shape_string(values));
  }
  const auto dimension = static_cast<Eigen::Index>(values.shape(1));
  std::vector<Eigen::VectorXd> centres;
  for (py::ssize_t k = 0; k < values.shape(0); ++k) {
    centres.emplace_back(Eigen::Map<const Eigen::VectorXd>(values.data() + k * dimension, dimension));
  }
  return centres;
}

py::array doubles(const std::vector<double>& values) {
  return py::array_t<double>(static_cast<py::ssize_t>(values.size()), values.data());
}

std::string statistics_text(const ErrorStatistics& s, const char* unit) {
  std::ostringstream text;
  text << "rmse=" << s.rmse << unit << ", mean=" << s.mean << unit << ", median=" << s.median << unit
       << ", max=" << s.max << unit;
  return text.str();
}

}  // namespace

void bind_evaluation(py::module_& m) {
  py::enum_<TrajectoryAlignment>(m, "TrajectoryAlignment")
      .value("none", TrajectoryAlignment::kNone)
      .value("first_pose", TrajectoryAlignment::kFirstPose)
      .value("rigid", TrajectoryAlignment::kRigid);
  py::enum_<RegionRelations>(m, "RegionRelations")
      .value("consecutive", RegionRelations::kConsecutive)
      .value("all_pairs", RegionRelations::kAllPairs);

  py::class_<ErrorStatistics>(m, "ErrorStatistics")
      .def_readonly("rmse", &ErrorStatistics::rmse)
      .def_readonly("mean", &ErrorStatistics::mean)
      .def_readonly("median", &ErrorStatistics::median)
      .def_readonly("max", &ErrorStatistics::max)
      .def_readonly("count", &ErrorStatistics::count)
      .def(pickle_by_fields<ErrorStatistics>("ErrorStatistics",
                                             [](auto& r, auto&& f) {
                                               f("rmse", r.rmse);
                                               f("mean", r.mean);
                                               f("median", r.median);
                                               f("max", r.max);
                                               f("count", r.count);
                                             }))
      .def("__repr__", [](const ErrorStatistics& s) {
        return "ErrorStatistics(" + statistics_text(s, "") + ", count=" + std::to_string(s.count) + ")";
      });

  py::class_<AbsoluteTrajectoryError>(m, "AbsoluteTrajectoryError")
      .def_readonly("alignment", &AbsoluteTrajectoryError::alignment, "(4, 4) applied to the estimate")
      .def_property_readonly(
          "translation_errors", [](const AbsoluteTrajectoryError& r) { return doubles(r.translation_errors_m); },
          "(K,) [m]")
      .def_property_readonly(
          "rotation_errors", [](const AbsoluteTrajectoryError& r) { return doubles(r.rotation_errors_deg); },
          "(K,) [deg]")
      .def_readonly("translation", &AbsoluteTrajectoryError::translation, "statistics [m]")
      .def_readonly("rotation", &AbsoluteTrajectoryError::rotation, "statistics [deg]")
      .def(pickle_by_fields<AbsoluteTrajectoryError>("AbsoluteTrajectoryError",
                                                     [](auto& r, auto&& f) {
                                                       f("alignment", r.alignment);
                                                       f("translation_errors", r.translation_errors_m);
                                                       f("rotation_errors", r.rotation_errors_deg);
                                                       f("translation", r.translation);
                                                       f("rotation", r.rotation);
                                                     }))
      .def("__repr__", [](const AbsoluteTrajectoryError& r) {
        return "AbsoluteTrajectoryError(poses=" + std::to_string(r.translation.count) +
               ", translation: " + statistics_text(r.translation, " m") +
               "; rotation: " + statistics_text(r.rotation, " deg") + ")";
      });

  py::class_<RelativePoseErrorParams>(m, "RelativePoseErrorParams")
      .def(py::init<>())
      .def_readwrite("lengths_m", &RelativePoseErrorParams::lengths_m)
      .def_readwrite("step_frames", &RelativePoseErrorParams::step_frames);

  py::class_<PoseSegmentError>(m, "PoseSegmentError")
      .def_readonly("first_frame", &PoseSegmentError::first_frame)
      .def_readonly("last_frame", &PoseSegmentError::last_frame)
      .def_readonly("length", &PoseSegmentError::length_m)
      .def_readonly("translation_percent", &PoseSegmentError::translation_percent)
      .def_readonly("rotation_deg_per_100m", &PoseSegmentError::rotation_deg_per_100m)
      .def(pickle_by_fields<PoseSegmentError>("PoseSegmentError", [](auto& r, auto&& f) {
        f("first_frame", r.first_frame);
        f("last_frame", r.last_frame);
        f("length", r.length_m);
        f("translation_percent", r.translation_percent);
        f("rotation_deg_per_100m", r.rotation_deg_per_100m);
      }));

  py::class_<SegmentLengthError>(m, "SegmentLengthError")
      .def_readonly("length", &SegmentLengthError::length_m)
      .def_readonly("num_segments", &SegmentLengthError::num_segments)
      .def_readonly("translation_percent", &SegmentLengthError::translation_percent)
      .def_readonly("rotation_deg_per_100m", &SegmentLengthError::rotation_deg_per_100m)
      .def(pickle_by_fields<SegmentLengthError>("SegmentLengthError",
                                                [](auto& r, auto&& f) {
                                                  f("length", r.length_m);
                                                  f("num_segments", r.num_segments);
                                                  f("translation_percent", r.translation_percent);
                                                  f("rotation_deg_per_100m", r.rotation_deg_per_100m);
                                                }))
      .def("__repr__", [](const SegmentLengthError& e) {
        std::ostringstream text;
        text << "SegmentLengthError(length=" << e.length_m << " m, segments=" << e.num_segments
             << ", translation=" << e.translation_percent << " %, rotation=" << e.rotation_deg_per_100m
             << " deg/100 m)";
        return text.str();
      });

  py::class_<RelativePoseError>(m, "RelativePoseError")
      .def_readonly("num_segments", &RelativePoseError::num_segments)
      .def_readonly("translation_percent", &RelativePoseError::translation_percent)
      .def_readonly("rotation_deg_per_100m", &RelativePoseError::rotation_deg_per_100m)
      .def_readonly("per_length", &RelativePoseError::per_length)
      .def_readonly("segments", &RelativePoseError::segments)
      .def(pickle_by_fields<RelativePoseError>("RelativePoseError",
                                               [](auto& r, auto&& f) {
                                                 f("num_segments", r.num_segments);
                                                 f("translation_percent", r.translation_percent);
                                                 f("rotation_deg_per_100m", r.rotation_deg_per_100m);
                                                 f("per_length", r.per_length);
                                                 f("segments", r.segments);
                                               }))
      .def("__repr__", [](const RelativePoseError& r) {
        std::ostringstream text;
        text << "RelativePoseError(segments=" << r.num_segments << ", translation=" << r.translation_percent
             << " %, rotation=" << r.rotation_deg_per_100m << " deg/100 m)";
        return text.str();
      });

  py::class_<RegionPairError>(m, "RegionPairError")
      .def_readonly("i", &RegionPairError::i)
      .def_readonly("j", &RegionPairError::j)
      .def_readonly("map_distance", &RegionPairError::map_distance_m)
      .def_readonly("dsm_distance", &RegionPairError::dsm_distance_m)
      .def_readonly("error", &RegionPairError::error_m)
      .def(pickle_by_fields<RegionPairError>("RegionPairError", [](auto& r, auto&& f) {
        f("i", r.i);
        f("j", r.j);
        f("map_distance", r.map_distance_m);
        f("dsm_distance", r.dsm_distance_m);
        f("error", r.error_m);
      }));

  py::class_<RegionTripleError>(m, "RegionTripleError")
      .def_readonly("i", &RegionTripleError::i)
      .def_readonly("j", &RegionTripleError::j)
      .def_readonly("k", &RegionTripleError::k)
      .def_readonly("map_angle", &RegionTripleError::map_angle_deg)
      .def_readonly("dsm_angle", &RegionTripleError::dsm_angle_deg)
      .def_readonly("error", &RegionTripleError::error_deg)
      .def(pickle_by_fields<RegionTripleError>("RegionTripleError", [](auto& r, auto&& f) {
        f("i", r.i);
        f("j", r.j);
        f("k", r.k);
        f("map_angle", r.map_angle_deg);
        f("dsm_angle", r.dsm_angle_deg);
        f("error", r.error_deg);
      }));

  py::class_<RegionLayoutComparison>(m, "RegionLayoutComparison")
      .def_readonly("pairs", &RegionLayoutComparison::pairs)
      .def_readonly("triples", &RegionLayoutComparison::triples)
      .def_readonly("mean_distance_error", &RegionLayoutComparison::mean_distance_error_m)
      .def_readonly("max_distance_error", &RegionLayoutComparison::max_distance_error_m)
      .def_readonly("mean_angle_error", &RegionLayoutComparison::mean_angle_error_deg)
      .def_readonly("max_angle_error", &RegionLayoutComparison::max_angle_error_deg)
      .def(pickle_by_fields<RegionLayoutComparison>("RegionLayoutComparison",
                                                    [](auto& r, auto&& f) {
                                                      f("pairs", r.pairs);
                                                      f("triples", r.triples);
                                                      f("mean_distance_error", r.mean_distance_error_m);
                                                      f("max_distance_error", r.max_distance_error_m);
                                                      f("mean_angle_error", r.mean_angle_error_deg);
                                                      f("max_angle_error", r.max_angle_error_deg);
                                                    }))
      .def("__repr__", [](const RegionLayoutComparison& c) {
        std::ostringstream text;
        text << "RegionLayoutComparison(pairs=" << c.pairs.size() << ", mean distance error=" << c.mean_distance_error_m
             << " m, triples=" << c.triples.size() << ", mean angle error=" << c.mean_angle_error_deg << " deg)";
        return text.str();
      });

  m.def("error_statistics", &error_statistics, py::arg("errors"));
  m.def(
      "absolute_trajectory_error",
      [](const py::array& estimate, const py::array& ground_truth, TrajectoryAlignment alignment) {
        const auto est = poses_from_array(estimate, "estimate");
        const auto gt = poses_from_array(ground_truth, "ground_truth");
        py::gil_scoped_release release;
        return absolute_trajectory_error(est, gt, alignment);
      },
      py::arg("estimate"), py::arg("ground_truth"), py::arg("alignment"));
  m.def(
      "rigid_alignment",
      [](const py::array& source, const py::array& target) {
        const auto read = [](const py::array& array, const char* name) {
          std::vector<Eigen::Vector3d> out;
          with_points(array, name, [&](const auto& view) {
            for (std::size_t k = 0; k < view.size; ++k) {
              const auto* row = view.data + static_cast<std::ptrdiff_t>(k) * view.row_stride;
              out.emplace_back(static_cast<double>(row[0]), static_cast<double>(row[view.column_stride]),
                               static_cast<double>(row[2 * view.column_stride]));
            }
            return 0;
          });
          return out;
        };
        const auto s = read(source, "source");
        const auto t = read(target, "target");
        py::gil_scoped_release release;
        return rigid_alignment(s, t);
      },
      py::arg("source"), py::arg("target"));
  m.def(
      "relative_pose_error",
      [](const py::array& estimate, const py::array& ground_truth, const RelativePoseErrorParams& params) {
        const auto est = poses_from_array(estimate, "estimate");
        const auto gt = poses_from_array(ground_truth, "ground_truth");
        py::gil_scoped_release release;
        return relative_pose_error(est, gt, params);
      },
      py::arg("estimate"), py::arg("ground_truth"), py::arg("params"));
  m.def(
      "compare_region_layouts",
      [](const py::array& map_centres, const py::array& dsm_centres, RegionRelations relations) {
        const auto map = centres_from_array(map_centres, "map_centres");
        const auto dsm = centres_from_array(dsm_centres, "dsm_centres");
        py::gil_scoped_release release;
        return compare_region_layouts(map, dsm, relations);
      },
      py::arg("map_centres"), py::arg("dsm_centres"), py::arg("relations") = RegionRelations::kConsecutive);
}

}  // namespace terracube::python
