// The LiDAR backward pass's public types (LidarRenderer::Backward, lidar_backward.h).
#pragma once

#include <vector>

namespace streetsim {

// Per-Gaussian gradients in the store's order and layout: means [3N], log_scales [3N], rotations
// [4N] (w.r.t. the raw, unnormalised quaternion the store keeps), opacity_logits [N], reflectance
// [N] (w.r.t. the reflectance in [0, 1] the renderer takes; 0 where the input was outside [0, 1]
// and clamped; a trainer learning a logit chains its sigmoid). Zero for undrawn Gaussians.
template <typename Real>
struct LidarGaussianGradsT {
  std::vector<Real> means, log_scales, rotations, opacity_logits, reflectance;
};
using LidarGaussianGrads = LidarGaussianGradsT<float>;

// Upstream gradients per ray [beams * columns] (row-major like the outputs); null: zero.
template <typename Real>
struct LidarUpstreamGradsT {
  const Real* d_range_sum = nullptr;
  const Real* d_alpha = nullptr;  // alpha = 1 - final transmittance
  const Real* d_intensity_sum = nullptr;
};
using LidarUpstreamGrads = LidarUpstreamGradsT<float>;

}  // namespace streetsim
