// PCL's pcl::IterativeClosestPoint (and GICP) on terracube point sets: the external baselines
// that the registration tests and benchmarks compare against. No PCL type appears here, so including
// this header never needs PCL; the library target terracube::pcl_baseline links PCL privately
// and exists only when CMake found PCL (TERRACUBE_WITH_PCL). Build tree only: neither the target
// nor this header is installed.
#pragma once

#include <Eigen/Core>
#include <vector>

namespace terracube {

/// The settings of pcl::IterativeClosestPoint that terracube's ICP mirrors.
struct PclIcpParams {
  double max_correspondence_distance_m = 1.0;  ///< setMaxCorrespondenceDistance [m]
  int max_iterations = 30;                     ///< setMaximumIterations, in [1, kMaxIterationsLimit] (icp.hpp)
  double transformation_epsilon = 1e-10;       ///< setTransformationEpsilon (squared translation [m^2])
  double rotation_epsilon = 1.0 - 1e-10;       ///< setTransformationRotationEpsilon (cosine of the angle)
  double euclidean_fitness_epsilon = 0.0;      ///< setEuclideanFitnessEpsilon [m^2]; 0 disables it
  double relative_mse_epsilon = 1e-5;          ///< getConvergeCriteria()->setRelativeMSE (PCL's default)
};

/// Throws std::invalid_argument naming the first field out of range; the PCL ICP baseline calls it first, and a
/// configuration can call it before the first scan.
void check_pcl_icp_params(const PclIcpParams& params);

/// Outcome of pcl_icp.
struct PclIcpResult {
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();  ///< source -> target
  bool converged = false;                                   ///< hasConverged()
  double fitness_m2 = 0.0;  ///< getFitnessScore(): mean squared distance of the pairs [m^2]
  int iterations = 0;       ///< getConvergeCriteria()->getCurrentIterations()
};

/// pcl::IterativeClosestPoint<PointXYZ, PointXYZ> (SVD point-to-point estimation) aligning
/// `source` onto `target` from `initial`. Throws std::invalid_argument on empty or non-finite
/// input, a non-rigid `initial` or invalid parameters.
PclIcpResult pcl_icp(const std::vector<Eigen::Vector3d>& source, const std::vector<Eigen::Vector3d>& target,
                     const Eigen::Matrix4d& initial, const PclIcpParams& params = {});

/// pcl::GeneralizedIterativeClosestPoint<PointXYZ, PointXYZ> (Segal et al. 2009: plane-to-plane,
/// each point's covariance from its 20 nearest neighbours) with the same settings, its own stopping
/// test mapped onto them: rotation-matrix entries moving less than acos(rotation_epsilon) and
/// translation entries less than sqrt(transformation_epsilon) (the relative MSE does not apply). Not one of the papers'
/// methods: a strong dense scan matcher, used by the benchmarks to tell what raw scans allow. Same errors as pcl_icp.
PclIcpResult pcl_gicp(const std::vector<Eigen::Vector3d>& source, const std::vector<Eigen::Vector3d>& target,
                      const Eigen::Matrix4d& initial, const PclIcpParams& params = {});

}  // namespace terracube
