#include "scene/field/nn/activation.h"

#include <cmath>

namespace streetsim::field::nn {

const char* ActivationName(Activation a) {
  switch (a) {
    case Activation::kRelu: return "relu";
    case Activation::kGelu: return "gelu";
    case Activation::kSilu: return "silu";
  }
  return "?";
}

absl::StatusOr<Activation> ParseActivation(const std::string& name) {
  if (name == "relu") return Activation::kRelu;
  if (name == "gelu") return Activation::kGelu;
  if (name == "silu") return Activation::kSilu;
  return absl::InvalidArgumentError(absl::StrCat("unknown activation '", name, "' (relu, gelu, silu)"));
}

template <typename T>
T ActivationValue(Activation a, T x) {
  switch (a) {
    case Activation::kRelu:
      return x < T(0) ? T(0) : x;  // NaN compares false: stays NaN
    case Activation::kGelu:
      return T(0.5) * x * (T(1) + std::erf(x * T(M_SQRT1_2)));
    case Activation::kSilu:
      return x / (T(1) + std::exp(-x));
  }
  return x;
}

template <typename T>
T ActivationDerivative(Activation a, T x) {
  switch (a) {
    case Activation::kRelu:
      return x > T(0) ? T(1) : (x <= T(0) ? T(0) : x);  // NaN -> NaN
    case Activation::kGelu: {
      const T cdf = T(0.5) * (T(1) + std::erf(x * T(M_SQRT1_2)));
      const T pdf = std::exp(T(-0.5) * x * x) * T(0.5 * M_2_SQRTPI * M_SQRT1_2);  // 1/sqrt(2 pi)
      return cdf + x * pdf;
    }
    case Activation::kSilu: {
      const T sig = T(1) / (T(1) + std::exp(-x));
      return sig * (T(1) + x * (T(1) - sig));
    }
  }
  return T(1);
}

// ReLU and SiLU as Eigen array expressions (vectorised, Eigen's logistic for float within a few
// ulp); GELU per element through std::erf (Eigen's vectorised erf lives in an unsupported module).
template <typename T>
void ActivationForward(Activation a, const ConstRef<T>& x, Mat<T>* y, ActivationCache<T>* cache) {
  cache->x = x;
  y->resize(x.rows(), x.cols());
  const auto xa = cache->x.array();
  switch (a) {
    case Activation::kRelu:
      y->array() = (xa < T(0)).select(T(0), xa);  // NaN compares false: stays NaN
      return;
    case Activation::kSilu:
      y->array() = xa * xa.logistic();
      return;
    case Activation::kGelu:
      for (Eigen::Index i = 0; i < y->size(); ++i) y->data()[i] = ActivationValue(a, cache->x.data()[i]);
      return;
  }
}

template <typename T>
absl::Status ActivationBackward(Activation a, const ActivationCache<T>& cache, const ConstRef<T>& dy, Mat<T>* dx) {
  STREETSIM_NN_RETURN_IF_ERROR(
      CheckShape("activation backward", "dy", dy.rows(), dy.cols(), cache.x.rows(), cache.x.cols()));
  dx->resize(dy.rows(), dy.cols());
  const auto xa = cache.x.array();
  switch (a) {
    case Activation::kRelu:
      for (Eigen::Index r = 0; r < dy.rows(); ++r) {
        const T* x = cache.x.row(r).data();
        const T* g = dy.row(r).data();
        T* out = dx->row(r).data();
        for (Eigen::Index c = 0; c < dy.cols(); ++c) out[c] = x[c] > T(0) ? g[c] : (x[c] <= T(0) ? T(0) : x[c]);
      }
      break;
    case Activation::kSilu:
      dx->array() = dy.array() * xa.logistic() * (T(1) + xa * (T(1) - xa.logistic()));
      break;
    case Activation::kGelu:
      for (Eigen::Index r = 0; r < dy.rows(); ++r)
        for (Eigen::Index c = 0; c < dy.cols(); ++c)
          (*dx)(r, c) = dy(r, c) * ActivationDerivative(a, cache.x(r, c));
      break;
  }
  return absl::OkStatus();
}

#define STREETSIM_NN_INSTANTIATE(T)                                                                          \
  template T ActivationValue<T>(Activation, T);                                                             \
  template T ActivationDerivative<T>(Activation, T);                                                        \
  template void ActivationForward<T>(Activation, const ConstRef<T>&, Mat<T>*, ActivationCache<T>*);         \
  template absl::Status ActivationBackward<T>(Activation, const ActivationCache<T>&, const ConstRef<T>&, Mat<T>*);
STREETSIM_NN_INSTANTIATE(float)
STREETSIM_NN_INSTANTIATE(double)
#undef STREETSIM_NN_INSTANTIATE

}  // namespace streetsim::field::nn
