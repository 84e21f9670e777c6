// Multi-head attention between the projections (scene/field/nn/attention.cc), one invocation per
// (row b, head h), head_dim dh, T tokens, scale s = 1 / sqrt(dh); K, V rows b*T + j:
//   forward:  a_j = softmax_j(s Q_h . K_jh) -> A[b][h T + j],  O_h = sum_j a_j V_jh
//   backward: g_j = dO_h . V_jh, mu = sum_j a_j g_j, ds_j = a_j (g_j - mu) s,
//             dV_jh = a_j dO_h, dK_jh = ds_j Q_h, dQ_h = sum_j ds_j K_jh
// Every output element belongs to one invocation: no atomics, sums in token order as the cpu.
// Loop iterations per invocation: about 3 T (dh + 1) (the host keeps it far below 65 535).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "nn_common.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer Qb { float q[]; };
layout(std430, binding = 1) readonly buffer Kb { float k[]; };
layout(std430, binding = 2) readonly buffer Vb { float v[]; };
layout(std430, binding = 3) buffer Ab { float a[]; };        // forward: written; backward: read
layout(std430, binding = 4) buffer Ob { float o[]; };        // forward: O; backward: dO (read)
layout(std430, binding = 5) buffer DQ { float dq[]; };  // summed over tokens in place, in token order
layout(std430, binding = 6) writeonly buffer DK { float dk[]; };
layout(std430, binding = 7) writeonly buffer DV { float dv[]; };
layout(push_constant, std430) uniform Push {
  uint rows, T, H, dh, backward;
  float scale;
  uint q_off, q_stride, k_off, k_stride, v_off, v_stride, a_off, a_stride, o_off, o_stride;
  uint dq_off, dq_stride, dk_off, dk_stride, dv_off, dv_stride;
} pc;

void main() {
  const uint i = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  if (i >= pc.rows * pc.H) return;  // the host keeps rows * H within 32 bits
  const uint b = i / pc.H, h = i % pc.H;
  const uint qb = pc.q_off + b * pc.q_stride + h * pc.dh;
  const uint ab = pc.a_off + b * pc.a_stride + h * pc.T;
  const uint ob = pc.o_off + b * pc.o_stride + h * pc.dh;
  const uint kr = b * pc.T;  // first token row
  if (pc.backward == 0u) {
    float mx = -1.0 / 0.0;
    for (uint j = 0u; j < pc.T; ++j) {
      const uint kb = pc.k_off + (kr + j) * pc.k_stride + h * pc.dh;
      float dot = 0.0;
      for (uint d = 0u; d < pc.dh; ++d) dot += q[qb + d] * k[kb + d];
      const float sc = dot * pc.scale;
      a[ab + j] = sc;
      mx = max(mx, sc);
    }
    float sum = 0.0;
    for (uint j = 0u; j < pc.T; ++j) {
      const float e = exp(a[ab + j] - mx);
      a[ab + j] = e;
      sum += e;
    }
    const float inv = 1.0 / sum;
    for (uint j = 0u; j < pc.T; ++j) a[ab + j] *= inv;
    for (uint d = 0u; d < pc.dh; ++d) {
      float acc = 0.0;
      for (uint j = 0u; j < pc.T; ++j) acc += a[ab + j] * v[pc.v_off + (kr + j) * pc.v_stride + h * pc.dh + d];
      o[ob + d] = acc;
    }
    return;
  }
  float mu = 0.0;
  for (uint j = 0u; j < pc.T; ++j) {
    const uint vb = pc.v_off + (kr + j) * pc.v_stride + h * pc.dh;
    float g = 0.0;
    for (uint d = 0u; d < pc.dh; ++d) g += o[ob + d] * v[vb + d];
    mu += a[ab + j] * g;
  }
  const uint dqb = pc.dq_off + b * pc.dq_stride + h * pc.dh;
  for (uint d = 0u; d < pc.dh; ++d) dq[dqb + d] = 0.0;
  for (uint j = 0u; j < pc.T; ++j) {
    const uint vb = pc.v_off + (kr + j) * pc.v_stride + h * pc.dh;
    const uint kb = pc.k_off + (kr + j) * pc.k_stride + h * pc.dh;
    const uint dkb = pc.dk_off + (kr + j) * pc.dk_stride + h * pc.dh;
    const uint dvb = pc.dv_off + (kr + j) * pc.dv_stride + h * pc.dh;
    const float aj = a[ab + j];
    float g = 0.0;
    for (uint d = 0u; d < pc.dh; ++d) g += o[ob + d] * v[vb + d];
    const float ds = aj * (g - mu) * pc.scale;
    for (uint d = 0u; d < pc.dh; ++d) {
      dv[dvb + d] = aj * o[ob + d];
      dk[dkb + d] = ds * q[qb + d];
      dq[dqb + d] += ds * k[kb + d];
    }
  }
}
