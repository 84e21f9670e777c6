// First pass of a column-sum reduction (bias, LayerNorm gain / bias and gate gradients):
//   partials[chunk * p_stride + p_off + k] = sum over rows r of the chunk of A[r][k] (⊙ B[r][k])
// The second pass is field_reduce.comp (chunks summed in order): deterministic, no atomics.
// A workgroup takes one chunk and 64 columns; its 4 lanes per column sum every 4th row, then
// add up in a fixed order. rows_per_chunk / 4 loop iterations per invocation (lavapipe stops an
// invocation's loops after 65 535).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "nn_common.glsl"

#define COLS 64u
#define LANES 4u

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer A { float a[]; };
layout(std430, binding = 1) readonly buffer B { float b[]; };
layout(std430, binding = 2) writeonly buffer Partials { float partials[]; };
layout(push_constant, std430) uniform Push {
  uint rows, cols, rows_per_chunk, has_b;
  uint a_off, a_stride, b_off, b_stride, p_off, p_stride;
} pc;

shared float sums[LANES][COLS];

void main() {
  const uint tiles = (pc.cols + COLS - 1u) / COLS;
  const uint wg = linear_group_id();
  const uint chunk = wg / tiles;
  const uint k = (wg % tiles) * COLS + gl_LocalInvocationID.x % COLS;
  const uint lane = gl_LocalInvocationID.x / COLS;
  const uint rbeg = chunk * pc.rows_per_chunk;
  if (rbeg >= pc.rows) return;  // uniform per workgroup
  const uint rend = min(pc.rows, rbeg + pc.rows_per_chunk);
  float s = 0.0;
  if (k < pc.cols) {
    for (uint r = rbeg + lane; r < rend; r += LANES) {
      float v = a[pc.a_off + r * pc.a_stride + k];
      if (pc.has_b != 0u) v *= b[pc.b_off + r * pc.b_stride + k];
      s += v;
    }
  }
  sums[lane][gl_LocalInvocationID.x % COLS] = s;
  memoryBarrierShared();
  barrier();
  if (lane == 0u && k < pc.cols) {
    const uint t = gl_LocalInvocationID.x;
    partials[chunk * pc.p_stride + pc.p_off + k] = (sums[0][t] + sums[1][t]) + (sums[2][t] + sums[3][t]);
  }
}
