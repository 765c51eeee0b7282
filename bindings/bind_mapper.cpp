// Bindings for mapper.hpp.
#include <pybind11/eigen.h>
#include <pybind11/stl.h>
#include <terracube/mapper.hpp>

#include "pickle.hpp"
#include "points.hpp"

namespace terracube::python {

namespace {

/// (K, 4, 4) float64 array of poses.
py::array_t<double> pose_array(const std::vector<Eigen::Matrix4d>& poses) {
  py::array_t<double> out({static_cast<py::ssize_t>(poses.size()), py::ssize_t{4}, py::ssize_t{4}});
  auto view = out.mutable_unchecked<3>();
  for (std::size_t k = 0; k < poses.size(); ++k) {
    for (int r = 0; r < 4; ++r) {
      for (int c = 0; c < 4; ++c) view(static_cast<py::ssize_t>(k), r, c) = poses[k](r, c);
    }
  }
  return out;
}

Eigen::Matrix4d as_pose(const py::array& pose) {
  const auto array = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(pose);
  if (!array || array.ndim() != 2 || array.shape(0) != 4 || array.shape(1) != 4) {
    throw py::value_error("pose must be a (4, 4) rigid transform, got shape " + shape_string(pose));
  }
  Eigen::Matrix4d out;
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) out(r, c) = array.at(r, c);
  }
  return out;
}

}  // namespace

void bind_mapper(py::module_& m) {
  py::class_<MapperParams>(m, "MapperParams")
      .def(py::init<>())
      .def("check", &check_mapper_params,
           "Raises ValueError naming the first field out of range (as every call taking them).")
      .def_readwrite("keyframe_distance_m", &MapperParams::keyframe_distance_m)
      .def_readwrite("keyframe_rotation_rad", &MapperParams::keyframe_rotation_rad)
      .def_readwrite("resolution_m", &MapperParams::resolution_m)
      .def_readwrite("local_map_size_m", &MapperParams::local_map_size_m)
      .def_readwrite("max_scans_per_local_map", &MapperParams::max_scans_per_local_map)
      .def_readwrite("num_threads", &MapperParams::num_threads)
      .def_readwrite("keep_local_maps", &MapperParams::keep_local_maps)
      .def_readwrite("min_range_m", &MapperParams::min_range_m)
      .def_readwrite("max_range_m", &MapperParams::max_range_m)
      .def_readwrite("discontinuity_m", &MapperParams::discontinuity_m)
      .def_readwrite("terrain", &MapperParams::terrain)
      .def_readwrite("use_registration", &MapperParams::use_registration)
      .def_readwrite("lidar_only", &MapperParams::lidar_only)
      .def_readwrite("registration", &MapperParams::registration)
      .def_readwrite("yaw_only_registration", &MapperParams::yaw_only_registration)
      .def_readwrite("ground_step_height", &MapperParams::ground_step_height)
      .def_readwrite("max_correction_m", &MapperParams::max_correction_m)
      .def_readwrite("max_odometry_step_m", &MapperParams::max_odometry_step_m)
      .def_readwrite("max_correction_rad", &MapperParams::max_correction_rad)
      .def_readwrite("registration_sigma_m", &MapperParams::registration_sigma_m)
      .def_readwrite("registration_sigma_rad", &MapperParams::registration_sigma_rad)
      .def_readwrite("odometry_sigma_m_per_m", &MapperParams::odometry_sigma_m_per_m)
      .def_readwrite("odometry_sigma_rad_per_m", &MapperParams::odometry_sigma_rad_per_m)
      .def_readwrite("loop_closing", &MapperParams::loop_closing)
      .def_readwrite("loop_search_radius_m", &MapperParams::loop_search_radius_m)
      .def_readwrite("loop_min_travel_m", &MapperParams::loop_min_travel_m)
      .def_readwrite("loop_min_overlap", &MapperParams::loop_min_overlap)
      .def_readwrite("overlap_block_m", &MapperParams::overlap_block_m)
      .def_readwrite("loop_max_candidates", &MapperParams::loop_max_candidates)
      .def_readwrite("loop_search_window_m", &MapperParams::loop_search_window_m)
      .def_readwrite("loop_yaw_search_rad", &MapperParams::loop_yaw_search_rad)
      .def_readwrite("loop_yaw_hypotheses", &MapperParams::loop_yaw_hypotheses)
      .def_readwrite("loop_max_rmse_m", &MapperParams::loop_max_rmse_m)
      .def_readwrite("loop_min_inlier_ratio", &MapperParams::loop_min_inlier_ratio)
      .def_readwrite("pose_graph_iterations", &MapperParams::pose_graph_iterations)
      .def_readwrite("optimize_interval_keyframes", &MapperParams::optimize_interval_keyframes);

  py::class_<ScanReport>(m, "ScanReport")
      .def_readonly("keyframe", &ScanReport::keyframe)
      .def_readonly("index", &ScanReport::index)
      .def_readonly("registered", &ScanReport::registered)
      .def_readonly("registration", &ScanReport::registration)
      .def_readonly("loops_closed", &ScanReport::loops_closed)
      .def_readonly("num_out_of_range", &ScanReport::num_out_of_range,
                    "points of the scan left out by min_range and max_range")
      .def_readonly("pose", &ScanReport::pose,
                    "(4, 4) the scan's estimated world <- sensor when it was added (loop closing may correct "
                    "the keyframes later)")
      .def(pickle_by_fields<ScanReport>("ScanReport",
                                        [](auto& r, auto&& f) {
                                          f("keyframe", r.keyframe);
                                          f("index", r.index);
                                          f("registered", r.registered);
                                          f("registration", r.registration);
                                          f("loops_closed", r.loops_closed);
                                          f("num_out_of_range", r.num_out_of_range);
                                          f("pose", r.pose);
                                        }))
      .def("__repr__", [](const ScanReport& r) {
        return "ScanReport(keyframe=" + std::string(r.keyframe ? "True" : "False") +
               ", index=" + std::to_string(r.index) + ", registered=" + (r.registered ? "True" : "False") +
               ", loops_closed=" + std::to_string(r.loops_closed) +
               ", num_out_of_range=" + std::to_string(r.num_out_of_range) + ")";
      });

  py::class_<LoopClosure>(m, "LoopClosure")
      .def_readonly("source", &LoopClosure::to, "the later keyframe")
      .def_readonly("target", &LoopClosure::from, "the earlier keyframe")
      .def_readonly("relative", &LoopClosure::relative, "(4, 4) L_target <- L_source")
      .def_readonly("rmse", &LoopClosure::rmse_m)
      .def_readonly("overlap", &LoopClosure::overlap)
      .def(pickle_by_fields<LoopClosure>("LoopClosure",
                                         [](auto& r, auto&& f) {
                                           f("source", r.to);
                                           f("target", r.from);
                                           f("relative", r.relative);
                                           f("rmse", r.rmse_m);
                                           f("overlap", r.overlap);
                                         }))
      .def("__repr__", [](const LoopClosure& l) {
        return "LoopClosure(target=" + std::to_string(l.from) + ", source=" + std::to_string(l.to) +
               ", rmse=" + std::to_string(l.rmse_m) + ", overlap=" + std::to_string(l.overlap) + ")";
      });

  py::class_<MapperTimings>(m, "MapperTimings")
      .def_readonly("map_building_ms", &MapperTimings::map_building_ms)
      .def_readonly("classification_ms", &MapperTimings::classification_ms)
      .def_readonly("registration_ms", &MapperTimings::registration_ms)
      .def_readonly("fusion_ms", &MapperTimings::fusion_ms)
      .def_readonly("loop_closing_ms", &MapperTimings::loop_closing_ms)
      .def_readonly("scans", &MapperTimings::scans)
      .def_readonly("keyframes", &MapperTimings::keyframes)
      .def_readonly("registered_steps", &MapperTimings::registered_steps, "steps whose registration was accepted")
      .def_readonly("untrusted_steps", &MapperTimings::untrusted_steps,
                    "steps whose registration was not trusted (odometry or the prediction was used)")
      .def(pickle_by_fields<MapperTimings>("MapperTimings", [](auto& r, auto&& f) {
        f("map_building_ms", r.map_building_ms);
        f("classification_ms", r.classification_ms);
        f("registration_ms", r.registration_ms);
        f("fusion_ms", r.fusion_ms);
        f("loop_closing_ms", r.loop_closing_ms);
        f("scans", r.scans);
        f("keyframes", r.keyframes);
        f("registered_steps", r.registered_steps);
        f("untrusted_steps", r.untrusted_steps);
      }));

  py::class_<Mapper>(m, "Mapper")
      .def(py::init<const MapperParams&>(), py::arg("params"))
      .def(
          "add_scan",
          [](Mapper& mapper, const py::array& points, const py::array& pose) {
            const Eigen::Matrix4d odometry = as_pose(pose);
            return with_points(points, "points", [&](const auto& view) {
              py::gil_scoped_release release;
              return mapper.add_scan(view, odometry);
            });
          },
          py::arg("points"), py::arg("pose"))
      .def_property_readonly("num_keyframes", &Mapper::num_keyframes)
      .def_property_readonly("pending_loops", &Mapper::pending_loops)
      .def_property_readonly("points_out_of_range", &Mapper::points_out_of_range)
      .def("keyframe_poses", [](const Mapper& mapper) { return pose_array(mapper.keyframe_poses()); })
      .def("keyframe_odometry", [](const Mapper& mapper) { return pose_array(mapper.keyframe_odometry()); })
      .def("keyframe_scan_indices", &Mapper::keyframe_scan_indices)
      .def_property_readonly("loop_closures", &Mapper::loop_closures)
      .def_property_readonly("timings", &Mapper::timings)
      .def("local_map", &Mapper::local_map, py::arg("k"))
      .def(
          "global_map",
          [](const Mapper& mapper, bool classify) {
            py::gil_scoped_release release;
            return mapper.global_map(classify);
          },
          py::arg("classify") = true)
      .def_property_readonly("global_memory_bytes", [](const Mapper& m) { return m.tiles().memory_bytes(); })
      .def_property_readonly("global_tiles", [](const Mapper& m) { return m.tiles().num_tiles(); })
      .def("optimize", [](Mapper& mapper) {
        py::gil_scoped_release release;
        mapper.optimize();
      });
}

}  // namespace terracube::python
