// LayerNorm over each row of a [rows x dim] view (scene/field/nn/layer_norm.cc, PyTorch's
// nn.LayerNorm: biased variance), forward and the input gradient:
//   forward:  mean, var = mean((x - mean)^2), rstd = 1 / sqrt(var + eps), xhat = (x - mean) rstd,
//             y = g ⊙ xhat + b                              (writes y, xhat, rstd)
//   backward: gd = g ⊙ dy, dx = rstd (gd - mean(gd) - xhat mean(gd ⊙ xhat))   (writes dx)
// (the gain / bias gradients are column sums: nn_colsum.comp). 32 lanes per row, 8 rows per
// workgroup; the lanes' partial sums are added as a fixed tree in shared memory: deterministic.
// Each lane loops dim / 32 times per pass.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "nn_common.glsl"

#define LANES 32u
#define ROWS_PER_WG 8u

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer X { float x[]; };   // forward: x; backward: xhat
layout(std430, binding = 1) readonly buffer P { float p[]; };   // gain at g_off, bias at b_off
layout(std430, binding = 2) buffer Y { float y[]; };            // forward: y; backward: dx
layout(std430, binding = 3) buffer Xhat { float xhat[]; };      // forward: xhat (written)
layout(std430, binding = 4) buffer Rstd { float rstd[]; };      // [rows x 1]
layout(std430, binding = 5) readonly buffer DY { float dy[]; }; // backward
layout(push_constant, std430) uniform Push {
  uint rows, dim, backward, g_off, b_off;
  float eps;
  uint x_off, x_stride, y_off, y_stride, h_off, h_stride, r_off, r_stride, d_off, d_stride;
} pc;

shared float red[2][256];

// Sum of (a, b) over the row's 32 lanes, in a fixed tree.
vec2 RowSum(vec2 v) {
  const uint t = gl_LocalInvocationID.x, lane = t % LANES;
  red[0][t] = v.x;
  red[1][t] = v.y;
  memoryBarrierShared();
  barrier();
  for (uint s = LANES / 2u; s > 0u; s >>= 1u) {
    if (lane < s) {
      red[0][t] += red[0][t + s];
      red[1][t] += red[1][t + s];
    }
    memoryBarrierShared();
    barrier();
  }
  const vec2 r = vec2(red[0][t - lane], red[1][t - lane]);
  barrier();  // before the next call overwrites red
  return r;
}

void main() {
  const uint lane = gl_LocalInvocationID.x % LANES;
  const uint row = linear_group_id() * ROWS_PER_WG + gl_LocalInvocationID.x / LANES;
  // Rows past the end still take part in the barriers; they read and write nothing.
  const bool live = row < pc.rows;
  const float inv_dim = 1.0 / float(pc.dim);
  if (pc.backward == 0u) {
    const uint xb = pc.x_off + row * pc.x_stride;
    float s = 0.0;
    if (live)
      for (uint c = lane; c < pc.dim; c += LANES) s += x[xb + c];
    const float mean = RowSum(vec2(s, 0.0)).x * inv_dim;
    float q = 0.0;
    if (live) {
      for (uint c = lane; c < pc.dim; c += LANES) {
        const float d = x[xb + c] - mean;
        q += d * d;
      }
    }
    const float var = RowSum(vec2(q, 0.0)).x * inv_dim;
    const float r = 1.0 / sqrt(var + pc.eps);
    if (!live) return;
    if (lane == 0u) rstd[pc.r_off + row * pc.r_stride] = r;
    for (uint c = lane; c < pc.dim; c += LANES) {
      const float h = (x[xb + c] - mean) * r;
      xhat[pc.h_off + row * pc.h_stride + c] = h;
      y[pc.y_off + row * pc.y_stride + c] = p[pc.g_off + c] * h + p[pc.b_off + c];
    }
  } else {
    // x holds xhat here.
    const uint hb = pc.x_off + row * pc.x_stride, db = pc.d_off + row * pc.d_stride;
    vec2 s = vec2(0.0);
    if (live) {
      for (uint c = lane; c < pc.dim; c += LANES) {
        const float gd = p[pc.g_off + c] * dy[db + c];
        s += vec2(gd, gd * x[hb + c]);
      }
    }
    const vec2 m = RowSum(s) * inv_dim;
    if (!live) return;
    const float r = rstd[pc.r_off + row * pc.r_stride];
    for (uint c = lane; c < pc.dim; c += LANES) {
      const float gd = p[pc.g_off + c] * dy[db + c];
      y[pc.y_off + row * pc.y_stride + c] = (gd - m.x - x[hb + c] * m.y) * r;
    }
  }
}
