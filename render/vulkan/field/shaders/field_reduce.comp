// Second pass of the parameter-gradient reductions: for i < count,
//   d[dst_off + i] += sum over chunks c (in order) of partials[src_off + c * src_stride + i]
// (field_linear_grad.comp's blocks, nn/shaders/nn_colsum.comp's). chunks stays far below the
// 65 535 loop iterations lavapipe allows one invocation (the hosts check).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "field_common.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer Partials { float partials[]; };
layout(std430, binding = 1) buffer D { float d[]; };
layout(push_constant, std430) uniform Push {
  uint count, chunks, src_off, src_stride, dst_off;
} pc;

void main() {
  const uint i = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  if (i >= pc.count) return;
  float s = 0.0;
  for (uint c = 0u; c < pc.chunks; ++c) s += partials[pc.src_off + c * pc.src_stride + i];
  d[pc.dst_off + i] += s;
}
