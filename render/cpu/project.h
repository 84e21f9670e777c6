// cpu projection stage: every Gaussian -> screen-space splat, tile rectangle, visibility.
#pragma once

#include "render/camera.h"
#include "render/common/thread_pool.h"
#include "render/cpu/frame.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::cpu {

template <typename Real>
projection::CameraParams<Real> MakeCameraParams(const PinholeCamera& camera);

// Fills frame->splats/rects/visible for all Gaussians and frame->visible_ids (index order).
template <typename Real>
void ProjectGaussians(ThreadPool& pool, const GaussianStore& store,
                      const projection::CameraParams<Real>& cam, Frame<Real>* frame);

}  // namespace streetsim::cpu
