// LiDAR training losses on a rendered range image (render/lidar: range_sum, alpha, intensity_sum
// per ray) against a real scan binned to the same image (BinPointsToRangeImage: range and
// intensity per ray, range 0 = no return). Plain arrays of `rays` floats, row-major like the
// renderer's outputs; no renderer dependency.
//
// As scene/train/losses.h: each function returns the unweighted loss and ADDS weight * dLoss/d(its
// inputs) into the gradient arrays given (null: value only), so the terms of a total loss
// accumulate into the buffers LidarRenderer::Backward takes. Deterministic (one pass in ray order,
// double sums).
//
// Alpha near 0 (docs/lidar.md "Losses"): the range and intensity terms are L1 on the normalised
// values (range_sum / alpha, intensity_sum / alpha) where alpha >= alpha_floor, and fade linearly
// with alpha below it: per ray min(1, alpha / floor) |sum / alpha - real|, i.e.
// |sum - real alpha| / floor under the floor. The term is continuous, its gradients bounded by
// 1 / floor (the plain normalised L1 explodes as 1 / alpha on barely covered rays), and a ray
// with no coverage costs nothing there: raising its alpha is the BCE's job.
#pragma once

#include <cstddef>

namespace streetsim::train {

struct LidarLossOptions {
  float alpha_floor = 0.1f;  // the range / intensity terms fade linearly below this alpha
  float bce_eps = 1e-3f;     // the BCE clamps alpha to [eps, 1 - eps] (no gradient outside)
};

// mean over rays where the real scan returns (real_range > 0) of
// min(1, alpha / floor) |range_sum / alpha - real_range|  (alpha = 0: the ray contributes 0).
// Gradients into d_range_sum and d_alpha. 0 without real returns.
double LidarRangeL1(const float* range_sum, const float* alpha, const float* real_range, size_t rays, float weight,
                    float* d_range_sum, float* d_alpha, const LidarLossOptions& options = {});

// mean over all rays of the binary cross-entropy between alpha (clamped to [eps, 1 - eps]) and the
// real return mask (real_range > 0). Gradient into d_alpha.
double LidarReturnBce(const float* alpha, const float* real_range, size_t rays, float weight, float* d_alpha,
                      const LidarLossOptions& options = {});

// As LidarRangeL1 for the intensity: min(1, alpha / floor) |intensity_sum / alpha - real_intensity|
// over rays where the real scan returns. Gradients into d_intensity_sum and d_alpha.
double LidarIntensityL1(const float* intensity_sum, const float* alpha, const float* real_range,
                        const float* real_intensity, size_t rays, float weight, float* d_intensity_sum,
                        float* d_alpha, const LidarLossOptions& options = {});

}  // namespace streetsim::train
