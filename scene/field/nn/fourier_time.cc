#include "scene/field/nn/fourier_time.h"

#include <cmath>

namespace streetsim::field::nn {

absl::StatusOr<FourierTimeSpec> MakeFourierTime(int frequencies, int tokens, int feature_dim) {
  // 2^k pi for k >= 24 is beyond float resolution of t: useless and not representable.
  if (frequencies < 0 || frequencies > 24 || tokens <= 0 || feature_dim < 0 || frequencies + feature_dim == 0) {
    return absl::InvalidArgumentError(absl::StrCat("fourier_time: need 0 <= frequencies <= 24, tokens > 0, "
                                                   "feature_dim >= 0 and a non-empty token, got ",
                                                   frequencies, ", ", tokens, ", ", feature_dim));
  }
  FourierTimeSpec s;
  s.frequencies = frequencies;
  s.tokens = tokens;
  s.feature_dim = feature_dim;
  return s;
}

template <typename T>
absl::Status FourierTimeForward(const FourierTimeSpec& s, const ConstRef<T>& times, const ConstRef<T>& features,
                                Mat<T>* tokens, FourierTimeCache<T>* cache) {
  const Eigen::Index rows = times.rows();
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("fourier_time", "times", rows, times.cols(), -1, s.tokens));
  STREETSIM_NN_RETURN_IF_ERROR(
      CheckShape("fourier_time", "features", features.rows(), features.cols(), rows, s.tokens * s.feature_dim));
  const int m = s.frequencies, f = s.feature_dim, d = s.token_dim();
  // Arguments 2^k pi t_j in the sin block, then Eigen's vectorised sin / cos (per-element std::sin
  // and std::cos were most of this op's time).
  cache->sin.resize(rows, s.tokens * m);
  for (int j = 0; j < s.tokens; ++j)
    for (int k = 0; k < m; ++k) cache->sin.col(j * m + k) = times.col(j) * static_cast<T>(std::ldexp(M_PI, k));
  cache->cos = cache->sin.array().cos();
  cache->sin = cache->sin.array().sin();
  tokens->resize(rows, s.tokens * d);
  for (int j = 0; j < s.tokens; ++j) {
    tokens->middleCols(j * d, m) = cache->sin.middleCols(j * m, m);
    tokens->middleCols(j * d + m, m) = cache->cos.middleCols(j * m, m);
    tokens->middleCols(j * d + 2 * m, f) = features.middleCols(j * f, f);
  }
  return absl::OkStatus();
}

template <typename T>
absl::Status FourierTimeBackward(const FourierTimeSpec& s, const FourierTimeCache<T>& cache,
                                 const ConstRef<T>& d_tokens, Mat<T>* d_times, Mat<T>* d_features) {
  const Eigen::Index rows = cache.sin.rows();
  const int m = s.frequencies, f = s.feature_dim, d = s.token_dim();
  STREETSIM_NN_RETURN_IF_ERROR(
      CheckShape("fourier_time backward", "d_tokens", d_tokens.rows(), d_tokens.cols(), rows, s.tokens * d));
  if (d_times != nullptr) {
    // d/dt sin(w t) = w cos(w t), d/dt cos(w t) = -w sin(w t).
    RowVec<T> w(m);
    for (int k = 0; k < m; ++k) w(k) = static_cast<T>(std::ldexp(M_PI, k));
    d_times->resize(rows, s.tokens);
    for (int j = 0; j < s.tokens; ++j) {
      d_times->col(j) = ((cache.cos.middleCols(j * m, m).array() * d_tokens.middleCols(j * d, m).array() -
                          cache.sin.middleCols(j * m, m).array() * d_tokens.middleCols(j * d + m, m).array())
                             .matrix() *
                         w.transpose());
    }
  }
  if (d_features != nullptr) {
    d_features->resize(rows, s.tokens * f);
    for (int j = 0; j < s.tokens; ++j) d_features->middleCols(j * f, f) = d_tokens.middleCols(j * d + 2 * m, f);
  }
  return absl::OkStatus();
}

#define STREETSIM_NN_INSTANTIATE(T)                                                                             \
  template absl::Status FourierTimeForward<T>(const FourierTimeSpec&, const ConstRef<T>&, const ConstRef<T>&,   \
                                              Mat<T>*, FourierTimeCache<T>*);                                  \
  template absl::Status FourierTimeBackward<T>(const FourierTimeSpec&, const FourierTimeCache<T>&,             \
                                               const ConstRef<T>&, Mat<T>*, Mat<T>*);
STREETSIM_NN_INSTANTIATE(float)
STREETSIM_NN_INSTANTIATE(double)
#undef STREETSIM_NN_INSTANTIATE

}  // namespace streetsim::field::nn
