#include "scene/field/field_adam.h"

#include <algorithm>
#include <cmath>

#include "scene/optim/adam_kernel.h"

namespace streetsim::field {

double FieldExpLr(double lr_init, double lr_final, int64_t step, int max_steps) {
  const double tau = std::clamp(static_cast<double>(step) / std::max(1, max_steps), 0.0, 1.0);
  return std::exp((1 - tau) * std::log(lr_init) + tau * std::log(lr_final));
}

FieldLrs FieldLearningRates(const FieldHyper& h, int64_t iteration, double extent) {
  const double e = (h.scale_lr_by_extent ? extent : 1.0) * h.lr_scale;
  FieldLrs lrs;
  lrs.grid = FieldExpLr(h.grid_lr_init * e, h.grid_lr_final * e, iteration, h.lr_decay_steps);
  lrs.deformation = FieldExpLr(h.deformation_lr_init * e, h.deformation_lr_final * e, iteration, h.lr_decay_steps);
  return lrs;
}

using optim::AdamRange;
constexpr float kBeta1 = optim::kAdamBeta1, kBeta2 = optim::kAdamBeta2;

FieldAdamScales FieldAdamStepScales(const FieldLrs& lrs, int64_t step) {
  const double bc1 = 1 - std::pow(double(kBeta1), double(step));
  const double bc2 = 1 - std::pow(double(kBeta2), double(step));
  return FieldAdamScales{static_cast<float>(lrs.grid / bc1), static_cast<float>(lrs.deformation / bc1),
                         static_cast<float>(1 / std::sqrt(bc2))};
}

void FieldAdamStep(const FieldLayout& L, float* params, const float* grads, FieldAdamState* s, const FieldLrs& lrs,
                   ThreadPool& pool) {
  if (s->m.size() != L.total) s->Init(L.total);
  s->step += 1;
  const FieldAdamScales scales = FieldAdamStepScales(lrs, s->step);
  const float isb2 = scales.inv_sqrt_bc2, grid_step = scales.grid_step, mlp_step = scales.mlp_step;
  constexpr int64_t kChunk = 1 << 16;
  pool.ParallelFor(static_cast<int64_t>(L.total), kChunk, [&](int64_t b, int64_t e, int) {
    // Split the chunk at the group boundary.
    const int64_t mid = std::clamp<int64_t>(static_cast<int64_t>(L.grid_size), b, e);
    if (mid > b) AdamRange(params + b, grads + b, &s->m[b], &s->v[b], mid - b, grid_step, isb2);
    if (e > mid) AdamRange(params + mid, grads + mid, &s->m[mid], &s->v[mid], e - mid, mlp_step, isb2);
  });
}

}  // namespace streetsim::field
