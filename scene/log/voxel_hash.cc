#include "scene/log/voxel_hash.h"

#include <unordered_map>

namespace streetsim {

std::vector<Eigen::Vector3f> VoxelDownsample(const std::vector<Eigen::Vector3f>& points, double voxel_m) {
  const double inv = 1.0 / voxel_m;
  std::unordered_map<VoxelKey, int, VoxelKeyHash> slot;
  slot.reserve(points.size() / 2 + 1);
  std::vector<Eigen::Vector3d> sum;
  std::vector<int> count;
  for (const Eigen::Vector3f& p : points) {
    const Eigen::Vector3d pd = p.cast<double>();
    auto [it, inserted] = slot.try_emplace(VoxelOf(pd, inv), static_cast<int>(sum.size()));
    if (inserted) {
      sum.push_back(pd);
      count.push_back(1);
    } else {
      sum[it->second] += pd;
      ++count[it->second];
    }
  }
  std::vector<Eigen::Vector3f> out(sum.size());
  for (size_t i = 0; i < sum.size(); ++i) out[i] = (sum[i] / count[i]).cast<float>();
  return out;
}

}  // namespace streetsim
