// Small random scenes and a scalar loss through the cpu double-precision forward, for the
// finite-difference gradient checks of both backends (tests/train/grad_check_test.cc,
// tests/render/vulkan_backward_test.cc).
#pragma once

#include <vector>

#include <Eigen/Core>

#include "render/camera.h"
#include "render/common/thread_pool.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::gradcheck {

struct Scene {
  GaussianStore store;
  PinholeCamera cam;
  Eigen::Vector3f background;
  std::vector<double> w_rgb, w_depth, w_alpha;  // the loss: sum of w . outputs
};

// n Gaussians in front of a slightly rotated camera, opacities below the 0.99 clamp, random loss
// weights per output value.
Scene RandomScene(unsigned seed, int n, int degree, int width = 72, int height = 56);

// The loss through the double-precision forward (cpu internals, no float outputs in between).
double LossDouble(ThreadPool& pool, const Scene& s, const GaussianStore& store);

}  // namespace streetsim::gradcheck
