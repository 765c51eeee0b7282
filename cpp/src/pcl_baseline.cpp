// The only translation unit that includes PCL.
#include "terracube/pcl_baseline.hpp"

#include <pcl/point_types.h>
#include <pcl/registration/icp.h>

#include <cmath>
#include <stdexcept>
#include <string>

#include "cloud_frame.hpp"

namespace terracube {

namespace {

pcl::PointCloud<pcl::PointXYZ>::Ptr to_cloud(const std::vector<Eigen::Vector3d>& points, const char* what) {
  if (points.empty()) throw std::invalid_argument(std::string(what) + " is empty");
  auto cloud = std::make_shared<pcl::PointCloud<pcl::PointXYZ>>();
  cloud->reserve(points.size());
  for (const Eigen::Vector3d& p : points) {
    if (!p.allFinite()) throw std::invalid_argument(std::string(what) + " contains NaN or Inf");
    cloud->emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()), static_cast<float>(p.z()));
  }
  return cloud;
}

/// pcl::IterativeClosestPoint does not expose its iteration count in PCL 1.13.
class CountingIcp : public pcl::IterativeClosestPoint<pcl::PointXYZ, pcl::PointXYZ> {
 public:
  int iterations() const { return nr_iterations_; }
};

}  // namespace

PclIcpResult pcl_icp(const std::vector<Eigen::Vector3d>& source, const std::vector<Eigen::Vector3d>& target,
                     const Eigen::Matrix4d& initial, const PclIcpParams& params) {
  detail::check_rigid_transform(initial, "initial transform");
  if (!(params.max_correspondence_distance_m > 0.0) || !std::isfinite(params.max_correspondence_distance_m) ||
      params.max_iterations < 1) {
    throw std::invalid_argument("PCL ICP needs a positive max correspondence distance and at least 1 iteration");
  }
  CountingIcp icp;
  icp.setInputSource(to_cloud(source, "source"));
  icp.setInputTarget(to_cloud(target, "target"));
  icp.setMaxCorrespondenceDistance(params.max_correspondence_distance_m);
  icp.setMaximumIterations(params.max_iterations);
  icp.setTransformationEpsilon(params.transformation_epsilon);
  icp.setTransformationRotationEpsilon(params.rotation_epsilon);
  icp.setEuclideanFitnessEpsilon(params.euclidean_fitness_epsilon);
  icp.getConvergeCriteria()->setRelativeMSE(params.relative_mse_epsilon);
  pcl::PointCloud<pcl::PointXYZ> aligned;
  icp.align(aligned, initial.cast<float>());
  PclIcpResult result;
  result.transform = icp.getFinalTransformation().cast<double>();
  result.converged = icp.hasConverged();
  result.fitness_m2 = icp.getFitnessScore(params.max_correspondence_distance_m);
  result.iterations = icp.iterations();
  return result;
}

}  // namespace terracube
