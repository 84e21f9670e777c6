// lidar_losses.h's three terms in double on a double reference render (render/lidar/lidar_backward.h),
// for the finite-difference checks of the LiDAR training step (so that the differences are not
// drowned by float rounding of the loss inputs).
#pragma once

#include <algorithm>
#include <cmath>

#include "render/lidar/lidar_backward.h"
#include "scene/train/lidar_stage.h"

namespace streetsim::train {

inline double DoubleLidarLoss(const LidarReferenceOutput& o, const LidarFrameTarget& t, const LidarLossWeights& w) {
  const double floor = 0.1, eps = 1e-3;
  double range = 0, intensity = 0, bce = 0;
  size_t returns = 0;
  for (size_t p = 0; p < t.range.size(); ++p) {
    const double a = o.alpha[p];
    const bool ret = t.range[p] > 0;
    const double ac = std::min(std::max(a, eps), 1 - eps);
    bce += ret ? -std::log(ac) : -std::log(1 - ac);
    if (!ret) continue;
    ++returns;
    if (a <= 0) continue;
    const double k = std::min(1.0, a / floor);
    range += k * std::fabs(o.range_sum[p] / a - t.range[p]);
    intensity += k * std::fabs(o.intensity_sum[p] / a - t.intensity[p]);
  }
  const double r = std::max<size_t>(returns, 1);
  return w.range * range / r + w.ret * bce / t.range.size() + w.intensity * intensity / r;
}

}  // namespace streetsim::train
