// cpu projection backward over a frame's visible Gaussians: dL/d(splat) (blend_backward.h) ->
// GaussianGrads (render/engine.h), one Gaussian per iteration, in parallel (no two write the
// same Gaussian, so no reduction is needed).
#pragma once

#include <vector>

#include "render/common/thread_pool.h"
#include "render/cpu/frame.h"
#include "render/cpu/scene_soa.h"
#include "render/engine.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::cpu {

// From the store layout (the scalar float and double paths).
template <typename Real>
void ProjectBackwardStore(ThreadPool& pool, const GaussianStore& store,
                          const projection::CameraParams<Real>& cam, const Frame<Real>& frame,
                          const std::vector<Real>& splat_grads, GaussianGrads* out);

// From the engine's structure-of-arrays copy, vectorised across Gaussians (the production float
// path; project_backward_simd.inc, AVX2 or AVX-512 chosen at run time).
void ProjectBackwardSoa(ThreadPool& pool, const SceneSoa& scene, const projection::CameraParams<float>& cam,
                        const Frame<float>& frame, const std::vector<float>& splat_grads, GaussianGrads* out);

// The same from the SoA copy one Gaussian at a time through the scalar reference (what the
// vectorised path is tested against).
void ProjectBackwardSoaScalar(ThreadPool& pool, const SceneSoa& scene, const projection::CameraParams<float>& cam,
                              const Frame<float>& frame, const std::vector<float>& splat_grads, GaussianGrads* out);

// Gaussians [begin, end) of the vectorised path; `out` already sized.
namespace pbwd_avx2 {
void ProjectBackwardRange(const SceneSoa& s, const projection::CameraParams<float>& cam, const uint8_t* visible,
                          const float* splat_grads, int64_t begin, int64_t end, GaussianGrads* out);
}
namespace pbwd_avx512 {
void ProjectBackwardRange(const SceneSoa& s, const projection::CameraParams<float>& cam, const uint8_t* visible,
                          const float* splat_grads, int64_t begin, int64_t end, GaussianGrads* out);
}

}  // namespace streetsim::cpu
