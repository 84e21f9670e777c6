// Training losses and image metrics (S3Gaussian's static stage, ../shared/docs/s3gaussian-spec.md
// section 5), each with its gradient with respect to the rendered image / depth.
//
// Images are interleaved linear RGB floats [H*W*3] as RenderOutput holds them. Every *Grad
// function ADDS weight * dLoss/d(render) into `grad` (so the terms of a total loss accumulate into
// one buffer) and returns the loss value (unweighted). Deterministic: fixed-order reductions.
#pragma once

#include <cstdint>
#include <vector>

#include "render/common/thread_pool.h"

namespace streetsim::train {

// mean |render - target| over 3HW.
double L1Loss(ThreadPool& pool, const float* render, const float* target, size_t n, float weight, float* grad);

// Mean SSIM over the 3 channels and all pixels, 11x11 Gaussian window (sigma 1.5), zero padding
// (as 3DGS's conv2d), C1 = 0.01^2, C2 = 0.03^2. With grad: adds weight * d(mean SSIM)/d(render)
// (pass a negative weight for the D-SSIM loss 1 - SSIM).
double Ssim(ThreadPool& pool, const float* render, const float* target, int width, int height, float weight,
            float* grad);

// One LiDAR sample of the sparse depth map of a view (pixel index, metres).
struct DepthSample {
  uint32_t pixel;
  float depth;
};

// S3Gaussian's LiDAR depth loss over samples with 0.01 < D < 80:
// mean((clip(render/80, 0, 1) - clip(D/80, 0, 1))^2). Returns 0 without samples.
double DepthLoss(const float* render_depth, const std::vector<DepthSample>& samples, float weight, float* grad);

// 10 log10(1 / MSE) of images clamped to [0, 1].
double Psnr(const float* render, const float* target, size_t n);

// A grayscale camera's view beside colour cameras (docs/training.md "Grayscale cameras"): the
// render's luminance (Rec. 601: 0.299 R + 0.587 G + 0.114 B) in all three channels of `y3`, so
// that the RGB losses above compare it with the grayscale image (loaded with equal channels).
void LuminanceRgb(const float* rgb, size_t pixels, float* y3);
// Chains a gradient with respect to `y3` back to the render: adds w_c * sum_k d_y3[p, k] to
// d_rgb[p, c].
void LuminanceBackward(const float* d_y3, size_t pixels, float* d_rgb);

}  // namespace streetsim::train
