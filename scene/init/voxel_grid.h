// A sparse accumulation grid: points from many scans fall into voxels, each voxel keeps the mean
// position and reflectance of what fell into it, so memory grows with the scene, not the log.
#pragma once

#include <vector>

#include <Eigen/Core>

#include "scene/log/voxel_hash.h"

namespace streetsim {

class VoxelGrid {
 public:
  explicit VoxelGrid(double voxel_m) : inv_voxel_(1.0 / voxel_m), voxel_m_(voxel_m) {}
  void Add(const Eigen::Vector3d& p, float reflectance);
  size_t size() const { return sum_.size(); }
  double voxel_m() const { return voxel_m_; }
  // Mean position and reflectance per voxel, in insertion order; voxels with fewer than
  // min_hits points (e.g. a single stray return) are left out.
  void Extract(int min_hits, std::vector<Eigen::Vector3f>* points, std::vector<float>* reflectance) const;

 private:
  double inv_voxel_, voxel_m_;
  VoxelIndex slot_;
  std::vector<Eigen::Vector3d> sum_;
  std::vector<float> reflectance_sum_;
  std::vector<int> count_;
};

}  // namespace streetsim
