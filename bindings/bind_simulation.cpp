// Bindings for simulation.hpp, in the submodule _core.simulation (its names stay out of the way of
// the other areas').
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/stl.h>
#include <terracube/simulation.hpp>

#include <memory>
#include <sstream>

namespace py = pybind11;

namespace terracube::python {

namespace {

namespace sim = terracube::simulation;

py::array_t<double> stack_poses(const std::vector<Eigen::Matrix4d>& poses) {
  py::array_t<double> out({static_cast<py::ssize_t>(poses.size()), py::ssize_t{4}, py::ssize_t{4}});
  auto view = out.mutable_unchecked<3>();
  for (std::size_t k = 0; k < poses.size(); ++k) {
    for (int row = 0; row < 4; ++row) {
      for (int col = 0; col < 4; ++col) view(static_cast<py::ssize_t>(k), row, col) = poses[k](row, col);
    }
  }
  return out;
}

/// (points (N, 3) float32, labels (N,) uint8, ray_indices (N,) uint32), copied once.
py::tuple scan_arrays(const sim::Scan& scan) {
  const auto n = static_cast<py::ssize_t>(scan.size());
  py::array_t<float> points({n, py::ssize_t{3}});
  py::array_t<std::uint8_t> labels(n);
  py::array_t<std::uint32_t> rays(n);
  float* p = points.mutable_data();
  std::uint8_t* l = labels.mutable_data();
  std::uint32_t* r = rays.mutable_data();
  for (std::size_t i = 0; i < scan.size(); ++i) {
    for (int axis = 0; axis < 3; ++axis) p[3 * i + axis] = scan.points[i][axis];
    l[i] = static_cast<std::uint8_t>(scan.labels[i]);
    r[i] = scan.ray_indices[i];
  }
  return py::make_tuple(points, labels, rays);
}

Eigen::Matrix4d as_pose(const py::array& pose) {
  const auto matrix = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(pose);
  if (!matrix || matrix.ndim() != 2 || matrix.shape(0) != 4 || matrix.shape(1) != 4) {
    throw py::value_error("world_T_sensor must be a (4, 4) rigid transform");
  }
  Eigen::Matrix4d out;
  for (int row = 0; row < 4; ++row) {
    for (int col = 0; col < 4; ++col) out(row, col) = matrix.at(row, col);
  }
  return out;
}

template <typename Model>
py::tuple cast(const sim::Scene& scene, const py::array& pose, const Model& model, std::uint64_t seed) {
  const Eigen::Matrix4d world_T_sensor = as_pose(pose);
  sim::Scan scan;
  {
    py::gil_scoped_release release;
    scan = sim::cast_scan(scene, world_T_sensor, model, seed);
  }
  return scan_arrays(scan);
}

template <typename Model>
py::array_t<double> rays_of(const Model& model) {
  const std::vector<Eigen::Vector3d> rays = sim::sensor_rays(model);
  py::array_t<double> out({static_cast<py::ssize_t>(rays.size()), py::ssize_t{3}});
  double* data = out.mutable_data();
  for (std::size_t i = 0; i < rays.size(); ++i) {
    for (int axis = 0; axis < 3; ++axis) data[3 * i + axis] = rays[i][axis];
  }
  return out;
}

const char* kind_name(sim::PrimitiveKind kind) {
  switch (kind) {
    case sim::PrimitiveKind::kBox:
      return "box";
    case sim::PrimitiveKind::kCylinder:
      return "cylinder";
    case sim::PrimitiveKind::kEllipsoid:
      return "ellipsoid";
  }
  return "unknown";
}

sim::Label label_of(int value) {
  if (value < 0 || value >= sim::kNumLabels)
    throw py::value_error("label must be in [0, 9), got " + std::to_string(value));
  return static_cast<sim::Label>(value);
}

}  // namespace

void bind_simulation(py::module_& parent) {
  py::module_ m = parent.def_submodule("simulation", "Synthetic LiDAR sequences (terracube::simulation)");

  py::list names;
  for (int k = 0; k < sim::kNumLabels; ++k) names.append(sim::to_string(static_cast<sim::Label>(k)));
  m.attr("label_names") = names;

  py::class_<sim::Ramp>(m, "Ramp")
      .def(py::init<>())
      .def_readwrite("center", &sim::Ramp::center)
      .def_readwrite("heading_rad", &sim::Ramp::heading_rad)
      .def_readwrite("height_m", &sim::Ramp::height_m)
      .def_readwrite("ramp_length_m", &sim::Ramp::ramp_length_m)
      .def_readwrite("plateau_length_m", &sim::Ramp::plateau_length_m)
      .def_readwrite("half_width_m", &sim::Ramp::half_width_m)
      .def_readwrite("side_falloff_m", &sim::Ramp::side_falloff_m);
  py::class_<sim::Hill>(m, "Hill")
      .def(py::init<>())
      .def_readwrite("center", &sim::Hill::center)
      .def_readwrite("height_m", &sim::Hill::height_m)
      .def_readwrite("radius_m", &sim::Hill::radius_m);
  py::class_<sim::Terrain>(m, "Terrain")
      .def(py::init<>())
      .def_readwrite("base_height_m", &sim::Terrain::base_height_m)
      .def_readwrite("ramps", &sim::Terrain::ramps)
      .def_readwrite("hills", &sim::Terrain::hills)
      .def(
          "height",
          [](const sim::Terrain& terrain, const py::array_t<double, py::array::forcecast>& x,
             const py::array_t<double, py::array::forcecast>& y) {
            if (x.size() != y.size()) throw py::value_error("x and y must have the same size");
            py::array_t<double> out(x.size());
            for (py::ssize_t i = 0; i < x.size(); ++i) out.mutable_data()[i] = terrain.height(x.data()[i], y.data()[i]);
            return out;
          },
          py::arg("x"), py::arg("y"), "h(x, y) [m] for flat arrays x, y")
      .def(
          "gradient",
          [](const sim::Terrain& terrain, double x, double y) {
            const Eigen::Vector2d g = terrain.gradient(x, y);
            return py::make_tuple(g.x(), g.y());
          },
          py::arg("x"), py::arg("y"));

  py::class_<sim::Primitive>(m, "Primitive")
      .def_static(
          "box",
          [](const Eigen::Vector3d& c, const Eigen::Vector3d& h, double yaw, int label) {
            return sim::Primitive::box(c, h, yaw, label_of(label));
          },
          py::arg("center"), py::arg("half_extents"), py::arg("yaw"), py::arg("label"))
      .def_static(
          "cylinder",
          [](double x, double y, double r, double z0, double z1, int label) {
            return sim::Primitive::cylinder(x, y, r, z0, z1, label_of(label));
          },
          py::arg("x"), py::arg("y"), py::arg("radius"), py::arg("z_min"), py::arg("z_max"), py::arg("label"))
      .def_static(
          "ellipsoid",
          [](const Eigen::Vector3d& c, const Eigen::Vector3d& radii, int label) {
            return sim::Primitive::ellipsoid(c, radii, label_of(label));
          },
          py::arg("center"), py::arg("radii"), py::arg("label"))
      .def_property_readonly("kind", [](const sim::Primitive& p) { return kind_name(p.kind); })
      .def_property_readonly("label", [](const sim::Primitive& p) { return static_cast<int>(p.label); })
      .def_readonly("center", &sim::Primitive::center)
      .def_readonly("half_extents", &sim::Primitive::half_extents)
      .def_readonly("yaw", &sim::Primitive::yaw_rad)
      .def("__repr__", [](const sim::Primitive& p) {
        std::ostringstream text;
        text << "Primitive(" << kind_name(p.kind) << ", " << sim::to_string(p.label) << ", center=("
             << p.center.transpose() << "), half_extents=(" << p.half_extents.transpose() << "), yaw=" << p.yaw_rad
             << ")";
        return text.str();
      });

  py::class_<sim::Scene>(m, "Scene")
      .def(py::init<sim::Terrain, std::vector<sim::Primitive>, double>(), py::arg("terrain"), py::arg("primitives"),
           py::arg("grid_cell_m"))
      .def_property_readonly("terrain", &sim::Scene::terrain)
      .def_property_readonly("primitives", &sim::Scene::primitives)
      .def(
          "intersect",
          [](const sim::Scene& scene, const Eigen::Vector3d& origin, const Eigen::Vector3d& direction, double max_range,
             bool brute_force) {
            if (!origin.allFinite() || !direction.allFinite() || !(direction.norm() > 0.0)) {
              throw py::value_error("origin and direction must be finite and the direction non-zero");
            }
            const Eigen::Vector3d unit = direction.normalized();
            const sim::RayHit hit = brute_force ? scene.intersect_brute_force(origin, unit, max_range)
                                                : scene.intersect(origin, unit, max_range);
            return py::make_tuple(hit.range_m, static_cast<int>(hit.label), hit.primitive);
          },
          py::arg("origin"), py::arg("direction"), py::arg("max_range"), py::arg("brute_force") = false,
          "(range [m] or inf, label, primitive index or -1 for the terrain)");

  py::class_<sim::RotatingLidar>(m, "RotatingLidar")
      .def(py::init<>())
      .def_readwrite("channels", &sim::RotatingLidar::channels)
      .def_readwrite("vertical_fov_min_deg", &sim::RotatingLidar::vertical_fov_min_deg)
      .def_readwrite("vertical_fov_max_deg", &sim::RotatingLidar::vertical_fov_max_deg)
      .def_readwrite("steps_per_revolution", &sim::RotatingLidar::steps_per_revolution)
      .def_readwrite("min_range_m", &sim::RotatingLidar::min_range_m)
      .def_readwrite("max_range_m", &sim::RotatingLidar::max_range_m)
      .def_readwrite("range_noise_sigma_m", &sim::RotatingLidar::range_noise_sigma_m);
  py::class_<sim::Tilting2DScanner>(m, "Tilting2DScanner")
      .def(py::init<>())
      .def_readwrite("beams_per_line", &sim::Tilting2DScanner::beams_per_line)
      .def_readwrite("horizontal_fov_deg", &sim::Tilting2DScanner::horizontal_fov_deg)
      .def_readwrite("tilt_from_deg", &sim::Tilting2DScanner::tilt_from_deg)
      .def_readwrite("tilt_to_deg", &sim::Tilting2DScanner::tilt_to_deg)
      .def_readwrite("lines", &sim::Tilting2DScanner::lines)
      .def_readwrite("min_range_m", &sim::Tilting2DScanner::min_range_m)
      .def_readwrite("max_range_m", &sim::Tilting2DScanner::max_range_m)
      .def_readwrite("range_noise_sigma_m", &sim::Tilting2DScanner::range_noise_sigma_m);

  m.def("sensor_rays", &rays_of<sim::RotatingLidar>, py::arg("model"));
  m.def("sensor_rays", &rays_of<sim::Tilting2DScanner>, py::arg("model"));
  m.def("cast_scan", &cast<sim::RotatingLidar>, py::arg("scene"), py::arg("world_T_sensor"), py::arg("model"),
        py::arg("seed"));
  m.def("cast_scan", &cast<sim::Tilting2DScanner>, py::arg("scene"), py::arg("world_T_sensor"), py::arg("model"),
        py::arg("seed"));

  py::enum_<sim::PathShape>(m, "PathShape")
      .value("loop", sim::PathShape::kLoop)
      .value("straight", sim::PathShape::kStraight);
  py::class_<sim::LoopSceneParams>(m, "LoopSceneParams")
      .def(py::init<>())
      .def_readwrite("path", &sim::LoopSceneParams::path)
      .def_readwrite("loop_length_m", &sim::LoopSceneParams::loop_length_m)
      .def_readwrite("loop_width_m", &sim::LoopSceneParams::loop_width_m)
      .def_readwrite("corner_radius_m", &sim::LoopSceneParams::corner_radius_m)
      .def_readwrite("straight_length_m", &sim::LoopSceneParams::straight_length_m)
      .def_readwrite("road_width_m", &sim::LoopSceneParams::road_width_m)
      .def_readwrite("with_tunnel", &sim::LoopSceneParams::with_tunnel)
      .def_readwrite("with_bridge", &sim::LoopSceneParams::with_bridge)
      .def_readwrite("with_ramp", &sim::LoopSceneParams::with_ramp)
      .def_readwrite("with_trees", &sim::LoopSceneParams::with_trees)
      .def_readwrite("with_buildings", &sim::LoopSceneParams::with_buildings)
      .def_readwrite("tunnel_length_m", &sim::LoopSceneParams::tunnel_length_m)
      .def_readwrite("tunnel_clearance_m", &sim::LoopSceneParams::tunnel_clearance_m)
      .def_readwrite("bridge_clearance_m", &sim::LoopSceneParams::bridge_clearance_m)
      .def_readwrite("bridge_deck_width_m", &sim::LoopSceneParams::bridge_deck_width_m)
      .def_readwrite("ramp_height_m", &sim::LoopSceneParams::ramp_height_m)
      .def_readwrite("ramp_length_m", &sim::LoopSceneParams::ramp_length_m)
      .def_readwrite("ramp_plateau_m", &sim::LoopSceneParams::ramp_plateau_m)
      .def_readwrite("tree_spacing_m", &sim::LoopSceneParams::tree_spacing_m)
      .def_readwrite("canopy_bottom_m", &sim::LoopSceneParams::canopy_bottom_m)
      .def_readwrite("seed", &sim::LoopSceneParams::seed)
      .def_readwrite("grid_cell_m", &sim::LoopSceneParams::grid_cell_m);

  py::class_<sim::RoadPath>(m, "RoadPath")
      .def_property_readonly("length", &sim::RoadPath::length_m)
      .def_property_readonly("closed", &sim::RoadPath::closed)
      .def(
          "position",
          [](const sim::RoadPath& road, double s) {
            const Eigen::Vector2d p = road.position(s);
            return py::make_tuple(p.x(), p.y());
          },
          py::arg("s"))
      .def("heading", &sim::RoadPath::heading_rad, py::arg("s"));

  py::class_<sim::SyntheticWorld, std::shared_ptr<sim::SyntheticWorld>>(m, "SyntheticWorld")
      .def_property_readonly(
          "scene", [](const sim::SyntheticWorld& w) -> const sim::Scene& { return w.scene; },
          py::return_value_policy::reference_internal)
      .def_property_readonly(
          "road", [](const sim::SyntheticWorld& w) -> const sim::RoadPath& { return w.road; },
          py::return_value_policy::reference_internal)
      .def_readonly("params", &sim::SyntheticWorld::params);
  m.def(
      "make_loop_scene",
      [](const sim::LoopSceneParams& params) {
        py::gil_scoped_release release;
        return std::make_shared<sim::SyntheticWorld>(sim::make_loop_scene(params));
      },
      py::arg("params"));

  py::class_<sim::TrajectoryParams>(m, "TrajectoryParams")
      .def(py::init<>())
      .def_readwrite("scan_spacing_m", &sim::TrajectoryParams::scan_spacing_m)
      .def_readwrite("laps", &sim::TrajectoryParams::laps)
      .def_readwrite("mount_height_m", &sim::TrajectoryParams::mount_height_m)
      .def_readwrite("lateral_offset_m", &sim::TrajectoryParams::lateral_offset_m)
      .def_readwrite("start_arc_length_m", &sim::TrajectoryParams::start_arc_length_m)
      .def_readwrite("yaw_bias_rad_per_m", &sim::TrajectoryParams::yaw_bias_rad_per_m)
      .def_readwrite("yaw_random_walk_rad_per_sqrt_m", &sim::TrajectoryParams::yaw_random_walk_rad_per_sqrt_m)
      .def_readwrite("translation_scale_error", &sim::TrajectoryParams::translation_scale_error)
      .def_readwrite("translation_random_walk_m_per_sqrt_m",
                     &sim::TrajectoryParams::translation_random_walk_m_per_sqrt_m)
      .def_readwrite("roll_pitch_noise_rad", &sim::TrajectoryParams::roll_pitch_noise_rad)
      .def_readwrite("seed", &sim::TrajectoryParams::seed);
  m.def(
      "generate_trajectory",
      [](const sim::SyntheticWorld& world, const sim::TrajectoryParams& params) {
        sim::Trajectory t;
        {
          py::gil_scoped_release release;
          t = sim::generate_trajectory(world, params);
        }
        return py::make_tuple(
            stack_poses(t.poses), stack_poses(t.odometry),
            py::array_t<double>(static_cast<py::ssize_t>(t.arc_length_m.size()), t.arc_length_m.data()));
      },
      py::arg("world"), py::arg("params"), "(poses (K, 4, 4), odometry (K, 4, 4), arc_length (K,))");

  const auto make_sequence = [](const std::shared_ptr<sim::SyntheticWorld>& world, const sim::SensorModel& sensor,
                                const sim::TrajectoryParams& params, std::uint64_t seed) {
    sim::Trajectory t = sim::generate_trajectory(*world, params);
    return std::make_shared<sim::SyntheticSequence>(world, sensor, std::move(t), seed);
  };
  py::class_<sim::SyntheticSequence, std::shared_ptr<sim::SyntheticSequence>>(m, "SyntheticSequence")
      .def(py::init([make_sequence](const std::shared_ptr<sim::SyntheticWorld>& world, const sim::RotatingLidar& sensor,
                                    const sim::TrajectoryParams& params,
                                    std::uint64_t seed) { return make_sequence(world, sensor, params, seed); }),
           py::arg("world"), py::arg("sensor"), py::arg("trajectory"), py::arg("seed"))
      .def(py::init([make_sequence](const std::shared_ptr<sim::SyntheticWorld>& world,
                                    const sim::Tilting2DScanner& sensor, const sim::TrajectoryParams& params,
                                    std::uint64_t seed) { return make_sequence(world, sensor, params, seed); }),
           py::arg("world"), py::arg("sensor"), py::arg("trajectory"), py::arg("seed"))
      .def("__len__", &sim::SyntheticSequence::size)
      .def(
          "scan",
          [](const sim::SyntheticSequence& sequence, std::size_t k) {
            sim::Scan scan;
            {
              py::gil_scoped_release release;
              scan = sequence.scan(k);
            }
            return scan_arrays(scan);
          },
          py::arg("k"))
      .def_property_readonly("poses", [](const sim::SyntheticSequence& s) { return stack_poses(s.trajectory().poses); })
      .def_property_readonly("odometry",
                             [](const sim::SyntheticSequence& s) { return stack_poses(s.trajectory().odometry); })
      .def_property_readonly("arc_length",
                             [](const sim::SyntheticSequence& s) {
                               const auto& a = s.trajectory().arc_length_m;
                               return py::array_t<double>(static_cast<py::ssize_t>(a.size()), a.data());
                             })
      .def_property_readonly("seed", &sim::SyntheticSequence::seed);
}

}  // namespace terracube::python
