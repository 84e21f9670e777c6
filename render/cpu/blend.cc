#include "render/cpu/blend.h"
#include "render/cpu/simd_dispatch.h"

#include <algorithm>
#include <atomic>
#include <cmath>

namespace streetsim::cpu {

namespace {

using BlendFn = void (*)(const BlendArgs<float>&, int64_t, int64_t);

struct SimdChoice {
  BlendFn fn;
  const char* isa;
};

SimdChoice ChooseSimd() {
  switch (DetectSimdIsa()) {
    case SimdIsa::kAvx512: return {&simd_avx512::BlendTiles, "avx512"};
    case SimdIsa::kAvx2: return {&simd_avx2::BlendTiles, "avx2"};
    case SimdIsa::kGeneric: break;
  }
  return {&simd_avx2::BlendTiles, "generic"};
}

const SimdChoice& Simd() {
  static const SimdChoice choice = ChooseSimd();
  return choice;
}

// Tiles per work item: small enough that the dynamic schedule balances sky tiles (empty) against
// tiles full of parked cars (thousands of splats), large enough to amortise the atomic.
constexpr int64_t kTileGrain = 4;

// Runs body(begin, end) over the tile batches until args.should_stop says stop.
template <typename Args, typename Body>
void ForTileBatches(ThreadPool& pool, int64_t tiles, const Args& args, const Body& body) {
  if (args.should_stop == nullptr) {
    pool.ParallelFor(tiles, kTileGrain, [&](int64_t begin, int64_t end, int) { body(begin, end); });
    return;
  }
  std::atomic<bool> stopped{false};
  pool.ParallelFor(tiles, kTileGrain, [&](int64_t begin, int64_t end, int) {
    if (stopped.load(std::memory_order_relaxed)) return;
    if ((*args.should_stop)()) {
      stopped.store(true, std::memory_order_relaxed);
      return;
    }
    body(begin, end);
  });
}

}  // namespace

const char* BlendSimdIsa() { return Simd().isa; }

void BlendSimd(ThreadPool& pool, const BlendArgs<float>& args) {
  const BlendFn fn = Simd().fn;
  const int64_t tiles = static_cast<int64_t>(args.frame->tiles_x) * args.frame->tiles_y;
  ForTileBatches(pool, tiles, args, [&](int64_t begin, int64_t end) { fn(args, begin, end); });
}

template <typename Real>
void BlendScalar(ThreadPool& pool, const BlendArgs<Real>& args) {
  const Frame<Real>& f = *args.frame;
  const int64_t tiles = static_cast<int64_t>(f.tiles_x) * f.tiles_y;
  const Real min_alpha = Real(1) / Real(255);
  ForTileBatches(pool, tiles, args, [&](int64_t t0, int64_t t1) {
    for (int64_t tile = t0; tile < t1; ++tile) {
      const int tx = static_cast<int>(tile % f.tiles_x), ty = static_cast<int>(tile / f.tiles_x);
      const uint32_t begin = f.tile_offsets[tile], end = f.tile_offsets[tile + 1];
      for (int v = ty * 16; v < std::min(f.height, ty * 16 + 16); ++v) {
        for (int u = tx * 16; u < std::min(f.width, tx * 16 + 16); ++u) {
          Real T = 1, C[3] = {0, 0, 0}, D = 0;
          uint32_t last = 0;
          for (uint32_t j = begin; j < end; ++j) {
            const BlendSplat<Real>& s = f.splats[f.tile_ids[j]];
            const Real dx = s.x - Real(u), dy = s.y - Real(v);
            const Real power = Real(-0.5) * (s.a * dx * dx + s.c * dy * dy) - s.b * dx * dy;
            if (power > 0) continue;
            const Real alpha = std::min(Real(0.99), s.opacity * std::exp(power));
            if (alpha < min_alpha) continue;
            const Real test_T = T * (1 - alpha);
            if (test_T < Real(1e-4)) break;
            const Real w = alpha * T;
            C[0] += w * s.r;
            C[1] += w * s.g;
            C[2] += w * s.bl;
            D += w * s.depth;
            T = test_T;
            last = j - begin + 1;
          }
          const size_t pix = static_cast<size_t>(v) * f.width + u;
          for (int c = 0; c < 3; ++c) args.rgb[pix * 3 + c] = C[c] + T * args.background[c];
          if (args.depth) args.depth[pix] = D;
          if (args.alpha) args.alpha[pix] = 1 - T;
          if (args.final_T) args.final_T[pix] = T;
          if (args.n_contrib) args.n_contrib[pix] = last;
        }
      }
    }
  });
}

template void BlendScalar<float>(ThreadPool&, const BlendArgs<float>&);
template void BlendScalar<double>(ThreadPool&, const BlendArgs<double>&);

}  // namespace streetsim::cpu
