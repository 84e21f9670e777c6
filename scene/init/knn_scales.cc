#include "scene/init/knn_scales.h"

#include <algorithm>
#include <cmath>

#include "render/common/thread_pool.h"
#include "scene/log/kdtree.h"

namespace streetsim {

std::vector<float> KnnLogScales(const std::vector<Eigen::Vector3f>& points, int k, double max_scale_m) {
  std::vector<float> out(points.size(), static_cast<float>(std::log(max_scale_m)));
  if (points.size() < 2) return out;
  KdTree3 tree(&points);
  const float max_sq = static_cast<float>(max_scale_m * max_scale_m);
  const auto work = [&](size_t begin, size_t end) {
    int idx[32];
    float d2[32];
    for (size_t i = begin; i < end; ++i) {
      const int found = tree.KNearest(points[i], k, max_sq, idx, d2, static_cast<int>(i));
      double mean_sq = max_sq;
      if (found == k) {
        mean_sq = 0;
        for (int j = 0; j < found; ++j) mean_sq += d2[j];
        mean_sq /= found;
      }
      out[i] = static_cast<float>(0.5 * std::log(std::max(mean_sq, 1e-7)));  // 3DGS clamps at 1e-7
    }
  };
  ThreadPool pool;
  pool.ParallelFor(static_cast<int64_t>(points.size()), 4096,
                   [&](int64_t begin, int64_t end, int) { work(static_cast<size_t>(begin), static_cast<size_t>(end)); });
  return out;
}

}  // namespace streetsim
