// cpu LiDAR backward pass: dL/d(range_sum, alpha, intensity_sum) per ray -> dL/d(every Gaussian's
// mean, log-scale, raw quaternion, opacity logit, reflectance). The trainer's entry point is
// LidarRenderer::Backward (lidar_renderer.h); this header holds the gradient types, the templated
// stages it runs, and the double-precision reference the gradient checks use.
//
// Structure (as the camera's render/cpu/blend_backward.h + project_backward.h):
//  1. Blend backward, per tile: the tile's forward is replayed with the reference rules
//     (lidar_reference.h: BlendTileRef) to find every ray's final transmittance and last
//     contributor (the vectorised forward keeps no per-ray record), then the list is walked back
//     to front, each splat's 8 gradient terms summed over the tile's pixels and added once per
//     (splat, tile) into per-thread per-Gaussian arrays, merged at the end. A seam copy adds into
//     its Gaussian's slots (its x differs by a constant).
//  2. Projection backward, per Gaussian with a drawn splat: the spherical EWA projection
//     recomputed with the Gaussian's pose column (a constant: the rolling sweep's fixed-point
//     choice is not differentiated) and the beam table segment of its elevation (fixed), then
//     chained down to the raw parameters. docs/lidar.md "Backward pass" has the formulas.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/status.h"
#include "render/common/thread_pool.h"
#include "render/lidar/lidar_gradients.h"
#include "render/lidar/lidar_kernels.h"
#include "render/lidar/lidar_model.h"
#include "render/lidar/lidar_reference.h"
#include "render/lidar/lidar_sweep.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim {

namespace lidar {

// dL/d(one splat), summed per Gaussian by the blend backward.
enum LidarSplatGrad { kGu = 0, kGv, kGa, kGb, kGc, kGo, kGrange, kGrefl, kLidarSplatGradSize };

// The forward state the blend backward reads (kept by the forward).
template <typename Real>
struct LidarBackwardView {
  const LidarSplatT<Real>* splats = nullptr;
  const uint32_t* splat_gauss = nullptr;  // Gaussian index of each splat (indexed like splats)
  const uint32_t* tile_offsets = nullptr;
  const uint32_t* tile_ids = nullptr;
  int beams = 0, columns = 0, tiles_x = 0, tiles_y = 0;
  size_t num_gaussians = 0;
};

// Reused buffers of step 1.
template <typename Real>
struct LidarBackwardScratch {
  std::vector<std::vector<Real>> per_thread;  // fast mode: [N * 8] per thread
  std::vector<Real> per_instance;             // deterministic mode: [tile-list entries * 8]
};

// Step 1: out [N * kLidarSplatGradSize], overwritten. deterministic: one slot per tile-list entry
// reduced in list order (bit-identical across runs and thread counts); else per-thread arrays.
template <typename Real>
void BlendBackward(ThreadPool& pool, const LidarBackwardView<Real>& view, const LidarUpstreamGradsT<Real>& up,
                   bool deterministic, LidarBackwardScratch<Real>* scratch, std::vector<Real>* out);

// Step 1, vectorised (lidar_backward_simd.inc; AVX2 or AVX-512 picked at run time, or AVX2 forced).
void BlendBackwardVectorised(ThreadPool& pool, const LidarBackwardView<float>& view, const LidarUpstreamGrads& up,
                             bool force_avx2, bool deterministic, LidarBackwardScratch<float>* scratch,
                             std::vector<float>* out);

// Step 2 for one Gaussian projected with pose column col (as ProjectGaussianRef): g holds its
// kLidarSplatGradSize splat gradients; writes dL/d mean (3), log-scale (3), quaternion (4), logit.
template <typename Real>
void ProjectGaussianBackwardRef(const RefProjectParams<Real>& p, int col, const GaussianParams<Real>& gp,
                                const Real* g, Real* d_mean, Real* d_log_scale, Real* d_quat, Real* d_logit);

// Step 2 for every Gaussian with a non-zero splat gradient: out overwritten ([N] sized, zeros
// elsewhere). Parameters from the SoA copy; reflectance as given to the forward (null: 0.5);
// gauss_col: each drawn Gaussian's pose column as the forward chose it (null: PoseColumn again).
template <typename Real>
void ProjectBackward(ThreadPool& pool, const RefProjectParams<Real>& p, const LidarSoa& soa, const float* refl,
                     const uint32_t* gauss_col, const std::vector<Real>& splat_grads,
                     LidarGaussianGradsT<Real>* out);

}  // namespace lidar

// The double-precision reference: projection, sort, binning and blend in double (scalar, the rules
// of LidarRenderOptions::Kernel::kScalar), for gradient checks. Outputs [beams * columns]. With
// upstream and grads, also runs the backward in double. reflectance: [N] or null (0.5 each).
struct LidarReferenceOutput {
  std::vector<double> range_sum, alpha, intensity_sum;
};
absl::Status RenderLidarReference(ThreadPool& pool, const GaussianStore& store, const LidarModel& model,
                                  const LidarSweepPose& sweep, const std::vector<float>* reflectance,
                                  LidarReferenceOutput* out,
                                  const LidarUpstreamGradsT<double>* upstream = nullptr,
                                  LidarGaussianGradsT<double>* grads = nullptr);

}  // namespace streetsim
