#include "scene/log/voxel_hash.h"

namespace streetsim {

void VoxelIndex::Clear(size_t expected) {
  size_t capacity = 16;
  shift_ = 64 - 4;
  while (capacity < 2 * expected) {
    capacity <<= 1;
    --shift_;
  }
  table_.assign(capacity, -1);
  keys_.clear();
}

void VoxelIndex::Grow() {
  table_.assign(2 * table_.size(), -1);
  --shift_;
  for (size_t i = 0; i < keys_.size(); ++i) {
    size_t h = Slot(keys_[i]);
    while (table_[h] >= 0) h = (h + 1) & (table_.size() - 1);
    table_[h] = static_cast<int32_t>(i);
  }
}

namespace {

// VoxelDownsample's working arrays. A thread keeps them between calls: allocated afresh, their
// pages faulted in again on every call and cost more than the flat table saved (a dynamic-point
// mask filters two 100k-point scans).
struct DownsampleScratch {
  VoxelIndex index;
  std::vector<Eigen::Vector3d> sum;
  std::vector<int> count;
};

// Inputs above this many points use arrays of their own, freed at once: a thread keeps at most
// ~100 MB for later calls.
constexpr size_t kMostPointsKept = size_t{1} << 21;

}  // namespace

std::vector<Eigen::Vector3f> VoxelDownsample(const std::vector<Eigen::Vector3f>& points, double voxel_m) {
  thread_local DownsampleScratch kept;
  DownsampleScratch own;
  DownsampleScratch& s = points.size() <= kMostPointsKept ? kept : own;
  s.index.Clear(points.size());
  s.sum.clear();
  s.count.clear();
  const double inv = 1.0 / voxel_m;
  for (const Eigen::Vector3f& p : points) {
    const Eigen::Vector3d pd = p.cast<double>();
    bool inserted = false;
    const int32_t i = s.index.FindOrInsert(VoxelOf(pd, inv), &inserted);
    if (inserted) {
      s.sum.push_back(pd);
      s.count.push_back(1);
    } else {
      s.sum[i] += pd;
      ++s.count[i];
    }
  }
  std::vector<Eigen::Vector3f> out(s.sum.size());
  for (size_t i = 0; i < s.sum.size(); ++i) out[i] = (s.sum[i] / s.count[i]).cast<float>();
  return out;
}

}  // namespace streetsim
