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

// From the engine's structure-of-arrays copy (the production float path).
void ProjectBackwardSoa(ThreadPool& pool, const SceneSoa& scene, const projection::CameraParams<float>& cam,
                        const Frame<float>& frame, const std::vector<float>& splat_grads, GaussianGrads* out);

}  // namespace streetsim::cpu
