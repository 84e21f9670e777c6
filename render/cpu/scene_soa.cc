#include "render/cpu/scene_soa.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <string>
#if defined(__AVX2__)
#include <immintrin.h>
#endif

#include "absl/strings/str_cat.h"
#include "render/common/plane_tiles.h"

namespace streetsim::cpu {
namespace {

size_t ShPlaneFor(size_t n) { return (n + 15) / 16 * 16; }

}  // namespace

SceneSoa SceneSoa::FromStore(const GaussianStore& s) {
  SceneSoa o;
  o.n = s.size();
  o.sh_degree = s.sh_degree;
  const size_t n = o.n;
  for (auto* v : {&o.mx, &o.my, &o.mz, &o.ls0, &o.ls1, &o.ls2, &o.qw, &o.qx, &o.qy, &o.qz,
                  &o.opacity_logit}) {
    v->resize(n);
  }
  const int K = s.sh_coeffs();
  o.sh_plane = ShPlaneFor(n);
  o.sh.resize(static_cast<size_t>(K) * 3 * o.sh_plane);
  for (size_t i = 0; i < n; ++i) {
    o.mx[i] = s.means[i * 3];
    o.my[i] = s.means[i * 3 + 1];
    o.mz[i] = s.means[i * 3 + 2];
    o.ls0[i] = s.log_scales[i * 3];
    o.ls1[i] = s.log_scales[i * 3 + 1];
    o.ls2[i] = s.log_scales[i * 3 + 2];
    o.qw[i] = s.rotations[i * 4];
    o.qx[i] = s.rotations[i * 4 + 1];
    o.qy[i] = s.rotations[i * 4 + 2];
    o.qz[i] = s.rotations[i * 4 + 3];
    o.opacity_logit[i] = s.opacity_logits[i];
    for (int kc = 0; kc < K * 3; ++kc) o.sh[kc * o.sh_plane + i] = s.sh[i * K * 3 + kc];
  }
  return o;
}

namespace {
using planes::NonFinite;

// Names the first offending Gaussian and value, so that a diverging trainer says where (the error
// path only: a serial scan).
std::string FirstBadGaussian(const GaussianParamsView& p) {
  const int K = ShCoeffsForDegree(p.sh_degree);
  const size_t stride = static_cast<size_t>(p.sh_stride) * 3;
  auto bad = [](float v) { return !std::isfinite(v); };
  for (size_t i = 0; i < p.n; ++i) {
    for (int k = 0; k < 3; ++k) {
      if (bad(p.means[i * 3 + k])) return absl::StrCat("Gaussian ", i, ": mean[", k, "] = ", p.means[i * 3 + k]);
      if (bad(p.log_scales[i * 3 + k])) {
        return absl::StrCat("Gaussian ", i, ": log_scale[", k, "] = ", p.log_scales[i * 3 + k]);
      }
    }
    const float* q = p.rotations + i * 4;
    const float q2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    if (bad(q[0]) || bad(q[1]) || bad(q[2]) || bad(q[3]) || q2 < 1e-20f) {
      return absl::StrCat("Gaussian ", i, ": rotation = (", q[0], ", ", q[1], ", ", q[2], ", ", q[3], ")");
    }
    if (bad(p.opacity_logits[i])) return absl::StrCat("Gaussian ", i, ": opacity logit = ", p.opacity_logits[i]);
    for (int c = 0; c < K * 3; ++c) {
      if (bad(p.sh[i * stride + c])) return absl::StrCat("Gaussian ", i, ": SH[", c, "] = ", p.sh[i * stride + c]);
    }
  }
  return "none found on rescan";
}

}  // namespace

absl::Status SceneSoa::Assign(ThreadPool& pool, const GaussianParamsView& p) {
  const int K = ShCoeffsForDegree(p.sh_degree);
  if (p.sh_degree < 0 || p.sh_degree > kMaxShDegree || p.sh_stride < K) {
    return absl::InvalidArgumentError("UpdateSceneParams: bad SH degree or stride");
  }
  n = p.n;
  sh_degree = p.sh_degree;
  for (auto* v : {&mx, &my, &mz, &ls0, &ls1, &ls2, &qw, &qx, &qy, &qz, &opacity_logit}) v->resize(n);
  sh_plane = ShPlaneFor(n);
  sh.resize(static_cast<size_t>(K) * 3 * sh_plane);
  std::atomic<bool> bad{false};
  constexpr int64_t kBlock = 64;
  const int64_t blocks = static_cast<int64_t>((n + kBlock - 1) / kBlock);
  const size_t stride = static_cast<size_t>(p.sh_stride) * 3;
  pool.ParallelFor(blocks, 16, [&](int64_t b0, int64_t b1, int) {
    uint32_t nf = 0;
    for (int64_t blk = b0; blk < b1; ++blk) {
      const size_t i0 = static_cast<size_t>(blk) * kBlock, i1 = std::min(n, i0 + kBlock);
      for (size_t i = i0; i < i1; ++i) {
        const float* m = p.means + i * 3;
        const float* l = p.log_scales + i * 3;
        const float* q = p.rotations + i * 4;
        const float o = p.opacity_logits[i];
        mx[i] = m[0], my[i] = m[1], mz[i] = m[2];
        ls0[i] = l[0], ls1[i] = l[1], ls2[i] = l[2];
        qw[i] = q[0], qx[i] = q[1], qy[i] = q[2], qz[i] = q[3];
        opacity_logit[i] = o;
        nf |= NonFinite(m[0]) | NonFinite(m[1]) | NonFinite(m[2]) | NonFinite(l[0]) | NonFinite(l[1]) |
              NonFinite(l[2]) | NonFinite(q[0]) | NonFinite(q[1]) | NonFinite(q[2]) | NonFinite(q[3]) |
              NonFinite(o);
        nf |= (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3] < 1e-20f);
      }
      // SH: plane-major writes, a block of Gaussians at a time (64 consecutive floats per plane).
      int kc_done = 0;
#if defined(__AVX2__)
      // 8 x 8 blocks transposed in registers (a strided scalar copy was most of this pass).
      if (i1 - i0 == static_cast<size_t>(kBlock)) {
        kc_done = (K * 3) / 8 * 8;
        nf |= planes::TransposeRows8(p.sh + i0 * stride, stride, kBlock, kc_done, sh.data() + i0, sh_plane);
      }
#endif
      for (int kc = kc_done; kc < K * 3; ++kc) {
        float* dst = sh.data() + static_cast<size_t>(kc) * sh_plane;
        const float* src = p.sh + kc;
        for (size_t i = i0; i < i1; ++i) {
          const float v = src[i * stride];
          dst[i] = v;
          nf |= NonFinite(v);
        }
      }

    }
    if (nf) bad.store(true, std::memory_order_relaxed);
  });
  if (bad.load()) {
    return absl::InvalidArgumentError(
        absl::StrCat("UpdateSceneParams: a parameter is not finite or a rotation is zero (", FirstBadGaussian(p), ")"));
  }
  return absl::OkStatus();
}

absl::Status SceneSoa::AssignRows(ThreadPool& pool, const GaussianParamsView& p, const ParamsChange& c) {
  const int K = ShCoeffsForDegree(p.sh_degree);
  if (p.n != n || p.sh_degree != sh_degree || p.sh_stride < K || c.sh_coeffs < 0 || c.sh_coeffs > K) {
    return absl::InvalidArgumentError("UpdateSceneRows: the view does not match the scene");
  }
  std::atomic<bool> bad{false};
  const size_t stride = static_cast<size_t>(p.sh_stride) * 3;
  const int sh_values = c.sh_coeffs * 3;
  pool.ParallelFor(static_cast<int64_t>(c.num_rows), 4096, [&](int64_t b, int64_t e, int) {
    uint32_t nf = 0;
    for (int64_t r = b; r < e; ++r) {
      const size_t i = c.rows[r];
      if (i >= n) {
        nf = 1;
        continue;
      }
      if (c.means) {
        const float* m = p.means + i * 3;
        mx[i] = m[0], my[i] = m[1], mz[i] = m[2];
        nf |= NonFinite(m[0]) | NonFinite(m[1]) | NonFinite(m[2]);
      }
      if (c.log_scales) {
        const float* l = p.log_scales + i * 3;
        ls0[i] = l[0], ls1[i] = l[1], ls2[i] = l[2];
        nf |= NonFinite(l[0]) | NonFinite(l[1]) | NonFinite(l[2]);
      }
      if (c.rotations) {
        const float* q = p.rotations + i * 4;
        qw[i] = q[0], qx[i] = q[1], qy[i] = q[2], qz[i] = q[3];
        nf |= NonFinite(q[0]) | NonFinite(q[1]) | NonFinite(q[2]) | NonFinite(q[3]);
        nf |= (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3] < 1e-20f);
      }
      if (c.opacity) {
        opacity_logit[i] = p.opacity_logits[i];
        nf |= NonFinite(p.opacity_logits[i]);
      }
    }
    // SH is plane-major here: a row's values go to sh_values planes. Runs of kTile consecutive
    // rows (a dynamic scene's moving Gaussians mostly are) go a tile at a time, so that each plane
    // gets whole cache lines: streamed from a line start (rows before it one by one), or, for the
    // DC alone or without AVX2, through a local tile; other rows one by one.
    constexpr int kTile = 16, kMaxShValues = 48;
    bool streamed = false;
    for (int64_t r = b; r < e;) {
      const size_t i0 = c.rows[r];
      // Every row of the run is checked: rows need not be sorted, and a tile must not write a row
      // that is not in the change (its view values may be stale).
      bool run = r + kTile <= e && i0 + kTile <= n;
      for (int j = 1; run && j < kTile; ++j) run = c.rows[r + j] == i0 + j;
#if defined(__AVX2__)
      if (sh_values % 8 == 0) {
        if (run && i0 % kTile == 0) {
          nf |= planes::StreamRows16(p.sh + i0 * stride, stride, sh_values, sh.data() + i0, sh_plane);
          streamed = true;
          r += kTile;
          continue;
        }
        run = false;  // one by one up to the next line start (a gap in the rows, a block's start)
      }
#endif
      if (run) {
        const float* src = p.sh + i0 * stride;
        alignas(64) float tile[kMaxShValues * kTile];  // [value][row]
        for (int j = 0; j < kTile; ++j) {
          const float* row = src + j * stride;
          for (int kc = 0; kc < sh_values; ++kc) {
            tile[kc * kTile + j] = row[kc];
            nf |= NonFinite(row[kc]);
          }
        }
        for (int kc = 0; kc < sh_values; ++kc) {
          std::memcpy(sh.data() + static_cast<size_t>(kc) * sh_plane + i0, tile + kc * kTile, sizeof(float) * kTile);
        }
        r += kTile;
        continue;
      }
      if (i0 < n) {
        for (int kc = 0; kc < sh_values; ++kc) {
          const float v = p.sh[i0 * stride + kc];
          sh[static_cast<size_t>(kc) * sh_plane + i0] = v;
          nf |= NonFinite(v);
        }
      }
      ++r;
    }
#if defined(__AVX2__)
    if (streamed) _mm_sfence();  // streaming stores are weakly ordered: publish them before the join
#endif
    if (nf) bad.store(true, std::memory_order_relaxed);
  });
  if (bad.load()) {
    return absl::InvalidArgumentError(
        absl::StrCat("UpdateSceneRows: a changed parameter is not finite, a rotation is zero or a row is out of range (",
                     FirstBadGaussian(p), ")"));
  }
  return absl::OkStatus();
}

}  // namespace streetsim::cpu
