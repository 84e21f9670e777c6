// The scatter matrix of a point's neighbours, for the local-plane fits (normals, planarity) of
// LiDAR odometry and the moving-object tracker.
#pragma once

#include <vector>

#include <Eigen/Core>

namespace streetsim {

// Sum of (p - mean)(p - mean)^T over points[idx[0..n)], in double; n > 0.
inline Eigen::Matrix3d NeighbourScatter(const std::vector<Eigen::Vector3f>& points, const int* idx, int n) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (int k = 0; k < n; ++k) mean += points[idx[k]].cast<double>();
  mean /= n;
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (int k = 0; k < n; ++k) {
    const Eigen::Vector3d d = points[idx[k]].cast<double>() - mean;
    scatter += d * d.transpose();
  }
  return scatter;
}

}  // namespace streetsim
