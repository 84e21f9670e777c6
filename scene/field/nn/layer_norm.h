// Layer normalisation over each row's last `dim` values with a learned gain and bias:
// y = g ⊙ (x - mean) / sqrt(var + eps) + b (biased variance, PyTorch's nn.LayerNorm).
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "scene/field/nn/nn_layout.h"
#include "scene/field/nn/nn_types.h"

namespace streetsim::field::nn {

struct LayerNormSpec {
  int dim = 0;
  double eps = 1e-5;
  size_t gain_offset = 0, bias_offset = 0;
};

absl::StatusOr<LayerNormSpec> MakeLayerNorm(NnLayout* layout, const std::string& name, int dim, double eps = 1e-5);
// Gain 1, bias 0.
template <typename T>
void InitLayerNorm(const LayerNormSpec& s, T* params);

template <typename T>
struct LayerNormCache {
  Mat<T> xhat;     // (x - mean) * rstd
  ColVec<T> rstd;  // 1 / sqrt(var + eps) per row
};

// x [R, dim] -> y [R, dim] (R rows: Gaussians, or Gaussians x tokens).
template <typename T>
absl::Status LayerNormForward(const LayerNormSpec& s, const T* params, const ConstRef<T>& x, Mat<T>* y,
                              LayerNormCache<T>* cache);
template <typename T>
absl::Status LayerNormBackward(const LayerNormSpec& s, const T* params, const LayerNormCache<T>& cache,
                               const ConstRef<T>& dy, Mat<T>* dx, T* d_params);

}  // namespace streetsim::field::nn
