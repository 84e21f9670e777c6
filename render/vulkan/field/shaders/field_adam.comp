// One Adam step over `count` parameters of one buffer (the cpu's optim::AdamRange,
// scene/optim/adam_kernel.h: PyTorch's Adam, betas (0.9, 0.999), eps 1e-15, the bias corrections
// folded in by the host: step_size = lr / (1 - beta1^t), inv_sqrt_bc2 = 1 / sqrt(1 - beta2^t)).
// The constants come from the host as the cpu rounds them (1 - beta in float: a compiler may fold
// 1.0 - 0.999 in higher precision, 1.3e-5 away).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "field_common.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 0) buffer Params { float p[]; };
layout(std430, binding = 1) readonly buffer Grads { float g[]; };
layout(std430, binding = 2) buffer M { float m[]; };
layout(std430, binding = 3) buffer V { float v[]; };
layout(push_constant, std430) uniform Push {
  uint count;
  float step_size;
  float inv_sqrt_bc2;
  float beta1, one_minus_beta1, beta2, one_minus_beta2, eps;
} pc;

void main() {
  const uint i = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  if (i >= pc.count) return;
  const float gi = g[i];
  const float mi = pc.beta1 * m[i] + pc.one_minus_beta1 * gi;
  const float vi = pc.beta2 * v[i] + pc.one_minus_beta2 * gi * gi;
  m[i] = mi;
  v[i] = vi;
  p[i] -= pc.step_size * mi / (sqrt(vi) * pc.inv_sqrt_bc2 + pc.eps);
}
