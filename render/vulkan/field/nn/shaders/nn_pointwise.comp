// Element-wise ops over [rows x cols] views, one invocation per element:
//   OP_ACT        C = act(A)                      (C may be A)
//   OP_ACT_GRAD   C = B ⊙ act'(A)                  (A the pre-activation, B dy; C may be B)
//   OP_ADD        C += A
//   OP_GATE       C = A + g ⊙ B                    (ReZero gate: h = h0 + g ⊙ r, g per column)
//   OP_GATE_GRAD  C = g ⊙ A                        (dr = g ⊙ dh)
// g at g_off of P. Formulas: scene/field/nn/activation.cc, extended_config.h's gate.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "nn_common.glsl"

#define OP_ACT 0u
#define OP_ACT_GRAD 1u
#define OP_ADD 2u
#define OP_GATE 3u
#define OP_GATE_GRAD 4u

layout(local_size_x = 256) in;
layout(std430, binding = 0) readonly buffer A { float a[]; };
layout(std430, binding = 1) readonly buffer B { float b[]; };
layout(std430, binding = 2) buffer C { float c[]; };
layout(std430, binding = 3) readonly buffer P { float p[]; };
layout(push_constant, std430) uniform Push {
  uint rows, cols, op, act, g_off;
  uint a_off, a_stride, b_off, b_stride, c_off, c_stride;
} pc;

void main() {
  const uint i = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  if (i >= pc.rows * pc.cols) return;  // the host keeps rows * cols within 32 bits
  const uint r = i / pc.cols, k = i % pc.cols;
  const uint ai = pc.a_off + r * pc.a_stride + k;
  const uint ci = pc.c_off + r * pc.c_stride + k;
  if (pc.op == OP_ACT) {
    c[ci] = ActValue(pc.act, a[ai]);
  } else if (pc.op == OP_ACT_GRAD) {
    c[ci] = b[pc.b_off + r * pc.b_stride + k] * ActDerivative(pc.act, a[ai]);
  } else if (pc.op == OP_ADD) {
    c[ci] += a[ai];
  } else if (pc.op == OP_GATE) {
    c[ci] = a[ai] + p[pc.g_off + k] * b[pc.b_off + r * pc.b_stride + k];
  } else {
    c[ci] = p[pc.g_off + k] * a[ai];
  }
}
