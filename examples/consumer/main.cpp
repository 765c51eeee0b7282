// A robot stack's use of the installed terracube: removes a canopy hanging over flat ground, then
// fuses the same scan into a robot-centric local map and reads its planner layers.
#include <terracube/collapse.hpp>
#include <terracube/local_map.hpp>

#include <cmath>
#include <iostream>
#include <vector>

int main() {
  std::vector<Eigen::Vector3d> points;  // the sensor 1 m above a flat patch with a canopy 3 m up
  for (int i = -10; i < 10; ++i) {
    for (int j = -10; j < 10; ++j) {
      points.emplace_back(0.05 * i, 0.05 * j, -1.0);             // ground
      if (i >= 0) points.emplace_back(0.05 * i, 0.05 * j, 2.0);  // canopy
    }
  }
  terracube::CollapseParams params;
  params.edge_m = 0.5;
  params.sigma = terracube::sigma_from_robot_height(0.7, params.edge_m);
  const terracube::CollapseResult result = terracube::collapse_overhangs(points, params);
  std::cout << "removed " << result.num_overhang << " of " << result.num_points << " points\n";

  terracube::LocalMapParams map_params;
  map_params.length_m = 4.0;
  map_params.collapse = params;
  terracube::LocalMap map(map_params);
  Eigen::Matrix4d pose = Eigen::Matrix4d::Identity();
  pose(2, 3) = 1.0;  // odometry <- sensor
  map.update(terracube::PointsView<double>(points), pose);
  const terracube::CellIndex cell = *map.index_of(Eigen::Vector2d(0.2, 0.2));  // under the canopy
  const float height = map.get("elevation")(cell.x(), cell.y());
  const float traversability = map.get("traversability")(cell.x(), cell.y());
  std::cout << "under the canopy: elevation " << height << " m, traversability " << traversability << "\n";
  // Open, flat ground under 3 m of clearance: a 0.7 m robot passes (1 is open, 0 blocked).
  const bool ok = result.num_overhang == 200 && std::abs(height) < 0.01F && traversability > 0.9F;
  return ok ? 0 : 1;
}
