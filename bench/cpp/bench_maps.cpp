// C++-only timings of the elevation map, the terrain classes and the class-weighted ICP on KITTI
// (Google Benchmark). The side-by-side comparisons with numpy and PCL live in
// bench/bench_elevation.py and bench/bench_icp.py; this one times the C++ calls alone, for
// before/after runs of two builds.
#include <benchmark/benchmark.h>
#include <terracube/collapse.hpp>
#include <terracube/elevation_map.hpp>
#include <terracube/icp.hpp>
#include <terracube/mapper.hpp>
#include <terracube/terrain.hpp>

#include <Eigen/Geometry>
#include <array>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

namespace {

namespace fs = std::filesystem;

fs::path data_dir() {
  const char* env = std::getenv("TERRACUBE_DATA_DIR");
  for (const fs::path dir :
       {fs::path(env ? env : ""), fs::path(TERRACUBE_DEFAULT_DATA_DIR), fs::path("/work/shared/data")}) {
    if (fs::is_directory(dir / "kitti_seq00" / "velodyne")) return dir;
  }
  return {};
}

/// KITTI seq 00 scan `frame` (x y z intensity float rows), empty when the data is missing.
const std::vector<float>& kitti_scan(int frame) {
  static std::map<int, std::vector<float>> scans;
  auto [it, fresh] = scans.try_emplace(frame);
  if (!fresh) return it->second;
  const fs::path dir = data_dir();
  if (dir.empty()) return it->second;
  char name[16];
  std::snprintf(name, sizeof name, "%06d.bin", frame);
  std::ifstream file(dir / "kitti_seq00" / "velodyne" / name, std::ios::binary | std::ios::ate);
  if (!file) return it->second;
  it->second.resize(static_cast<std::size_t>(file.tellg()) / sizeof(float));
  file.seekg(0);
  file.read(reinterpret_cast<char*>(it->second.data()), static_cast<std::streamsize>(it->second.size() * 4));
  return it->second;
}

/// The bench_icp.py maps: 40 x 20 m at 0.1 m around the sensor.
terracube::ElevationParams map_params() {
  terracube::ElevationParams params;
  params.resolution_m = 0.1;
  params.origin_m = Eigen::Vector2d(-20.0, -10.0);
  params.size = terracube::CellIndex(400, 200);
  return params;
}

terracube::TerrainParams terrain_params() {
  terracube::TerrainParams params;
  params.sensor_height_m = 1.73;  // KITTI's Velodyne above the road
  return params;
}

terracube::PointsView<float> view_of(const std::vector<float>& xyzi) {
  return terracube::PointsView<float>(xyzi.data(), xyzi.size() / 4, 4, 1);
}

bool skip_without_kitti(benchmark::State& state) {
  if (!kitti_scan(0).empty()) return false;
  state.SkipWithError("KITTI seq 00 not found (set TERRACUBE_DATA_DIR)");
  return true;
}

/// The map path's cases: KITTI frame 0, the map's and the classes' parameters, both on
/// `state.range(0)` threads (1, or 0: every processor).
struct MapCase {
  terracube::PointsView<float> points;
  terracube::ElevationParams params = map_params();
  terracube::TerrainParams terrain = terrain_params();
  explicit MapCase(const benchmark::State& state) : points(view_of(kitti_scan(0))) {
    params.num_threads = terrain.num_threads = static_cast<int>(state.range(0));
  }
};

/// On `state.range(0)` threads (1, or 0: every processor).
void BM_BuildElevationMapKitti(benchmark::State& state) {
  if (skip_without_kitti(state)) return;
  const auto points = view_of(kitti_scan(0));
  terracube::ElevationParams params = map_params();
  params.num_threads = static_cast<int>(state.range(0));
  for (auto _ : state) benchmark::DoNotOptimize(terracube::build_elevation_map(points, params));
}
BENCHMARK(BM_BuildElevationMapKitti)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond);

void BM_MapAndClassifyKittiRefilled(benchmark::State& state) {
  if (skip_without_kitti(state)) return;
  const MapCase c(state);
  terracube::ElevationMap map = terracube::build_elevation_map(c.points, c.params);
  for (auto _ : state) {
    terracube::build_elevation_map_into(map, c.points, c.params);
    benchmark::DoNotOptimize(terracube::classify_terrain_layers(map, c.terrain));
  }
}
BENCHMARK(BM_MapAndClassifyKittiRefilled)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond);

/// The two parts of the refilled loop above, each alone: the refill (which also sets the class
/// layers of the previous classification to NaN) and the classification.
void BM_RefillClassifiedMapKitti(benchmark::State& state) {
  if (skip_without_kitti(state)) return;
  const MapCase c(state);
  terracube::ElevationMap map = terracube::build_elevation_map(c.points, c.params);
  terracube::classify_terrain_layers(map, c.terrain);
  for (auto _ : state) terracube::build_elevation_map_into(map, c.points, c.params);
}
BENCHMARK(BM_RefillClassifiedMapKitti)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond);

void BM_ClassifyTerrainKitti(benchmark::State& state) {
  if (skip_without_kitti(state)) return;
  const MapCase c(state);
  terracube::ElevationMap map = terracube::build_elevation_map(c.points, c.params);
  for (auto _ : state) benchmark::DoNotOptimize(terracube::classify_terrain_layers(map, c.terrain));
}
BENCHMARK(BM_ClassifyTerrainKitti)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond);

/// A fresh map + classes with the caches cold, as after other work (in bench_elevation.py: after a
/// numpy call): 64 MB are written and read between calls, outside the timing.
void BM_MapAndClassifyKittiCold(benchmark::State& state) {
  if (skip_without_kitti(state)) return;
  const MapCase c(state);
  std::vector<std::uint64_t> other(std::size_t{8} << 20, 1);
  std::uint64_t sink = 0;
  for (auto _ : state) {
    state.PauseTiming();
    for (std::uint64_t& word : other) sink += word++;
    state.ResumeTiming();
    terracube::ElevationMap map = terracube::build_elevation_map(c.points, c.params);
    benchmark::DoNotOptimize(terracube::classify_terrain_layers(map, c.terrain));
  }
  benchmark::DoNotOptimize(sink);
}
BENCHMARK(BM_MapAndClassifyKittiCold)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond);

void BM_DemWithoutOverhangsKitti(benchmark::State& state) {
  if (skip_without_kitti(state)) return;
  const auto points = view_of(kitti_scan(0));
  terracube::CollapseParams collapse;  // bench_elevation.py's: edge 0.5 m, sigma 5, its crop box
  collapse.edge_m = 0.5;
  collapse.sigma = 5;
  collapse.crop = terracube::CropBox{{-100.0, -100.0, -3.0}, {100.0, 100.0, 30.0}};
  const terracube::ElevationParams params = map_params();
  for (auto _ : state) benchmark::DoNotOptimize(terracube::build_overhang_free_map(points, collapse, params));
}
BENCHMARK(BM_DemWithoutOverhangsKitti)->Unit(benchmark::kMillisecond);

/// World <- velodyne pose of each KITTI frame: Tr^-1 P Tr (poses are of the left camera).
std::vector<Eigen::Matrix4d> kitti_world_velo() {
  const fs::path dir = data_dir();
  std::ifstream calib(dir / "kitti_seq00" / "calib.txt");
  Eigen::Matrix4d tr = Eigen::Matrix4d::Identity();
  for (std::string line; std::getline(calib, line);) {
    if (line.rfind("Tr:", 0) != 0) continue;
    std::istringstream values(line.substr(3));
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 4; ++c) values >> tr(r, c);
    }
  }
  std::vector<Eigen::Matrix4d> out;
  std::ifstream poses(dir / "kitti_seq00" / "poses.txt");
  for (std::string line; std::getline(poses, line);) {
    std::istringstream values(line);
    Eigen::Matrix4d p = Eigen::Matrix4d::Identity();
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 4; ++c) values >> p(r, c);
    }
    out.push_back(tr.inverse() * p * tr);
  }
  return out;
}

/// KITTI frame `s` registered onto frame `t` with the weighted ICP's defaults, from the ground
/// truth moved by 0.25 m and 2.5 degrees (one of bench_icp.py's perturbations, fixed here).
void BM_RegisterKitti(benchmark::State& state) {
  if (skip_without_kitti(state)) return;
  const auto s = static_cast<int>(state.range(0));
  const auto t = static_cast<int>(state.range(1));
  const terracube::ElevationParams params = map_params();
  const terracube::TerrainParams terrain = terrain_params();
  terracube::ElevationMap source = terracube::build_elevation_map(view_of(kitti_scan(s)), params);
  terracube::ElevationMap target = terracube::build_elevation_map(view_of(kitti_scan(t)), params);
  terracube::classify_terrain_layers(source, terrain);
  terracube::classify_terrain_layers(target, terrain);
  const std::vector<Eigen::Matrix4d> world = kitti_world_velo();
  const Eigen::Matrix4d truth = world.at(static_cast<std::size_t>(t)).inverse() * world.at(static_cast<std::size_t>(s));
  Eigen::Matrix4d offset = Eigen::Matrix4d::Identity();
  offset.topLeftCorner<3, 3>() =
      Eigen::AngleAxisd(2.5 * M_PI / 180.0, Eigen::Vector3d(0.3, -0.2, 1.0).normalized()).toRotationMatrix();
  offset.topRightCorner<3, 1>() = Eigen::Vector3d(0.6, -0.5, 0.3).normalized() * 0.25;
  const Eigen::Matrix4d guess = offset * truth;
  int iterations = 0;
  for (auto _ : state) {
    const terracube::RegistrationResult result = terracube::register_maps(source, target, guess);
    iterations = result.iterations;
    benchmark::DoNotOptimize(result.transform);
  }
  state.counters["iterations"] = iterations;
}
BENCHMARK(BM_RegisterKitti)->Args({0, 1})->Args({2, 3})->Args({0, 5})->Unit(benchmark::kMillisecond);

/// The Mapper with its defaults over KITTI frames 0-5 (the ground truth as odometry), on
/// `state.range(0)` threads: the time of one scan, averaged over the six (a fresh Mapper per round).
void BM_MapperPerScanKitti(benchmark::State& state) {
  if (skip_without_kitti(state)) return;
  const std::vector<Eigen::Matrix4d> world = kitti_world_velo();
  constexpr int kScans = 6;
  terracube::MapperParams params;
  params.num_threads = static_cast<int>(state.range(0));
  for (int frame = 0; frame < kScans; ++frame) kitti_scan(frame);  // read before the timing
  for (auto _ : state) {
    terracube::Mapper mapper(params);
    for (int frame = 0; frame < kScans; ++frame) {
      benchmark::DoNotOptimize(mapper.add_scan(view_of(kitti_scan(frame)), world.at(static_cast<std::size_t>(frame))));
    }
  }
  state.SetItemsProcessed(state.iterations() * kScans);
}
BENCHMARK(BM_MapperPerScanKitti)->Arg(1)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
