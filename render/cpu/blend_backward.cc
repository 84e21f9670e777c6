#include "render/cpu/blend_backward.h"
#include "render/cpu/simd_dispatch.h"

#include <algorithm>
#include <cmath>
#include <cstring>

namespace streetsim::cpu {
namespace {

using BwdFn = void (*)(const BlendBackwardArgs<float>&, int64_t, int64_t, float*, float*);

BwdFn ChooseBwd() { return PickSimd<BwdFn>(&bwd_avx2::BlendBackwardTiles, &bwd_avx512::BlendBackwardTiles); }

constexpr int64_t kBackwardTileGrain = 4;

// Sums the per-thread arrays into out (parallel over Gaussians; fixed thread order per element)
// and zeros them on the way: the lines are in cache then, which costs less than a separate
// zeroing pass over cold memory before the next backward.
template <typename Real>
void MergePerThread(ThreadPool& pool, BlendBackwardScratch<Real>* scratch, std::vector<Real>* out) {
  std::vector<std::vector<Real>>& per_thread = scratch->per_thread;
  const int64_t n = static_cast<int64_t>(out->size());
  pool.ParallelFor(n, 1 << 14, [&](int64_t b, int64_t e, int) {
    Real* o = out->data();
    std::memcpy(o + b, per_thread[0].data() + b, sizeof(Real) * (e - b));
    std::memset(per_thread[0].data() + b, 0, sizeof(Real) * (e - b));
    for (size_t t = 1; t < per_thread.size(); ++t) {
      Real* src = per_thread[t].data();
      for (int64_t i = b; i < e; ++i) o[i] += src[i];
      std::memset(src + b, 0, sizeof(Real) * (e - b));
    }
  });
  scratch->per_thread_zero = true;
}

// Per-thread arrays of n zeros: only a first call or a new size pays the zeroing pass.
template <typename Real>
void PreparePerThread(ThreadPool& pool, size_t n, BlendBackwardScratch<Real>* scratch) {
  const bool ready = scratch->per_thread_zero && scratch->per_thread.size() == static_cast<size_t>(pool.num_threads()) &&
                     scratch->per_thread[0].size() == n;
  scratch->per_thread_zero = false;  // until the merge has zeroed them again
  if (ready) return;
  scratch->per_thread.resize(pool.num_threads());
  pool.ParallelFor(pool.num_threads(), 1, [&](int64_t b, int64_t e, int) {
    for (int64_t t = b; t < e; ++t) scratch->per_thread[t].assign(n, Real(0));
  });
}

}  // namespace

void BlendBackwardSimd(ThreadPool& pool, const BlendBackwardArgs<float>& args, bool deterministic,
                       BlendBackwardScratch<float>* scratch, std::vector<float>* out) {
  static const BwdFn fn = ChooseBwd();
  const Frame<float>& f = *args.frame;
  const size_t n = f.splats.size() * kSplatGradSize;
  const int64_t tiles = static_cast<int64_t>(f.tiles_x) * f.tiles_y;
  out->resize(n);
  if (deterministic) {
    // One slot per tile-list entry, then a reduction in list order: the result does not depend
    // on how tiles were spread over threads.
    const size_t m = f.tile_ids.size() * kSplatGradSize;
    scratch->per_instance.resize(m);
    pool.ParallelFor(static_cast<int64_t>(m), 1 << 16, [&](int64_t b, int64_t e, int) {
      std::memset(scratch->per_instance.data() + b, 0, sizeof(float) * (e - b));
    });
    pool.ParallelFor(tiles, kBackwardTileGrain, [&](int64_t b, int64_t e, int) {
      fn(args, b, e, nullptr, scratch->per_instance.data());
    });
    std::fill(out->begin(), out->end(), 0.0f);
    const float* inst = scratch->per_instance.data();
    for (size_t j = 0; j < f.tile_ids.size(); ++j) {
      float* dst = out->data() + static_cast<size_t>(f.tile_ids[j]) * kSplatGradSize;
      for (int k = 0; k < kSplatGradSize; ++k) dst[k] += inst[j * kSplatGradSize + k];
    }
    return;
  }
  PreparePerThread(pool, n, scratch);
  pool.ParallelFor(tiles, kBackwardTileGrain, [&](int64_t b, int64_t e, int thread) {
    fn(args, b, e, scratch->per_thread[thread].data(), nullptr);
  });
  MergePerThread(pool, scratch, out);
}

template <typename Real>
void BlendBackwardScalar(ThreadPool& pool, const BlendBackwardArgs<Real>& args,
                         BlendBackwardScratch<Real>* scratch, std::vector<Real>* out) {
  const Frame<Real>& f = *args.frame;
  const size_t n = f.splats.size() * kSplatGradSize;
  out->resize(n);
  PreparePerThread(pool, n, scratch);
  const int64_t tiles = static_cast<int64_t>(f.tiles_x) * f.tiles_y;
  const Real min_alpha = Real(1) / Real(255);
  pool.ParallelFor(tiles, kBackwardTileGrain, [&](int64_t t0, int64_t t1, int thread) {
    Real* acc = scratch->per_thread[thread].data();
    for (int64_t tile = t0; tile < t1; ++tile) {
      const int tx = static_cast<int>(tile % f.tiles_x), ty = static_cast<int>(tile / f.tiles_x);
      const uint32_t begin = f.tile_offsets[tile];
      for (int v = ty * 16; v < std::min(f.height, ty * 16 + 16); ++v) {
        for (int u = tx * 16; u < std::min(f.width, tx * 16 + 16); ++u) {
          const size_t pix = static_cast<size_t>(v) * f.width + u;
          const Real Tf = f.final_T[pix];
          const Real g[3] = {args.d_rgb[pix * 3], args.d_rgb[pix * 3 + 1], args.d_rgb[pix * 3 + 2]};
          const Real gd = args.d_depth ? args.d_depth[pix] : Real(0);
          const Real ga = args.d_alpha ? args.d_alpha[pix] : Real(0);
          const Real gT = (ga - (g[0] * args.background[0] + g[1] * args.background[1] +
                                 g[2] * args.background[2])) * Tf;
          Real T = Tf, S[3] = {0, 0, 0}, Sd = 0;
          for (uint32_t jj = f.n_contrib[pix]; jj-- > 0;) {
            const uint32_t id = f.tile_ids[begin + jj];
            const BlendSplat<Real>& s = f.splats[id];
            const Real dx = s.x - Real(u), dy = s.y - Real(v);
            const Real power = Real(-0.5) * (s.a * dx * dx + s.c * dy * dy) - s.b * dx * dy;
            if (power > 0) continue;
            const Real G = std::exp(power);
            const Real oG = s.opacity * G;
            const Real alpha = std::min(Real(0.99), oG);
            if (alpha < min_alpha) continue;
            const Real om = Real(1) - alpha;
            const Real Ti = T / om;
            const Real w = alpha * Ti;
            const Real c[3] = {s.r, s.g, s.bl};
            Real* a = acc + static_cast<size_t>(id) * kSplatGradSize;
            Real d_alpha = gT / om;
            for (int k = 0; k < 3; ++k) {
              a[kGr + k] += w * g[k];
              d_alpha += Ti * g[k] * (c[k] - S[k]);
              S[k] = alpha * c[k] + om * S[k];
            }
            a[kGdepth] += w * gd;
            d_alpha += Ti * gd * (s.depth - Sd);
            Sd = alpha * s.depth + om * Sd;
            T = Ti;
            if (!(oG < Real(0.99))) continue;  // clamped: alpha does not depend on o or G
            a[kGo] += d_alpha * G;
            const Real d_power = d_alpha * s.opacity * G;
            a[kGx] += d_power * -(s.a * dx + s.b * dy);
            a[kGy] += d_power * -(s.c * dy + s.b * dx);
            a[kGa] += d_power * Real(-0.5) * dx * dx;
            a[kGb] += d_power * -dx * dy;
            a[kGc] += d_power * Real(-0.5) * dy * dy;
          }
        }
      }
    }
  });
  MergePerThread(pool, scratch, out);
}

template void BlendBackwardScalar<float>(ThreadPool&, const BlendBackwardArgs<float>&,
                                         BlendBackwardScratch<float>*, std::vector<float>*);
template void BlendBackwardScalar<double>(ThreadPool&, const BlendBackwardArgs<double>&,
                                          BlendBackwardScratch<double>*, std::vector<double>*);

}  // namespace streetsim::cpu
