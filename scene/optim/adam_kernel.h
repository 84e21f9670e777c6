// The Adam update shared by every optimiser in streetsim (the Gaussians' groups in
// scene/train/train_state.cc, the deformation field's in scene/field/field_adam.cc): PyTorch's
// Adam with betas (0.9, 0.999) and eps 1e-15 (../shared/docs/s3gaussian-spec.md section 6).
// Header-only so that each caller's loop vectorises under its own compile flags.
#pragma once

#include <cmath>
#include <cstddef>

namespace streetsim::optim {

inline constexpr float kAdamBeta1 = 0.9f, kAdamBeta2 = 0.999f, kAdamEps = 1e-15f;

// m, v updated in place; p -= step_size * m / (sqrt(v) * inv_sqrt_bc2 + eps), where the caller
// folds the bias corrections in: step_size = lr / (1 - beta1^t), inv_sqrt_bc2 = 1 / sqrt(1 - beta2^t).
inline void AdamRange(float* __restrict p, const float* __restrict g, float* __restrict m, float* __restrict v,
                      size_t n, float step_size, float inv_sqrt_bc2) {
  for (size_t i = 0; i < n; ++i) {
    const float gi = g[i];
    const float mi = kAdamBeta1 * m[i] + (1 - kAdamBeta1) * gi;
    const float vi = kAdamBeta2 * v[i] + (1 - kAdamBeta2) * gi * gi;
    m[i] = mi;
    v[i] = vi;
    p[i] -= step_size * mi / (std::sqrt(vi) * inv_sqrt_bc2 + kAdamEps);
  }
}

}  // namespace streetsim::optim
