// Fixtures for tests of the fine stage's bookkeeping (DynamicStage, its checkpoints, the Gaussians'
// order): scattered Gaussians and a tiny S3Gaussian field, where quality is not the point.
#pragma once

#include <cstddef>
#include <cstdint>
#include <random>

#include "scene/train/dynamic_stage.h"
#include "scene/train/train_state.h"

namespace streetsim::train::fixtures {

// n Gaussians at SH degree 3 scattered in a 40 x 20 x 4 m box, with random log-scales in [-3, -2],
// rotations near the identity, opacity logits in [-2, 2] and SH coefficients in [-0.5, 0.5].
inline GaussianStore ScatteredGaussians(size_t n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(0, 1);
  GaussianStore g;
  g.sh_degree = 3;
  for (size_t i = 0; i < n; ++i) {
    g.means.insert(g.means.end(), {40 * u(rng) - 20, 20 * u(rng) - 10, 4 * u(rng)});
    g.log_scales.insert(g.log_scales.end(), {-3 + u(rng), -3 + u(rng), -3 + u(rng)});
    g.rotations.insert(g.rotations.end(), {1, 0.3f * u(rng), 0.3f * u(rng), 0.3f * u(rng)});
    g.opacity_logits.push_back(4 * u(rng) - 2);
    for (int k = 0; k < 48; ++k) g.sh.push_back(u(rng) - 0.5f);
  }
  return g;
}

// S3Gaussian's field at toy sizes (4 channels, planes 8 and 16, width 16).
inline FieldOptions TinyFieldOptions(int time_resolution) {
  FieldOptions f;
  f.mode = FieldMode::kS3Gaussian;
  f.config.channels = 4;
  f.config.base_resolution = 8;
  f.config.multires = {1, 2};
  f.config.time_resolution = time_resolution;
  f.config.width = 16;
  return f;
}

}  // namespace streetsim::train::fixtures
