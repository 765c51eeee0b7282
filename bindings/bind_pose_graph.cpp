// Bindings for pose_graph.hpp.
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>
#include <terracube/pose_graph.hpp>

#include <sstream>
#include <vector>

#include "pickle.hpp"

namespace py = pybind11;

namespace terracube::python {

// Defined in bind_evaluation.cpp.
std::vector<Eigen::Matrix4d> poses_from_array(const py::array& array, const char* name);
py::array array_of_poses(const std::vector<Eigen::Matrix4d>& poses);

void bind_pose_graph(py::module_& m) {
  py::enum_<RobustLoss>(m, "RobustLoss").value("huber", RobustLoss::kHuber).value("cauchy", RobustLoss::kCauchy);

  py::class_<PoseGraphEdge>(m, "PoseGraphEdge")
      .def(py::init<>())
      .def_readwrite("from_", &PoseGraphEdge::from)
      .def_readwrite("to", &PoseGraphEdge::to)
      .def_readwrite("measurement", &PoseGraphEdge::measurement)
      .def_readwrite("information", &PoseGraphEdge::information)
      .def_readwrite("robust", &PoseGraphEdge::robust);

  py::class_<PoseGraphParams>(m, "PoseGraphParams")
      .def(py::init<>())
      .def_readwrite("max_iterations", &PoseGraphParams::max_iterations)
      .def_readwrite("robust_loss", &PoseGraphParams::robust_loss)
      .def_readwrite("robust_loss_scale", &PoseGraphParams::robust_loss_scale)
      .def_readwrite("fixed", &PoseGraphParams::fixed)
      .def_readwrite("fixed_rotations", &PoseGraphParams::fixed_rotations)
      .def_readwrite("function_tolerance", &PoseGraphParams::function_tolerance)
      .def_readwrite("gradient_tolerance", &PoseGraphParams::gradient_tolerance)
      .def_readwrite("parameter_tolerance", &PoseGraphParams::parameter_tolerance)
      .def_readwrite("num_threads", &PoseGraphParams::num_threads);

  py::class_<PoseGraphResult>(m, "PoseGraphResult")
      .def_property_readonly(
          "poses", [](const PoseGraphResult& r) { return array_of_poses(r.poses); }, "(K, 4, 4) optimised poses")
      .def_readonly("initial_cost", &PoseGraphResult::initial_cost)
      .def_readonly("final_cost", &PoseGraphResult::final_cost)
      .def_readonly("iterations", &PoseGraphResult::iterations)
      .def_readonly("converged", &PoseGraphResult::converged)
      .def_readonly("message", &PoseGraphResult::message)
      .def(pickle_by_fields<PoseGraphResult>("PoseGraphResult",
                                             [](auto& r, auto&& f) {
                                               f("poses", r.poses);
                                               f("initial_cost", r.initial_cost);
                                               f("final_cost", r.final_cost);
                                               f("iterations", r.iterations);
                                               f("converged", r.converged);
                                               f("message", r.message);
                                             }))
      .def("__repr__", [](const PoseGraphResult& r) {
        std::ostringstream text;
        text << "PoseGraphResult(poses=" << r.poses.size() << ", converged=" << (r.converged ? "True" : "False")
             << ", iterations=" << r.iterations << ", cost " << r.initial_cost << " -> " << r.final_cost << ")";
        return text.str();
      });

  m.def(
      "optimize_pose_graph",
      [](const py::array& poses, const std::vector<PoseGraphEdge>& edges, const PoseGraphParams& params) {
        const std::vector<Eigen::Matrix4d> initial = poses_from_array(poses, "poses");
        py::gil_scoped_release release;
        return optimize_pose_graph(initial, edges, params);
      },
      py::arg("poses"), py::arg("edges"), py::arg("params"));
}

}  // namespace terracube::python
