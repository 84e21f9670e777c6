// A GaussianStore as Engine::UpdateSceneParams takes it (a view, no copy), at its own SH degree.
#pragma once

#include "render/engine.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim {

inline GaussianParamsView ParamsViewOf(const GaussianStore& s) {
  GaussianParamsView v;
  v.n = s.size();
  v.sh_degree = s.sh_degree;
  v.sh_stride = s.sh_coeffs();
  v.means = s.means.data();
  v.log_scales = s.log_scales.data();
  v.rotations = s.rotations.data();
  v.opacity_logits = s.opacity_logits.data();
  v.sh = s.sh.data();
  return v;
}

}  // namespace streetsim
