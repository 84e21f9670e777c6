// A degree-3 GaussianStore (16 SH coefficients per channel, the trainer's layout) as the engines'
// two ways in take it at a lower active degree: a GaussianParamsView for UpdateSceneParams, and a
// store truncated to that degree for Upload. Tests compare the two renders.
#pragma once

#include <cstddef>

#include "render/engine.h"
#include "render/params_view.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::testing {

// A store as UpdateSceneParams takes it, at its own degree.
inline GaussianParamsView StoreParamsView(const GaussianStore& s) { return ParamsViewOf(s); }

// `full` (sh_degree 3) as UpdateSceneParams takes it, uploading `degree`.
inline GaussianParamsView FullDegreeParamsView(const GaussianStore& full, int degree) {
  GaussianParamsView v = StoreParamsView(full);
  v.sh_degree = degree;
  return v;
}

// `full` (sh_degree 3) with its SH cut to the first coefficients of `degree`.
inline GaussianStore TruncatedToDegree(const GaussianStore& full, int degree) {
  GaussianStore store = full;
  store.sh_degree = degree;
  const int K = store.sh_coeffs();
  store.sh.resize(full.size() * K * 3);
  for (size_t i = 0; i < full.size(); ++i)
    for (int kc = 0; kc < K * 3; ++kc) store.sh[i * K * 3 + kc] = full.sh[i * 48 + kc];
  return store;
}

}  // namespace streetsim::testing
