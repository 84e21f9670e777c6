#include "scene/train/lidar_losses.h"

#include <algorithm>
#include <cmath>

namespace streetsim::train {
namespace {

// Shared by the range and intensity terms: mean over returning rays of
// min(1, a / floor) |s / a - target|, gradients (scaled by weight / count) added into d_sum, d_alpha.
double FadedL1(const float* sum, const float* alpha, const float* real_range, const float* target, size_t rays,
               float weight, float* d_sum, float* d_alpha, float floor) {
  size_t count = 0;
  for (size_t p = 0; p < rays; ++p) count += real_range[p] > 0.0f;
  if (count == 0) return 0.0;
  const double scale = static_cast<double>(weight) / static_cast<double>(count);
  const double fl = std::max(static_cast<double>(floor), 1e-6);
  double loss = 0;
  for (size_t p = 0; p < rays; ++p) {
    if (!(real_range[p] > 0.0f)) continue;
    const double a = alpha[p], s = sum[p], t = target[p];
    if (a >= fl) {
      // |s / a - t|: d/ds = sign / a, d/da = -sign s / a^2.
      const double e = s / a - t;
      loss += std::abs(e);
      const double sg = e > 0 ? 1.0 : (e < 0 ? -1.0 : 0.0);
      if (d_sum) d_sum[p] += static_cast<float>(scale * sg / a);
      if (d_alpha) d_alpha[p] += static_cast<float>(-scale * sg * s / (a * a));
    } else {
      // (a / floor) |s / a - t| = |s - t a| / floor: bounded gradients, 0 at a = 0.
      const double e = s - t * a;
      loss += std::abs(e) / fl;
      const double sg = e > 0 ? 1.0 : (e < 0 ? -1.0 : 0.0);
      if (d_sum) d_sum[p] += static_cast<float>(scale * sg / fl);
      if (d_alpha) d_alpha[p] += static_cast<float>(-scale * sg * t / fl);
    }
  }
  return loss / static_cast<double>(count);
}

}  // namespace

double LidarRangeL1(const float* range_sum, const float* alpha, const float* real_range, size_t rays, float weight,
                    float* d_range_sum, float* d_alpha, const LidarLossOptions& options) {
  return FadedL1(range_sum, alpha, real_range, real_range, rays, weight, d_range_sum, d_alpha, options.alpha_floor);
}

double LidarIntensityL1(const float* intensity_sum, const float* alpha, const float* real_range,
                        const float* real_intensity, size_t rays, float weight, float* d_intensity_sum,
                        float* d_alpha, const LidarLossOptions& options) {
  return FadedL1(intensity_sum, alpha, real_range, real_intensity, rays, weight, d_intensity_sum, d_alpha,
                 options.alpha_floor);
}

double LidarReturnBce(const float* alpha, const float* real_range, size_t rays, float weight, float* d_alpha,
                      const LidarLossOptions& options) {
  if (rays == 0) return 0.0;
  const double eps = std::clamp(static_cast<double>(options.bce_eps), 1e-7, 0.49);
  const double scale = static_cast<double>(weight) / static_cast<double>(rays);
  double loss = 0;
  for (size_t p = 0; p < rays; ++p) {
    const double raw = alpha[p];
    const double a = std::clamp(raw, eps, 1.0 - eps);
    const bool hit = real_range[p] > 0.0f;
    loss -= hit ? std::log(a) : std::log(1.0 - a);
    if (d_alpha && raw > eps && raw < 1.0 - eps) {
      d_alpha[p] += static_cast<float>(scale * (hit ? -1.0 / a : 1.0 / (1.0 - a)));
    }
  }
  return loss / static_cast<double>(rays);
}

}  // namespace streetsim::train
