// Integer voxel keys and a centroid voxel filter. Shared by LiDAR odometry (downsampling scans)
// and scene/init's accumulation grid.
#pragma once

#include <cmath>
#include <cstdint>
#include <vector>

#include <Eigen/Core>

namespace streetsim {

struct VoxelKey {
  int32_t x, y, z;
  bool operator==(const VoxelKey& o) const { return x == o.x && y == o.y && z == o.z; }
};

struct VoxelKeyHash {
  size_t operator()(const VoxelKey& k) const {
    // Large odd multipliers decorrelate the axes (spatial hashing, Teschner et al. 2003).
    return (static_cast<size_t>(static_cast<uint32_t>(k.x)) * 73856093u) ^
           (static_cast<size_t>(static_cast<uint32_t>(k.y)) * 19349669u) ^
           (static_cast<size_t>(static_cast<uint32_t>(k.z)) * 83492791u);
  }
};

inline VoxelKey VoxelOf(const Eigen::Vector3d& p, double inv_voxel) {
  return {static_cast<int32_t>(std::floor(p.x() * inv_voxel)),
          static_cast<int32_t>(std::floor(p.y() * inv_voxel)),
          static_cast<int32_t>(std::floor(p.z() * inv_voxel))};
}

// One centroid per occupied voxel (insertion order of the first point of each voxel, so the
// result is deterministic).
std::vector<Eigen::Vector3f> VoxelDownsample(const std::vector<Eigen::Vector3f>& points, double voxel_m);

}  // namespace streetsim
