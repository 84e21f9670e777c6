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

// Voxel -> dense index, in the order voxels were first seen: open addressing in one flat table
// kept at most half full (std::unordered_map's node per voxel was most of the time of the voxel
// filters over 100k-point scans). Clear() keeps the memory for the next use.
class VoxelIndex {
 public:
  VoxelIndex() { Clear(0); }
  // k's index; a new voxel gets size() and *inserted is set.
  int32_t FindOrInsert(const VoxelKey& k, bool* inserted) {
    size_t h = Slot(k);
    while (table_[h] >= 0) {
      if (keys_[table_[h]] == k) {
        *inserted = false;
        return table_[h];
      }
      h = (h + 1) & (table_.size() - 1);
    }
    *inserted = true;
    const int32_t index = static_cast<int32_t>(keys_.size());
    table_[h] = index;
    keys_.push_back(k);
    if (2 * keys_.size() > table_.size()) Grow();
    return index;
  }
  // k's index, or -1 when it has none.
  int32_t Find(const VoxelKey& k) const {
    for (size_t h = Slot(k); table_[h] >= 0; h = (h + 1) & (table_.size() - 1)) {
      if (keys_[table_[h]] == k) return table_[h];
    }
    return -1;
  }
  size_t size() const { return keys_.size(); }
  // The key of index i (0 <= i < size(): indices count insertions).
  const VoxelKey& key(int32_t i) const { return keys_[i]; }
  // Empties it, sized for about `expected` voxels without growing.
  void Clear(size_t expected);

 private:
  size_t Slot(const VoxelKey& k) const {
    // Fibonacci hashing: the top bits of the product depend on all of the key's bits.
    return static_cast<size_t>((static_cast<uint64_t>(VoxelKeyHash{}(k)) * 0x9E3779B97F4A7C15ull) >> shift_);
  }
  void Grow();

  std::vector<int32_t> table_;  // -1: empty
  std::vector<VoxelKey> keys_;
  int shift_ = 60;
};

// One centroid per occupied voxel (insertion order of the first point of each voxel, so the
// result is deterministic).
std::vector<Eigen::Vector3f> VoxelDownsample(const std::vector<Eigen::Vector3f>& points, double voxel_m);

}  // namespace streetsim
