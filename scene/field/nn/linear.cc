#include "scene/field/nn/linear.h"

#include <cmath>

namespace streetsim::field::nn {

absl::StatusOr<LinearSpec> MakeLinear(NnLayout* layout, const std::string& name, int in, int out, bool bias) {
  if (in <= 0 || out <= 0) {
    return absl::InvalidArgumentError(absl::StrCat("linear ", name, ": sizes must be positive, got ", in, " -> ", out));
  }
  LinearSpec s;
  s.in = in;
  s.out = out;
  s.bias = bias;
  s.w_offset = layout->Add(name + ".weight", static_cast<size_t>(in) * out);
  if (bias) s.b_offset = layout->Add(name + ".bias", out);
  return s;
}

template <typename T>
void InitLinear(const LinearSpec& s, std::mt19937_64& rng, T* params) {
  const double a = std::sqrt(6.0 / (s.in + s.out));
  FillUniform(params, s.w_offset, static_cast<size_t>(s.in) * s.out, -a, a, rng);
  if (s.bias) {
    const double b = 1.0 / std::sqrt(static_cast<double>(s.in));
    FillUniform(params, s.b_offset, s.out, -b, b, rng);
  }
}

template <typename T>
absl::Status LinearApply(const LinearSpec& s, const T* params, const ConstRef<T>& x, Mat<T>* y) {
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("linear", "x", x.rows(), x.cols(), -1, s.in));
  const ConstMatMap<T> w(params + s.w_offset, s.out, s.in);
  y->resize(x.rows(), s.out);
  y->noalias() = x * w.transpose();
  if (s.bias) y->rowwise() += Eigen::Map<const RowVec<T>>(params + s.b_offset, s.out);
  return absl::OkStatus();
}

template <typename T>
absl::Status LinearGrad(const LinearSpec& s, const T* params, const ConstRef<T>& x, const ConstRef<T>& dy,
                        Mat<T>* dx, bool accumulate, T* d_params) {
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("linear backward", "x", x.rows(), x.cols(), -1, s.in));
  STREETSIM_NN_RETURN_IF_ERROR(CheckShape("linear backward", "dy", dy.rows(), dy.cols(), x.rows(), s.out));
  MatMap<T>(d_params + s.w_offset, s.out, s.in).noalias() += dy.transpose() * x;
  if (s.bias) AddColumnSums(dy, d_params + s.b_offset);
  if (dx != nullptr) {
    const ConstMatMap<T> w(params + s.w_offset, s.out, s.in);
    if (accumulate) {
      STREETSIM_NN_RETURN_IF_ERROR(CheckShape("linear backward", "dx", dx->rows(), dx->cols(), x.rows(), s.in));
      dx->noalias() += dy * w;
    } else {
      dx->resize(x.rows(), s.in);
      dx->noalias() = dy * w;
    }
  }
  return absl::OkStatus();
}

template <typename T>
absl::Status LinearForward(const LinearSpec& s, const T* params, const ConstRef<T>& x, Mat<T>* y,
                           LinearCache<T>* cache) {
  STREETSIM_NN_RETURN_IF_ERROR(LinearApply(s, params, x, y));
  cache->x = x;
  return absl::OkStatus();
}

template <typename T>
absl::Status LinearBackward(const LinearSpec& s, const T* params, const LinearCache<T>& cache, const ConstRef<T>& dy,
                            Mat<T>* dx, T* d_params) {
  return LinearGrad<T>(s, params, cache.x, dy, dx, /*accumulate=*/false, d_params);
}

#define STREETSIM_NN_INSTANTIATE(T)                                                                             \
  template void InitLinear<T>(const LinearSpec&, std::mt19937_64&, T*);                                        \
  template absl::Status LinearForward<T>(const LinearSpec&, const T*, const ConstRef<T>&, Mat<T>*,              \
                                         LinearCache<T>*);                                                      \
  template absl::Status LinearBackward<T>(const LinearSpec&, const T*, const LinearCache<T>&, const ConstRef<T>&, \
                                          Mat<T>*, T*);                                                         \
  template absl::Status LinearApply<T>(const LinearSpec&, const T*, const ConstRef<T>&, Mat<T>*);               \
  template absl::Status LinearGrad<T>(const LinearSpec&, const T*, const ConstRef<T>&, const ConstRef<T>&,      \
                                      Mat<T>*, bool, T*);
STREETSIM_NN_INSTANTIATE(float)
STREETSIM_NN_INSTANTIATE(double)
#undef STREETSIM_NN_INSTANTIATE

}  // namespace streetsim::field::nn
