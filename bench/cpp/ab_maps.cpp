// Paired before/after timing of two builds of the elevation map path in one process (used by
// bench/ab_builds.sh, which compiles this file three times):
//  - with TERRACUBE_AB_SIDE=A (or B) and -Dterracube=tcA (tcB), against that build's headers: the
//    side's calls, run_A / run_B;
//  - with neither: main(), which loads KITTI 00/000000 and times the two sides in alternation.
// Each round times `reps` calls of one side, then of the other (which one goes first alternates),
// so that both see the same stretch of the shared machine; the ratio B / A of each round is kept and
// their median and quartiles printed. Code placement alone moves a side by up to about 5 %, which
// is why ab_builds.sh also runs the two builds with the sides swapped.
//
// On several threads each side has its own thread pool (revisions since the library's own pool).
// Before a side's round the program sleeps 25 ms, so that the other side's pool threads stop
// spinning (they sleep after 20 ms without work), then makes untimed calls for 25 ms: calls that
// keep coming for 20 ms wake this side's threads, and the timed calls find them awake.
#include <cstddef>

#ifdef TERRACUBE_AB_SIDE

#include <terracube/collapse.hpp>
#include <terracube/elevation_map.hpp>
#include <terracube/terrain.hpp>
#include <vector>

#define TERRACUBE_AB_CAT2(a, b) a##b
#define TERRACUBE_AB_CAT(a, b) TERRACUBE_AB_CAT2(a, b)

namespace {
struct Side {
  terracube::ElevationParams map;
  terracube::TerrainParams terrain;
  terracube::ElevationMap refilled;
  std::vector<double> xyz;  ///< the scan as float64 x y z rows (numpy's default dtype), for WHAT 4
  bool ready = false;
};
Side& side() {
  static Side s;
  return s;
}
}  // namespace

/// `reps` calls of `what` (0: refill one map + classes, 1: fresh map + classes, 2: fresh map, 4:
/// fresh map + classes from float64 x y z rows, 5: collapse_overhangs with E 0.5 m and sigma 2 as
/// bench_collapse_cpp, 6: the same from float64 rows) on `threads` threads; returns a checksum.
std::size_t TERRACUBE_AB_CAT(run_, TERRACUBE_AB_SIDE)(const float* xyzi, std::size_t rows, int what, int reps,
                                                      int threads) {
  const terracube::PointsView<float> view(xyzi, rows, 4, 1);
  Side& s = side();
  if (!s.ready) {
    s.map.resolution_m = 0.1;
    s.map.origin_m = Eigen::Vector2d(-20.0, -10.0);
    s.map.size = terracube::CellIndex(400, 200);
    s.terrain.sensor_height_m = 1.73;
    s.refilled = terracube::build_elevation_map(view, s.map);
    s.xyz.resize(3 * rows);
    for (std::size_t row = 0; row < rows; ++row) {
      for (std::size_t axis = 0; axis < 3; ++axis) s.xyz[3 * row + axis] = xyzi[4 * row + axis];
    }
    s.ready = true;
  }
  s.map.num_threads = threads;
  s.terrain.num_threads = threads;
  std::size_t sum = 0;
  for (int r = 0; r < reps; ++r) {
    if (what == 5 || what == 6) {
      terracube::CollapseParams collapse;
      collapse.edge_m = 0.5;
      collapse.sigma = 2;
      collapse.num_threads = threads;
      const terracube::CollapseResult result =
          what == 5 ? terracube::collapse_overhangs(view, collapse)
                    : terracube::collapse_overhangs(terracube::PointsView<double>(s.xyz.data(), rows, 3, 1), collapse);
      sum += result.num_overhang + result.occupied_cubes.size();
    } else if (what == 0) {
      terracube::build_elevation_map_into(s.refilled, view, s.map);
      sum += static_cast<std::size_t>(terracube::classify_terrain_layers(s.refilled, s.terrain)(200, 100));
    } else if (what == 1 || what == 4) {
      terracube::ElevationMap fresh =
          what == 1 ? terracube::build_elevation_map(view, s.map)
                    : terracube::build_elevation_map(terracube::PointsView<double>(s.xyz.data(), rows, 3, 1), s.map);
      sum += static_cast<std::size_t>(terracube::classify_terrain_layers(fresh, s.terrain)(200, 100));
    } else {
      sum += static_cast<std::size_t>(terracube::build_elevation_map(view, s.map).get("count")(200, 100));
    }
  }
  return sum;
}

#else

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

std::size_t run_A(const float* xyzi, std::size_t rows, int what, int reps, int threads);
std::size_t run_B(const float* xyzi, std::size_t rows, int what, int reps, int threads);

namespace {
double quantile(std::vector<double> values, double q) {
  std::sort(values.begin(), values.end());
  return values[static_cast<std::size_t>(q * static_cast<double>(values.size() - 1) + 0.5)];
}
}  // namespace

int main(int argc, char** argv) {
  if (argc != 6) {
    std::fprintf(stderr,
                 "usage: %s KITTI_BIN WHAT(0 refill+classes, 1 fresh+classes, 2 fresh map, 3 fresh+classes cold, 4 "
                 "fresh+classes from float64, 5 collapse, 6 collapse from float64) "
                 "THREADS ROUNDS REPS\n",
                 argv[0]);
    return 2;
  }
  const int what = std::atoi(argv[2]);
  const int threads = std::atoi(argv[3]);
  const int rounds = std::atoi(argv[4]);
  const int reps = std::atoi(argv[5]);
  std::ifstream file(argv[1], std::ios::binary | std::ios::ate);
  if (!file || what < 0 || what > 6 || threads < 0 || rounds < 1 || reps < 1) {
    std::fprintf(stderr, "cannot read %s, or a bad argument\n", argv[1]);
    return 2;
  }
  std::vector<float> xyzi(static_cast<std::size_t>(file.tellg()) / sizeof(float));
  file.seekg(0);
  file.read(reinterpret_cast<char*>(xyzi.data()), static_cast<std::streamsize>(xyzi.size() * sizeof(float)));
  const std::size_t rows = xyzi.size() / 4;
  // WHAT 3: the calls of WHAT 1 one at a time, each after 64 MB were written and read (untimed), as
  // after other work: the caches are cold.
  const bool cold = what == 3;
  const int call = cold ? 1 : what;
  std::vector<std::uint64_t> other(cold ? std::size_t{8} << 20 : 0, 1);
  std::uint64_t sink = 0;
  const auto timed = [&](int which) {
    if (threads != 1) {  // the other side's pool threads asleep, this side's awake (see the top)
      std::this_thread::sleep_for(std::chrono::milliseconds(25));
      const auto warm_until = std::chrono::steady_clock::now() + std::chrono::milliseconds(25);
      while (std::chrono::steady_clock::now() < warm_until) {
        which == 0 ? run_A(xyzi.data(), rows, call, 1, threads) : run_B(xyzi.data(), rows, call, 1, threads);
      }
    }
    if (!cold) {
      const auto start = std::chrono::steady_clock::now();
      which == 0 ? run_A(xyzi.data(), rows, call, reps, threads) : run_B(xyzi.data(), rows, call, reps, threads);
      return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count() / reps;
    }
    double total = 0.0;
    for (int r = 0; r < reps; ++r) {
      for (std::uint64_t& word : other) sink += word++;
      const auto start = std::chrono::steady_clock::now();
      which == 0 ? run_A(xyzi.data(), rows, call, 1, threads) : run_B(xyzi.data(), rows, call, 1, threads);
      total += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    }
    return total / reps;
  };
  // Warm up both sides, and check that they compute the same.
  const std::size_t check_a = run_A(xyzi.data(), rows, call, 3, threads);
  const std::size_t check_b = run_B(xyzi.data(), rows, call, 3, threads);
  std::vector<double> a, b, ratio;
  for (int round = 0; round < rounds; ++round) {
    double time[2] = {0.0, 0.0};
    for (int k = 0; k < 2; ++k) {
      const int which = (k + round) % 2;  // 0: A, 1: B
      time[which] = timed(which);
    }
    a.push_back(time[0]);
    b.push_back(time[1]);
    ratio.push_back(time[1] / time[0]);
  }
  static const char* const kWhat[] = {"refilled map + classes", "fresh map + classes", "fresh map",
                                      "fresh map + classes, cold caches", "fresh map + classes from float64 rows",
                                      "collapse", "collapse from float64 rows"};
  std::printf("%s, %d thread(s), %d rounds of %d calls: A %.3f ms, B %.3f ms (medians); B / A %.3f [%.3f, %.3f]%s\n",
              kWhat[what], threads, rounds, reps, quantile(a, 0.5), quantile(b, 0.5), quantile(ratio, 0.5),
              quantile(ratio, 0.25), quantile(ratio, 0.75), check_a == check_b ? "" : "  (results differ!)");
  volatile std::uint64_t keep = sink;  // the cold passes are not optimised away
  (void)keep;
  return 0;
}

#endif
