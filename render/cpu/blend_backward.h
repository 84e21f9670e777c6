// cpu blend backward: the 3DGS backward of per-tile front-to-back compositing, replayed per pixel
// back to front from the forward's per-pixel contributor count (Frame::n_contrib) and final
// transmittance (Frame::final_T). Produces dL/d(splat) per Gaussian (SplatGradIndex layout,
// kSplatGradSize values per Gaussian id).
//
// Two implementations of the same math:
//  - BlendBackwardSimd (float): a tile's 256 pixels as 16 rows of 16 lanes, like the forward
//    (blend_simd.inc); per splat the 10 gradient terms are summed over the lanes of every row it
//    reaches, then added once per splat and tile into per-thread arrays merged at the end
//    (or, deterministic, into one slot per tile-list entry reduced in list order).
//  - BlendBackwardScalar<Real>: one pixel at a time, std::exp; the reference (float, double).
#pragma once

#include <cstdint>
#include <vector>

#include "render/common/thread_pool.h"
#include "render/cpu/frame.h"
#include "render/cpu/project_backward.h"

namespace streetsim::cpu {

template <typename Real>
struct BlendBackwardArgs {
  const Frame<Real>* frame = nullptr;  // forward state: splats, tile lists, final_T, n_contrib
  Real background[3] = {0, 0, 0};
  const Real* d_rgb = nullptr;    // [H*W*3] dL/d(rgb); required
  const Real* d_depth = nullptr;  // [H*W] or null
  const Real* d_alpha = nullptr;  // [H*W] or null
};

// Reused buffers (per-thread accumulators, per-instance slots).
template <typename Real>
struct BlendBackwardScratch {
  std::vector<std::vector<Real>> per_thread;
  bool per_thread_zero = false;  // every per-thread array is all zeros (the merge leaves them so)
  std::vector<Real> per_instance;
};

// out: [N * kSplatGradSize], overwritten (zero where a Gaussian is not visible).
void BlendBackwardSimd(ThreadPool& pool, const BlendBackwardArgs<float>& args, bool deterministic,
                       BlendBackwardScratch<float>* scratch, std::vector<float>* out);

template <typename Real>
void BlendBackwardScalar(ThreadPool& pool, const BlendBackwardArgs<Real>& args,
                         BlendBackwardScratch<Real>* scratch, std::vector<Real>* out);

// Tiles [tile_begin, tile_end): adds each splat's per-tile gradient either into acc[id * 10 + k]
// (per_instance == null) or into per_instance[list_index * 10 + k].
namespace bwd_avx2 {
void BlendBackwardTiles(const BlendBackwardArgs<float>& args, int64_t tile_begin, int64_t tile_end,
                        float* acc, float* per_instance);
}
namespace bwd_avx512 {
void BlendBackwardTiles(const BlendBackwardArgs<float>& args, int64_t tile_begin, int64_t tile_end,
                        float* acc, float* per_instance);
}

}  // namespace streetsim::cpu
