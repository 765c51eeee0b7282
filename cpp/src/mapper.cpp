// Mapper: local classified elevation maps chained by class-weighted ICP into a global elevation
// map, with loop closing on a Ceres pose graph ([TC] sections 3.3 and 4).
#include "terracube/mapper.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <deque>
#include <limits>
#include <optional>
#include <stdexcept>
#include <string>
#include <unordered_map>

#include "cloud_frame.hpp"
#include "number_text.hpp"
#include "parallel.hpp"
#include "terracube/collapse.hpp"
#include "terracube/pose_graph.hpp"

namespace terracube {

namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr double kInfinity = std::numeric_limits<double>::infinity();

}  // namespace

void check_mapper_params(const MapperParams& p) {
  detail::check_positive(p.keyframe_distance_m, "MapperParams.keyframe_distance_m");
  detail::check_positive(p.keyframe_rotation_rad, "MapperParams.keyframe_rotation_rad");
  detail::check_positive(p.resolution_m, "MapperParams.resolution_m");
  detail::check_positive(p.local_map_size_m, "MapperParams.local_map_size_m");
  detail::check_positive(p.discontinuity_m, "MapperParams.discontinuity_m");
  detail::check_positive(p.max_correction_m, "MapperParams.max_correction_m");
  detail::check_positive(p.max_odometry_step_m, "MapperParams.max_odometry_step_m");
  detail::check_positive(p.max_correction_rad, "MapperParams.max_correction_rad");
  detail::check_positive(p.registration_sigma_m, "MapperParams.registration_sigma_m");
  detail::check_positive(p.registration_sigma_rad, "MapperParams.registration_sigma_rad");
  detail::check_positive(p.odometry_sigma_m_per_m, "MapperParams.odometry_sigma_m_per_m");
  detail::check_positive(p.odometry_sigma_rad_per_m, "MapperParams.odometry_sigma_rad_per_m");
  detail::check_positive(p.loop_search_radius_m, "MapperParams.loop_search_radius_m");
  detail::check_positive(p.loop_max_rmse_m, "MapperParams.loop_max_rmse_m");
  if (!(p.loop_min_inlier_ratio >= 0.0 && p.loop_min_inlier_ratio <= 1.0)) {
    throw std::invalid_argument("MapperParams.loop_min_inlier_ratio must lie in [0, 1]");
  }
  detail::check_positive(p.loop_search_window_m, "MapperParams.loop_search_window_m");
  detail::check_positive(p.overlap_block_m, "MapperParams.overlap_block_m");
  if (p.max_scans_per_local_map < 1) throw std::invalid_argument("MapperParams.max_scans_per_local_map must be >= 1");
  detail::check_num_threads(p.num_threads, "MapperParams");
  if (!(p.loop_yaw_search_rad >= 0.0) || !std::isfinite(p.loop_yaw_search_rad)) {
    throw std::invalid_argument("MapperParams.loop_yaw_search_rad must be finite and >= 0");
  }
  if (p.loop_yaw_hypotheses < 1) throw std::invalid_argument("MapperParams.loop_yaw_hypotheses must be >= 1");
  if (!(p.min_range_m >= 0.0) || !std::isfinite(p.min_range_m)) {
    throw std::invalid_argument("MapperParams.min_range_m must be finite and >= 0");
  }
  if (!(p.max_range_m > p.min_range_m)) {
    throw std::invalid_argument("MapperParams.max_range_m must exceed min_range_m (+inf: no limit), got " +
                                detail::number_text(p.max_range_m));
  }
  if (!(p.loop_min_travel_m >= 0.0) || !std::isfinite(p.loop_min_travel_m)) {
    throw std::invalid_argument("MapperParams.loop_min_travel_m must be finite and >= 0");
  }
  if (!(p.loop_min_overlap >= 0.0 && p.loop_min_overlap <= 1.0)) {
    throw std::invalid_argument("MapperParams.loop_min_overlap must lie in [0, 1]");
  }
  if (p.loop_max_candidates < 1) throw std::invalid_argument("MapperParams.loop_max_candidates must be >= 1");
  if (p.optimize_interval_keyframes < 1) {
    throw std::invalid_argument("MapperParams.optimize_interval_keyframes must be >= 1");
  }
  if (p.pose_graph_iterations < 1 || p.pose_graph_iterations > kMaxIterationsLimit) {
    throw std::invalid_argument("MapperParams.pose_graph_iterations must lie in [1, " +
                                std::to_string(kMaxIterationsLimit) + "], got " +
                                std::to_string(p.pose_graph_iterations));
  }
  if (p.lidar_only && !p.use_registration) {
    throw std::invalid_argument("MapperParams.lidar_only needs use_registration (nothing else moves the robot)");
  }
  const double cells = std::ceil(p.local_map_size_m / p.resolution_m);
  if (cells > 8192.0) {
    throw std::invalid_argument("MapperParams: local_map_size_m / resolution_m = " + std::to_string(cells) +
                                " cells per side (at most 8192)");
  }
  check_terrain_params(p.terrain);
  check_registration_params(p.registration);
}

namespace {

Eigen::Matrix4d inverse_rigid(const Eigen::Matrix4d& t) {
  Eigen::Matrix4d inv = Eigen::Matrix4d::Identity();
  inv.topLeftCorner<3, 3>() = t.topLeftCorner<3, 3>().transpose();
  inv.topRightCorner<3, 1>() = -inv.topLeftCorner<3, 3>() * t.topRightCorner<3, 1>();
  return inv;
}

double rotation_angle(const Eigen::Matrix4d& t) {
  const double c = std::clamp((t.topLeftCorner<3, 3>().trace() - 1.0) * 0.5, -1.0, 1.0);
  return std::acos(c);
}

/// The transform with its rotation reduced to the rotation about z (yaw) it contains.
Eigen::Matrix4d yaw_only(const Eigen::Matrix4d& t) {
  Eigen::Matrix4d out = t;
  const double yaw = std::atan2(t(1, 0), t(0, 0));
  out.topLeftCorner<3, 3>() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  return out;
}

/// Splits world <- sensor into world <- L (yaw and translation only) and L <- sensor (roll, pitch).
void split_leveling(const Eigen::Matrix4d& world_sensor, Eigen::Matrix4d& world_level, Eigen::Matrix4d& level_sensor) {
  const Eigen::Matrix3d r = world_sensor.topLeftCorner<3, 3>();
  // r = Rz(yaw) Ry(pitch) Rx(roll).
  const double yaw = std::atan2(r(1, 0), r(0, 0));
  const double pitch = std::asin(std::clamp(-r(2, 0), -1.0, 1.0));
  const double roll = std::atan2(r(2, 1), r(2, 2));
  level_sensor = leveling_transform(roll, pitch);
  world_level = Eigen::Matrix4d::Identity();
  world_level.topLeftCorner<3, 3>() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  world_level.topRightCorner<3, 1>() = world_sensor.topRightCorner<3, 1>();
}

/// One cell of a local map, kept for fusion and rebuilds.
struct CellSample {
  float x, y;  // cell centre in the keyframe's leveled frame [m]
  float z_min, z_max, z_mean, z_std;
  std::uint32_t count;
  std::uint8_t discontinuous;
  std::uint8_t ground;  // classified ground ([TC] Table 1)
};

struct Keyframe {
  std::size_t scan_index = 0;
  Eigen::Matrix4d odometry = Eigen::Matrix4d::Identity();        // world <- sensor, as given
  Eigen::Matrix4d level_sensor = Eigen::Matrix4d::Identity();    // L <- sensor
  Eigen::Matrix4d odometry_level = Eigen::Matrix4d::Identity();  // odometry world <- L
  Eigen::Matrix4d estimate = Eigen::Matrix4d::Identity();        // estimated world <- L
  double path_m = 0.0;                                           // odometry path length up to it
  std::size_t num_points = 0, num_scans = 0;                     // that built the local map
  MapGeometry geometry;                                          // of the local map
  ElevationMap map;         // local classified map: kept for the newest keyframe, or all with keep_local_maps
  ClassifiedPoints points;  // its cells as ICP points
  std::vector<CellSample> cells;
};

/// The height correction of a registered motion `relative` (L_fixed <- L_moved) from the ground
/// the two keyframes' local maps share (not in [TC]). The ICP leaves the ground out, which leaves
/// the height loose (without odometry it drifted 0.9 m over 30 m of simulated level road; with
/// exact odometry the steps still moved the height by up to 1.2 m): the median, over the moved
/// keyframe's ground cells that land on a ground cell of the fixed one, of the fixed mean
/// elevation minus the moved one. 0 with fewer than 100 such cells.
double shared_ground_offset(const Keyframe& moved, const Keyframe& fixed, const Eigen::Matrix4d& relative) {
  const MapGeometry& g = fixed.geometry;
  std::vector<float> ground(static_cast<std::size_t>(g.size.x()) * static_cast<std::size_t>(g.size.y()), kNaN);
  for (const CellSample& cell : fixed.cells) {
    const std::optional<CellIndex> at = g.index_of(Eigen::Vector2d(cell.x, cell.y));
    if (cell.ground != 0 && at) ground[static_cast<std::size_t>((*at)(0)) * g.size.y() + (*at)(1)] = cell.z_mean;
  }
  const Eigen::Matrix3d rotation = relative.topLeftCorner<3, 3>();
  const Eigen::Vector3d translation = relative.topRightCorner<3, 1>();
  std::vector<double> offsets;
  for (const CellSample& cell : moved.cells) {
    if (cell.ground == 0) continue;
    const Eigen::Vector3d p = rotation * Eigen::Vector3d(cell.x, cell.y, cell.z_mean) + translation;
    const std::optional<CellIndex> at = g.index_of(p.head<2>());
    if (!at) continue;
    const float there = ground[static_cast<std::size_t>((*at)(0)) * g.size.y() + (*at)(1)];
    if (!std::isnan(there)) offsets.push_back(static_cast<double>(there) - p.z());
  }
  if (offsets.size() < 100) return 0.0;
  const auto middle = offsets.begin() + static_cast<std::ptrdiff_t>(offsets.size() / 2);
  std::nth_element(offsets.begin(), middle, offsets.end());
  return *middle;
}

struct BufferedScan {
  std::vector<float> xyz;  // x, y, z, x, y, z, ... in the sensor frame
  Eigen::Matrix4d odometry;
};

struct Edge {
  std::size_t from, to;
  Eigen::Matrix4d relative;           // L_from <- L_to
  Eigen::Matrix<double, 6, 1> sigma;  // translation xyz [m], rotation xyz [rad]
  bool loop;
};

}  // namespace

// ---------------------------------------------------------------------------------------------
// TiledElevationMap

struct TiledElevationMap::Impl {
  struct Tile {
    static constexpr int kCells = TiledElevationMap::kTileCells * TiledElevationMap::kTileCells;
    std::array<std::uint32_t, kCells> count{};
    std::array<float, kCells> min, max;
    std::array<double, kCells> sum{}, sum_squares{};
    std::array<std::uint8_t, kCells> discontinuous{};
    Tile() {
      min.fill(std::numeric_limits<float>::infinity());
      max.fill(-std::numeric_limits<float>::infinity());
    }
  };
  // Tile coordinates (32-bit each, checked in fuse) packed into one key, without signed shifts.
  static std::uint64_t key(std::int64_t tx, std::int64_t ty) {
    return (static_cast<std::uint64_t>(static_cast<std::uint32_t>(tx)) << 32) | static_cast<std::uint32_t>(ty);
  }
  static std::int64_t tile_x(std::uint64_t key) {
    return static_cast<std::int32_t>(static_cast<std::uint32_t>(key >> 32));
  }
  static std::int64_t tile_y(std::uint64_t key) { return static_cast<std::int32_t>(static_cast<std::uint32_t>(key)); }
  std::unordered_map<std::uint64_t, std::unique_ptr<Tile>> tiles;
};

TiledElevationMap::TiledElevationMap(double resolution_m) : resolution_m_(resolution_m), impl_(new Impl) {
  detail::check_positive(resolution_m, "TiledElevationMap resolution_m");
}
TiledElevationMap::~TiledElevationMap() = default;
TiledElevationMap::TiledElevationMap(TiledElevationMap&&) noexcept = default;
TiledElevationMap& TiledElevationMap::operator=(TiledElevationMap&&) noexcept = default;

void TiledElevationMap::clear() { impl_->tiles.clear(); }
std::size_t TiledElevationMap::num_tiles() const { return impl_->tiles.size(); }
std::size_t TiledElevationMap::memory_bytes() const { return impl_->tiles.size() * sizeof(Impl::Tile); }

void TiledElevationMap::fuse(double x, double y, float z_min, float z_max, float z_mean, float z_std,
                             std::uint32_t count, bool discontinuous) {
  // Tile coordinates must fit 32 bits: |x|, |y| below 2^31 tiles (2.7e10 m at 0.2 m cells).
  const double limit = 2147483647.0 * kTileCells * resolution_m_;
  if (!(std::abs(x) < limit && std::abs(y) < limit)) {
    throw std::invalid_argument("global map position (" + std::to_string(x) + ", " + std::to_string(y) +
                                ") is NaN or beyond the map's range");
  }
  const auto ci = static_cast<std::int64_t>(std::floor(x / resolution_m_));
  const auto cj = static_cast<std::int64_t>(std::floor(y / resolution_m_));
  const std::int64_t n = kTileCells;
  const std::int64_t tx = ci >= 0 ? ci / n : -((-ci - 1) / n) - 1;
  const std::int64_t ty = cj >= 0 ? cj / n : -((-cj - 1) / n) - 1;
  auto& slot = impl_->tiles[Impl::key(tx, ty)];
  if (!slot) slot = std::make_unique<Impl::Tile>();
  Impl::Tile& tile = *slot;
  const auto k = static_cast<std::size_t>((ci - tx * n) * n + (cj - ty * n));
  tile.count[k] += count;
  tile.min[k] = std::min(tile.min[k], z_min);
  tile.max[k] = std::max(tile.max[k], z_max);
  // Sums of the points' elevations and squares, recovered from each sample's mean and std-dev.
  const double c = count;
  tile.sum[k] += c * z_mean;
  tile.sum_squares[k] += c * (static_cast<double>(z_std) * z_std + static_cast<double>(z_mean) * z_mean);
  tile.discontinuous[k] |= static_cast<std::uint8_t>(discontinuous);
}

ElevationMap TiledElevationMap::to_map(std::size_t max_cells) const {
  MapGeometry geometry;
  geometry.resolution_m = resolution_m_;
  if (impl_->tiles.empty()) {
    ElevationMap empty(geometry);
    for (const char* name : {"count", "min", "max", "mean", "std_dev", "discontinuity"}) empty.add(name);
    return empty;
  }
  std::int64_t tx0 = std::numeric_limits<std::int64_t>::max(), ty0 = tx0;
  std::int64_t tx1 = std::numeric_limits<std::int64_t>::min(), ty1 = tx1;
  for (const auto& [key, tile] : impl_->tiles) {
    const std::int64_t tx = Impl::tile_x(key), ty = Impl::tile_y(key);
    tx0 = std::min(tx0, tx), tx1 = std::max(tx1, tx), ty0 = std::min(ty0, ty), ty1 = std::max(ty1, ty);
  }
  const std::int64_t n = kTileCells;
  const std::int64_t nx = (tx1 - tx0 + 1) * n, ny = (ty1 - ty0 + 1) * n;
  if (static_cast<double>(nx) * static_cast<double>(ny) > static_cast<double>(max_cells)) {
    throw std::length_error("global map of " + std::to_string(nx) + " x " + std::to_string(ny) +
                            " cells exceeds max_cells = " + std::to_string(max_cells));
  }
  geometry.origin_m = Eigen::Vector2d(static_cast<double>(tx0 * n), static_cast<double>(ty0 * n)) * resolution_m_;
  geometry.size = CellIndex(static_cast<int>(nx), static_cast<int>(ny));
  ElevationMap map(geometry);
  for (const char* name : {"count", "min", "max", "mean", "std_dev", "discontinuity"}) map.add(name);
  map.get("count").setZero();
  Layer& count = map.get("count");
  Layer& min = map.get("min");
  Layer& max = map.get("max");
  Layer& mean = map.get("mean");
  Layer& std_dev = map.get("std_dev");
  Layer& discontinuity = map.get("discontinuity");
  for (const auto& [key, tile] : impl_->tiles) {
    const std::int64_t tx = Impl::tile_x(key), ty = Impl::tile_y(key);
    for (std::int64_t a = 0; a < n; ++a) {
      for (std::int64_t b = 0; b < n; ++b) {
        const auto k = static_cast<std::size_t>(a * n + b);
        if (tile->count[k] == 0) continue;
        const auto i = static_cast<Eigen::Index>((tx - tx0) * n + a);
        const auto j = static_cast<Eigen::Index>((ty - ty0) * n + b);
        const double c = tile->count[k];
        const double m = tile->sum[k] / c;
        count(i, j) = static_cast<float>(c);
        min(i, j) = tile->min[k];
        max(i, j) = tile->max[k];
        mean(i, j) = static_cast<float>(m);
        std_dev(i, j) = static_cast<float>(std::sqrt(std::max(0.0, tile->sum_squares[k] / c - m * m)));
        discontinuity(i, j) = tile->discontinuous[k];
      }
    }
  }
  return map;
}

// ---------------------------------------------------------------------------------------------
// Mapper

struct Mapper::Impl {
  MapperParams params;
  std::vector<Keyframe> keyframes;
  std::vector<Edge> edges;  // steps (k-1 -> k) and loops
  std::vector<LoopClosure> loops;
  TiledElevationMap global;
  MapperTimings timings;
  std::size_t scans = 0;
  /// The robot's progress along its path (restored as a whole when a scan throws).
  struct Motion {
    double path_m = 0.0;  ///< path length so far: odometry's (LiDAR-only: the estimates')
    Eigen::Matrix4d last_odometry = Eigen::Matrix4d::Identity();
    bool have_last = false;
    /// LiDAR-only: the newest scan's estimated world <- L, and its motion from the scan before
    /// (L_previous <- L_newest), the next scan's prediction once have_velocity.
    Eigen::Matrix4d last_estimate = Eigen::Matrix4d::Identity();
    Eigen::Matrix4d velocity = Eigen::Matrix4d::Identity();
    bool have_velocity = false;
  } motion;
  /// Scans since the previous keyframe (the newest last), their points within the range limits in
  /// the sensor frame.
  std::deque<BufferedScan> pending;
  std::size_t points_out_of_range = 0;  // of the scans added
  std::size_t pending_loops = 0;        // loop edges added since the last optimisation
  std::size_t optimized_at = 0;         // keyframe count at the last optimisation

  explicit Impl(const MapperParams& p) : params(p), global(p.resolution_m) {}

  template <typename Scalar>
  ScanReport add(const PointsView<Scalar>& points, const Eigen::Matrix4d& odometry);
  template <typename Scalar>
  ScanReport add_checked(const PointsView<Scalar>& points, const Eigen::Matrix4d& odometry);
  ScanReport add_with_odometry(std::size_t scan_index, const Eigen::Matrix4d& odometry);
  ScanReport add_lidar_only(std::size_t scan_index, const Eigen::Matrix4d& attitude);
  void append_keyframe(Keyframe keyframe, const Eigen::Matrix4d& step, const Eigen::Matrix<double, 6, 1>& sigma,
                       ScanReport& report);
  Eigen::Matrix<double, 6, 1> step_sigma(double travelled_m) const;
  void build_local_map(Keyframe& keyframe);
  Eigen::Matrix4d registered_step(const Keyframe& keyframe, const Keyframe& previous, const Eigen::Matrix4d& guess,
                                  ScanReport& report, Eigen::Matrix<double, 6, 1>& sigma);
  template <typename Scalar>
  std::size_t buffer_scan(const PointsView<Scalar>& points, const Eigen::Matrix4d& odometry);
  void fuse(const Keyframe& keyframe);
  void rebuild();
  std::size_t close_loops(std::size_t k);
  void optimize();
};

void Mapper::Impl::build_local_map(Keyframe& keyframe) {
  auto start = Clock::now();
  ElevationParams elevation;
  elevation.resolution_m = params.resolution_m;
  const int cells = static_cast<int>(std::ceil(params.local_map_size_m / params.resolution_m));
  elevation.size = CellIndex(cells, cells);
  elevation.origin_m = Eigen::Vector2d::Constant(-0.5 * cells * params.resolution_m);
  elevation.discontinuity_m = params.discontinuity_m;
  elevation.num_threads = params.num_threads;
  // The keyframe's own scan and the buffered scans since the previous keyframe, moved into the
  // keyframe's leveled frame L by odometry (locally accurate): a denser local map than one scan.
  const Eigen::Matrix4d level_world = inverse_rigid(keyframe.odometry_level);
  std::size_t total = 0;
  for (const BufferedScan& scan : pending) total += scan.xyz.size() / 3;
  std::vector<float> leveled;
  leveled.reserve(3 * total);
  for (const BufferedScan& scan : pending) {
    const Eigen::Matrix4d t = level_world * scan.odometry;
    const Eigen::Matrix3f r = t.topLeftCorner<3, 3>().cast<float>();
    const Eigen::Vector3f o = t.topRightCorner<3, 1>().cast<float>();
    for (std::size_t i = 0; i + 2 < scan.xyz.size(); i += 3) {
      const Eigen::Vector3f q = r * Eigen::Vector3f(scan.xyz[i], scan.xyz[i + 1], scan.xyz[i + 2]) + o;
      leveled.insert(leveled.end(), {q.x(), q.y(), q.z()});
    }
  }
  keyframe.num_points = leveled.size() / 3;
  keyframe.num_scans = pending.size();
  keyframe.map = build_elevation_map(PointsView<float>(leveled.data(), leveled.size() / 3), elevation);
  timings.map_building_ms += ms_since(start);

  start = Clock::now();
  TerrainParams terrain = params.terrain;
  classify_terrain_layers(keyframe.map, terrain);
  keyframe.points = points_of_map(keyframe.map);
  if (params.registration.use_classes) {
    // Classes of weight 0 (unknown, ground) never pair: keep only the cells that can (ground too
    // when it registers as planes, ground_weight).
    const bool ground_planes = params.registration.ground_weight > 0.0;
    ClassifiedPoints kept;
    for (std::size_t i = 0; i < keyframe.points.size(); ++i) {
      const std::uint8_t c = keyframe.points.classes[i];
      if (params.registration.class_weights[c] > 0.0 ||
          (ground_planes && c == static_cast<std::uint8_t>(TerrainClass::kGround))) {
        kept.points.push_back(keyframe.points.points[i]);
        kept.classes.push_back(keyframe.points.classes[i]);
      }
    }
    keyframe.points = std::move(kept);
  }
  timings.classification_ms += ms_since(start);
  keyframe.geometry = keyframe.map.geometry();

  const MapGeometry& g = keyframe.map.geometry();
  const Layer& count = keyframe.map.get("count");
  const Layer& min = keyframe.map.get("min");
  const Layer& max = keyframe.map.get("max");
  const Layer& mean = keyframe.map.get("mean");
  const Layer& std_dev = keyframe.map.get("std_dev");
  const Layer& discontinuity = keyframe.map.get("discontinuity");
  const Layer& classes = keyframe.map.get("class");
  constexpr float kGroundValue = 1.0F;  // TerrainClass::kGround in the "class" layer
  keyframe.cells.clear();
  for (Eigen::Index i = 0; i < count.rows(); ++i) {
    for (Eigen::Index j = 0; j < count.cols(); ++j) {
      if (!(count(i, j) > 0.0f)) continue;
      const Eigen::Vector2d c = g.position_of(CellIndex(static_cast<int>(i), static_cast<int>(j)));
      keyframe.cells.push_back({static_cast<float>(c.x()), static_cast<float>(c.y()), min(i, j), max(i, j), mean(i, j),
                                std_dev(i, j), static_cast<std::uint32_t>(count(i, j)),
                                static_cast<std::uint8_t>(discontinuity(i, j) > 0.5f),
                                static_cast<std::uint8_t>(classes(i, j) == kGroundValue)});
    }
  }
}

void Mapper::Impl::fuse(const Keyframe& keyframe) {
  const Eigen::Matrix3d r = keyframe.estimate.topLeftCorner<3, 3>();
  const Eigen::Vector3d t = keyframe.estimate.topRightCorner<3, 1>();
  for (const CellSample& cell : keyframe.cells) {
    // The cell's column through (x, y): its world position at the mean elevation; the other
    // elevations move along the frame's z axis (a leveled frame's is vertical up to ICP's tilt).
    const Eigen::Vector3d at_mean = r * Eigen::Vector3d(cell.x, cell.y, cell.z_mean) + t;
    const double up = r(2, 2);
    global.fuse(at_mean.x(), at_mean.y(), static_cast<float>(at_mean.z() + up * (cell.z_min - cell.z_mean)),
                static_cast<float>(at_mean.z() + up * (cell.z_max - cell.z_mean)), static_cast<float>(at_mean.z()),
                cell.z_std, cell.count, cell.discontinuous != 0);
  }
}

void Mapper::Impl::rebuild() {
  global.clear();
  for (const Keyframe& keyframe : keyframes) fuse(keyframe);
}

template <typename Scalar>
ScanReport Mapper::Impl::add(const PointsView<Scalar>& points, const Eigen::Matrix4d& odometry) {
  detail::check_rigid_transform(odometry, "odometry pose");
  if (motion.have_last) {
    const double step = (odometry.topRightCorner<3, 1>() - motion.last_odometry.topRightCorner<3, 1>()).norm();
    if (!(step <= params.max_odometry_step_m)) {
      throw std::invalid_argument("odometry moved " + std::to_string(step) + " m since the previous scan, over " +
                                  "max_odometry_step_m = " + std::to_string(params.max_odometry_step_m) +
                                  " m: a glitch? The scan was not added");
    }
  }
  // Bad points throw from the map building below: leave the mapper as it was before this scan.
  struct Rollback {
    Impl& impl;
    std::size_t scans, keyframes, edges;
    Motion motion;
    bool done = false;
    ~Rollback() {
      if (done) return;
      impl.scans = scans, impl.timings.scans = scans, impl.motion = motion;
      impl.keyframes.resize(keyframes), impl.edges.resize(edges), impl.timings.keyframes = keyframes;
    }
  } rollback{*this, scans, keyframes.size(), edges.size(), motion};
  ScanReport report = add_checked(points, odometry);
  rollback.done = true;
  points_out_of_range += report.num_out_of_range;
  return report;
}

/// Keeps the scan's points within the range limits (as float x, y, z) for its local map; returns
/// how many it left out. Throws on NaN/Inf points before anything changes.
template <typename Scalar>
std::size_t Mapper::Impl::buffer_scan(const PointsView<Scalar>& points, const Eigen::Matrix4d& odometry) {
  BufferedScan scan;
  scan.odometry = odometry;
  scan.xyz.resize(3 * points.size);
  const double nearest = params.min_range_m * params.min_range_m;
  const double farthest = params.max_range_m * params.max_range_m;  // +inf without a limit
  std::size_t kept = 0;
  for (std::size_t i = 0; i < points.size; ++i) {
    const Eigen::Vector3d p = points.point(i);
    if (!p.allFinite()) {
      throw std::invalid_argument("scan point " + std::to_string(i) + " is NaN or Inf (of " +
                                  std::to_string(points.size) + " points)");
    }
    const double squared = p.squaredNorm();
    if (!(squared >= nearest && squared <= farthest)) continue;
    for (int axis = 0; axis < 3; ++axis) scan.xyz[3 * kept + axis] = static_cast<float>(p[axis]);
    ++kept;
  }
  scan.xyz.resize(3 * kept);
  while (!pending.empty() && pending.size() >= static_cast<std::size_t>(params.max_scans_per_local_map)) {
    pending.pop_front();
  }
  pending.push_back(std::move(scan));
  return points.size - kept;
}

template <typename Scalar>
ScanReport Mapper::Impl::add_checked(const PointsView<Scalar>& points, const Eigen::Matrix4d& odometry) {
  const std::size_t out_of_range = buffer_scan(points, odometry);  // throws on NaN/Inf before anything changes
  const std::size_t scan_index = scans++;
  timings.scans = scans;
  ScanReport report =
      params.lidar_only ? add_lidar_only(scan_index, odometry) : add_with_odometry(scan_index, odometry);
  report.num_out_of_range = out_of_range;
  return report;
}

/// The odometry standard deviations of a step over `travelled_m` (at least 0.1 m).
Eigen::Matrix<double, 6, 1> Mapper::Impl::step_sigma(double travelled_m) const {
  const double travelled = std::max(travelled_m, 0.1);
  Eigen::Matrix<double, 6, 1> sigma;
  sigma << Eigen::Vector3d::Constant(params.odometry_sigma_m_per_m * travelled),
      Eigen::Vector3d::Constant(params.odometry_sigma_rad_per_m * travelled);
  return sigma;
}

/// A keyframe every keyframe_distance_m of odometry's path (or keyframe_rotation_rad of turn),
/// its step from the previous keyframe registered from odometry's guess; the scans between are
/// buffered for its local map (max_scans_per_local_map).
ScanReport Mapper::Impl::add_with_odometry(std::size_t scan_index, const Eigen::Matrix4d& odometry) {
  ScanReport report;
  if (motion.have_last) {
    motion.path_m += (odometry.topRightCorner<3, 1>() - motion.last_odometry.topRightCorner<3, 1>()).norm();
  }
  motion.last_odometry = odometry;
  motion.have_last = true;

  if (!keyframes.empty()) {
    const Keyframe& last = keyframes.back();
    const bool moved = motion.path_m - last.path_m >= params.keyframe_distance_m;
    const bool turned = rotation_angle(inverse_rigid(last.odometry) * odometry) >= params.keyframe_rotation_rad;
    if (!moved && !turned) {
      report.pose = last.estimate * inverse_rigid(last.odometry_level) * odometry;
      return report;
    }
  }

  Keyframe keyframe;
  keyframe.scan_index = scan_index;
  keyframe.odometry = odometry;
  keyframe.path_m = motion.path_m;
  split_leveling(odometry, keyframe.odometry_level, keyframe.level_sensor);
  build_local_map(keyframe);
  pending.clear();
  if (keyframes.empty()) {
    keyframe.estimate = keyframe.odometry_level;
    append_keyframe(std::move(keyframe), Eigen::Matrix4d::Identity(), step_sigma(0.0), report);
    return report;
  }
  const Keyframe& previous = keyframes.back();
  // Odometry's motion between the leveled frames: the initial guess of the registration.
  const Eigen::Matrix4d guess = inverse_rigid(previous.odometry_level) * keyframe.odometry_level;
  Eigen::Matrix<double, 6, 1> sigma = step_sigma(keyframe.path_m - previous.path_m);
  Eigen::Matrix4d step = guess;
  if (params.use_registration) {
    step = registered_step(keyframe, previous, guess, report, sigma);
    if (report.registered && params.ground_step_height) step(2, 3) += shared_ground_offset(keyframe, previous, step);
  }
  keyframe.estimate = previous.estimate * step;
  append_keyframe(std::move(keyframe), step, sigma, report);
  return report;
}

/// LiDAR-only: every scan registered to the newest keyframe from the constant-velocity prediction;
/// a keyframe once the estimates travelled keyframe_distance_m (or turned keyframe_rotation_rad)
/// since the newest one.
ScanReport Mapper::Impl::add_lidar_only(std::size_t scan_index, const Eigen::Matrix4d& attitude) {
  ScanReport report;
  Keyframe scan;  // a keyframe if it is far enough from the newest one
  scan.scan_index = scan_index;
  split_leveling(attitude, scan.odometry_level, scan.level_sensor);
  if (!keyframes.empty()) scan.odometry_level = motion.last_estimate * motion.velocity;  // the prediction
  scan.odometry = scan.odometry_level * scan.level_sensor;
  pending.back().odometry = scan.odometry;  // the scan (the only one pending) in its own frame
  build_local_map(scan);
  pending.clear();
  if (keyframes.empty()) {
    scan.estimate = motion.last_estimate = scan.odometry_level;
    append_keyframe(std::move(scan), Eigen::Matrix4d::Identity(), step_sigma(0.0), report);
    return report;
  }
  const Keyframe& previous = keyframes.back();
  const Eigen::Matrix4d guess = inverse_rigid(previous.estimate) * scan.odometry_level;
  Eigen::Matrix<double, 6, 1> sigma = step_sigma(guess.topRightCorner<3, 1>().norm());
  Eigen::Matrix4d step = registered_step(scan, previous, guess, report, sigma);
  if (report.registered && params.ground_step_height) step(2, 3) += shared_ground_offset(scan, previous, step);
  scan.estimate = previous.estimate * step;
  motion.velocity = inverse_rigid(motion.last_estimate) * scan.estimate;
  motion.have_velocity = motion.have_velocity || report.registered;
  motion.last_estimate = scan.estimate;
  motion.path_m += motion.velocity.topRightCorner<3, 1>().norm();
  scan.path_m = motion.path_m;
  report.pose = scan.estimate * scan.level_sensor;
  const bool moved = motion.path_m - previous.path_m >= params.keyframe_distance_m;
  const bool turned = rotation_angle(step) >= params.keyframe_rotation_rad;
  if (moved || turned) append_keyframe(std::move(scan), step, sigma, report);
  return report;
}

/// Adds `keyframe` (its estimate set) with the step from the previous keyframe (none for the
/// first), fuses it into the global map and looks for loops.
void Mapper::Impl::append_keyframe(Keyframe keyframe, const Eigen::Matrix4d& step,
                                   const Eigen::Matrix<double, 6, 1>& sigma, ScanReport& report) {
  report.keyframe = true;
  report.index = static_cast<std::ptrdiff_t>(keyframes.size());
  if (!keyframes.empty()) {
    edges.push_back({keyframes.size() - 1, keyframes.size(), step, sigma, false});
    if (!params.keep_local_maps) keyframes.back().map = ElevationMap();
  }
  keyframes.push_back(std::move(keyframe));
  timings.keyframes = keyframes.size();

  auto start = Clock::now();
  fuse(keyframes.back());
  timings.fusion_ms += ms_since(start);

  if (params.loop_closing) {
    start = Clock::now();
    report.loops_closed = close_loops(keyframes.size() - 1);
    pending_loops += report.loops_closed;
    // While a revisit keeps closing loops, optimise (and rebuild the map) at most every
    // optimize_interval_keyframes keyframes; optimize() applies the rest.
    if (pending_loops > 0 &&
        keyframes.size() - optimized_at >= static_cast<std::size_t>(params.optimize_interval_keyframes)) {
      optimize();
    }
    timings.loop_closing_ms += ms_since(start);
  }
  // After any optimisation above: the scans until the next keyframe are posed from this estimate too.
  report.pose = keyframes.back().estimate * keyframes.back().level_sensor;
}

/// The step L_{k-1} <- L_k from the previous keyframe: registered from `guess` when the result
/// is trusted and its correction of the guess within bounds (then `sigma` becomes the
/// registration's), else the guess.
Eigen::Matrix4d Mapper::Impl::registered_step(const Keyframe& keyframe, const Keyframe& previous,
                                              const Eigen::Matrix4d& guess, ScanReport& report,
                                              Eigen::Matrix<double, 6, 1>& sigma) {
  Eigen::Matrix4d step = guess;
  const auto start = Clock::now();
  RegistrationParams registration = params.registration;
  // LiDAR-only without a velocity yet: the search covers a keyframe's travel.
  const bool first_blind_step = params.lidar_only && !motion.have_velocity;
  if (first_blind_step) registration.search.window_m += params.keyframe_distance_m;
  if (!params.lidar_only && registration.correlative_search) {
    // Odometry is usually close: the ICP from it alone first (the search can only blur a good
    // guess); the search only when that answer is not trusted (a slip, a bad guess).
    RegistrationParams from_guess = registration;
    from_guess.correlative_search = false;
    report.registration = register_points(keyframe.points, previous.points, guess, from_guess);
    if (!report.registration.trusted) {
      report.registration = register_points(keyframe.points, previous.points, guess, registration);
    }
  } else {
    report.registration = register_points(keyframe.points, previous.points, guess, registration);
  }
  timings.registration_ms += ms_since(start);
  const RegistrationResult& r = report.registration;
  // The correction the step would apply (its yaw and translation with yaw_only_registration).
  const Eigen::Matrix4d candidate = params.yaw_only_registration ? yaw_only(r.transform) : r.transform;
  const Eigen::Matrix4d correction = inverse_rigid(guess) * candidate;
  // LiDAR-only, there is no independent guess to bound the correction by: the verdict decides.
  const double max_correction_m = params.lidar_only ? kInfinity : params.max_correction_m;
  const double max_correction_rad = params.lidar_only ? kInfinity : params.max_correction_rad;
  if (!r.trusted) {
    ++timings.untrusted_steps;
  } else if (correction.topRightCorner<3, 1>().norm() <= max_correction_m &&
             rotation_angle(correction) <= max_correction_rad) {
    step = candidate;
    report.registered = true;
    ++timings.registered_steps;
    sigma << Eigen::Vector3d::Constant(params.registration_sigma_m),
        Eigen::Vector3d::Constant(params.registration_sigma_rad);
  }
  return step;
}

std::size_t Mapper::Impl::close_loops(std::size_t k) {
  const Keyframe& current = keyframes[k];
  const Eigen::Vector3d position = current.estimate.topRightCorner<3, 1>();
  // Candidates: far enough along the path, near in space; nearest first.
  std::vector<std::pair<double, std::size_t>> candidates;
  for (std::size_t j = 0; j < k; ++j) {
    if (current.path_m - keyframes[j].path_m < params.loop_min_travel_m) continue;
    const double distance = (keyframes[j].estimate.topRightCorner<3, 1>() - position).norm();
    if (distance <= params.loop_search_radius_m) candidates.emplace_back(distance, j);
  }
  std::sort(candidates.begin(), candidates.end());
  std::size_t closed = 0;
  int tried = 0;
  for (const auto& [distance, j] : candidates) {
    if (tried >= params.loop_max_candidates) break;
    const Keyframe& other = keyframes[j];
    const Eigen::Matrix4d guess = inverse_rigid(other.estimate) * current.estimate;  // L_j <- L_k
    // Overlap: the share of the current map's cells that land in blocks of overlap_block_m with data
    // in the other map (blocks, not cells: sparse scans sample different cells of the same ground).
    const MapGeometry& g = other.geometry;
    const int per_block = std::max(1, static_cast<int>(std::lround(params.overlap_block_m / g.resolution_m)));
    const int bx = (g.size.x() + per_block - 1) / per_block, by = (g.size.y() + per_block - 1) / per_block;
    std::vector<std::uint8_t> blocks(static_cast<std::size_t>(bx) * by, 0);
    for (const CellSample& cell : other.cells) {
      const auto index = g.index_of(Eigen::Vector2d(cell.x, cell.y));
      if (index) blocks[static_cast<std::size_t>(index->x() / per_block) * by + index->y() / per_block] = 1;
    }
    std::size_t hits = 0;
    for (const CellSample& cell : current.cells) {
      const Eigen::Vector3d p =
          guess.topLeftCorner<3, 3>() * Eigen::Vector3d(cell.x, cell.y, cell.z_mean) + guess.topRightCorner<3, 1>();
      const auto index = g.index_of(p.head<2>());
      if (index && blocks[static_cast<std::size_t>(index->x() / per_block) * by + index->y() / per_block]) ++hits;
    }
    const double overlap = current.cells.empty() ? 0.0 : static_cast<double>(hits) / current.cells.size();
    if (overlap < params.loop_min_overlap) continue;
    ++tried;
    // The correlative search shared with register_points, over the loop's wider window (two-cell
    // steps); the ICP then starts from its best hypothesis.
    CorrelativeSearchParams search;
    search.window_m = params.loop_search_window_m;
    search.cell_m = other.geometry.resolution_m;
    search.step_cells = 2;
    search.yaw_window_rad = params.loop_yaw_search_rad;
    search.yaw_hypotheses = params.loop_yaw_hypotheses;
    const Eigen::Matrix4d start = correlative_search(current.points, other.points, guess, search).transform;
    RegistrationParams registration = params.registration;
    registration.correlative_search = false;
    std::size_t weighted = 0;  // source cells that can take part
    for (const std::uint8_t c : current.points.classes) {
      weighted += !registration.use_classes || registration.class_weights[c] > 0.0;
    }
    const double min_pairs = std::max<double>(static_cast<double>(params.registration.min_correspondences),
                                              params.loop_min_inlier_ratio * static_cast<double>(weighted));
    std::optional<RegistrationResult> best = register_points(current.points, other.points, start, registration);
    const RegistrationResult& r0 = *best;
    const bool usable = r0.converged || r0.reason == StopReason::kMaxIterations;
    if (!usable || !(r0.rmse_m <= params.loop_max_rmse_m) || static_cast<double>(r0.num_correspondences) < min_pairs) {
      best.reset();
    }
    if (!best) continue;
    const RegistrationResult& r = *best;
    Eigen::Matrix<double, 6, 1> sigma;
    sigma << Eigen::Vector3d::Constant(params.registration_sigma_m),
        Eigen::Vector3d::Constant(params.registration_sigma_rad);
    Eigen::Matrix4d relative = params.yaw_only_registration ? yaw_only(r.transform) : r.transform;
    if (params.ground_step_height) relative(2, 3) += shared_ground_offset(current, other, relative);
    edges.push_back({j, k, relative, sigma, true});
    loops.push_back({j, k, relative, r.rmse_m, overlap});
    ++closed;
  }
  return closed;
}

void Mapper::Impl::optimize() {
  pending_loops = 0;
  optimized_at = keyframes.size();
  if (loops.empty() || keyframes.size() < 2) return;
  std::vector<Eigen::Matrix4d> poses;
  poses.reserve(keyframes.size());
  for (const Keyframe& keyframe : keyframes) poses.push_back(keyframe.estimate);
  std::vector<PoseGraphEdge> graph;
  graph.reserve(edges.size());
  for (const Edge& edge : edges) {
    PoseGraphEdge e;
    e.from = edge.from;
    e.to = edge.to;
    e.measurement = edge.relative;
    e.information = edge.sigma.cwiseAbs2().cwiseInverse().asDiagonal();
    e.robust = edge.loop;
    graph.push_back(e);
  }
  PoseGraphParams pose_graph;
  pose_graph.max_iterations = params.pose_graph_iterations;
  const PoseGraphResult result = optimize_pose_graph(poses, graph, pose_graph);
  for (std::size_t k = 0; k < keyframes.size(); ++k) keyframes[k].estimate = result.poses[k];
  const auto start = Clock::now();
  rebuild();
  timings.fusion_ms += ms_since(start);
}

Mapper::Mapper(const MapperParams& params) {
  check_mapper_params(params);
  impl_ = std::make_unique<Impl>(params);
}
Mapper::~Mapper() = default;
Mapper::Mapper(Mapper&&) noexcept = default;
Mapper& Mapper::operator=(Mapper&&) noexcept = default;

const MapperParams& Mapper::params() const { return impl_->params; }
ScanReport Mapper::add_scan(const PointsView<float>& points, const Eigen::Matrix4d& odometry_pose) {
  return impl_->add(points, odometry_pose);
}
ScanReport Mapper::add_scan(const PointsView<double>& points, const Eigen::Matrix4d& odometry_pose) {
  return impl_->add(points, odometry_pose);
}
std::size_t Mapper::num_keyframes() const { return impl_->keyframes.size(); }
std::size_t Mapper::pending_loops() const { return impl_->pending_loops; }
std::size_t Mapper::points_out_of_range() const { return impl_->points_out_of_range; }

std::vector<Eigen::Matrix4d> Mapper::keyframe_poses() const {
  std::vector<Eigen::Matrix4d> poses;
  for (const Keyframe& k : impl_->keyframes) poses.push_back(k.estimate * k.level_sensor);
  return poses;
}
std::vector<Eigen::Matrix4d> Mapper::keyframe_odometry() const {
  std::vector<Eigen::Matrix4d> poses;
  for (const Keyframe& k : impl_->keyframes) poses.push_back(k.odometry);
  return poses;
}
std::vector<std::size_t> Mapper::keyframe_scan_indices() const {
  std::vector<std::size_t> indices;
  for (const Keyframe& k : impl_->keyframes) indices.push_back(k.scan_index);
  return indices;
}
const std::vector<LoopClosure>& Mapper::loop_closures() const { return impl_->loops; }
const MapperTimings& Mapper::timings() const { return impl_->timings; }

const ElevationMap& Mapper::local_map(std::size_t k) const {
  if (k >= impl_->keyframes.size()) {
    throw std::out_of_range("keyframe " + std::to_string(k) + " does not exist (" +
                            std::to_string(impl_->keyframes.size()) + " keyframes)");
  }
  if (impl_->keyframes[k].map.layers().empty()) {
    throw std::out_of_range("the local map of keyframe " + std::to_string(k) +
                            " was not kept (only the newest is, unless MapperParams.keep_local_maps)");
  }
  return impl_->keyframes[k].map;
}

ElevationMap Mapper::global_map(bool classify) const {
  ElevationMap map = impl_->global.to_map();
  if (classify && map.geometry().num_cells() > 0) classify_terrain_layers(map, impl_->params.terrain);
  return map;
}
const TiledElevationMap& Mapper::tiles() const { return impl_->global; }
void Mapper::optimize() { impl_->optimize(); }

}  // namespace terracube
