// cpu projection stage: every Gaussian -> screen-space splat, tile rectangle, visibility.
#pragma once

#include "render/camera.h"
#include "render/common/thread_pool.h"
#include "render/cpu/frame.h"
#include "render/cpu/scene_soa.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::cpu {

template <typename Real>
projection::CameraParams<Real> MakeCameraParams(const PinholeCamera& camera);

// Fills frame->splats/rects/visible for all Gaussians and frame->visible_ids (index order).
template <typename Real>
void ProjectGaussians(ThreadPool& pool, const GaussianStore& store,
                      const projection::CameraParams<Real>& cam, Frame<Real>* frame);

// The production float path: the same projection vectorised across Gaussians (project_simd.inc),
// AVX2 or AVX-512 chosen at run time. Fills the same frame fields as ProjectGaussians.
void ProjectGaussiansSimd(ThreadPool& pool, const SceneSoa& scene,
                          const projection::CameraParams<float>& cam, Frame<float>* frame);

namespace project_avx2 {
void ProjectRange(const SceneSoa& s, const projection::CameraParams<float>& cam, int64_t begin,
                  int64_t end, Frame<float>* frame);
}
namespace project_avx512 {
void ProjectRange(const SceneSoa& s, const projection::CameraParams<float>& cam, int64_t begin,
                  int64_t end, Frame<float>* frame);
}

}  // namespace streetsim::cpu
