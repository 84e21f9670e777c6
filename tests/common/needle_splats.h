#pragma once
// Needle splats for the projection tests (docs/rendering.md "Needle splats"): Gaussian i's axis
// i % 3 gets a log-scale uniform in long_log_scale_m +- long_half_range, the other two
// -4 +- 2 (millimetres). The long axes reach kilometres, as an unbounded field Δlog-scale made them
// on KITTI; their 2D covariance is nearly rank one.
#include <cstddef>
#include <random>

#include "scene/gaussians/gaussian_store.h"

namespace streetsim::testing {

inline void MakeNeedles(float long_log_scale_m, float long_half_range, std::mt19937& rng, GaussianStore* store) {
  std::uniform_real_distribution<float> u(-1, 1);
  for (size_t i = 0; i < store->size(); ++i) {
    for (int k = 0; k < 3; ++k) {
      store->log_scales[i * 3 + k] = k == static_cast<int>(i % 3) ? long_log_scale_m + long_half_range * u(rng)
                                                                   : -4.0f + 2.0f * u(rng);
    }
  }
}

}  // namespace streetsim::testing
