// C++-only timings of collapse_overhangs and its C++ baselines (Google Benchmark).
// The side-by-side comparison with numpy lives in bench/bench_collapse.py.
#include <benchmark/benchmark.h>
#include <terracube/baselines.hpp>
#include <terracube/collapse.hpp>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <random>

namespace {

std::vector<double> synthetic_cloud(std::size_t n) {
  std::mt19937_64 rng(42);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, 0.05);
  std::vector<double> xyz(3 * n);
  for (std::size_t i = 0; i < n; ++i) {
    const double x = 50.0 * unit(rng);
    const double y = 50.0 * unit(rng);
    double z = 0.3 * std::sin(0.3 * x) + noise(rng);
    if (unit(rng) < 0.2) z += 2.0 + 4.0 * unit(rng);
    xyz[3 * i] = x;
    xyz[3 * i + 1] = y;
    xyz[3 * i + 2] = z;
  }
  return xyz;
}

/// x y z intensity float rows of a file under the data directory, empty when it is missing.
std::vector<float> xyzi_scan(const char* relative) {
  namespace fs = std::filesystem;
  const char* env = std::getenv("TERRACUBE_DATA_DIR");
  for (const fs::path dir :
       {fs::path(env ? env : ""), fs::path(TERRACUBE_DEFAULT_DATA_DIR), fs::path("/work/shared/data")}) {
    std::ifstream file(dir / relative, std::ios::binary | std::ios::ate);
    if (!file) continue;
    std::vector<float> values(static_cast<std::size_t>(file.tellg()) / sizeof(float));
    file.seekg(0);
    file.read(reinterpret_cast<char*>(values.data()), static_cast<std::streamsize>(values.size() * sizeof(float)));
    return values;
  }
  return {};
}

void BM_CollapseSynthetic500k(benchmark::State& state) {
  static const std::vector<double> xyz = synthetic_cloud(500000);
  terracube::CollapseParams params;
  params.edge_m = 0.5;
  params.sigma = 2;
  const terracube::PointsView<double> view(xyz.data(), xyz.size() / 3);
  for (auto _ : state) benchmark::DoNotOptimize(terracube::collapse_overhangs(view, params));
  state.SetItemsProcessed(state.iterations() * static_cast<std::int64_t>(view.size));
}
BENCHMARK(BM_CollapseSynthetic500k)->Unit(benchmark::kMillisecond);

void BM_CollapseSynthetic500kSparse(benchmark::State& state) {
  static const std::vector<double> xyz = synthetic_cloud(500000);
  terracube::CollapseParams params;
  params.storage = terracube::CubeStorage::kSparse;
  const terracube::PointsView<double> view(xyz.data(), xyz.size() / 3);
  for (auto _ : state) benchmark::DoNotOptimize(terracube::collapse_overhangs(view, params));
  state.SetItemsProcessed(state.iterations() * static_cast<std::int64_t>(view.size));
}
BENCHMARK(BM_CollapseSynthetic500kSparse)->Unit(benchmark::kMillisecond);

template <int kMethod>
void BM_Kitti(benchmark::State& state) {
  static const std::vector<float> values = xyzi_scan("kitti_seq00/velodyne/000000.bin");
  if (values.empty()) {
    state.SkipWithError("KITTI scan not found");
    return;
  }
  const terracube::PointsView<float> view(values.data(), values.size() / 4, 4, 1);
  terracube::CollapseParams params;
  const terracube::PointBasedParams point_based;  // E = 0.5 m, sigma = 2, as params
  for (auto _ : state) {
    if constexpr (kMethod == 0) benchmark::DoNotOptimize(terracube::collapse_overhangs(view, params));
    if constexpr (kMethod == 1) benchmark::DoNotOptimize(terracube::point_based_overhangs(view, point_based));
    if constexpr (kMethod == 2) benchmark::DoNotOptimize(terracube::octomap_column_overhangs(view, params));
  }
  state.SetItemsProcessed(state.iterations() * static_cast<std::int64_t>(view.size));
}
BENCHMARK(BM_Kitti<0>)->Name("BM_KittiCollapse")->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Kitti<1>)->Name("BM_KittiPointBased")->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Kitti<2>)->Name("BM_KittiOctomap")->Unit(benchmark::kMillisecond);

/// The bundled-size Ouster OS-128 scan of bench_collapse.py, on `state.range(0)` threads.
void BM_OusterCollapse(benchmark::State& state) {
  static const std::vector<float> values = xyzi_scan("ouster128/ouster128_000000_xyzi_valid.bin");
  if (values.empty()) {
    state.SkipWithError("Ouster scan not found");
    return;
  }
  const terracube::PointsView<float> view(values.data(), values.size() / 4, 4, 1);
  terracube::CollapseParams params;
  params.num_threads = static_cast<int>(state.range(0));
  for (auto _ : state) benchmark::DoNotOptimize(terracube::collapse_overhangs(view, params));
  state.SetItemsProcessed(state.iterations() * static_cast<std::int64_t>(view.size));
}
BENCHMARK(BM_OusterCollapse)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
