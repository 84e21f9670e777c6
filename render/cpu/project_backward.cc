#include "render/cpu/project_backward.h"

#include <cstring>

#include "render/cpu/project_bwd.h"
#include "render/cpu/simd_dispatch.h"

namespace streetsim::cpu {
namespace {

// Sizes the outputs without clearing them: RunBackward writes every element once (visible
// Gaussians their gradients, the others zeros), so the arrays are not zeroed in a separate pass.
void Resize(size_t n, int K, GaussianGrads* out) {
  out->means.resize(n * 3);
  out->log_scales.resize(n * 3);
  out->rotations.resize(n * 4);
  out->opacity_logits.resize(n);
  out->sh.resize(n * K * 3);
  out->means2d.resize(n * 2);
  out->radii.resize(n);
}

// Zeros Gaussians [g0, g1) of every output array.
void ZeroRange(size_t g0, size_t g1, int K, GaussianGrads* out) {
  if (g1 <= g0) return;
  auto z = [&](std::vector<float>& v, size_t stride) {
    std::fill(v.begin() + g0 * stride, v.begin() + g1 * stride, 0.0f);
  };
  z(out->means, 3);
  z(out->log_scales, 3);
  z(out->rotations, 4);
  z(out->opacity_logits, 1);
  z(out->sh, static_cast<size_t>(K) * 3);
  z(out->means2d, 2);
  z(out->radii, 1);
}

// Gathers Gaussian i's parameters (Real working copies) from either layout.
template <typename Real, typename Source>
void RunBackward(ThreadPool& pool, const Source& src, size_t n, int degree,
                 const projection::CameraParams<Real>& cam, const Frame<Real>& frame,
                 const std::vector<Real>& splat_grads, GaussianGrads* out) {
  const int K = (degree + 1) * (degree + 1);
  Resize(n, K, out);
  const std::vector<uint32_t>& ids = frame.visible_ids;  // ascending
  if (ids.empty()) {
    ZeroRange(0, n, K, out);
    return;
  }
  pool.ParallelFor(static_cast<int64_t>(ids.size()), 1024, [&](int64_t b, int64_t e, int) {
    // This chunk also zeros the invisible Gaussians before each of its ids (and after the last).
    size_t prev_end = b > 0 ? static_cast<size_t>(ids[b - 1]) + 1 : 0;
    Real mean[3], ls[3], q[4], logit, sh[48], g[kSplatGradSize];
    ParamGrads<Real> pg;
    for (int64_t j = b; j < e; ++j) {
      const uint32_t i = ids[j];
      ZeroRange(prev_end, i, K, out);
      prev_end = static_cast<size_t>(i) + 1;
      src.Get(i, K, mean, ls, q, &logit, sh);
      for (int k = 0; k < kSplatGradSize; ++k) g[k] = splat_grads[static_cast<size_t>(i) * kSplatGradSize + k];
      ProjectGaussianBackward<Real>(cam, mean, ls, q, logit, sh, degree, g, &pg);
      for (int k = 0; k < 3; ++k) {
        out->means[i * 3 + k] = static_cast<float>(pg.mean[k]);
        out->log_scales[i * 3 + k] = static_cast<float>(pg.log_scale[k]);
      }
      for (int k = 0; k < 4; ++k) out->rotations[i * 4 + k] = static_cast<float>(pg.quat[k]);
      out->opacity_logits[i] = static_cast<float>(pg.logit);
      float* dsh = &out->sh[static_cast<size_t>(i) * K * 3];
      for (int k = 0; k < K * 3; ++k) dsh[k] = static_cast<float>(pg.sh[k]);
      out->means2d[i * 2 + 0] = static_cast<float>(g[kGx]);
      out->means2d[i * 2 + 1] = static_cast<float>(g[kGy]);
      out->radii[i] = static_cast<float>(pg.radius);
    }
    if (e == static_cast<int64_t>(ids.size())) ZeroRange(prev_end, n, K, out);
  });
}

template <typename Real>
struct StoreSource {
  const GaussianStore& s;
  void Get(size_t i, int K, Real* mean, Real* ls, Real* q, Real* logit, Real* sh) const {
    for (int k = 0; k < 3; ++k) {
      mean[k] = s.means[i * 3 + k];
      ls[k] = s.log_scales[i * 3 + k];
    }
    for (int k = 0; k < 4; ++k) q[k] = s.rotations[i * 4 + k];
    *logit = s.opacity_logits[i];
    const float* p = &s.sh[i * K * 3];
    for (int k = 0; k < K * 3; ++k) sh[k] = p[k];
  }
};

struct SoaSource {
  const SceneSoa& s;
  void Get(size_t i, int K, float* mean, float* ls, float* q, float* logit, float* sh) const {
    mean[0] = s.mx[i]; mean[1] = s.my[i]; mean[2] = s.mz[i];
    // The forward clamps what could overflow; the same clamps here.
    ls[0] = std::min(std::max(s.ls0[i], -30.0f), 30.0f);
    ls[1] = std::min(std::max(s.ls1[i], -30.0f), 30.0f);
    ls[2] = std::min(std::max(s.ls2[i], -30.0f), 30.0f);
    q[0] = s.qw[i]; q[1] = s.qx[i]; q[2] = s.qy[i]; q[3] = s.qz[i];
    *logit = std::min(std::max(s.opacity_logit[i], -80.0f), 80.0f);
    for (int k = 0; k < K * 3; ++k) sh[k] = s.sh[static_cast<size_t>(k) * s.sh_plane + i];
  }
};

}  // namespace

template <typename Real>
void ProjectBackwardStore(ThreadPool& pool, const GaussianStore& store,
                          const projection::CameraParams<Real>& cam, const Frame<Real>& frame,
                          const std::vector<Real>& splat_grads, GaussianGrads* out) {
  RunBackward<Real>(pool, StoreSource<Real>{store}, store.size(), store.sh_degree, cam, frame, splat_grads, out);
}

void ProjectBackwardSoaScalar(ThreadPool& pool, const SceneSoa& scene, const projection::CameraParams<float>& cam,
                              const Frame<float>& frame, const std::vector<float>& splat_grads, GaussianGrads* out) {
  RunBackward<float>(pool, SoaSource{scene}, scene.n, scene.sh_degree, cam, frame, splat_grads, out);
}

void ProjectBackwardSoa(ThreadPool& pool, const SceneSoa& scene, const projection::CameraParams<float>& cam,
                        const Frame<float>& frame, const std::vector<float>& splat_grads, GaussianGrads* out) {
  using RangeFn = void (*)(const SceneSoa&, const projection::CameraParams<float>&, const uint8_t*, const float*,
                           int64_t, int64_t, GaussianGrads*);
  static const RangeFn fn = PickSimd<RangeFn>(&pbwd_avx2::ProjectBackwardRange, &pbwd_avx512::ProjectBackwardRange);
  const int K = (scene.sh_degree + 1) * (scene.sh_degree + 1);
  Resize(scene.n, K, out);
  pool.ParallelFor(static_cast<int64_t>(scene.n), 4096, [&](int64_t b, int64_t e, int) {
    fn(scene, cam, frame.visible.data(), splat_grads.data(), b, e, out);
  });
}

template void ProjectBackwardStore<float>(ThreadPool&, const GaussianStore&, const projection::CameraParams<float>&,
                                          const Frame<float>&, const std::vector<float>&, GaussianGrads*);
template void ProjectBackwardStore<double>(ThreadPool&, const GaussianStore&,
                                           const projection::CameraParams<double>&, const Frame<double>&,
                                           const std::vector<double>&, GaussianGrads*);

}  // namespace streetsim::cpu
