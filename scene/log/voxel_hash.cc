#include "scene/log/voxel_hash.h"

namespace streetsim {

namespace {

// VoxelDownsample's working arrays. A thread keeps them between calls: allocated afresh, their
// pages faulted in again on every call and cost more than the hashing saved (a dynamic-point
// mask filters two 100k-point scans).
struct DownsampleScratch {
  std::vector<int32_t> table;  // open addressing, at most half full: index into the voxels, -1 empty
  std::vector<VoxelKey> key;   // the voxels in the order of their first point
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
  // A flat table instead of std::unordered_map's node per voxel: same voxels, order and sums, so
  // the same output, at a fraction of the time.
  int shift = 64 - 4;
  size_t capacity = 16;
  while (capacity < 2 * points.size()) {
    capacity <<= 1;
    --shift;
  }
  s.table.assign(capacity, -1);
  s.key.clear();
  s.sum.clear();
  s.count.clear();
  const double inv = 1.0 / voxel_m;
  for (const Eigen::Vector3f& p : points) {
    const Eigen::Vector3d pd = p.cast<double>();
    const VoxelKey k = VoxelOf(pd, inv);
    // Fibonacci hashing: the top bits of the product depend on all of the key's bits.
    size_t h = static_cast<size_t>((static_cast<uint64_t>(VoxelKeyHash{}(k)) * 0x9E3779B97F4A7C15ull) >> shift);
    while (s.table[h] >= 0 && !(s.key[s.table[h]] == k)) h = (h + 1) & (capacity - 1);
    if (s.table[h] < 0) {
      s.table[h] = static_cast<int32_t>(s.key.size());
      s.key.push_back(k);
      s.sum.push_back(pd);
      s.count.push_back(1);
    } else {
      s.sum[s.table[h]] += pd;
      ++s.count[s.table[h]];
    }
  }
  std::vector<Eigen::Vector3f> out(s.sum.size());
  for (size_t i = 0; i < s.sum.size(); ++i) out[i] = (s.sum[i] / s.count[i]).cast<float>();
  return out;
}

}  // namespace streetsim
