// Removes a canopy hanging over flat ground with the installed terracube.
#include <terracube/collapse.hpp>

#include <iostream>
#include <vector>

int main() {
  std::vector<Eigen::Vector3d> points;
  for (int i = 0; i < 10; ++i) {
    points.emplace_back(0.1 * i, 0.0, 0.0);  // ground
    points.emplace_back(0.1 * i, 0.0, 3.0);  // canopy 3 m up
  }
  terracube::CollapseParams params;
  params.edge_m = 0.5;
  params.sigma = terracube::sigma_from_robot_height(0.7, params.edge_m);
  const terracube::CollapseResult result = terracube::collapse_overhangs(points, params);
  std::cout << "removed " << result.num_overhang << " of " << result.num_points << " points\n";
  return result.num_overhang == 10 ? 0 : 1;
}
