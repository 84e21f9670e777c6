#include "scene/log/kdtree.h"

#include <algorithm>
#include <numeric>

namespace streetsim {
namespace {
constexpr int kLeafSize = 12;
}  // namespace

void KdTree3::Build(const std::vector<Eigen::Vector3f>* points) {
  points_ = points;
  index_.resize(points->size());
  std::iota(index_.begin(), index_.end(), 0);
  nodes_.clear();
  nodes_.reserve(2 * points->size() / kLeafSize + 2);
  if (!points->empty()) BuildNode(0, static_cast<int>(index_.size()), 0);
}

int KdTree3::BuildNode(int begin, int end, int depth) {
  const int id = static_cast<int>(nodes_.size());
  nodes_.push_back(Node{begin, end});
  if (end - begin <= kLeafSize) return id;
  // Split the widest extent: better balanced than cycling axes on street scans (long and flat).
  Eigen::Vector3f lo = (*points_)[index_[begin]], hi = lo;
  for (int i = begin + 1; i < end; ++i) {
    lo = lo.cwiseMin((*points_)[index_[i]]);
    hi = hi.cwiseMax((*points_)[index_[i]]);
  }
  int axis;
  (hi - lo).maxCoeff(&axis);
  const int mid = (begin + end) / 2;
  std::nth_element(index_.begin() + begin, index_.begin() + mid, index_.begin() + end,
                   [&](int a, int b) { return (*points_)[a][axis] < (*points_)[b][axis]; });
  const float split = (*points_)[index_[mid]][axis];
  const int left = BuildNode(begin, mid, depth + 1);
  const int right = BuildNode(mid, end, depth + 1);
  Node& node = nodes_[id];
  node.axis = axis;
  node.split = split;
  node.left = left;
  node.right = right;
  return id;
}

template <typename Visit>
void KdTree3::Search(int node_id, const Eigen::Vector3f& q, float* bound_sq, Visit&& visit) const {
  const Node& node = nodes_[node_id];
  if (node.axis < 0) {
    for (int i = node.begin; i < node.end; ++i) {
      const int idx = index_[i];
      const float d = ((*points_)[idx] - q).squaredNorm();
      if (d < *bound_sq) visit(idx, d);
    }
    return;
  }
  const float diff = q[node.axis] - node.split;
  const int near = diff < 0 ? node.left : node.right;
  const int far = diff < 0 ? node.right : node.left;
  Search(near, q, bound_sq, visit);
  if (diff * diff < *bound_sq) Search(far, q, bound_sq, visit);
}

int KdTree3::Nearest(const Eigen::Vector3f& query, float max_dist_sq, float* dist_sq) const {
  if (nodes_.empty()) return -1;
  int best = -1;
  float bound = max_dist_sq;
  Search(0, query, &bound, [&](int idx, float d) {
    best = idx;
    bound = d;
  });
  if (dist_sq) *dist_sq = bound;
  return best;
}

int KdTree3::KNearest(const Eigen::Vector3f& query, int k, float max_dist_sq, int* indices,
                      float* dists_sq, int exclude) const {
  if (nodes_.empty() || k <= 0) return 0;
  k = std::min(k, 32);
  int count = 0;
  float bound = max_dist_sq;
  Search(0, query, &bound, [&](int idx, float d) {
    if (idx == exclude) return;
    // Insertion into the sorted list; the bound shrinks once k are held.
    int pos = count < k ? count++ : k - 1;
    while (pos > 0 && dists_sq[pos - 1] > d) {
      dists_sq[pos] = dists_sq[pos - 1];
      indices[pos] = indices[pos - 1];
      --pos;
    }
    dists_sq[pos] = d;
    indices[pos] = idx;
    if (count == k) bound = dists_sq[k - 1];
  });
  return count;
}

}  // namespace streetsim
