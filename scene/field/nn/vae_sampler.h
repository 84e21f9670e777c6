// Sparse variational encoder's sampling step and KL term (method.md section 2 item 2; spec 14):
// the input row is (mu, log sigma^2) in R^{L+L} (from the preceding Linear branches);
//   training:  z = mu + sigma ⊙ eps, sigma = exp(log sigma^2 / 2), eps ~ N(0, I) given by the caller
//   inference: z = mu (deterministic serving)
//   KL(N(mu, sigma^2) || N(0, I)) = 1/2 sum_i (mu_i^2 + sigma_i^2 - log sigma_i^2 - 1) per row.
// log sigma^2 is not clamped: a trainer that lets it grow past ~88 overflows sigma in float.
#pragma once

#include "absl/status/statusor.h"
#include "scene/field/nn/nn_types.h"

namespace streetsim::field::nn {

struct VaeSpec {
  int latent = 0;  // L
};

absl::StatusOr<VaeSpec> MakeVae(int latent);

template <typename T>
struct VaeCache {
  Mat<T> eps, sigma;  // [B, L]
};

// mu_logvar [B, 2L] (mu in the first L columns), eps [B, L] -> z [B, L].
template <typename T>
absl::Status VaeSampleForward(const VaeSpec& s, const ConstRef<T>& mu_logvar, const ConstRef<T>& eps, Mat<T>* z,
                              VaeCache<T>* cache);
// dz [B, L] -> d_mu_logvar [B, 2L] (written).
template <typename T>
absl::Status VaeSampleBackward(const VaeSpec& s, const VaeCache<T>& cache, const ConstRef<T>& dz,
                               Mat<T>* d_mu_logvar);
// Inference: z = mu. (Its gradient is dz in the mu columns, zero in the others.)
template <typename T>
absl::Status VaeMean(const VaeSpec& s, const ConstRef<T>& mu_logvar, Mat<T>* z);

// weight * sum over rows of KL (the caller picks weight = beta / number of Gaussians for a mean);
// its gradient is ADDED to *d_mu_logvar (non-null: must be [B, 2L]).
template <typename T>
absl::Status VaeKl(const VaeSpec& s, const ConstRef<T>& mu_logvar, T weight, T* kl, Mat<T>* d_mu_logvar);

}  // namespace streetsim::field::nn
