// Temporal tokens (scene/field/nn/fourier_time.h), one invocation per output element:
//   forward:  token j of row b = [sin(2^k pi t_j) k < m, cos(2^k pi t_j) k < m, features_j]
//   backward: d_features[b][j F + f] = d_tokens[b][j D + 2m + f]   (D = 2m + F)
// The phase 2^k pi t = 2 pi (2^(k-1) t) is reduced in turns before sin / cos: 2^(k-1) t is exact
// in float and GLSL's sin / cos are only specified on [-pi, pi].
#version 460
#extension GL_GOOGLE_include_directive : require
#include "nn_common.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer Times { float times[]; };  // [rows x T]
layout(std430, binding = 1) readonly buffer In { float src[]; };       // forward: features; backward: d_tokens
layout(std430, binding = 2) writeonly buffer Out { float dst[]; };     // forward: tokens; backward: d_features
layout(push_constant, std430) uniform Push {
  uint rows, tokens, m, F, backward;
  uint t_off, t_stride, s_off, s_stride, o_off, o_stride;
} pc;

void main() {
  const uint i = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  const uint D = 2u * pc.m + pc.F;
  const uint cols = pc.tokens * (pc.backward != 0u ? pc.F : D);
  if (i >= pc.rows * cols) return;  // the host keeps rows * cols within 32 bits
  const uint b = i / cols, col = i % cols;
  const uint o = pc.o_off + b * pc.o_stride + col;
  if (pc.backward != 0u) {
    const uint j = col / pc.F, f = col % pc.F;
    dst[o] = src[pc.s_off + b * pc.s_stride + j * D + 2u * pc.m + f];
    return;
  }
  const uint j = col / D, c = col % D;
  if (c >= 2u * pc.m) {
    dst[o] = src[pc.s_off + b * pc.s_stride + j * pc.F + (c - 2u * pc.m)];
    return;
  }
  const uint k = c < pc.m ? c : c - pc.m;
  const float turns = ldexp(times[pc.t_off + b * pc.t_stride + j], int(k) - 1);
  const float phase = 6.283185307179586 * (turns - round(turns));  // in [-pi, pi]; NaN stays NaN
  dst[o] = c < pc.m ? sin(phase) : cos(phase);
}
