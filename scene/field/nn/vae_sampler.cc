#include "scene/field/nn/vae_sampler.h"

#include <cmath>

namespace streetsim::field::nn {

absl::StatusOr<VaeSpec> MakeVae(int latent) {
  if (latent <= 0) return absl::InvalidArgumentError(absl::StrCat("vae: latent must be positive, got ", latent));
  return VaeSpec{latent};
}

template <typename T>
absl::Status VaeSampleForward(const VaeSpec& s, const ConstRef<T>& mu_logvar, const ConstRef<T>& eps, Mat<T>* z,
                              VaeCache<T>* c) {
  const Eigen::Index rows = mu_logvar.rows();
  const int l = s.latent;
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("vae", "mu_logvar", rows, mu_logvar.cols(), -1, 2 * l));
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("vae", "eps", eps.rows(), eps.cols(), rows, l));
  c->eps = eps;
  c->sigma = (mu_logvar.rightCols(l).array() * T(0.5)).exp();
  z->resize(rows, l);
  z->array() = mu_logvar.leftCols(l).array() + c->sigma.array() * c->eps.array();
  return absl::OkStatus();
}

// dz/dmu = 1, dz/dlogvar = eps ⊙ sigma / 2.
template <typename T>
absl::Status VaeSampleBackward(const VaeSpec& s, const VaeCache<T>& c, const ConstRef<T>& dz, Mat<T>* d_mu_logvar) {
  const Eigen::Index rows = c.eps.rows();
  const int l = s.latent;
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("vae backward", "dz", dz.rows(), dz.cols(), rows, l));
  d_mu_logvar->resize(rows, 2 * l);
  d_mu_logvar->leftCols(l) = dz;
  d_mu_logvar->rightCols(l).array() = dz.array() * c.eps.array() * c.sigma.array() * T(0.5);
  return absl::OkStatus();
}

template <typename T>
absl::Status VaeMean(const VaeSpec& s, const ConstRef<T>& mu_logvar, Mat<T>* z) {
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("vae", "mu_logvar", mu_logvar.rows(), mu_logvar.cols(), -1, 2 * s.latent));
  *z = mu_logvar.leftCols(s.latent);
  return absl::OkStatus();
}

// dKL/dmu = mu, dKL/dlogvar = (sigma^2 - 1) / 2.
template <typename T>
absl::Status VaeKl(const VaeSpec& s, const ConstRef<T>& mu_logvar, T weight, T* kl, Mat<T>* d_mu_logvar) {
  const Eigen::Index rows = mu_logvar.rows();
  const int l = s.latent;
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("vae kl", "mu_logvar", rows, mu_logvar.cols(), -1, 2 * l));
  if (d_mu_logvar != nullptr) {
    STREETSIM_NN_RETURN_IF_ERROR(
        CheckShape("vae kl", "d_mu_logvar", d_mu_logvar->rows(), d_mu_logvar->cols(), rows, 2 * l));
  }
  T sum = 0;
  for (Eigen::Index r = 0; r < rows; ++r) {
    for (int i = 0; i < l; ++i) {
      const T mu = mu_logvar(r, i), lv = mu_logvar(r, l + i);
      const T var = std::exp(lv);
      sum += mu * mu + var - lv - T(1);
      if (d_mu_logvar != nullptr) {
        (*d_mu_logvar)(r, i) += weight * mu;
        (*d_mu_logvar)(r, l + i) += weight * T(0.5) * (var - T(1));
      }
    }
  }
  *kl = weight * T(0.5) * sum;
  return absl::OkStatus();
}

#define STREETSIM_NN_INSTANTIATE(T)                                                                              \
  template absl::Status VaeSampleForward<T>(const VaeSpec&, const ConstRef<T>&, const ConstRef<T>&, Mat<T>*,     \
                                            VaeCache<T>*);                                                       \
  template absl::Status VaeSampleBackward<T>(const VaeSpec&, const VaeCache<T>&, const ConstRef<T>&, Mat<T>*);   \
  template absl::Status VaeMean<T>(const VaeSpec&, const ConstRef<T>&, Mat<T>*);                                  \
  template absl::Status VaeKl<T>(const VaeSpec&, const ConstRef<T>&, T, T*, Mat<T>*);
STREETSIM_NN_INSTANTIATE(float)
STREETSIM_NN_INSTANTIATE(double)
#undef STREETSIM_NN_INSTANTIATE

}  // namespace streetsim::field::nn
