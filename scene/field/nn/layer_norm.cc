#include "scene/field/nn/layer_norm.h"

#include <cmath>

namespace streetsim::field::nn {

absl::StatusOr<LayerNormSpec> MakeLayerNorm(NnLayout* layout, const std::string& name, int dim, double eps) {
  if (dim <= 0 || !(eps > 0)) {
    return absl::InvalidArgumentError(absl::StrCat("layer_norm ", name, ": dim must be positive and eps > 0, got ",
                                                   dim, ", ", eps));
  }
  LayerNormSpec s;
  s.dim = dim;
  s.eps = eps;
  s.gain_offset = layout->Add(name + ".gain", dim);
  s.bias_offset = layout->Add(name + ".bias", dim);
  return s;
}

template <typename T>
void InitLayerNorm(const LayerNormSpec& s, T* params) {
  FillConstant(params, s.gain_offset, s.dim, 1.0);
  FillConstant(params, s.bias_offset, s.dim, 0.0);
}

template <typename T>
absl::Status LayerNormForward(const LayerNormSpec& s, const T* params, const ConstRef<T>& x, Mat<T>* y,
                              LayerNormCache<T>* cache) {
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("layer_norm", "x", x.rows(), x.cols(), -1, s.dim));
  const Eigen::Index rows = x.rows();
  const Eigen::Map<const RowVec<T>> gain(params + s.gain_offset, s.dim), bias(params + s.bias_offset, s.dim);
  cache->xhat.resize(rows, s.dim);
  cache->rstd.resize(rows);
  y->resize(rows, s.dim);
  const T inv_dim = T(1) / T(s.dim);
  for (Eigen::Index r = 0; r < rows; ++r) {
    const T mean = x.row(r).sum() * inv_dim;
    const T var = (x.row(r).array() - mean).square().sum() * inv_dim;
    const T rstd = T(1) / std::sqrt(var + static_cast<T>(s.eps));
    cache->rstd(r) = rstd;
    cache->xhat.row(r) = (x.row(r).array() - mean) * rstd;
    y->row(r) = cache->xhat.row(r).cwiseProduct(gain) + bias;
  }
  return absl::OkStatus();
}

// dx = rstd (g⊙dy - mean(g⊙dy) - xhat mean(g⊙dy ⊙ xhat)).
template <typename T>
absl::Status LayerNormBackward(const LayerNormSpec& s, const T* params, const LayerNormCache<T>& cache,
                               const ConstRef<T>& dy, Mat<T>* dx, T* d_params) {
  const Eigen::Index rows = cache.xhat.rows();
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("layer_norm backward", "dy", dy.rows(), dy.cols(), rows, s.dim));
  AddColumnSums(dy.cwiseProduct(cache.xhat), d_params + s.gain_offset);
  AddColumnSums(dy, d_params + s.bias_offset);
  if (dx == nullptr) return absl::OkStatus();
  const Eigen::Map<const RowVec<T>> gain(params + s.gain_offset, s.dim);
  dx->resize(rows, s.dim);
  const T inv_dim = T(1) / T(s.dim);
  RowVec<T> g(s.dim);
  for (Eigen::Index r = 0; r < rows; ++r) {
    g = dy.row(r).cwiseProduct(gain);
    const T mean_g = g.sum() * inv_dim;
    const T mean_gx = g.dot(cache.xhat.row(r)) * inv_dim;
    dx->row(r) = (g.array() - mean_g - cache.xhat.row(r).array() * mean_gx) * cache.rstd(r);
  }
  return absl::OkStatus();
}

#define STREETSIM_NN_INSTANTIATE(T)                                                                          \
  template void InitLayerNorm<T>(const LayerNormSpec&, T*);                                                 \
  template absl::Status LayerNormForward<T>(const LayerNormSpec&, const T*, const ConstRef<T>&, Mat<T>*,    \
                                            LayerNormCache<T>*);                                            \
  template absl::Status LayerNormBackward<T>(const LayerNormSpec&, const T*, const LayerNormCache<T>&,      \
                                             const ConstRef<T>&, Mat<T>*, T*);
STREETSIM_NN_INSTANTIATE(float)
STREETSIM_NN_INSTANTIATE(double)
#undef STREETSIM_NN_INSTANTIATE

}  // namespace streetsim::field::nn
