// Weight and bias gradients of one Linear layer over a batch, first pass of a two-pass reduction:
//   partial[chunk][W(n, k)] = sum_{r in chunk} dY[r][n] act_in(X[r][k]),
//   partial[chunk][b(n)]    = sum_{r in chunk} dY[r][n]   (the bias as an extra input column of 1s)
// at w_off + n * K + k and b_off + n of chunk's block (partial_stride floats per chunk; b_off
// NO_BIAS: none), so that a reduction pass (field_reduce.comp) sums the chunks in a fixed order:
// deterministic, no atomics. (The deformation field puts every layer of its MLP at its own
// offsets of one block; the extended field's Linear one layer per block.) dY and X are row-strided
// views (dy_off + r * dy_stride + n, x_off + r * x_stride + k), indices within 32 bits (host).
// One workgroup per (chunk of rows, 64 x 64 tile of [N x (K + 1)]), rows in steps of 16.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "field_common.glsl"

#define TN 64u
#define TK 64u
#define TR 16u
#define NO_BIAS 0xffffffffu

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer DY { float dy[]; };  // [rows x N] view
layout(std430, binding = 1) readonly buffer X { float x[]; };    // [rows x K] view
layout(std430, binding = 2) writeonly buffer Partials { float partials[]; };  // [chunks * partial_stride]
layout(push_constant, std430) uniform Push {
  uint rows, N, K, rows_per_chunk, w_off, b_off, partial_stride, relu_in;
  uint dy_off, dy_stride, x_off, x_stride;
} pc;

shared float ds[TR][TN];
shared float xs[TR][TK];

void main() {
  const uint tiles_n = (pc.N + TN - 1u) / TN;
  const uint tiles_k = (pc.K + 1u + TK - 1u) / TK;
  const uint wg = linear_group_id();
  const uint chunk = wg / (tiles_n * tiles_k);
  const uint tile = wg % (tiles_n * tiles_k);
  const uint n0 = (tile / tiles_k) * TN, k0 = (tile % tiles_k) * TK;
  const uint rbeg = chunk * pc.rows_per_chunk;
  if (rbeg >= pc.rows) return;  // uniform per workgroup
  const uint rend = min(pc.rows, rbeg + pc.rows_per_chunk);
  const uint tid = gl_LocalInvocationID.x;
  const uint tx = tid % 16u, ty = tid / 16u;
  float acc[4][4];
  for (uint i = 0u; i < 4u; ++i)
    for (uint j = 0u; j < 4u; ++j) acc[i][j] = 0.0;
  for (uint r0 = rbeg; r0 < rend; r0 += TR) {
    for (uint j = 0u; j < 4u; ++j) {
      const uint e = tid + 256u * j;
      const uint rr = e / 64u, cc = e % 64u;
      const uint r = r0 + rr;
      const uint n = n0 + cc, k = k0 + cc;
      ds[rr][cc] = (r < rend && n < pc.N) ? dy[pc.dy_off + r * pc.dy_stride + n] : 0.0;
      float v = 0.0;
      if (r < rend) {
        if (k < pc.K) {
          v = x[pc.x_off + r * pc.x_stride + k];
          if (pc.relu_in != 0u) v = max(v, 0.0);
        } else if (k == pc.K) {
          v = 1.0;
        }
      }
      xs[rr][cc] = v;
    }
    memoryBarrierShared();
    barrier();
    for (uint rr = 0u; rr < TR; ++rr) {
      float a[4], b[4];
      for (uint i = 0u; i < 4u; ++i) a[i] = ds[rr][ty + 16u * i];
      for (uint j = 0u; j < 4u; ++j) b[j] = xs[rr][tx + 16u * j];
      for (uint i = 0u; i < 4u; ++i)
        for (uint j = 0u; j < 4u; ++j) acc[i][j] += a[i] * b[j];
    }
    barrier();
  }
  for (uint i = 0u; i < 4u; ++i) {
    const uint n = n0 + ty + 16u * i;
    if (n >= pc.N) continue;
    for (uint j = 0u; j < 4u; ++j) {
      const uint k = k0 + tx + 16u * j;
      if (k > pc.K || (k == pc.K && pc.b_off == NO_BIAS)) continue;
      const uint idx = k < pc.K ? pc.w_off + n * pc.K + k : pc.b_off + n;
      partials[chunk * pc.partial_stride + idx] = acc[i][j];
    }
  }
}
