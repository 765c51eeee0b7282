#include "test_support.hpp"

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <stdexcept>

namespace terracube::test {

std::optional<std::string> shared_data_dir() {
  namespace fs = std::filesystem;
  std::vector<std::string> candidates;
  if (const char* env = std::getenv("TERRACUBE_DATA_DIR")) candidates.emplace_back(env);
  candidates.emplace_back(TERRACUBE_DEFAULT_DATA_DIR);
  candidates.emplace_back("/work/shared/data");
  for (const std::string& candidate : candidates) {
    if (fs::is_directory(fs::path(candidate) / "kitti_seq00")) return candidate;
  }
  return std::nullopt;
}

XyziScan read_xyzi_bin(const std::string& path) {
  std::ifstream file(path, std::ios::binary | std::ios::ate);
  if (!file) throw std::runtime_error("cannot open " + path);
  const auto bytes = static_cast<std::size_t>(file.tellg());
  if (bytes % (4 * sizeof(float)) != 0) throw std::runtime_error(path + " is not float32 x 4 rows");
  XyziScan scan;
  scan.values.resize(bytes / sizeof(float));
  file.seekg(0);
  file.read(reinterpret_cast<char*>(scan.values.data()), static_cast<std::streamsize>(bytes));
  return scan;
}

std::vector<Eigen::Vector3d> XyziScan::as_vectors() const {
  std::vector<Eigen::Vector3d> points(values.size() / 4);
  for (std::size_t i = 0; i < points.size(); ++i) {
    points[i] = {values[4 * i], values[4 * i + 1], values[4 * i + 2]};
  }
  return points;
}

std::vector<std::uint16_t> read_semantic_labels(const std::string& path) {
  std::ifstream file(path, std::ios::binary | std::ios::ate);
  if (!file) throw std::runtime_error("cannot open " + path);
  const auto bytes = static_cast<std::size_t>(file.tellg());
  std::vector<std::uint32_t> raw(bytes / sizeof(std::uint32_t));
  file.seekg(0);
  file.read(reinterpret_cast<char*>(raw.data()), static_cast<std::streamsize>(bytes));
  std::vector<std::uint16_t> labels(raw.size());
  for (std::size_t i = 0; i < raw.size(); ++i) labels[i] = static_cast<std::uint16_t>(raw[i] & 0xFFFFu);
  return labels;
}

std::vector<Eigen::Vector3d> random_scene(std::uint32_t seed, std::size_t num_points, double extent_m) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, 0.05);
  std::vector<Eigen::Vector3d> points;
  points.reserve(num_points);
  const auto ground_height = [](double x, double y) { return 0.3 * std::sin(0.4 * x) + 0.2 * std::cos(0.3 * y); };
  while (points.size() < num_points) {
    const double x = extent_m * unit(rng);
    const double y = extent_m * unit(rng);
    const double kind = unit(rng);
    double z = ground_height(x, y) + noise(rng);
    if (kind > 0.85) {
      z += 2.0 + 3.0 * unit(rng);  // canopy, tunnel ceilings, eaves
    } else if (kind > 0.75) {
      z += 4.0 * unit(rng);  // walls and trunks: continuous columns
    } else if (kind > 0.72) {
      z += 20.0 * unit(rng) - 2.0;  // outliers above and below
    }
    points.emplace_back(x, y, z);
  }
  return points;
}

}  // namespace terracube::test
