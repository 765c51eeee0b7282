// The only translation unit that includes PCL.
#include "terracube/pcl_baseline.hpp"

#include <pcl/point_types.h>
#include <pcl/registration/gicp.h>
#include <pcl/registration/icp.h>

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "cloud_frame.hpp"
#include "number_text.hpp"
#include "terracube/icp.hpp"

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

/// PCL 1.13 exposes neither registration's iteration count.
template <typename Registration>
class Counting : public Registration {
 public:
  int iterations() const { return this->nr_iterations_; }
};

}  // namespace

void check_pcl_icp_params(const PclIcpParams& params) {
  if (!(params.max_correspondence_distance_m > 0.0) || !std::isfinite(params.max_correspondence_distance_m) ||
      params.max_iterations < 1 || params.max_iterations > kMaxIterationsLimit) {
    throw std::invalid_argument("PCL ICP needs a positive max correspondence distance and 1 to " +
                                std::to_string(kMaxIterationsLimit) + " iterations");
  }
  const double epsilons[] = {params.transformation_epsilon, params.rotation_epsilon, params.euclidean_fitness_epsilon,
                             params.relative_mse_epsilon};
  for (const double epsilon : epsilons) {
    if (!(epsilon >= 0.0) || !std::isfinite(epsilon)) {
      throw std::invalid_argument("PCL ICP's convergence epsilons must be finite and >= 0, got " +
                                  detail::number_text(epsilon));
    }
  }
}

namespace {

void check(const Eigen::Matrix4d& initial, const PclIcpParams& params) {
  detail::check_rigid_transform(initial, "initial transform");
  check_pcl_icp_params(params);
}

template <typename Registration>
PclIcpResult run(Counting<Registration>& icp, const Eigen::Matrix4d& initial, const PclIcpParams& params) {
  icp.setMaxCorrespondenceDistance(params.max_correspondence_distance_m);
  icp.setMaximumIterations(params.max_iterations);
  icp.setTransformationEpsilon(params.transformation_epsilon);
  icp.setTransformationRotationEpsilon(params.rotation_epsilon);
  icp.setEuclideanFitnessEpsilon(params.euclidean_fitness_epsilon);
  pcl::PointCloud<pcl::PointXYZ> aligned;
  icp.align(aligned, initial.cast<float>());
  PclIcpResult result;
  result.transform = icp.getFinalTransformation().template cast<double>();
  result.converged = icp.hasConverged();
  result.fitness_m2 = icp.getFitnessScore(params.max_correspondence_distance_m);
  result.iterations = icp.iterations();
  return result;
}

}  // namespace

PclIcpResult pcl_icp(const std::vector<Eigen::Vector3d>& source, const std::vector<Eigen::Vector3d>& target,
                     const Eigen::Matrix4d& initial, const PclIcpParams& params) {
  check(initial, params);
  Counting<pcl::IterativeClosestPoint<pcl::PointXYZ, pcl::PointXYZ>> icp;
  icp.setInputSource(to_cloud(source, "source"));
  icp.setInputTarget(to_cloud(target, "target"));
  icp.getConvergeCriteria()->setRelativeMSE(params.relative_mse_epsilon);
  return run(icp, initial, params);
}

PclIcpResult pcl_gicp(const std::vector<Eigen::Vector3d>& source, const std::vector<Eigen::Vector3d>& target,
                      const Eigen::Matrix4d& initial, const PclIcpParams& params) {
  check(initial, params);
  Counting<pcl::GeneralizedIterativeClosestPoint<pcl::PointXYZ, pcl::PointXYZ>> icp;
  icp.setInputSource(to_cloud(source, "source"));
  icp.setInputTarget(to_cloud(target, "target"));
  // GICP stops on its own test: every rotation-matrix entry moves less than its rotation
  // epsilon and every translation entry less than the transformation epsilon. The same
  // thresholds as pcl_icp's: the angle of the cosine, the square root of the squared translation.
  icp.setRotationEpsilon(std::acos(std::clamp(params.rotation_epsilon, -1.0, 1.0)));
  PclIcpParams gicp = params;
  gicp.transformation_epsilon = std::sqrt(std::max(params.transformation_epsilon, 0.0));
  return run(icp, initial, gicp);
}

}  // namespace terracube
