// Spatio-temporal multi-head attention (method.md section 2 item 4): the row's spatial latent is
// the query, its T temporal tokens are keys and values.
//
//   Q = q Wq + bq [M], K_j = x_j Wk, V_j = x_j Wv + bv [M] (M = heads * head_dim; no key bias:
//   the softmax cancels it)
//   a_hj = softmax_j(Q_h . K_jh / sqrt(head_dim)),   O_h = sum_j a_hj V_jh
//   u = O Wo + bo,   y = LayerNorm(q + u)   (residual + normalisation; residual_norm = false: y = u)
//
// The residual needs query_dim == model_dim (the spatial latent is projected to M before).
#pragma once

#include <cstdint>
#include <random>
#include <string>

#include "absl/status/statusor.h"
#include "scene/field/nn/layer_norm.h"
#include "scene/field/nn/linear.h"

namespace streetsim::field::nn {

struct AttentionSpec {
  int query_dim = 0, token_dim = 0, tokens = 0, heads = 0, model_dim = 0;
  bool residual_norm = true;
  LinearSpec q, k, v, o;
  LayerNormSpec norm;  // only with residual_norm
  int head_dim() const { return model_dim / heads; }
  int64_t Macs() const;  // per row, forward
};

absl::StatusOr<AttentionSpec> MakeAttention(NnLayout* layout, const std::string& name, int query_dim, int token_dim,
                                            int tokens, int heads, int model_dim, bool residual_norm = true);
template <typename T>
void InitAttention(const AttentionSpec& s, std::mt19937_64& rng, T* params);

template <typename T>
struct AttentionCache {
  Mat<T> query, x;     // inputs: [B, Dq], tokens as [B*T, Dkv]
  Mat<T> Q, K, V;      // [B, M], [B*T, M], [B*T, M]
  Mat<T> A;            // softmax weights [B, H*T]
  Mat<T> O, u;         // [B, M]; u holds q + u when residual_norm (the LayerNorm's input)
  LayerNormCache<T> norm;
  // Backward scratch.
  Mat<T> dz, dO, dQ, dK, dV, dx;
};

// query [B, Dq], tokens [B, T*Dkv] -> y [B, M].
template <typename T>
absl::Status AttentionForward(const AttentionSpec& s, const T* params, const ConstRef<T>& query,
                              const ConstRef<T>& tokens, Mat<T>* y, AttentionCache<T>* cache);
// dy [B, M] -> d_query [B, Dq], d_tokens [B, T*Dkv] (either may be null); parameter gradients added.
template <typename T>
absl::Status AttentionBackward(const AttentionSpec& s, const T* params, AttentionCache<T>& cache,
                               const ConstRef<T>& dy, Mat<T>* d_query, Mat<T>* d_tokens, T* d_params);

}  // namespace streetsim::field::nn
