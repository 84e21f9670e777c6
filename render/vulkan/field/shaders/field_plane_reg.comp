// The plane regularisers' gradient and loss on one plane (the cpu's PlaneRegularizers,
// scene/field/field_regularizers.cc, element for element): S2(P) = mean over (h, row element) of
// (P[h+2] - 2 P[h+1] + P[h])^2 along the plane's second coordinate (time for space-time planes)
// and, for space-time planes, L1 = mean |1 - P|. Gather form: each invocation adds the gradient of
// its own element (rows h-2..h+2 read), so no two invocations write the same float. Loss terms
// (already divided by their counts) are summed per workgroup into partial[pc.partial_off + wg].
#version 460
#extension GL_GOOGLE_include_directive : require
#include "field_common.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer Params { float p[]; };  // the plane's group
layout(std430, binding = 1) buffer Grads { float g[]; };            // the same group's gradient
layout(std430, binding = 2) writeonly buffer Partials { vec2 partial[]; };
layout(push_constant, std430) uniform Push {
  uint offset;      // the plane's first float in its group
  uint row_len;     // floats per row: width * channels
  uint height;      // rows (H)
  uint groups;      // workgroups dispatched for this plane (a grid-stride loop)
  float c_s2;       // 2 w_s2 / ((H - 2) row_len); 0 when H < 3
  float c_l1;       // w_l1 / (H row_len); 0 for spatial planes
  float inv_n_s2;   // 1 / ((H - 2) row_len) (0 when H < 3)
  float inv_n_l1;   // 1 / (H row_len) for space-time planes, else 0
  uint partial_off;
} pc;

shared vec2 red[FIELD_WG];

float At(int h, uint col) {
  const int hc = clamp(h, 0, int(pc.height) - 1);
  return p[pc.offset + uint(hc) * pc.row_len + col];
}

void main() {
  const uint lid = gl_LocalInvocationID.x;
  const uint count = pc.row_len * pc.height;
  const int H = int(pc.height);
  vec2 acc = vec2(0.0);
  for (uint i = gl_WorkGroupID.x * FIELD_WG + lid; i < count; i += pc.groups * FIELD_WG) {
    const int v = int(i / pc.row_len);
    const uint col = i - uint(v) * pc.row_len;
    const float a0 = At(v - 2, col), a1 = At(v - 1, col), a2 = At(v, col), a3 = At(v + 1, col),
                a4 = At(v + 2, col);
    const float d0 = a2 - 2.0 * a1 + a0;
    const float d1 = a3 - 2.0 * a2 + a1;
    const float d2 = a4 - 2.0 * a3 + a2;
    const float f0 = v - 2 >= 0 ? 1.0 : 0.0;
    const float f1 = (v - 1 >= 0 && v + 1 < H) ? 1.0 : 0.0;
    const float f2 = v + 2 < H ? 1.0 : 0.0;
    float grad = g[pc.offset + i];
    grad += pc.c_s2 * (f0 * d0 - 2.0 * f1 * d1 + f2 * d2);
    acc.x += f2 * d2 * d2;  // the term whose second difference starts at row v
    if (pc.c_l1 != 0.0 || pc.inv_n_l1 != 0.0) {
      const float x = a2 - 1.0;
      grad += pc.c_l1 * sign(x);
      acc.y += abs(x);
    }
    g[pc.offset + i] = grad;
  }
  red[lid] = acc * vec2(pc.inv_n_s2, pc.inv_n_l1);
  barrier();
  for (uint s = FIELD_WG / 2u; s > 0u; s >>= 1u) {
    if (lid < s) red[lid] += red[lid + s];
    barrier();
  }
  if (lid == 0u) partial[pc.partial_off + gl_WorkGroupID.x] = red[0];
}
