// Element-wise activations. method.md section 2 item 1 says only "Linear + normalisation +
// activation"; S3Gaussian's MLP (whose heads stay unchanged) uses ReLU, so ReLU is the default of
// the extended field. GELU (exact, erf form, PyTorch's nn.GELU()) and SiLU are there for the
// ablation and because they are smooth (no kinks inside a finite-difference step). NaN in -> NaN out.
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "scene/field/nn/nn_types.h"

namespace streetsim::field::nn {

enum class Activation { kRelu, kGelu, kSilu };

const char* ActivationName(Activation a);
absl::StatusOr<Activation> ParseActivation(const std::string& name);  // "relu", "gelu", "silu"

template <typename T>
struct ActivationCache {
  Mat<T> x;  // pre-activation
};

// y = act(x), any shape.
template <typename T>
void ActivationForward(Activation a, const ConstRef<T>& x, Mat<T>* y, ActivationCache<T>* cache);
template <typename T>
absl::Status ActivationBackward(Activation a, const ActivationCache<T>& cache, const ConstRef<T>& dy, Mat<T>* dx);

// Scalar forms (shared with the composite ops and the tests).
template <typename T>
T ActivationValue(Activation a, T x);
template <typename T>
T ActivationDerivative(Activation a, T x);

}  // namespace streetsim::field::nn
