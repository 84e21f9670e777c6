// Second pass of the MLP gradient reduction: d_mlp[i] += sum over chunks (in order) of
// partial[chunk][i] (field_linear_grad.comp).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "field_common.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer Partials { float partials[]; };
layout(std430, binding = 1) buffer DMlp { float d_mlp[]; };
layout(push_constant, std430) uniform Push {
  uint mlp_total, chunks;
} pc;

void main() {
  const uint i = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  if (i >= pc.mlp_total) return;
  float s = 0.0;
  for (uint c = 0u; c < pc.chunks; ++c) s += partials[c * pc.mlp_total + i];
  d_mlp[i] += s;
}
