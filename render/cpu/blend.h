// cpu blend stage: per-tile front-to-back alpha compositing with the 3DGS rules.
//
// Two implementations of the same rules:
//  - BlendSimd (float): 64 pixels (4 rows x 16) per step so the compiler vectorises every
//    operation, with an inline exp; compiled for AVX2 and AVX-512 and picked at run time.
//  - BlendScalar<Real>: one pixel at a time, std::exp; float or double. The reference the tests
//    compare against, and the double-precision path for gradient checks.
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

#include "render/common/thread_pool.h"
#include "render/cpu/frame.h"

namespace streetsim::cpu {

template <typename Real>
struct BlendArgs {
  const Frame<Real>* frame = nullptr;
  Real background[3] = {0, 0, 0};
  Real* rgb = nullptr;    // [H*W*3]
  Real* depth = nullptr;  // [H*W] or null
  Real* alpha = nullptr;  // [H*W] or null
  Real* final_T = nullptr;          // [H*W] or null
  uint32_t* n_contrib = nullptr;    // [H*W] or null: only the backward pass needs it
  // Polled before each batch of tiles (from the pool's threads); once it returns true the
  // remaining batches are skipped and the image is left incomplete (the caller gives up on it).
  const std::function<bool()>* should_stop = nullptr;
};

void BlendSimd(ThreadPool& pool, const BlendArgs<float>& args);

template <typename Real>
void BlendScalar(ThreadPool& pool, const BlendArgs<Real>& args);

// Which SIMD kernel BlendSimd runs on this machine: "avx512", "avx2" or "generic".
const char* BlendSimdIsa();

namespace simd_avx2 {
void BlendTiles(const BlendArgs<float>& args, int64_t tile_begin, int64_t tile_end);
}
namespace simd_avx512 {
void BlendTiles(const BlendArgs<float>& args, int64_t tile_begin, int64_t tile_end);
}

}  // namespace streetsim::cpu
