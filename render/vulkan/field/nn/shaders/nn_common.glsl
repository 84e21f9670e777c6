// Shared pieces of the extended field's Vulkan kernels (render/vulkan/field/nn/vk_nn_kernels.h).
// Tensors are row-major views: element (r, c) at off + r * stride + c; the host checks that every
// such index of a dispatch fits in 32 bits and lies inside its buffer.
#ifndef STREETSIM_NN_COMMON_GLSL_
#define STREETSIM_NN_COMMON_GLSL_

#include "field_common.glsl"

// Activations (scene/field/nn/activation.h): 0 relu, 1 gelu (erf form), 2 silu.
#define ACT_RELU 0u
#define ACT_GELU 1u
#define ACT_SILU 2u

// erfc(|x|) with a fractional error below 1.2e-7 everywhere (the Chebyshev fit of Press et al.,
// Numerical Recipes 6.2): GLSL has no erf, and GELU's 1 + erf(x) for x << 0 needs a relative,
// not an absolute, accuracy.
float ErfcAbs(float x) {
  const float z = abs(x);
  const float t = 1.0 / (1.0 + 0.5 * z);
  const float p =
      -1.26551223 +
      t * (1.00002368 +
           t * (0.37409196 +
                t * (0.09678418 +
                     t * (-0.18628806 +
                          t * (0.27886807 + t * (-1.13520398 + t * (1.48851587 + t * (-0.82215223 + t * 0.17087277))))))));
  return t * exp(-z * z + p);
}
// Phi(x) = (1 + erf(x / sqrt 2)) / 2.
float NormalCdf(float x) {
  const float e = ErfcAbs(x * 0.70710678118654752);
  return x >= 0.0 ? 1.0 - 0.5 * e : 0.5 * e;  // NaN: the second branch, NaN
}
float Sigmoid(float x) { return 1.0 / (1.0 + exp(-x)); }
// tanh without the overflow of (e^2x - 1) / (e^2x + 1) at large |x|; NaN stays NaN.
float SafeTanh(float x) {
  const float t = exp(-2.0 * abs(x));
  const float r = (1.0 - t) / (1.0 + t);
  return x < 0.0 ? -r : r;
}

float ActValue(uint a, float x) {
  if (a == ACT_RELU) return x < 0.0 ? 0.0 : x;  // NaN compares false: stays NaN
  if (a == ACT_GELU) return x * NormalCdf(x);
  return x * Sigmoid(x);
}
float ActDerivative(uint a, float x) {
  if (a == ACT_RELU) return x > 0.0 ? 1.0 : (x <= 0.0 ? 0.0 : x);  // NaN -> NaN
  if (a == ACT_GELU) return NormalCdf(x) + x * exp(-0.5 * x * x) * 0.3989422804014327;  // 1/sqrt(2 pi)
  const float s = Sigmoid(x);
  return s * (1.0 + x * (1.0 - s));
}

#endif  // STREETSIM_NN_COMMON_GLSL_
