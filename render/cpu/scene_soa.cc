#include "render/cpu/scene_soa.h"

#include <algorithm>
#include <atomic>
#include <cstring>

#include "absl/strings/str_cat.h"

namespace streetsim::cpu {

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
  o.sh.resize(static_cast<size_t>(K) * 3 * n);
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
    for (int kc = 0; kc < K * 3; ++kc) o.sh[kc * n + i] = s.sh[i * K * 3 + kc];
  }
  return o;
}

namespace {
// 1 where the float is inf or nan (exponent all ones); integer test, immune to -ffast-math.
inline uint32_t NonFinite(float v) {
  uint32_t b;
  std::memcpy(&b, &v, 4);
  return (b & 0x7f800000u) == 0x7f800000u;
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
  sh.resize(static_cast<size_t>(K) * 3 * n);
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
      for (int kc = 0; kc < K * 3; ++kc) {
        float* dst = sh.data() + static_cast<size_t>(kc) * n;
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
    return absl::InvalidArgumentError("UpdateSceneParams: a parameter is not finite or a rotation is zero");
  }
  return absl::OkStatus();
}

}  // namespace streetsim::cpu
