// One Linear layer on a batch of rows, as a tiled GEMM in shared memory (the deformation field's
// MLP, vulkan_field.cc, and the extended field's Linear, nn/vk_nn_kernels.cc):
//   forward  (no F_TRANS): Y[r][n] = act(sum_k act_in(X[r][k]) W[n][k] + b[n])   W: [N x K]
//   backward (F_TRANS):    Y[r][n] = (sum_k X[r][k] W[k][n] (+ Y[r][n])) * [M[r][n] > 0]   W: [K x N]
// (W row-major [out x in], PyTorch's layout, at w_off in the parameter buffer.) X and Y are
// row-strided views: X[r][k] at x_off + r * x_stride + k, Y (and the mask M) at
// y_off + r * y_stride + n; the host keeps every such index within 32 bits. Each workgroup
// computes a 64 x 64 tile of Y, each invocation 4 x 4 outputs, K in steps of 16.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "field_common.glsl"

#define TM 64u
#define TN 64u
#define TK 16u
#define F_RELU_IN 1u
#define F_RELU_OUT 2u
#define F_TRANS 4u
#define F_ACCUM 8u
#define F_MASK 16u
#define F_BIAS 32u

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer X { float x[]; };      // [rows x K] view
layout(std430, binding = 1) readonly buffer Mlp { float mlp[]; };  // parameters
layout(std430, binding = 2) buffer Y { float y[]; };               // [rows x N] view
layout(std430, binding = 3) readonly buffer Mask { float mask[]; };  // Y's layout (F_MASK)
layout(push_constant, std430) uniform Push {
  uint rows, K, N, w_off, b_off, flags;
  uint x_off, x_stride, y_off, y_stride;
} pc;

shared float xs[TK][TM];
shared float ws[TK][TN];

void main() {
  const uint tiles_n = (pc.N + TN - 1u) / TN;
  const uint tile = linear_group_id();
  const uint r0 = (tile / tiles_n) * TM, n0 = (tile % tiles_n) * TN;
  if (r0 >= pc.rows) return;  // uniform per workgroup: no barrier is skipped by part of it
  const uint tid = gl_LocalInvocationID.x;
  const uint tx = tid % 16u, ty = tid / 16u;
  const bool trans = (pc.flags & F_TRANS) != 0u;
  const bool relu_in = (pc.flags & F_RELU_IN) != 0u;
  float acc[4][4];
  for (uint i = 0u; i < 4u; ++i)
    for (uint j = 0u; j < 4u; ++j) acc[i][j] = 0.0;
  for (uint k0 = 0u; k0 < pc.K; k0 += TK) {
    for (uint j = 0u; j < 4u; ++j) {
      const uint e = tid + 256u * j;
      const uint row = e / TK, kk = e % TK;
      const uint r = r0 + row, k = k0 + kk;
      float v = (r < pc.rows && k < pc.K) ? x[pc.x_off + r * pc.x_stride + k] : 0.0;
      if (relu_in) v = max(v, 0.0);
      xs[kk][row] = v;
    }
    for (uint j = 0u; j < 4u; ++j) {
      const uint e = tid + 256u * j;
      uint nn, kk;
      if (trans) {
        kk = e / TN;
        nn = e % TN;
      } else {
        nn = e / TK;
        kk = e % TK;
      }
      const uint n = n0 + nn, k = k0 + kk;
      float v = 0.0;
      if (n < pc.N && k < pc.K) v = trans ? mlp[pc.w_off + k * pc.N + n] : mlp[pc.w_off + n * pc.K + k];
      ws[kk][nn] = v;
    }
    memoryBarrierShared();
    barrier();
    for (uint kk = 0u; kk < TK; ++kk) {
      float a[4], b[4];
      for (uint i = 0u; i < 4u; ++i) a[i] = xs[kk][ty + 16u * i];
      for (uint j = 0u; j < 4u; ++j) b[j] = ws[kk][tx + 16u * j];
      for (uint i = 0u; i < 4u; ++i)
        for (uint j = 0u; j < 4u; ++j) acc[i][j] += a[i] * b[j];
    }
    barrier();
  }
  for (uint i = 0u; i < 4u; ++i) {
    const uint r = r0 + ty + 16u * i;
    if (r >= pc.rows) continue;
    for (uint j = 0u; j < 4u; ++j) {
      const uint n = n0 + tx + 16u * j;
      if (n >= pc.N) continue;
      const uint yi = pc.y_off + r * pc.y_stride + n;
      float v = acc[i][j];
      if ((pc.flags & F_BIAS) != 0u) v += mlp[pc.b_off + n];
      if ((pc.flags & F_ACCUM) != 0u) v += y[yi];
      if ((pc.flags & F_RELU_OUT) != 0u) v = max(v, 0.0);
      if ((pc.flags & F_MASK) != 0u && !(mask[yi] > 0.0)) v = 0.0;
      y[yi] = v;
    }
  }
}
