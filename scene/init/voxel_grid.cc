#include "scene/init/voxel_grid.h"

namespace streetsim {

void VoxelGrid::Add(const Eigen::Vector3d& p, float reflectance) {
  bool inserted = false;
  const int32_t i = slot_.FindOrInsert(VoxelOf(p, inv_voxel_), &inserted);
  if (inserted) {
    sum_.push_back(p);
    reflectance_sum_.push_back(reflectance);
    count_.push_back(1);
  } else {
    sum_[i] += p;
    reflectance_sum_[i] += reflectance;
    ++count_[i];
  }
}

void VoxelGrid::Extract(int min_hits, std::vector<Eigen::Vector3f>* points,
                        std::vector<float>* reflectance) const {
  points->clear();
  if (reflectance) reflectance->clear();
  for (size_t i = 0; i < sum_.size(); ++i) {
    if (count_[i] < min_hits) continue;
    points->push_back((sum_[i] / count_[i]).cast<float>());
    if (reflectance) reflectance->push_back(reflectance_sum_[i] / count_[i]);
  }
}

}  // namespace streetsim
