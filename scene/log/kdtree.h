// A static 3-D k-d tree for nearest-neighbour queries (ICP correspondences, normals, 3DGS initial
// scales, dynamic-point checks). Built once over a point set that must outlive it; queries are
// const and thread-safe.
#pragma once

#include <cstdint>
#include <vector>

#include <Eigen/Core>

namespace streetsim {

class KdTree3 {
 public:
  KdTree3() = default;
  explicit KdTree3(const std::vector<Eigen::Vector3f>* points) { Build(points); }
  void Build(const std::vector<Eigen::Vector3f>* points);

  size_t size() const { return index_.size(); }

  // Nearest point within max_dist_sq (squared metres); returns -1 when none.
  int Nearest(const Eigen::Vector3f& query, float max_dist_sq, float* dist_sq = nullptr) const;

  // Up to k nearest (k <= 32) within max_dist_sq, closest first. `exclude` skips one point index
  // (the query point itself when it belongs to the set). Returns the number found.
  int KNearest(const Eigen::Vector3f& query, int k, float max_dist_sq, int* indices,
               float* dists_sq, int exclude = -1) const;

 private:
  struct Node {
    // Leaf when axis < 0: points index_[begin, end). Else split on `axis` at `split`.
    int begin = 0, end = 0;
    int left = -1, right = -1;
    int axis = -1;
    float split = 0;
  };
  int BuildNode(int begin, int end, int depth);
  template <typename Visit>
  void Search(int node, const Eigen::Vector3f& q, float* bound_sq, Visit&& visit) const;

  const std::vector<Eigen::Vector3f>* points_ = nullptr;
  std::vector<int> index_;
  std::vector<Node> nodes_;
};

}  // namespace streetsim
